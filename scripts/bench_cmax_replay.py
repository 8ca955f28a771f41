#!/usr/bin/env python
"""cmax's CPU cost per update on recorded closed-loop events, and its estimates on them.

``record`` flies ``montecarlo_efference`` with ``cmax`` (one torch thread, renderer threads 1, as
``dvsland bench campaign`` does) and stores every step's events, true altitude and velocity, and
the active mask in an ``.npz``. ``replay`` feeds those events to a fresh ``cmax`` (the configured
one, plus ``--set`` overrides) and prints the CPU ms per descent-step over the run and per sixth of
it (the phases of the descent), the global searches, and the median |relative error| against the
recorded truth; ``--out`` keeps the estimates, so two versions (or the compiled kernel and the
torch path, ``DVSLAND_NATIVE_CMAX=0``) can be compared on the very same events.

    python scripts/bench_cmax_replay.py record --seeds 7 --t-max 60 /tmp/rec_b63.npz
    python scripts/bench_cmax_replay.py replay /tmp/rec_b63.npz [--out est.npz] [--set estimator.cmax.KEY=VALUE]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch


def record(seeds: int, t_max: float, path: str) -> None:
    from dvsland.bench.campaign import campaign_overrides
    from dvsland.config import load_config
    from dvsland.sim.step import init_state, loop_step
    from dvsland.stages import build_stages

    cfg = load_config("montecarlo_efference", campaign_overrides("cmax", seeds, t_max, True))
    st = build_stages(cfg)
    s = init_state(st)
    fields = {k: [] for k in "bxytp"}
    steps, z, v, act = [], [], [], []
    c0 = time.process_time()
    while not s.done and s.step < st.settings.n_steps_max:
        s, o = loop_step(st, s)
        ev = o.events
        n = 0 if ev is None else len(ev)
        if n:
            for k, dt in zip("bxytp", (torch.int16, torch.int16, torch.int16, torch.int64, torch.int8)):
                fields[k].append(getattr(ev, k).to(dt).numpy())
        steps.append((o.t_us, n))
        z.append(o.z_m.numpy())
        v.append(o.v_mps.numpy())
        act.append(o.active.numpy())
    print(f"recorded B = {st.batch_size}, {len(steps)} steps, {sum(n for _, n in steps)} events, "
          f"{time.process_time() - c0:.1f} s CPU")
    np.savez(path, **{k: np.concatenate(f) for k, f in fields.items()}, steps=np.array(steps), z=np.array(z),
             v=np.array(v), active=np.array(act), B=st.batch_size)


def replay(path: str, overrides, out: str = "", max_steps: int = 0) -> None:
    from dvsland.config import load_config
    from dvsland.estimators import Truth, make_estimator
    from dvsland.events import Events

    r = np.load(path)
    B, steps = int(r["B"]), r["steps"]
    ns = len(steps) if not max_steps else min(max_steps, len(steps))
    est = make_estimator(load_config("montecarlo_efference", ["estimator.name=cmax", *overrides]), B, name="cmax")
    off = np.concatenate([[0], np.cumsum(steps[:, 1])])
    f = {k: torch.from_numpy(r[k]) for k in "bxytp"}
    d = np.full((ns, B), np.nan)
    cpu, glob = np.zeros(ns), np.zeros(ns)
    for k in range(1, ns):
        i0, i1 = off[k], off[k + 1]
        ev = None if i1 == i0 else Events(f["b"][i0:i1].long(), f["x"][i0:i1].long(), f["y"][i0:i1].long(),
                                          f["t"][i0:i1], f["p"][i0:i1])
        truth = Truth(torch.from_numpy(r["z"][k]), torch.from_numpy(r["v"][k]))
        c0 = time.process_time()
        d[k] = est.update(ev, int(steps[k, 0]), truth=truth).numpy()
        cpu[k] = time.process_time() - c0
        glob[k] = float(est.diagnostics()["global_search"].sum())
    print(f"B = {B}, {ns} steps: cmax {cpu.sum():.2f} s CPU, {1e3 * cpu.sum() / (ns * B):.3f} ms per descent-step; "
          f"{glob.sum():.0f} global searches")
    part = max(ns // 6, 1)
    for q in range(0, ns, part):
        sl = slice(q, q + part)
        print(f"  steps {q:5d}+: {1e3 * cpu[sl].sum() / (B * len(cpu[sl])):.3f} ms per descent-step, "
              f"{glob[sl].sum():.0f} global searches")
    act = r["active"][:ns]
    dtrue = r["v"][:ns] / r["z"][:ns]
    rel = np.abs(d - dtrue) / np.abs(dtrue)
    ok = np.isfinite(rel) & act
    print(f"  median |rel err| {100 * np.median(rel[ok]):.2f} % over {ok.sum()} estimates, "
          f"no estimate {100 * np.mean(~np.isfinite(d[act])):.1f} % of the flying steps")
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if out:
        np.savez(out, d=d, cpu=cpu, glob=glob)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a_rec = sub.add_parser("record")
    a_rec.add_argument("path")
    a_rec.add_argument("--seeds", type=int, default=7)
    a_rec.add_argument("--t-max", type=float, default=60.0)
    a_rep = sub.add_parser("replay")
    a_rep.add_argument("path")
    a_rep.add_argument("--out", default="")
    a_rep.add_argument("--max-steps", type=int, default=0)
    a_rep.add_argument("--set", action="append", default=[], dest="overrides")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.cmd == "record":
        record(a.seeds, a.t_max, a.path)
    else:
        replay(a.path, a.overrides, a.out, a.max_steps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
