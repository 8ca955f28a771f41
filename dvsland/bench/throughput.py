"""Throughput of the batched loop: descent-steps per second and per stage against the batch size.

    python -m dvsland.bench.throughput --device cuda --batches 576,2304,4608 --estimators learned,cmax
    python -m dvsland.bench.throughput --batches 18,63 --steps 20          # this CPU
    dvsland bench throughput [--device cuda] [--quick]                     # the same, into a bench run folder

For each (estimator, B): the ``montecarlo_efference`` preset as shipped (every dispersion on), the
first B elements of its layout in seed-major order; set-up (terrain, stages, first state) is timed
apart; then ``--warmup`` steps and ``--steps`` timed steps of ``loop_step`` from t = 0, each stage
timed (synchronised on CUDA), and the host syncs of one more step counted
(:mod:`dvsland.bench.syncs`). One JSON line per case on stdout, and a markdown table with the
machine and load in ``--out`` (``throughput.md``, ``throughput.json``). Meant to finish within a
few minutes on a lent GPU machine with the default batches.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path
from typing import Dict, List, Sequence

import torch

STAGE_KEYS = ("render", "emulate", "estimate", "control", "dynamics")


def run_case(estimator: str, batch_size: int, device: str, steps: int, warmup: int, preset: str,
             overrides=()) -> Dict:
    """One (estimator, B) case: set-up seconds, descent-steps/s, ms per step by stage, syncs/step."""
    from dvsland.bench.syncs import SyncCounter
    from dvsland.config import load_config
    from dvsland.config.validate import estimate_run_bytes
    from dvsland.envs.layout import fit_layout
    from dvsland.sim import init_state, loop_step
    from dvsland.sim.loop import StageTimer
    from dvsland.stages import build_stages

    t0 = time.perf_counter()
    cfg = load_config(preset, [f"estimator.name={estimator}", "render.threads=1", f"simulation.device={device}",
                               *overrides])
    layout = fit_layout(cfg, None, batch_size)
    stages = build_stages(cfg, layout, device)
    state = init_state(stages)
    cuda = torch.device(device).type == "cuda"
    for _ in range(warmup):
        state, _ = loop_step(stages, state)
    _sync(cuda)
    setup_s = time.perf_counter() - t0
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    # the throughput: plain steps, one synchronisation at the end
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        state, _ = loop_step(stages, state)
    _sync(cuda)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    # the stages: a few more steps, each stage synchronised (slower on a GPU: the stages cannot overlap)
    n_timed = max(1, min(steps, 5))
    timer = StageTimer(device, sync=True)
    for _ in range(n_timed):
        state, _ = loop_step(stages, state, timer=timer)
    _sync(cuda)
    with SyncCounter() as sc:
        state, _ = loop_step(stages, state)
    calls = python_calls(lambda: loop_step(stages, state), 2)
    B = stages.batch_size
    row = {"estimator": estimator, "B": B, "device": str(device), "setup_s": round(setup_s, 2), "steps": steps,
           "descent_steps_per_s": round(B * steps / wall), "wall_ms_per_step": round(1e3 * wall / steps, 2),
           "cpu_ms_per_step": round(1e3 * cpu / steps, 2),
           "us_per_descent_step": round(1e6 * wall / (steps * B), 3),
           "stage_ms": {k: round(1e3 * timer.seconds.get(k, 0.0) / n_timed, 2) for k in STAGE_KEYS},
           "syncs_per_step": sc.total, "syncs_by_call": dict(sorted(sc.calls.items())), "calls_per_step": calls,
           "active": int(state.active.sum()),
           "memory_estimate_gib": round(estimate_run_bytes(cfg, batch_size=B) / 2 ** 30, 2)}
    if cuda:
        row["peak_memory_gib"] = round(torch.cuda.max_memory_allocated() / 2 ** 30, 2)
    return row


def run_env_case(batch_size: int, device: str, steps: int, preset: str, overrides=(),
                 observation: str = "events") -> Dict:
    """The gymnasium vector env with ``array_api="torch"`` on ``device`` (oracle estimator, random
    thrust in the action space): env-steps per second over ``steps`` steps after two warm-up steps."""
    from dvsland.envs import LandingVectorEnv

    t0 = time.perf_counter()
    env = LandingVectorEnv(num_envs=batch_size, config=preset, estimator="oracle", observation=observation,
                           device=device, overrides=["render.threads=1", *overrides], array_api="torch")
    env.reset(seed=0)
    lo = torch.as_tensor(env.action_space.low, dtype=torch.float32, device=device)
    hi = torch.as_tensor(env.action_space.high, dtype=torch.float32, device=device)
    gen = torch.Generator(device=device).manual_seed(0)

    def act():
        return lo + (hi - lo) * torch.rand(lo.shape, generator=gen, device=device)

    cuda = torch.device(device).type == "cuda"
    for _ in range(2):
        env.step(act())
    _sync(cuda)
    setup_s = time.perf_counter() - t0
    w0 = time.perf_counter()
    for _ in range(steps):
        env.step(act())
    _sync(cuda)
    wall = time.perf_counter() - w0
    env.close()
    return {"env": observation, "B": env.num_envs, "device": str(device), "setup_s": round(setup_s, 2),
            "steps": steps, "env_steps_per_s": round(env.num_envs * steps / wall),
            "wall_ms_per_step": round(1e3 * wall / steps, 2)}


def python_calls(step, n: int) -> float:
    """Function calls per call of ``step`` (Python functions and the C functions they call, as
    cProfile counts them: torch operators included) over ``n`` calls; the state is not advanced
    (``step``'s results are dropped)."""
    import cProfile
    import pstats

    prof = cProfile.Profile()
    prof.enable()
    for _ in range(n):
        step()
    prof.disable()
    return round(pstats.Stats(prof).total_calls / n, 1)


def _sync(cuda: bool) -> None:
    if cuda:
        torch.cuda.synchronize()


def machine() -> Dict:
    """What ran it: CPU, cores, load, torch, device name."""
    m = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
         "load_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
         "torch": torch.__version__, "threads": torch.get_num_threads()}
    if torch.cuda.is_available():
        m["gpu"] = torch.cuda.get_device_name(0)
    return m


def table(rows: List[Dict], info: Dict, env_rows: Sequence[Dict] = ()) -> str:
    """The markdown tables of ``rows`` (and ``env_rows``) with the machine line."""
    head = ("| estimator | B | device | set-up s | descent-steps/s | µs per descent-step | render | emulate | "
            "estimate | control | dynamics | syncs/step | calls/step | memory GiB (estimate) |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    body = "".join(f"| {r['estimator']} | {r['B']} | {r['device']} | {r['setup_s']} | {r['descent_steps_per_s']:,} | "
                   f"{r['us_per_descent_step']} | " + " | ".join(f"{r['stage_ms'][k]}" for k in STAGE_KEYS)
                   + f" | {r['syncs_per_step']} | {r.get('calls_per_step', '–')} | "
                     f"{r.get('peak_memory_gib', '–')} ({r.get('memory_estimate_gib', '–')}) |\n"
                   for r in rows)
    text = (f"Machine: {json.dumps(info)}; descent-steps/s from plain steps; stage columns in ms per step, "
            "each stage synchronised.\n\n" + head + body)
    if env_rows:
        text += ("\n| env observation | num_envs | device | set-up s | env-steps/s | ms per step |\n|---|---|---|---|---|---|\n"
                 + "".join(f"| {r['env']} | {r['B']} | {r['device']} | {r['setup_s']} | {r['env_steps_per_s']:,} | "
                           f"{r['wall_ms_per_step']} |\n" for r in env_rows))
    return text


def main(argv=None) -> int:
    if argv is None:  # run as a program: keep freed memory as the dvsland command does
        from dvsland.allocator import tune_allocator

        tune_allocator()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--batches", default="18,63", help="comma-separated batch sizes")
    ap.add_argument("--estimators", default="learned,cmax,oracle")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--preset", default="montecarlo_efference")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="config override (repeatable)")
    ap.add_argument("--env-batches", default="", help="also time the torch-API vector env at these num_envs")
    ap.add_argument("--env-steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None, help="folder for throughput.json and throughput.md")
    ap.add_argument("--json", default=None, help="also write the rows and the machine to this JSON file")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    rows = []
    for est in a.estimators.split(","):
        for b in (int(x) for x in a.batches.split(",")):
            r = run_case(est, b, a.device, a.steps, a.warmup, a.preset, a.overrides)
            print(json.dumps(r), flush=True)
            rows.append(r)
    env_rows = []
    for b in (int(x) for x in a.env_batches.split(",") if x):
        r = run_env_case(b, a.device, a.env_steps, a.preset, a.overrides)
        print(json.dumps(r), flush=True)
        env_rows.append(r)
    info = machine()
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "throughput.json").write_text(json.dumps({"machine": info, "rows": rows, "env_rows": env_rows}, indent=1) + "\n")
        (out / "throughput.md").write_text(table(rows, info, env_rows))
    if a.json:
        Path(a.json).write_text(json.dumps({"machine": info, "rows": rows, "env_rows": env_rows}, indent=1) + "\n")
    print(table(rows, info, env_rows))
    return 0 if all(math.isfinite(r["descent_steps_per_s"]) for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
