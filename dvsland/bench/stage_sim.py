#!/usr/bin/env python
"""Where the simulator's time goes: per-stage timers of the closed loop, wall time, real-time factor.

    python scripts/profile_sim.py                         # paper experiment, fast + dpr
    python scripts/profile_sim.py --estimator oracle      # no rendering / events
    python scripts/profile_sim.py --sites A,D --set simulation.t_max_s=20 --cprofile 25

Stages: setup (renderer, emulator, estimator, run folder), render, emulate, estimate, control
(filter + Eq. 2), dynamics (exact step + termination), record (trace buffers), logging
(TensorBoard + progress), outputs (results.json, traces.npz), figures. With --device cuda the
stage timers synchronise the GPU (so they add up, at some cost).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import tempfile
import time

import torch


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("config", nargs="?", default=None, help="YAML config (default configs/paper.yaml)")
    p.add_argument("--estimator", default=None)
    p.add_argument("--renderer", default=None)
    p.add_argument("--sites", default=None)
    p.add_argument("--device", default=None)
    p.add_argument("--set", dest="overrides", action="append", default=[])
    p.add_argument("--figures", action="store_true", help="include PNG figures (off by default)")
    p.add_argument("--no-tensorboard", action="store_true")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    p.add_argument("--cprofile", type=int, default=0, metavar="N", help="also print the top N cProfile entries")
    p.add_argument("--json", default=None, help="write the numbers to this JSON file")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="keep the simulation's run folder here (default: a temporary folder, removed after)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    overrides = list(args.overrides)
    if not args.figures:
        overrides.append("logging.figures=false")
    if args.no_tensorboard:
        overrides.append("logging.tensorboard=false")
    tmp = None
    if args.out:
        out = args.out
    else:
        tmp = tempfile.TemporaryDirectory(prefix="dvsland-profile-")
        out = tmp.name
    try:
        return _profile(args, overrides, out)
    finally:
        if tmp is not None:
            tmp.cleanup()


def _profile(args, overrides, out) -> int:
    from dvsland.sim import simulate

    prof = cProfile.Profile() if args.cprofile else None
    t0 = time.perf_counter()
    if prof:
        prof.enable()
    r = simulate(args.config, estimator=args.estimator, renderer=args.renderer, sites=args.sites,
                 device=args.device, out=out, quiet=True, overrides=overrides,
                 sync_timers=(args.device or "").startswith("cuda"))
    if prof:
        prof.disable()
    total = time.perf_counter() - t0
    steps = max(r.n_steps, 1)
    tm = r.timings_s
    print(f"B = {len(r.runs)} descents, {r.n_steps} steps, estimator {r.runs[0]['estimator']}, "
          f"device {args.device or 'config'}, torch threads {torch.get_num_threads()}")
    print(f"wall {r.wall_time_s:.2f} s (call {total:.2f} s), descent-seconds {r.sim_time_s:.1f}, "
          f"real-time factor {r.real_time_factor:.1f}")
    print(f"{'stage':<10} {'seconds':>8} {'ms/step':>8} {'share':>6}")
    for k in ("setup", "render", "emulate", "estimate", "control", "dynamics", "record", "logging", "outputs",
              "figures"):
        if k in tm:
            share = tm[k] / r.wall_time_s if r.wall_time_s else 0.0
            print(f"{k:<10} {tm[k]:8.3f} {1e3 * tm[k] / steps:8.2f} {100 * share:5.1f}%")
    print("outcomes:", r.outcome_counts(), " run folder:", r.run_dir if args.out else "(temporary, removed)")
    if prof:
        pstats.Stats(prof, stream=sys.stdout).sort_stats("cumulative").print_stats(args.cprofile)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"wall_time_s": r.wall_time_s, "n_steps": r.n_steps, "sim_time_s": r.sim_time_s,
                       "real_time_factor": r.real_time_factor, "timings_s": tm, "outcomes": r.outcome_counts()},
                      f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
