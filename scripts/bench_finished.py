#!/usr/bin/env python
"""What finished descents still cost on a CPU: the loop's step once most of the batch has ended.

    OMP_NUM_THREADS=1 python scripts/bench_finished.py --batch 36 --flying 4
    OMP_NUM_THREADS=1 python scripts/bench_finished.py --filter-only --batch 90 --steps 1500

Loop (default): ``montecarlo_efference`` with ``--estimator`` (default ``cmax``), the first B
descents of its layout flown ``--warmup`` steps; then all but ``--flying`` of them are marked ended
and the batch flies ``--settle`` more steps (the estimator's windows empty of the finished
descents' old events), and the process CPU ms per step are timed over ``--steps`` steps with the
efference filter's compaction (``efference_fit.CPU_COMPACT``) and the emulator's rows step
(``dvsland.sim.step.EMULATOR_ROWS_SHARE``) off and on, beside the step with every descent flying.

Filter only (``--filter-only``): the ``efference_fit`` filter alone over ``--steps`` steps of B
descents that end one after another (most between 50 and 80 % of the steps, one in 20 flies to the
end), compaction off and on: total CPU s and CPU ms per step over the last 20 % of the steps.
"""

from __future__ import annotations

import argparse
import time

import torch


def _cpu_ms(fn, n: int) -> float:
    c = time.process_time()
    for _ in range(n):
        fn()
    return 1e3 * (time.process_time() - c) / n


def bench_loop(a) -> None:
    import dvsland.control.efference_fit as fit
    import dvsland.sim.step as step
    from dvsland.config import load_config
    from dvsland.envs.layout import fit_layout
    from dvsland.sim import init_state, loop_step
    from dvsland.stages import build_stages

    cfg = load_config("montecarlo_efference", [f"estimator.name={a.estimator}", "render.threads=1"])
    stages = build_stages(cfg, fit_layout(cfg, None, a.batch), "cpu")
    state = init_state(stages)
    for _ in range(a.warmup):
        state, _ = loop_step(stages, state)
    act = torch.zeros(a.batch, dtype=torch.bool)
    act[torch.linspace(0, a.batch - 1, a.flying).round().long()] = True
    tail = state._replace(active=act & state.active)
    for _ in range(a.settle):
        tail, _ = loop_step(stages, tail)
        state, _ = loop_step(stages, state)

    def fly(st):
        def run():
            nonlocal st
            st, _ = loop_step(stages, st)
        return run

    print(f"B = {a.batch}, {a.estimator}, t = {float(state.step) * stages.settings.dt_s:.1f} s: every descent "
          f"flying {_cpu_ms(fly(state), a.steps):.1f} CPU ms/step")
    for share, compact in ((0.0, False), (0.0, True), (step.EMULATOR_ROWS_SHARE, True)):
        old = step.EMULATOR_ROWS_SHARE, fit.CPU_COMPACT
        step.EMULATOR_ROWS_SHARE, fit.CPU_COMPACT = share, compact
        try:
            ms = _cpu_ms(fly(tail), a.steps)
        finally:
            step.EMULATOR_ROWS_SHARE, fit.CPU_COMPACT = old
        print(f"  {int(tail.active.sum())} of {a.batch} flying, filter compaction {'on ' if compact else 'off'}, "
              f"emulator rows step {'on ' if share else 'off'}: {ms:.1f} CPU ms/step")


def bench_filter(a) -> None:
    import dvsland.control.efference_fit as fit
    from dvsland.control import EfferenceFitFilter

    B, K, dt = a.batch, a.steps, 0.1
    g = torch.Generator().manual_seed(0)
    z0 = 3000.0 + 2000.0 * torch.rand(B, generator=g, dtype=torch.float64)
    v0 = -(60.0 + 60.0 * torch.rand(B, generator=g, dtype=torch.float64))
    ends = (K * (0.5 + 0.3 * torch.rand(B, generator=g))).long()
    ends[: max(1, B // 20)] = K
    for compact in (False, True):
        fit.CPU_COMPACT = compact
        f = EfferenceFitFilter(z0, v0, dt)
        st, z, v = f.init_state(), z0 * 1.05, v0.clone()
        acc = torch.full((B,), 0.3, dtype=torch.float64)
        c0, tail = time.process_time(), 0.0
        for k in range(K):
            c1 = time.process_time()
            st, _ = f.step_state(st, v / z, ends > k, None if k == 0 else acc, None, None)
            if k >= int(0.8 * K):
                tail += time.process_time() - c1
            z, v = z + v * dt, v + acc * dt
        tail_ms = 1e3 * tail / (K - int(0.8 * K))
        print(f"efference_fit, B = {B}, {K} steps, compaction {'on ' if compact else 'off'}: "
              f"{time.process_time() - c0:.2f} CPU s, last 20 % of the steps {tail_ms:.2f} ms/step")
    fit.CPU_COMPACT = True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=36)
    ap.add_argument("--flying", type=int, default=4, help="descents left flying (loop)")
    ap.add_argument("--estimator", default="cmax")
    ap.add_argument("--warmup", type=int, default=150, help="steps flown before the descents end (loop)")
    ap.add_argument("--settle", type=int, default=80, help="steps flown after they end, before timing (loop)")
    ap.add_argument("--steps", type=int, default=20, help="timed steps (loop) / steps of the filter run")
    ap.add_argument("--filter-only", action="store_true")
    a = ap.parse_args(argv)
    if not 1 <= a.flying <= a.batch:
        raise SystemExit(f"--flying must be in [1, --batch = {a.batch}], got {a.flying}")
    torch.set_num_threads(1)
    (bench_filter if a.filter_only else bench_loop)(a)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
