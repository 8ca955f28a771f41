"""Record (or check) short flights of every shipped preset, as a bit-for-bit reference of the loop.

Each case flies a few sites for a few seconds through :func:`dvsland.simulate` and keeps the
SHA-256 of every trace array and the run summaries. ``--write`` stores them in
``tests/data/loop_reference.json``; without it the script compares and prints the differences.

    python scripts/loop_reference.py --write      # record (from a trusted commit)
    python scripts/loop_reference.py --write --cases paper_cmax,montecarlo_cmax   # re-record only these
    python scripts/loop_reference.py              # check the working tree against the record
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REF = Path(__file__).resolve().parents[1] / "tests" / "data" / "loop_reference.json"

#: (case name, preset, estimator, sites, extra overrides)
CASES = [
    ("paper_dpr", "paper", "dpr", "A,H", ["simulation.t_max_s=6"]),
    ("paper_eq2_dpr", "paper_eq2", "dpr", "D", ["simulation.t_max_s=4"]),
    ("paper_oracle", "paper", "oracle", "A,D,H", ["simulation.t_max_s=30"]),
    ("paper_eq2_oracle_full", "paper_eq2", "oracle", "A,D,H", []),
    ("montecarlo_efference_oracle_full", "montecarlo_efference", "oracle", "E,H", ["simulation.n_seeds=2"]),
    ("paper_cmax", "paper", "cmax", "D", ["simulation.t_max_s=5"]),
    ("paper_snn", "paper", "snn", "F", ["simulation.t_max_s=4"]),
    ("paper_montecarlo_dpr", "paper_montecarlo", "dpr", "B", ["simulation.t_max_s=4", "simulation.n_seeds=2"]),
    ("realistic_dpr", "realistic", "dpr", "E", ["simulation.t_max_s=4"]),
    ("montecarlo_cmax", "montecarlo", "cmax", "G", ["simulation.t_max_s=4", "simulation.n_seeds=2"]),
    ("montecarlo_efference_cmax", "montecarlo_efference", "cmax", "C,I",
     ["simulation.t_max_s=5", "simulation.n_seeds=2"]),
]


def _digest(a: np.ndarray) -> str:
    a = np.ascontiguousarray(a)
    if a.dtype.kind in "US":
        return hashlib.sha256("\n".join(map(str, a.ravel())).encode()).hexdigest()
    return hashlib.sha256(a.tobytes()).hexdigest()


def fly_case(preset: str, estimator: str, sites: str, overrides) -> dict:
    """Fly one case; returns {"traces": {field: sha256}, "runs": [...summaries]}."""
    from dvsland import simulate

    with tempfile.TemporaryDirectory() as tmp:
        res = simulate(preset, estimator=estimator, sites=sites, quiet=True, out=Path(tmp) / "run",
                       overrides=["render.threads=1", "logging.tensorboard=false", "logging.figures=false",
                                  *overrides])
    drop = {"wall_s", "wall_time_s"}
    runs = [{k: v for k, v in r.items() if k not in drop} for r in res.runs]
    return {"traces": {k: _digest(v) for k, v in sorted(res.traces.items())}, "runs": runs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="store the reference instead of checking it")
    ap.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    names = [c for c in a.cases.split(",") if c]
    got = {name: fly_case(p, e, s, o) for name, p, e, s, o in CASES if not names or name in names}
    if a.write:
        # with --cases, only those cases are re-recorded; the others keep their stored reference
        stored = json.loads(REF.read_text()) if names and REF.exists() else {}
        REF.write_text(json.dumps({**stored, **got}, indent=1, sort_keys=True) + "\n")
        print(f"wrote {REF} ({len(got)} cases re-recorded, {len({**stored, **got})} in all)")
        return 0
    ref = json.loads(REF.read_text())
    bad = 0
    for name, g in got.items():
        r = ref[name]
        diff = [k for k in r["traces"] if r["traces"][k] != g["traces"].get(k)]
        if diff or r["runs"] != json.loads(json.dumps(g["runs"])):
            bad += 1
            print(f"{name}: differs (traces {diff})")
        else:
            print(f"{name}: identical")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
