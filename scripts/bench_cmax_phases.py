#!/usr/bin/env python
"""cmax's cost per update early (high altitude) and late (low altitude) in the descent.

Records the events of the evaluation descents of sites A-I (closed form, the configured renderer and
emulator) over the first and the last ``--steps`` steps of each site's descent, replicates them to
the batch size B (element b + 9 k sees site b's events), and times ``cmax.update`` over each phase
on one torch thread: wall and CPU ms per update, from a fresh estimator (the early phase includes
the first global searches and the long windows of 10 km; the late one warms up on its first
``--warmup`` steps, not timed). Prints the load average at the end.

    python scripts/bench_cmax_phases.py --batch 18,63 [--set estimator.cmax.KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch


def record(cfg, steps: int):
    """{phase: [Events (B=9) per step]} for 'early' (first steps) and 'late' (last steps)."""
    from dvsland.evaluate import closed_form_descents
    from dvsland.stages import build_event_source

    desc = closed_form_descents(cfg)
    src = build_event_source(cfg, desc.sites)
    dt_us = int(round(cfg.dt_s * 1e6))
    last = desc.valid.sum(1) - 1  # each site's last valid step
    out = {}
    for phase in ("early", "late"):
        k0 = np.zeros_like(last) if phase == "early" else last - steps
        site = torch.arange(len(desc.sites))
        alt = lambda j: torch.as_tensor(desc.altitude_m[np.arange(len(last)), k0 + j])  # noqa: E731
        src.reset(alt(0), site, 0)
        out[phase] = [src.step(alt(j), site, j * dt_us)[1] for j in range(1, steps + 1)]
    return out


def tile(ev, reps: int, n_sites: int):
    from dvsland.events import Events

    if reps == 1:
        return ev
    b = torch.cat([ev.b + k * n_sites for k in range(reps)])
    cat = lambda f: torch.cat([getattr(ev, f)] * reps)  # noqa: E731
    return Events(b, cat("x"), cat("y"), cat("t"), cat("p"), sort=True)


def time_phase(cfg, events, batch: int, warmup: int):
    from dvsland.estimators import make_estimator

    est = make_estimator(cfg, batch, name="cmax")
    dt_us = int(round(cfg.dt_s * 1e6))
    wall, cpu = [], []
    for j, ev in enumerate(events, start=1):
        t0, c0 = time.perf_counter(), time.process_time()
        est.update(ev, j * dt_us)
        if j > warmup:
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    return 1e3 * float(np.mean(wall)), 1e3 * float(np.mean(cpu))


def main(argv=None) -> int:
    from dvsland.config import load_config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", nargs="?", default="paper_eq2")
    ap.add_argument("--batch", default="18,63")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--warmup", type=int, default=30, help="untimed first updates of the late phase")
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    ap.add_argument("--json", default="")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = load_config(a.config, ["render.threads=1", *a.overrides])
    rec = record(cfg, a.steps)
    rows = []
    for B in [int(x) for x in a.batch.split(",")]:
        reps = -(-B // 9)
        for phase, evs in rec.items():
            evs_b = [tile(e, reps, 9) for e in evs]
            evs_b = [_keep(e, B) for e in evs_b]
            w, c = time_phase(cfg, evs_b, B, a.warmup if phase == "late" else 0)
            rows.append(dict(batch=B, phase=phase, wall_ms=w, cpu_ms=c))
            print(f"B={B:3d} {phase:5s}: {w:7.2f} ms wall, {c:7.2f} ms CPU per update "
                  f"({c / B:.3f} ms CPU per descent-update)", flush=True)
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(dict(rows=rows, load=load, overrides=a.overrides), f, indent=1)
    return 0


def _keep(ev, B: int):
    from dvsland.events import Events

    m = ev.b < B
    return Events(ev.b[m], ev.x[m], ev.y[m], ev.t[m], ev.p[m], sort=True)


if __name__ == "__main__":
    raise SystemExit(main())
