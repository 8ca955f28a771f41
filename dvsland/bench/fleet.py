"""Whole descents per minute: a fleet of ``--descents`` descents through ``--batch`` slots.

    python -m dvsland.bench.fleet --device cuda --batch 8192 --descents 16384 --estimator learned
    python -m dvsland.bench.fleet --batch 18 --descents 36 --estimator oracle         # this CPU
    dvsland bench fleet [--device cuda] [--quick]                                      # into a bench run folder

:func:`dvsland.sim.fleet.fly_fleet` on the preset (``montecarlo_efference`` as shipped unless
``--set`` changes it): every slot restarts as soon as its descent ends, so no descent waits for its
batch-mates. Reported: set-up seconds (terrain, stages), the flight's wall time, whole descents per
minute over the whole flight (the first descents' start to the last one's end: ramp and tail
included) and in the steady part (from the first restart until the last descent has started: every
slot busy), steps, the outcome counts and the landings by site. One JSON line and a per-site table
(as a campaign's: success rate with its 95 % interval, lowest altitude, fuel) on stdout; ``--json``
writes the line to a file, ``--runs-csv`` one row per descent.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import torch


def run_fleet(estimator: str, batch_size: int, n_descents: int, device: str, preset: str = "montecarlo_efference",
              overrides: Sequence[str] = (), check_every: int = 4, max_steps=None,
              on_rows=None) -> Tuple[List[dict], Dict]:
    """One fleet: (its descents' rows (:func:`dvsland.sim.fleet.fleet_rows`), a dict of set-up,
    flight, descents per minute (whole and steady), outcomes and landings by site). ``on_rows(rows)``:
    called with each check's ended descents as rows, as they end."""
    from dvsland.config import load_config
    from dvsland.envs.layout import fit_layout
    from dvsland.report.stats import group_stats
    from dvsland.sim.fleet import fleet_rows, fly_fleet
    from dvsland.stages import build_stages

    t0 = time.perf_counter()
    cfg = load_config(preset, [f"estimator.name={estimator}", "render.threads=1", f"simulation.device={device}",
                               *overrides])
    stages = build_stages(cfg, fit_layout(cfg, None, batch_size), device)
    setup_s = time.perf_counter() - t0
    checks: List[tuple] = []
    t_fly = time.perf_counter()
    result = fly_fleet(stages, n_descents, check_every=check_every, max_steps=max_steps,
                       on_check=lambda step, ended, started: checks.append((time.perf_counter() - t_fly, step,
                                                                            ended, started)),
                       on_ended=None if on_rows is None else (lambda d: on_rows(fleet_rows(stages, d))))
    steady = steady_rate(checks, stages.batch_size, result.n_started)
    rows = fleet_rows(stages, result)
    B = stages.batch_size
    return rows, {"estimator": estimator, "B": B, "device": str(device), "descents": n_descents,
            "check_every": check_every, "setup_s": round(setup_s, 2), "wall_s": round(result.wall_s, 2),
            "steps": result.steps, "descent_steps_per_s": round(B * result.steps / max(result.wall_s, 1e-9)),
            "descents_per_min": round(result.descents_per_minute(), 1), "steady_descents_per_min": steady,
            "n_ended": result.n_ended, "complete": result.complete,
            "mean_flight_s": round(float(result.descents["t_end_s"].mean()), 2) if result.n_ended else None,
            "outcomes": result.outcome_counts(),
            "landed_by_site": {g["site"]: [g["n_success"], g["n"]] for g in group_stats(rows, ["site"])}}


def steady_rate(checks: Sequence[tuple], batch_size: int, n_started: int):
    """Descents ended per minute between the first restart and the check at which the last descent
    started (every slot busy); None when the fleet never restarted a slot. ``checks``: (wall s,
    step, ended, started) per check."""
    first = next((c for c in checks if c[3] > batch_size), None)
    last = next((c for c in checks if c[3] >= n_started), None)
    if first is None or last is None or last[0] <= first[0]:
        return None
    return round(60.0 * (last[2] - first[2]) / (last[0] - first[0]), 1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--batch", type=int, default=18, help="slots B")
    ap.add_argument("--descents", type=int, default=36, help="whole descents to fly")
    ap.add_argument("--estimator", default="learned")
    ap.add_argument("--preset", default="montecarlo_efference")
    ap.add_argument("--check-every", type=int, default=4, help="steps between checks for ended descents")
    ap.add_argument("--max-steps", type=int, default=None, help="stop after this many steps")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="config override (repeatable)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None, help="also write the row and the machine to this JSON file")
    ap.add_argument("--runs-csv", default=None, help="write one row per ended descent to this CSV file, as "
                    "they end (a fleet stopped half-way keeps what it flew)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    from dvsland.bench.throughput import machine
    from dvsland.report.stats import format_group_table, group_stats

    with RowsCsv(a.runs_csv) as out:
        runs, row = run_fleet(a.estimator, a.batch, a.descents, a.device, a.preset, a.overrides, a.check_every,
                              a.max_steps, on_rows=out.write if a.runs_csv else None)
    print(json.dumps(row), flush=True)
    by = ["site", "label", "estimator"]
    by_site = sorted(runs, key=lambda r: (r["site"], r["label"]))
    print(format_group_table(group_stats(by_site, by), by, markdown=True), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps({"machine": machine(), "rows": [row]}, indent=1) + "\n")
    return 0 if row["n_ended"] else 1


class RowsCsv:
    """A CSV file of dict rows written as they come (the header from the first rows; flushed after
    each write), or nothing when ``path`` is None."""

    def __init__(self, path):
        self.path, self.fh, self.writer = path, None, None

    def __enter__(self):
        if self.path:
            self.fh = open(self.path, "w", newline="")
        return self

    def write(self, rows) -> None:
        import csv

        if not rows or self.fh is None:
            return
        if self.writer is None:
            self.writer = csv.DictWriter(self.fh, fieldnames=list(rows[0]))
            self.writer.writeheader()
        self.writer.writerows(rows)
        self.fh.flush()

    def __exit__(self, *exc):
        if self.fh is not None:
            self.fh.close()
        return False


if __name__ == "__main__":
    raise SystemExit(main())
