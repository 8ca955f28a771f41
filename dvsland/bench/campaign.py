"""What a campaign costs: one batch of a named preset and estimator, set-up and every stage timed.

``dvsland bench campaign`` flies ``simulation.n_seeds`` seeds of every configured site and
controller setting of a preset as one batch (one process, as one campaign shard), with the
estimator given, and reports:

- set-up (build the stages: terrain and scene preparation, atlas, estimator) in wall and CPU
  seconds per descent, and where the scenes came from (computed, disk or memory cache);
- CPU ms per descent-step of each stage of :func:`dvsland.sim.loop_step` (a descent-step is one
  control step of one descent of the batch, flying or finished, so the figure includes what finished
  descents still cost) and per flying descent-step;
- descents per CPU-minute (set-up included) and the outcomes.

CPU time is the process's (``time.process_time``): on a shared machine it is close to the cost a
stage would have alone, where wall time also counts waiting for a core. The machine, torch threads
and load average go with every figure.
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Dict, Optional, Sequence

import torch

from dvsland.config import load_config

from .machine import load_average

#: the loop's stages in the order of the report (sim.loop.STAGES without logging)
LOOP_STAGES = ("render", "emulate", "estimate", "control", "dynamics", "record")


def campaign_overrides(estimator: str, n_seeds: int, t_max_s: Optional[float], compact: bool) -> list:
    """The ``--set`` strings of one measured batch: estimator, seeds, timeout, compaction, no outputs."""
    over = [f"estimator.name={estimator}", f"simulation.n_seeds={int(n_seeds)}", "render.threads=1",
            f"simulation.compact={'true' if compact else 'false'}", "logging.tensorboard=false",
            "logging.figures=false", "logging.quiet=true"]
    if t_max_s is not None:
        over.append(f"simulation.t_max_s={float(t_max_s)}")
    return over


def bench_campaign(preset: str = "montecarlo_efference", estimator: str = "cmax", n_seeds: int = 1,
                   t_max_s: Optional[float] = None, sites: Optional[Sequence[str]] = None, device="cpu",
                   overrides: Sequence[str] = (), compact: bool = True, log=print) -> Dict:
    """Fly one batch (``n_seeds`` seeds x sites x settings of ``preset``) and time it.

    Args:
        preset: config name or path.  estimator: a registered estimator name.
        n_seeds: seeds per site and setting, >= 1.  t_max_s: timeout, s (None: the preset's).
        sites: a subset of the preset's sites (None: all).  device: torch device.
        overrides: further ``section.key=value`` strings.  compact: ``simulation.compact``.

    Returns:
        dict: preset, estimator, batch_size, n_steps, descent_steps (steps x B), flying_steps,
        setup_wall_s, setup_cpu_s, scene_sources {source: count}, stage_cpu_s, stage_wall_s,
        cpu_ms_per_descent_step {stage: ms, "total": ms}, cpu_ms_per_flying_step, loop_wall_s,
        loop_cpu_s, descents_per_cpu_min, outcomes, load_average_start/_end, torch_threads.

    Raises:
        ValueError: ``n_seeds`` < 1 or ``t_max_s`` <= 0 (names the parameter).
    """
    from dvsland.sim.loop import ClosedLoop
    from dvsland.stages import build_stages

    if int(n_seeds) < 1:
        raise ValueError(f"n_seeds must be >= 1, got {n_seeds}")
    if t_max_s is not None and not float(t_max_s) > 0:
        raise ValueError(f"t_max_s must be > 0 s, got {t_max_s}")
    cfg = load_config(preset, [*campaign_overrides(estimator, n_seeds, t_max_s, compact), *overrides])
    load0 = load_average()
    t0, c0 = time.perf_counter(), time.process_time()
    stages = build_stages(cfg, list(sites) if sites else None, device)
    setup_wall, setup_cpu = time.perf_counter() - t0, time.process_time() - c0
    B = stages.batch_size
    log(f"  {preset} + {estimator}: B = {B}, set-up {setup_wall:.1f} s wall, {setup_cpu:.1f} s CPU")
    loop = ClosedLoop(stages)
    t1, c1 = time.perf_counter(), time.process_time()
    loop.run()
    loop_wall, loop_cpu = time.perf_counter() - t1, time.process_time() - c1
    return _summary(preset, estimator, stages, loop, dict(
        setup_wall_s=setup_wall, setup_cpu_s=setup_cpu, loop_wall_s=loop_wall, loop_cpu_s=loop_cpu,
        load_average_start=load0, load_average_end=load_average(), compact=bool(compact)))


def _summary(preset, estimator, stages, loop, extra: dict) -> Dict:
    B, steps = stages.batch_size, loop.step_index
    descent_steps = max(steps * B, 1)
    flying = int(loop.traces.flags["active"][:steps].sum()) or 1
    cpu = {k: float(loop.timer.cpu_seconds.get(k, 0.0)) for k in LOOP_STAGES}
    wall = {k: float(loop.timer.seconds.get(k, 0.0)) for k in LOOP_STAGES}
    per = {k: 1e3 * v / descent_steps for k, v in cpu.items()}
    per["total"] = 1e3 * sum(cpu.values()) / descent_steps
    renderer = stages.renderer
    sources = dict(Counter(getattr(renderer, "sources", {}).values())) if renderer is not None else {}
    total_cpu = extra["setup_cpu_s"] + extra["loop_cpu_s"]
    out = dict(preset=str(preset), estimator=str(estimator), batch_size=B, n_steps=steps,
               t_max_s=float(stages.settings.t_max_s), descent_steps=steps * B, flying_steps=flying,
               scene_sources=sources, stage_cpu_s=cpu, stage_wall_s=wall, cpu_ms_per_descent_step=per,
               cpu_ms_per_flying_step=1e3 * sum(cpu.values()) / flying,
               setup_cpu_s_per_descent=extra["setup_cpu_s"] / B, setup_wall_s_per_descent=extra["setup_wall_s"] / B,
               descents_per_cpu_min=60.0 * B / total_cpu if total_cpu > 0 else float("inf"),
               outcomes=dict(Counter(r["outcome"] for r in loop.summaries())),
               torch_threads=torch.get_num_threads(), **extra)
    return out


def campaign_lines(rows: Sequence[Dict]) -> list:
    """Markdown lines of the campaign part (one table row per measured batch)."""
    lines = ["| preset + estimator | B | t_max s | steps | set-up CPU s / descent (wall) | scenes "
             "| " + " | ".join(LOOP_STAGES) + " | CPU ms / descent-step | per flying step | descents / CPU-min "
             "| outcomes | load start / end |",
             "|---" * (len(LOOP_STAGES) + 11) + "|"]
    for r in rows:
        if r.get("failed"):
            lines.append(f"| {r.get('preset')} + {r.get('estimator')} | failed: {r['failed']} |"
                         + " |" * (len(LOOP_STAGES) + 9))
            continue
        per = r["cpu_ms_per_descent_step"]
        src = ", ".join(f"{k} {v}" for k, v in sorted(r["scene_sources"].items())) or "-"
        oc = ", ".join(f"{k} {v}" for k, v in sorted(r["outcomes"].items()))
        lines.append(f"| {r['preset']} + {r['estimator']}{'' if r.get('compact', True) else ' (compact off)'} "
                     f"| {r['batch_size']} | {r['t_max_s']:g} | {r['n_steps']} "
                     f"| {r['setup_cpu_s_per_descent']:.3f} ({r['setup_wall_s_per_descent']:.3f}) | {src} | "
                     + " | ".join(f"{per[k]:.3f}" for k in LOOP_STAGES)
                     + f" | **{per['total']:.3f}** | {r['cpu_ms_per_flying_step']:.3f} | {r['descents_per_cpu_min']:.1f} "
                     f"| {oc} | {r['load_average_start']} / {r['load_average_end']} |")
    return lines
