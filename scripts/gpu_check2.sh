#!/usr/bin/env bash
# A second, shorter device check after scripts/gpu_check.sh (about 5 minutes): the CUDA tests again,
# learned at B = 8192 eager against simulation.compile=true in the same call, and the 450-descent
# cmax campaign with its progress bar in the log.
#   run(command="bash scripts/gpu_check2.sh", carry=[".whl"], timeout_s=420)
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${OUT:-/tmp/gpu_check}"; mkdir -p "$OUT"
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="${PYTHONPATH:+$PYTHONPATH:}$PWD" PYTHONUNBUFFERED=1 PYOPENGL_PLATFORM=egl
FIX=(--set dispersion.terrain_variants=1 --set 'dispersion.sun_elevation_deg={kind: "off"}')
timeout 100 python3 -m pytest -q -p no:cacheprovider -k "cuda" tests/ 2>&1 | tail -30 | tee "$OUT/cuda_tests.log"
for c in false true; do
  timeout 110 python3 -m dvsland.bench.throughput --device cuda --batches 8192 --estimators learned --steps 10 \
    "${FIX[@]}" --set simulation.compile=$c --out "$OUT/compile_$c" 2>&1 | tail -6 | tee -a "$OUT/throughput.log"
done
s=$SECONDS
timeout 150 python3 -m dvsland.cli.main campaign montecarlo_efference --estimator cmax --n-seeds 50 \
  --set simulation.device=cuda "${FIX[@]}" --out /tmp/camp > "$OUT/campaign.log" 2>&1
echo "campaign rc=$? wall_s=$((SECONDS - s))" | tee -a "$OUT/campaign.log"
tail -c 3000 "$OUT/campaign.log"
