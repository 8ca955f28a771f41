#!/usr/bin/env bash
# Resume check of a campaign: run it uninterrupted, run it again and kill it (SIGTERM: no clean-up, like
# a kill) once half of its shards are written, resume it, and compare the merged runs and group
# statistics of both. Usage: bash scripts/campaign_resume_check.sh OUT_DIR [campaign args...]
# e.g.  bash scripts/campaign_resume_check.sh /tmp/resume montecarlo --estimator oracle --n-seeds 50
set -euo pipefail
out="$1"; shift
dvs="$(dirname "$0")/../.venv/bin/dvsland"
py="$(dirname "$0")/../.venv/bin/python"
rm -rf "$out"; mkdir -p "$out"
"$dvs" campaign "$@" --quiet --out "$out/full"
n=$(ls "$out/full/shards" | wc -l)
"$dvs" campaign "$@" --quiet --out "$out/cut" & pid=$!
while [ "$(ls "$out/cut/shards" 2>/dev/null | grep -c 'json$' || true)" -lt $((n / 2)) ]; do sleep 0.2; done
kill -TERM "$pid"; wait "$pid" || true
echo "killed with $(ls "$out/cut/shards" | grep -c 'json$') of $n shards written"
"$dvs" campaign --resume "$out/cut" --quiet
"$py" - "$out" <<'PY'
import json, sys
a = json.load(open(f"{sys.argv[1]}/full/results.json")); b = json.load(open(f"{sys.argv[1]}/cut/results.json"))
print("resumed run:", b["session"]["shards_run"], "shards;", "status", b["status"])
print("merged runs identical:", a["runs"] == b["runs"], f"({len(a['runs'])} runs)")
print("group statistics identical:", a["groups"] == b["groups"], f"({len(a['groups'])} groups)")
sys.exit(0 if a["runs"] == b["runs"] and a["groups"] == b["groups"] else 1)
PY
