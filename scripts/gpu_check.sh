#!/usr/bin/env bash
# The one prepared device check for a lent GPU machine (H100/H200, about 7 minutes by default): the
# CUDA tests, the throughput table of `dvsland bench throughput` on CUDA (as shipped: simulation.compile
# =auto fuses the filter and the law on the card; EAGER=1 adds learned at B = 8192 uncompiled; LATE=1
# adds it after 1,200 steps, near the ground, compiled and not; FUSED=1 adds it with the renderer's sampling
# and the emulator's pixel step fused too: render.compile / emulator.compile=auto), the 450-descent cmax campaign in one
# process (and, as part 4, in CAMPAIGN_WORKERS processes sharing the card), whole `learned` descents
# per minute (part 5: LEARNED_SEEDS x 9 descents flown to the end in LEARNED_WORKERS processes; part 7:
# a fleet), and where a step's time goes by dvsland function (part 6; PROFILE_SKIP=1300 profiles late
# in the flight, near the ground).
# $OUT/summary.log gathers the figures as they come; $OUT/results.tgz (refreshed after every part, so
# a run cut short still brings back what it finished) holds every log, table and profile. Without
# $OUT (a machine of your own) both go to /tmp/gpu_check.
#
# Here, once: `bash scripts/gpu_check.sh --wheels` downloads the packages the device machine lacks
# into .whl/ (git-ignored through .git/info/exclude). Then, with the device tool:
#   run(command="bash scripts/gpu_check.sh", carry=[".whl"], timeout_s=570)
# PARTS="1 2 3 7" (the default) picks the parts to run: part 7 flies FLEET_N whole descents through
# FLEET_B slots that restart as theirs end, for at most FLEET_STEPS steps (whole descents per minute;
# it replaces part 5, whole batches flown to their last descent; FLEET_EAGER=1 flies it uncompiled).
# On 2026-11-28 an H200 took 45 s (1; 97 s once the filter and the law compiled by default), 30 s (2;
# about 200 s with BATCHES=8192 LATE=1), 132 s (3), about 50 s (6, two profiles; about 100 s for one
# with PROFILE_SKIP=1300) and 190-250 s (7, 3,200 steps); the default parts take about 8 minutes, so a
# 15-minute lease has room for one more short call, not for a rerun. On 2026-11-27: 182 s (5, 600
# seeds). Part 4 (the campaign in several processes on one card) finished no shard in 120 s.
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
OUT="${OUT:-/tmp/gpu_check}"; RES=/tmp/gpu_check_results; mkdir -p "$OUT" "$RES"
SUM="$OUT/summary.log"
snapshot() { tar czf "$OUT/results.tgz" -C "$RES" . 2>/dev/null; }
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="${PYTHONPATH:+$PYTHONPATH:}$PWD" PYTHONUNBUFFERED=1 PYOPENGL_PLATFORM=egl
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee -a "$SUM"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())" | tee -a "$SUM"
PARTS=" ${PARTS:-1 2 3 7} "
FIX=(--set dispersion.terrain_variants=1 --set 'dispersion.sun_elevation_deg={kind: "off"}')
# 1. the CUDA tests (every test that names cuda, and tests/test_cuda_loop.py; they skip on a CPU machine)
if [[ $PARTS == *" 1 "* ]]; then
  s=$SECONDS; timeout 240 python3 -m pytest -q -p no:cacheprovider -k "cuda" tests/ > "$RES/cuda_tests.log" 2>&1
  { echo "## 1. CUDA tests ($((SECONDS - s)) s)"; grep -E "passed|failed|FAILED|Error" "$RES/cuda_tests.log" | tail -15; } | tee -a "$SUM"
  snapshot
fi
# 2. the throughput table and the torch-API env: terrain variants and the sun fixed, so that set-up stays short
if [[ $PARTS == *" 2 "* ]]; then
  echo "## 2. throughput" | tee -a "$SUM"
  timeout 250 python3 -m dvsland.bench.throughput --device cuda --batches "${BATCHES:-576,4608,8192}" \
    --estimators learned,cmax --steps 10 --env-batches 4608 --env-steps 20 "${FIX[@]}" \
    --out "$RES" > "$RES/throughput.log" 2>&1; tail -14 "$RES/throughput.log" | tee -a "$SUM"
  # LATE=1 adds learned at B = 8192 after 1,200 steps (near the ground), as shipped (simulation.compile=auto:
  # compiled on the card) and eager (compile=false); about a minute each
  if [[ ${LATE:-0} == 1 ]]; then
    for mode in auto false; do
      timeout 150 python3 -m dvsland.bench.throughput --device cuda --batches 8192 --estimators learned --steps 10 \
        --warmup 1200 "${FIX[@]}" --set simulation.compile=$mode > "$RES/throughput_late_$mode.log" 2>&1
      echo "late, simulation.compile=$mode:" | tee -a "$SUM"; tail -3 "$RES/throughput_late_$mode.log" | tee -a "$SUM"
    done
  fi
  # FUSED=1 adds learned at B = 8192 with the renderer's torch sampling (render.compile=auto), the emulator's pixel
  # step (emulator.compile=auto) and both fused too: off by default until measured here; about 40 s each, their
  # compiles included; with LATE=1 also both after 1,200 steps
  if [[ ${FUSED:-0} == 1 ]]; then
    for sets in render emulator "render emulator" "render emulator late"; do
      args=(); warm=3; tag=${sets// /_}
      for w in $sets; do [[ $w == late ]] && warm=1200 || args+=(--set "$w.compile=auto"); done
      [[ $warm == 1200 && ${LATE:-0} != 1 ]] && continue
      timeout 150 python3 -m dvsland.bench.throughput --device cuda --batches 8192 --estimators learned --steps 10 \
        --warmup "$warm" "${FIX[@]}" "${args[@]}" > "$RES/throughput_fused_$tag.log" 2>&1
      echo "fused: $sets (${args[*]}):" | tee -a "$SUM"; tail -3 "$RES/throughput_fused_$tag.log" | tee -a "$SUM"
    done
  fi
  if [[ ${EAGER:-0} == 1 ]]; then  # EAGER=1 adds the first steps at B = 8192 uncompiled (about 30 s)
    timeout 100 python3 -m dvsland.bench.throughput --device cuda --batches 8192 --estimators learned --steps 10 \
      "${FIX[@]}" --set simulation.compile=false > "$RES/throughput_eager.log" 2>&1
    tail -3 "$RES/throughput_eager.log" | tee -a "$SUM"
  fi
  snapshot
fi
# one campaign on the card: campaign LABEL ESTIMATOR N_SEEDS WORKERS TIMEOUT_S -> $RES/LABEL.log (wall time
# with set-up, the outcomes, the session's descents per minute) and $RES/LABEL_table.md
campaign() {
  local label=$1 est=$2 seeds=$3 workers=$4 limit=$5 s=$SECONDS
  echo "## $label: $est, $seeds seeds x 9 sites, $workers process(es)" | tee -a "$SUM"
  timeout "$limit" python3 -m dvsland.cli.main campaign montecarlo_efference --estimator "$est" --n-seeds "$seeds" \
    --workers "$workers" --quiet --set simulation.device="${DEVICE:-cuda}" "${FIX[@]}" --out "/tmp/$label" > "$RES/$label.log" 2>&1
  echo "$label rc=$? wall_s=$((SECONDS - s))" | tee -a "$RES/$label.log" "$SUM"
  cp "/tmp/$label/table.md" "$RES/${label}_table.md" 2>/dev/null
  python3 - "/tmp/$label/results.json" <<'PY' 2>&1 | tee -a "$RES/$label.log" "$SUM"
import json, collections, sys
r = json.load(open(sys.argv[1]))
print(r.get("status"), collections.Counter(x.get("outcome") for x in r.get("runs", [])), r.get("session", ""),
      "shards", r.get("n_shards"))
PY
  snapshot
}
# 3. the 450-descent cmax campaign on the card in one process, wall time (set-up included)
[[ $PARTS == *" 3 "* ]] && campaign campaign cmax "${CMAX_SEEDS:-50}" 1 150
# 4. the same in CAMPAIGN_WORKERS processes sharing the card (each one's host work overlaps the others')
[[ $PARTS == *" 4 "* ]] && campaign campaign_workers cmax "${CMAX_SEEDS:-50}" "${CAMPAIGN_WORKERS:-4}" 120
# 5. whole learned descents per minute: LEARNED_SEEDS x 9 sites flown to the end (set-up included in the
#    wall time, reported apart by the campaign); the issue's goal is 20,000 per minute
[[ $PARTS == *" 5 "* ]] && campaign campaign_learned learned "${LEARNED_SEEDS:-600}" "${LEARNED_WORKERS:-2}" 200
# 6. where a step's time goes, by dvsland function (device time, the host's own time, launches)
if [[ $PARTS == *" 6 "* ]]; then
  # PROFILE_SKIP steps flown first (default 3: the first steps; 1300: late in the flight, near the ground,
  # where whole descents spend their time: more events, a long filter history)
  for eb in ${PROFILES:-cmax:4608 learned:4608 cmax:576}; do
    timeout $((90 + ${PROFILE_SKIP:-3} / 8)) python3 scripts/gpu_profile_step.py --device cuda --batch "${eb#*:}" \
      --estimator "${eb%:*}" --steps 3 --skip "${PROFILE_SKIP:-3}" \
      --rows 25 --lines 40 > "$RES/profile_${eb%:*}_${eb#*:}.txt" 2>&1
    grep -m1 "^B = " "$RES/profile_${eb%:*}_${eb#*:}.txt" | tee -a "$SUM"
    snapshot
  done
fi
# 7. whole descents per minute in a fleet (dvsland.sim.fly_fleet: every slot restarts as its descent ends)
if [[ $PARTS == *" 7 "* ]]; then
  echo "## 7. fleet" | tee -a "$SUM"
  timeout "${FLEET_LIMIT:-200}" python3 -m dvsland.bench.fleet --device cuda --batch "${FLEET_B:-8192}" \
    --descents "${FLEET_N:-24576}" --estimator "${FLEET_EST:-learned}" --max-steps "${FLEET_STEPS:-3200}" "${FIX[@]}" \
    ${FLEET_EAGER:+--set simulation.compile=false} \
    --json "$RES/fleet.json" > "$RES/fleet.log" 2>&1; tail -2 "$RES/fleet.log" | tee -a "$SUM"
  snapshot
fi
exit 0
