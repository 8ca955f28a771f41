"""Record (or check) short flights of every shipped preset, as a bit-for-bit reference of the loop.

Each case flies a few sites for a few seconds through :func:`dvsland.simulate` and keeps the
SHA-256 of every trace array and the run summaries. ``--write`` stores them in
``tests/data/loop_reference.json``; without it the script compares and prints the differences.

Float reductions (convolutions, sums) round differently on other CPUs (the vector units differ),
so one case may have several recorded variants, each bit for bit from one machine: a flight matches
when it equals any of them. The trace values of the last recording are kept too
(``tests/data/loop_reference_values.npz``): a flight that matches no variant but lies within
``rtol=1e-3, atol=1e-4`` of those values with the same outcomes is reported as ``close`` (another
CPU's rounding) and passes; anything else differs.

    python scripts/loop_reference.py --write      # record (from a trusted commit)
    python scripts/loop_reference.py --write --cases paper_cmax,montecarlo_cmax   # re-record only these
    python scripts/loop_reference.py --add-variant --cases paper_cmax   # this machine's bits beside the others
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
VALUES = REF.with_name("loop_reference_values.npz")
#: tolerance of a flight that matches no recorded variant (another CPU's rounding)
RTOL, ATOL = 1e-3, 1e-4

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
    values = {k: np.asarray(v) for k, v in res.traces.items() if np.asarray(v).dtype.kind == "f"}
    return {"traces": {k: _digest(v) for k, v in sorted(res.traces.items())}, "runs": runs, "values": values}


def _variants(stored) -> list:
    """A case's recorded variants (older files hold one record, not a list)."""
    return stored if isinstance(stored, list) else [stored]


def _record(g: dict) -> dict:
    return {"traces": g["traces"], "runs": json.loads(json.dumps(g["runs"]))}


def _matches(rec: dict, g: dict) -> bool:
    return rec["traces"] == g["traces"] and rec["runs"] == json.loads(json.dumps(g["runs"]))


def _close(name: str, g: dict, values) -> bool:
    """Within the tolerance of the recorded values, with the same outcomes."""
    keys = [k for k in values.files if k.startswith(name + "/")] if values is not None else []
    if not keys:
        return False
    for k in keys:
        f = k.split("/", 1)[1]
        if f not in g["values"] or not np.allclose(g["values"][f], values[k], rtol=RTOL, atol=ATOL, equal_nan=True):
            return False
    return True


def _write(got: dict, names, add_variant: bool) -> None:
    stored = json.loads(REF.read_text()) if REF.exists() and (names or add_variant) else {}
    for name, g in got.items():
        old = _variants(stored[name]) if add_variant and name in stored else []
        stored[name] = old + [_record(g)] if not any(_matches(r, g) for r in old) else old
    REF.write_text(json.dumps(stored, indent=1, sort_keys=True) + "\n")
    vals = dict(np.load(VALUES)) if VALUES.exists() else {}
    for name, g in got.items():
        vals = {k: v for k, v in vals.items() if not k.startswith(name + "/")}
        if "oracle" not in name:  # the oracle's float64 elementwise maths rounds alike on every CPU
            vals.update({f"{name}/{k}": v for k, v in g["values"].items()})
    np.savez_compressed(VALUES, **vals)
    print(f"wrote {REF} ({len(got)} cases recorded, {len(stored)} in all) and {VALUES.name}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="store the reference instead of checking it")
    ap.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    ap.add_argument("--add-variant", action="store_true",
                    help="with --write semantics: add this machine's bits beside the recorded variants")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    names = [c for c in a.cases.split(",") if c]
    got = {name: fly_case(p, e, s, o) for name, p, e, s, o in CASES if not names or name in names}
    if a.write or a.add_variant:
        _write(got, names, a.add_variant)
        return 0
    ref = json.loads(REF.read_text())
    values = np.load(VALUES) if VALUES.exists() else None
    bad = 0
    for name, g in got.items():
        if any(_matches(r, g) for r in _variants(ref[name])):
            print(f"{name}: identical")
        elif _close(name, g, values) and all(json.loads(json.dumps(g["runs"]))[i]["outcome"] == r["outcome"]
                                             for i, r in enumerate(_variants(ref[name])[0]["runs"])):
            print(f"{name}: close (no recorded variant bit for bit; within rtol={RTOL}, atol={ATOL}: "
                  "another CPU's rounding)")
        else:
            bad += 1
            diff = [k for k in _variants(ref[name])[0]["traces"]
                    if _variants(ref[name])[0]["traces"][k] != g["traces"].get(k)]
            print(f"{name}: differs (traces {diff})")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
