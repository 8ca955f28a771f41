"""Scaling: time per control step of each stage and peak memory against the batch size B."""

from __future__ import annotations

from typing import Dict, List, Sequence

from dvsland.config import Config

from .stages import STAGE_NAMES, peak_memory_subprocess, time_stages

BATCHES_FULL = (1, 18, 64, 256, 1024)
BATCHES_QUICK = (1, 18, 64, 256, 1024)
#: batch sizes whose CPU peak memory is measured (a fresh process each, about 10 s)
MEMORY_QUICK = (1, 256)


def run_scaling(cfg: Config, batches: Sequence[int], device="cpu", estimator: str = "dpr", quick: bool = True,
                log=print, memory_batches: Sequence[int] = None, config_name: str = "") -> List[Dict]:
    """:func:`time_stages` for each B (one renderer shared by all B); CPU peak memory of a fresh
    process (:func:`peak_memory_subprocess`) for ``memory_batches`` (default: all)."""
    memory_batches = batches if memory_batches is None else memory_batches
    from dvsland.render import get_renderer

    sites = [s.name for s in cfg.simulation.sites]
    renderer = get_renderer(cfg.render.renderer, sites, cfg.camera, cfg.render, device=device)
    rows = []
    for b in batches:
        big = b >= 256
        n_steps, warmup = ((1, 1) if big else (4, 2)) if quick else ((4, 2) if big else (10, 3))
        fr = (0.5,) if quick else (0.3, 0.8)
        r = time_stages(cfg, b, device, estimator, n_steps=n_steps, warmup=warmup, fractions=fr, renderer=renderer)
        if str(device) == "cpu" and b in memory_batches:
            m = peak_memory_subprocess(b, estimator, config_name)
            r["memory_process"] = m
            r["peak_memory_mib"] = m.get("growth_mib")
        rows.append(r)
        mem = r["peak_memory_mib"]
        log(f"  B = {b:>5}: " + ", ".join(f"{k} {r['cpu_ms'][k]:.1f}" for k in STAGE_NAMES)
            + f" CPU ms; total {r['cpu_ms_total']:.1f} CPU ms, {r['ms_total']:.1f} wall ms; "
            + (f"peak memory +{mem:.0f} MiB" if mem is not None else "peak memory n/a"))
    return rows
