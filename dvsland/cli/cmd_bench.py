"""``dvsland bench [WHAT ...] [--quick] [--out DIR]``: run the benchmark scripts of each stage.

Each stage keeps its benchmark in ``scripts/`` (render, events, estimators, renderer agreement,
simulator profile); this command runs the chosen ones in turn with the same Python, writes their
JSON into one folder (``logs/bench-<UTC stamp>/`` by default) and prints their tables.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from dvsland.config import repo_root
from dvsland.runs import utc_stamp

#: name -> (script, default args, quick args); "{json}" is replaced by the output path.
BENCHES = {
    "render": ("bench_render.py", ["--threads", "1", "--json", "{json}"],
               ["--threads", "1", "--batches", "18", "--repeat", "5", "--json", "{json}"]),
    "events": ("bench_events.py", ["--threads", "1", "--json", "{json}"],
               ["--threads", "1", "--batch", "18", "--no-memory", "--json", "{json}"]),
    "v2e": ("bench_v2e.py", ["--threads", "1", "--json", "{json}"],
            ["--threads", "1", "--batch", "6", "--steps", "6", "--json", "{json}"]),
    "estimators": ("bench_estimators.py", ["--threads", "1", "--json", "{json}"],
                   ["--threads", "1", "--batch", "18", "--steps", "10", "--estimators", "dpr,oracle",
                    "--json", "{json}"]),
    "renderers": ("compare_renderers.py", ["--out", "{json}"], ["--n-alt", "4", "--segments", "--out", "{json}"]),
    "sim": ("profile_sim.py", ["--json", "{json}"], ["--sites", "A,D,H", "--json", "{json}"]),
}


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="run the benchmarks (speed and error) of each stage")
    p.add_argument("what", nargs="*", metavar="WHAT",
                   help=f"which benchmarks: all (default), {', '.join(BENCHES)}")
    p.add_argument("--quick", action="store_true", help="smaller, faster settings")
    p.add_argument("--out", default=None, metavar="DIR", help="folder for the JSON results")
    p.set_defaults(func=run)


def run(args) -> int:
    what = args.what or ["all"]
    unknown = [w for w in what if w != "all" and w not in BENCHES]
    if unknown:
        raise ValueError(f"unknown benchmark {unknown[0]!r}; choose from all, {', '.join(BENCHES)}")
    names = list(BENCHES) if "all" in what else list(dict.fromkeys(what))
    out = Path(args.out) if args.out else Path("logs") / f"bench-{utc_stamp()}"
    out.mkdir(parents=True, exist_ok=True)
    scripts = repo_root() / "scripts"
    failed = []
    for name in names:
        script, full, quick = BENCHES[name]
        path = scripts / script
        if not path.is_file():
            print(f"dvsland bench: {name}: {path} not found", file=sys.stderr)
            failed.append(name)
            continue
        argv = [a.replace("{json}", str(out / f"{name}.json")) for a in (quick if args.quick else full)]
        print(f"== {name}: {script} {' '.join(argv)}", flush=True)
        rc = subprocess.call([sys.executable, str(path), *argv])
        if rc != 0:
            failed.append(name)
    print(f"results in {out}")
    if failed:
        print(f"dvsland bench: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0
