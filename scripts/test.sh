#!/usr/bin/env bash
# Set up (a virtual environment in .venv, CPU torch pinned by constraints.txt) and run the
# default test suite (slow tests excluded; `bash scripts/test.sh -m slow` runs them).
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q -c constraints.txt -e '.[dev]' 2>&1 | grep -v "^WARNING: Location" || true
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}" EGL_PLATFORM="${EGL_PLATFORM:-surfaceless}"
set +e
.venv/bin/python -m pytest "$@"
rc=$?
if [ "$rc" -eq 5 ]; then echo "no tests were collected: failing" >&2; exit 5; fi
exit "$rc"
