#!/usr/bin/env bash
# The one prepared device check for a lent GPU machine (H100/H200, about 7 minutes): the CUDA tests,
# the throughput table of `dvsland bench throughput` on CUDA (eager, and learned at B = 8192 with
# simulation.compile=true), a profile of one large step, the 450-descent cmax campaign and whole
# `learned` descents per minute (LEARNED_SEEDS x 9 descents flown to the end). Results go
# to $OUT (the device tool brings them back) or to /tmp/gpu_check; on 2026-11-26 an H200 ran the
# first three parts in about 3.5 minutes (docs/benchmarks.md).
#
# Here, once: `bash scripts/gpu_check.sh --wheels` downloads the packages the device machine lacks
# into .whl/ (git-ignored through .git/info/exclude). Then, with the device tool:
#   run(command="bash scripts/gpu_check.sh", carry=[".whl"], timeout_s=570)
# PARTS="1 2 3 4 5" (the default) picks the parts to run; part 6 (by-function profiles) runs when named.
set -uo pipefail
cd "$(dirname "$0")/.."
if [ "${1:-}" = "--wheels" ]; then
  grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo /.whl/ >> .git/info/exclude
  plat="--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64"
  for p in kornia==0.9.0 kornia_rs==0.2.0 trimesh==5.2.0 pyrender==0.1.45 pyglet==2.1.19 freetype-py==2.5.1 \
           gymnasium==1.4.0 Farama-Notifications==0.0.6; do
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $plat -d .whl "$p" \
      || python3 -m pip download -q --no-deps --only-binary=:all: -d .whl "$p"
  done
  python3 -m pip wheel -q --no-deps -w .whl PyOpenGL==3.1.0
  ls -la .whl
  exit 0
fi
OUT="${OUT:-/tmp/gpu_check}"; mkdir -p "$OUT"
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="${PYTHONPATH:+$PYTHONPATH:}$PWD" PYTHONUNBUFFERED=1 PYOPENGL_PLATFORM=egl
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/gpu.txt"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())" | tee -a "$OUT/gpu.txt"
PARTS=" ${PARTS:-1 2 3 4 5} "
FIX=(--set dispersion.terrain_variants=1 --set 'dispersion.sun_elevation_deg={kind: "off"}')
# 1. the CUDA tests (every test that names cuda, and tests/test_cuda_loop.py; they skip on a CPU machine)
[[ $PARTS == *" 1 "* ]] && timeout 170 python3 -m pytest -q -p no:cacheprovider -k "cuda" tests/ 2>&1 | tail -40 | tee "$OUT/cuda_tests.log"
# 2. the throughput table and the torch-API env: terrain variants and the sun fixed, so that set-up stays short
[[ $PARTS == *" 2 "* ]] && timeout 250 python3 -m dvsland.bench.throughput --device cuda --batches "${BATCHES:-576,4608,8192}" \
  --estimators learned,cmax --steps 10 --env-batches 4608 --env-steps 20 "${FIX[@]}" \
  --out "$OUT" 2>&1 | tail -40 | tee "$OUT/throughput.log"
[[ $PARTS == *" 2 "* ]] && timeout 100 python3 -m dvsland.bench.throughput --device cuda --batches 8192 --estimators learned --steps 10 \
  "${FIX[@]}" --set simulation.compile=true 2>&1 | tail -3 | tee -a "$OUT/throughput.log"
# 3. where a large step's device time goes
if [[ $PARTS == *" 3 "* ]]; then
  timeout 60 python3 scripts/gpu_profile_step.py --device cuda --batch 4608 --estimator learned --steps 3 --rows 25 \
    > "$OUT/profile.txt" 2>&1; tail -5 "$OUT/profile.txt"
fi
# one campaign on the card: campaign LABEL ESTIMATOR N_SEEDS TIMEOUT_S -> $OUT/LABEL.log (wall time with
# set-up, the outcomes, the session's descents per minute) and $OUT/LABEL_table.md
campaign() {
  local label=$1 est=$2 seeds=$3 limit=$4 s=$SECONDS
  timeout "$limit" python3 -m dvsland.cli.main campaign montecarlo_efference --estimator "$est" --n-seeds "$seeds" \
    --quiet --set simulation.device=cuda "${FIX[@]}" --out "/tmp/$label" > "$OUT/$label.log" 2>&1
  echo "$label rc=$? wall_s=$((SECONDS - s))" | tee -a "$OUT/$label.log"
  cp "/tmp/$label/table.md" "$OUT/${label}_table.md" 2>/dev/null
  python3 - "/tmp/$label/results.json" <<'PY' 2>&1 | tee -a "$OUT/$label.log"
import json, collections, sys
r = json.load(open(sys.argv[1]))
print(r.get("status"), collections.Counter(x.get("outcome") for x in r.get("runs", [])), r.get("session", ""),
      "shards", r.get("n_shards"))
PY
}
# 4. the 450-descent cmax campaign on the card, wall time (set-up included)
[[ $PARTS == *" 4 "* ]] && campaign campaign cmax 50 100
# 5. whole learned descents per minute: LEARNED_SEEDS x 9 sites flown to the end in one batch (set-up
#    included in the wall time, reported apart by the campaign); the issue's goal is 20,000 per minute
[[ $PARTS == *" 5 "* ]] && campaign campaign_learned learned "${LEARNED_SEEDS:-1000}" 150
# 6. where a step's time goes, by dvsland function (device time, the host's own time, launches): cmax at
#    the campaign's size and at a large one, learned at a large one
if [[ $PARTS == *" 6 "* ]]; then
  for eb in cmax:576 cmax:4608 learned:4608; do
    timeout 90 python3 scripts/gpu_profile_step.py --device cuda --batch "${eb#*:}" --estimator "${eb%:*}" --steps 3 \
      --rows 20 --lines 40 > "$OUT/lines_${eb%:*}_${eb#*:}.txt" 2>&1; head -45 "$OUT/lines_${eb%:*}_${eb#*:}.txt"
  done
fi
exit 0
