#!/usr/bin/env bash
# The one prepared device check for a lent GPU machine (H100/H200, about 8 minutes): the CUDA tests
# and the throughput table of `dvsland bench throughput` on CUDA. Results go to $OUT (the device
# tool brings them back) or to /tmp/gpu_check.
#
# Here, once: `bash scripts/gpu_check.sh --wheels` downloads the packages the device machine lacks
# into .whl/ (git-ignored through .git/info/exclude). Then, with the device tool:
#   run(command="bash scripts/gpu_check.sh", carry=[".whl"], timeout_s=560)
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
# the CUDA tests (every test that names cuda; they skip on a CPU machine)
timeout 240 python3 -m pytest -q -p no:cacheprovider -x -k "cuda" tests/ 2>&1 | tail -40 | tee "$OUT/cuda_tests.log"
# the throughput table: terrain variants and the sun fixed, so that set-up stays short
timeout 280 python3 -m dvsland.bench.throughput --device cuda --batches 576,2304,4608 --estimators learned,cmax \
  --set dispersion.terrain_variants=1 --set 'dispersion.sun_elevation_deg={kind: "off"}' \
  --out "$OUT" --json "$OUT/throughput.json" 2>&1 | tail -30 | tee "$OUT/throughput.log"
