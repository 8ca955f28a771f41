#!/usr/bin/env python
"""Where one batched step's device time goes: torch.profiler over a few ``loop_step`` calls.

    python scripts/gpu_profile_step.py --device cuda --batch 4608 --estimator learned --steps 3

Prints the operators sorted by device time (self), then by CPU time, for the ``montecarlo_efference``
preset (``--preset``) with the terrain variants and the sun fixed (short set-up). With ``--lines N`` it also prints
the N dvsland functions that cost the most (self device time, self CPU time and operator calls
per step, each operator charged to the innermost dvsland function that called it), and the step's wall
time against its device time: a step whose wall time is well above its device time is bound by the
host (Python, launches, syncs). Meant for a lent GPU machine; it runs on the CPU as well.
"""

from __future__ import annotations

import argparse
import time

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile


def _top_level_op(ev) -> bool:
    """Whether ``ev`` is an operator called from Python (not one run inside another operator)."""
    return ev.name.startswith("aten::") and not (ev.cpu_parent and ev.cpu_parent.name.startswith("aten::"))


def by_line(events, steps: int, rows: int) -> str:
    """A table of the ``rows`` dvsland functions with the most self device (else CPU) time.

    Every profiled event (an operator, or a Python function's own time) is charged to the innermost
    dvsland function that encloses it; "ops" counts the top-level operators (one launch or more each)."""
    acc = {}
    for ev in events:
        owner = ev
        while owner is not None and "dvsland/" not in owner.name:
            owner = owner.cpu_parent
        line = owner.name if owner is not None else next((f for f in ev.stack or [] if "dvsland/" in f), None)
        if line is None:
            continue
        line = line.split("dvsland/", 1)[1]
        dev_us, cpu_us, n = acc.get(line, (0.0, 0.0, 0))
        acc[line] = (dev_us + ev.self_device_time_total, cpu_us + ev.self_cpu_time_total, n + _top_level_op(ev))
    top = sorted(acc.items(), key=lambda kv: (kv[1][0], kv[1][1]), reverse=True)[:rows]
    out = ["| dvsland function | device ms/step | CPU ms/step (self) | operators/step |", "|---|---|---|---|"]
    out += [f"| {k} | {d / 1e3 / steps:.3f} | {c / 1e3 / steps:.3f} | {n / steps:.0f} |" for k, (d, c, n) in top]
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--batch", type=int, default=576)
    ap.add_argument("--estimator", default="learned")
    ap.add_argument("--preset", default="montecarlo_efference")
    ap.add_argument("--skip", type=int, default=3, help="steps flown before the timed ones")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--rows", type=int, default=30)
    ap.add_argument("--lines", type=int, default=0, help="also print the N costliest dvsland functions")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    from dvsland.config import load_config
    from dvsland.envs.layout import fit_layout
    from dvsland.sim import init_state, loop_step
    from dvsland.stages import build_stages

    cfg = load_config(a.preset, [f"estimator.name={a.estimator}", "render.threads=1", f"simulation.device={a.device}",
                                 "dispersion.terrain_variants=1", 'dispersion.sun_elevation_deg={kind: "off"}'])
    stages = build_stages(cfg, fit_layout(cfg, None, a.batch), a.device)
    state = init_state(stages)
    for _ in range(a.skip):
        state, _ = loop_step(stages, state)
    cuda = torch.device(a.device).type == "cuda"
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(a.steps):
        state, _ = loop_step(stages, state)
    sync()
    wall_ms = (time.perf_counter() - t0) * 1e3 / a.steps
    verbose = torch._C._profiler._ExperimentalConfig(verbose=True) if a.lines else None  # stacks on operators
    with profile(activities=acts, with_stack=a.lines > 0, experimental_config=verbose) as prof:
        for _ in range(a.steps):
            state, _ = loop_step(stages, state)
        sync()
    ka = prof.key_averages()
    dev_ms = sum(e.self_device_time_total for e in prof.events() if e.device_type != DeviceType.CPU) / 1e3 / a.steps
    n_ops = sum(_top_level_op(ev) for ev in prof.events())
    print(f"B = {stages.batch_size}, {a.estimator}: wall {wall_ms:.2f} ms per step unprofiled, device time "
          f"{dev_ms:.2f} ms per step, {n_ops / a.steps:.0f} top-level operator calls per step")
    if a.lines:
        print(by_line(prof.events(), a.steps, a.lines))
    if cuda:
        print(ka.table(sort_by="self_cuda_time_total", row_limit=a.rows))
    print(ka.table(sort_by="self_cpu_time_total", row_limit=a.rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
