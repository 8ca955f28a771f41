#!/usr/bin/env python
"""Where one batched step's device time goes: torch.profiler over a few ``loop_step`` calls.

    python scripts/gpu_profile_step.py --device cuda --batch 4608 --estimator learned --steps 3

Prints the operators sorted by device time (self), then by CPU time, for the ``montecarlo_efference``
preset with the terrain variants and the sun fixed (short set-up). Meant for a lent GPU machine;
it runs on the CPU as well.
"""

from __future__ import annotations

import argparse

import torch
from torch.profiler import ProfilerActivity, profile


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--batch", type=int, default=576)
    ap.add_argument("--estimator", default="learned")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--rows", type=int, default=30)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    from dvsland.config import load_config
    from dvsland.envs.layout import fit_layout
    from dvsland.sim import init_state, loop_step
    from dvsland.stages import build_stages

    cfg = load_config("montecarlo_efference", [f"estimator.name={a.estimator}", "render.threads=1",
                                               f"simulation.device={a.device}", "dispersion.terrain_variants=1",
                                               'dispersion.sun_elevation_deg={kind: "off"}'])
    stages = build_stages(cfg, fit_layout(cfg, None, a.batch), a.device)
    state = init_state(stages)
    for _ in range(3):
        state, _ = loop_step(stages, state)
    cuda = torch.device(a.device).type == "cuda"
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts) as prof:
        for _ in range(a.steps):
            state, _ = loop_step(stages, state)
        if cuda:
            torch.cuda.synchronize()
    ka = prof.key_averages()
    if cuda:
        print(ka.table(sort_by="self_cuda_time_total", row_limit=a.rows))
    print(ka.table(sort_by="self_cpu_time_total", row_limit=a.rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
