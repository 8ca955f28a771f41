"""``dvsland.simulate(config)``: fly the configured experiment as one batch and write its outputs."""

from __future__ import annotations

import copy
import platform
import sys
import time
from pathlib import Path
from typing import Optional, Sequence, Union

import torch

from dvsland._version import __version__
from dvsland.config import Config, dump_config, load_config
from dvsland.report import format_table, write_results_json, write_traces_npz
from dvsland.runs import make_run_dir
from dvsland.stages import build_stages, check_names

from .batch import build_layout
from .loop import ClosedLoop
from .result import SimulationResult

PathLike = Union[str, Path]


def _resolve_config(config, estimator, renderer, device, quiet, overrides) -> Config:
    if isinstance(config, Config):
        cfg = copy.deepcopy(config)
        if overrides:
            raise ValueError("overrides apply to a config file; edit the Config object instead")
    elif config is None or isinstance(config, (str, Path)):
        cfg = load_config(config, overrides or ())
    else:
        raise ValueError(f"config must be a Config, a path or None, got {type(config).__name__}")
    if isinstance(estimator, str):
        cfg.estimator.name = estimator
    if isinstance(renderer, str):
        if renderer not in ("fast", "pyrender"):
            raise ValueError(f"renderer must be 'fast' or 'pyrender', got {renderer!r}")
        cfg.render.renderer = renderer
    if device is not None:
        cfg.simulation.device = str(device)
    if quiet is not None:
        cfg.logging.quiet = bool(quiet)
    return cfg


def _device(name: str) -> torch.device:
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"simulation.device must be a torch device such as 'cpu' or 'cuda', got {name!r}") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"simulation.device={name!r} but CUDA is not available; use 'cpu'")
    return dev


def simulate(config: Union[Config, PathLike, None] = None, *, estimator=None, renderer=None,
             sites: Optional[Union[str, Sequence[str]]] = None, device=None, out: Optional[PathLike] = None,
             quiet: Optional[bool] = None, overrides: Sequence[str] = (), on_step=None,
             sync_timers: bool = False, controller=None) -> SimulationResult:
    """Fly every site x controller setting x seed of ``config`` as one batch.

    Args:
        config: a :class:`Config`, a YAML path, or None (``configs/paper.yaml``).
        estimator: estimator name (overrides ``estimator.name``) or a ready estimator instance for B elements.
        renderer: ``"fast"`` / ``"pyrender"`` or a renderer object (used only if the estimator needs events).
        sites: subset of the configured sites (``"A,B"`` or a list).
        device: torch device (overrides ``simulation.device``).
        out: run folder (default ``<logging.root>/<name>-<UTC stamp>/``).
        quiet: no progress bar or printed table (overrides ``logging.quiet``).
        overrides: ``section.key=value`` strings applied to a config file.
        on_step: optional callable ``f(loop)`` after every step (tests, custom logging).
        sync_timers: synchronise CUDA around the per-stage timers (profiling).
        controller: optional :class:`dvsland.control.Controller` instance for the B elements
            (element order: see :func:`dvsland.sim.build_layout`), replacing the Eq. 2 law.

    Returns:
        :class:`SimulationResult`. On an exception or Ctrl-C the outputs gathered so far are
        written (results.json ``status: "interrupted"``) and the exception is re-raised.
    """
    t_start = time.perf_counter()
    cfg = _resolve_config(config, estimator, renderer, device, quiet, overrides)
    if isinstance(sites, str):
        sites = sites.split(",")
    dev = _device(cfg.simulation.device)
    if cfg.simulation.torch_threads > 0:
        torch.set_num_threads(cfg.simulation.torch_threads)
    layout = build_layout(cfg, sites)
    if estimator is None or isinstance(estimator, str):
        check_names(cfg)
    run_dir = make_run_dir(cfg, out)  # config.yaml first: a failing set-up still leaves it
    B = layout.batch_size
    stages = build_stages(cfg, layout, dev, estimator=None if isinstance(estimator, str) else estimator,
                          renderer=renderer, controller=controller)
    est = stages.estimator
    if estimator is not None and not isinstance(estimator, str):
        est_name = type(est).__name__
        cfg.estimator.name = getattr(est, "name", cfg.estimator.name)
    else:
        est_name = cfg.estimator.name
    rend = stages.renderer
    loop = ClosedLoop(cfg, layout, est, rend, stages.emulator, dev, sync_timers=sync_timers,
                      controller=stages.controller)
    quiet_ = cfg.logging.quiet
    tb = None
    if cfg.logging.tensorboard:
        from dvsland.report.tensorboard import TensorBoardLogger

        tb = TensorBoardLogger(run_dir / "tb", layout.run_label, cfg.dt_s,
                               scalar_every_s=cfg.logging.scalar_every_s,
                               image_every_s=cfg.logging.image_every_s)
        tb.add_config(dump_config(cfg))
    meta = {"status": "running", "estimator": est_name, "device": str(dev), "dt_s": cfg.dt_s,
            "batch_size": B, "dvsland_version": __version__, "torch_version": torch.__version__,
            "python": sys.version.split()[0], "machine": platform.machine(),
            "renderer": cfg.render.renderer if rend is not None else None}
    write_results_json(run_dir / "results.json", loop.summaries(), **meta)
    setup_s = time.perf_counter() - t_start

    pbar = None
    if not quiet_:
        from tqdm.auto import tqdm

        pbar = tqdm(total=loop.n_steps_max, unit="step", desc=f"simulate B={B}", leave=False, file=sys.stderr)

    def _on_step(lp):
        if tb is not None:
            tb.on_step(lp)
        if on_step is not None:
            on_step(lp)
        if pbar is not None:
            pbar.update(1)
            if lp.step_index % 10 == 0:
                pbar.set_postfix(t=f"{lp.t_s:.1f}s", active=int(lp.active.sum()))

    status, error, exc_to_raise = "complete", None, None
    t_loop = time.perf_counter()
    try:
        loop.run(_on_step)
    except BaseException as exc:  # noqa: BLE001 - Ctrl-C too: write what we have, then re-raise
        status = "interrupted"
        error = f"{type(exc).__name__}: {exc}"
        exc_to_raise = exc
    loop_s = time.perf_counter() - t_loop
    if pbar is not None:
        pbar.close()
    t_out = time.perf_counter()
    try:
        if status != "complete":
            loop.mark_interrupted()
            loop.record_final()
        runs = loop.summaries()
        traces = loop.traces_numpy()
        table = format_table(runs)
        if tb is not None:
            tb.close(loop, format_table(runs, markdown=True))
        write_traces_npz(run_dir / "traces.npz", traces)
        sim_time_s = float(sum(r["t_end_s"] for r in runs))
        outputs_s = time.perf_counter() - t_out
        wall = time.perf_counter() - t_start
        timings = dict(loop.timer.seconds)
        timings.update(setup=setup_s, loop=loop_s, outputs=outputs_s)
        counts = {}
        for r in runs:
            counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
        meta.update(status=status, error=error, wall_time_s=wall, sim_time_s=sim_time_s,
                    real_time_factor=sim_time_s / wall if wall > 0 else None, n_steps=loop.step_index,
                    timings_s=timings, outcomes=counts)
        write_results_json(run_dir / "results.json", runs, **meta)
        result = SimulationResult(runs=runs, traces=traces, run_dir=run_dir, wall_time_s=wall, status=status,
                                  timings_s=timings, n_steps=loop.step_index, sim_time_s=sim_time_s, error=error)
        if cfg.logging.figures and status == "complete":
            from dvsland.report.figures import write_figures

            t_fig = time.perf_counter()
            write_figures(run_dir, runs, traces, cfg.controller.c2, cfg.simulation.success_altitude_m)
            timings["figures"] = time.perf_counter() - t_fig
            write_results_json(run_dir / "results.json", runs, **meta)
        if not quiet_:
            print(table)
            held = [r for r in runs if r["held_steps"]]
            if held:
                policy = cfg.controller.missing_policy
                print(f"note: the filtered estimate was missing or non-negative on {sum(r['held_steps'] for r in held)} "
                      f"steps in {len(held)} of {len(runs)} runs; the controller applied missing_policy={policy!r} "
                      f"(column 'held')")
            print(f"{status}: {B} descents, {loop.step_index} steps, wall {wall:.2f} s "
                  f"(loop {loop_s:.2f} s), real-time factor {result.real_time_factor:.1f}; output in {run_dir}")
    finally:
        if tb is not None:
            tb.close()
    if exc_to_raise is not None:
        raise exc_to_raise
    return result
