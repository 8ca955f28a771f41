#!/usr/bin/env bash
# The compiled filter and law against the eager loop on the card (about 2 minutes): learned at
# B = 8192, simulation.compile=false then true, in the same call.
#   run(command="bash scripts/gpu_check3.sh", carry=[".whl"], timeout_s=200)
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${OUT:-/tmp/gpu_check}"; mkdir -p "$OUT"
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="${PYTHONPATH:+$PYTHONPATH:}$PWD" PYTHONUNBUFFERED=1 PYOPENGL_PLATFORM=egl
for c in false true; do
  timeout 120 python3 -m dvsland.bench.throughput --device cuda --batches 8192 --estimators learned --steps 20 \
    --set dispersion.terrain_variants=1 --set 'dispersion.sun_elevation_deg={kind: "off"}' \
    --set simulation.compile=$c --out "$OUT/compile_$c" 2>&1 | tail -3 | tee -a "$OUT/throughput.log"
done
