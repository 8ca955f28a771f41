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
from dvsland.config import Config, load_config, validate_config
from dvsland.config.validate import check_memory
from dvsland.report import write_results_json, write_traces_npz
from dvsland.report.checkpoint import estimator_checkpoint
from dvsland.runs import failure_status, guarded_run, make_run_dir
from dvsland.stages import build_stages, check_names

from dvsland.layout import build_layout
from .callbacks import CallbackList, default_callbacks
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
        cfg.render.renderer = renderer  # checked against the renderer registry when built
    if device is not None:
        cfg.simulation.device = str(device)
    if quiet is not None:
        cfg.logging.quiet = bool(quiet)
    return validate_config(cfg)  # one check for files, the CLI and Config objects built in Python


def _device(name: str) -> torch.device:
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"simulation.device must be a torch device such as 'cpu' or 'cuda', got {name!r}") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"simulation.device={name!r} but CUDA is not available; use 'cpu'")
    return dev


def _run_meta(cfg: Config, estimator_name: str, device, batch_size: int, rendered: bool, estimator=None) -> dict:
    """The header fields of results.json (``checkpoint``: a trained estimator's file name and hash, or None)."""
    return {"status": "running", "estimator": estimator_name, "device": str(device), "dt_s": cfg.dt_s,
            "batch_size": batch_size, "dvsland_version": __version__, "torch_version": torch.__version__,
            "python": sys.version.split()[0], "machine": platform.machine(),
            "renderer": cfg.render.renderer if rendered else None,
            "checkpoint": estimator_checkpoint(cfg, cfg.estimator.name, estimator)}


@guarded_run  # SIGTERM = Ctrl-C; an interrupted set-up still leaves results.json
def simulate(config: Union[Config, PathLike, None] = None, *, estimator=None, renderer=None,
             sites: Optional[Union[str, Sequence[str]]] = None, device=None, out: Optional[PathLike] = None,
             quiet: Optional[bool] = None, overrides: Sequence[str] = (), on_step=None,
             sync_timers: bool = False, controller=None, callbacks: Sequence = ()) -> SimulationResult:
    """Fly every site x controller setting x seed of ``config`` as one batch.

    Build (config, run folder, stages) -> run (the loop, with callbacks) -> write (results.json,
    traces.npz), then the callbacks' ``on_end`` (TensorBoard summary, figures, printed table).

    Args:
        config: a :class:`Config`, a YAML path or shipped config name, or None (``configs/paper.yaml``).
        estimator: estimator name (overrides ``estimator.name``) or a ready estimator instance for B elements.
        renderer: a renderer name or a renderer object (used only if the estimator needs events).
        sites: subset of the configured sites (``"A,B"`` or a list).
        device: torch device (overrides ``simulation.device``).
        out: run folder (default ``<logging.root>/<name>-<UTC stamp>/``).
        quiet: no progress bar or printed table (overrides ``logging.quiet``).
        overrides: ``section.key=value`` strings applied to a config file.
        on_step: optional callable ``f(loop, out)`` after every step, with the :class:`ClosedLoop` (its
            ``state`` is the :class:`LoopState` after the step) and the step's :class:`StepOutput`.
        sync_timers: synchronise CUDA around the per-stage timers (profiling).
        controller: a controller name (sets ``controller.name``) or a :class:`dvsland.control.Controller`
            instance for the B elements
            (element order: see :func:`dvsland.sim.build_layout`), replacing the configured law.
        callbacks: more callbacks (:mod:`dvsland.sim.callbacks`), called after the built-in ones.

    Returns:
        :class:`SimulationResult`. On an exception, Ctrl-C or SIGTERM the outputs gathered so far
        are written (results.json ``status: "interrupted"``, also when it happens during set-up)
        and the exception is re-raised.
    """
    t_start = time.perf_counter()
    # ---- build
    cfg = _resolve_config(config, estimator, renderer, device, quiet, overrides)
    if isinstance(sites, str):
        sites = sites.split(",")
    if sites is not None and (not isinstance(sites, (list, tuple)) or not all(isinstance(s, str) for s in sites)):
        raise ValueError(f"sites must be 'A,B' or a list of site names, got {sites!r}")
    if estimator is not None and not isinstance(estimator, str) and not (
            callable(getattr(estimator, "update", None)) and callable(getattr(estimator, "reset", None))):
        raise ValueError(f"estimator must be a name or an estimator instance (with update and reset), "
                         f"got {type(estimator).__name__}")
    if isinstance(controller, str):  # a law by name (like estimator=): sets controller.name
        cfg.controller.name, controller = controller, None
    dev = _device(cfg.simulation.device)
    if cfg.simulation.torch_threads > 0:
        torch.set_num_threads(cfg.simulation.torch_threads)
    layout = build_layout(cfg, sites)
    check_memory(cfg, len(layout.scene_names), layout.batch_size)  # scenes: the sites, or their dispersed variants  # before anything large is allocated
    if estimator is None or isinstance(estimator, str):
        check_names(cfg)
    run_dir = make_run_dir(cfg, out)  # config.yaml first: a failing set-up still leaves it
    instance = estimator is not None and not isinstance(estimator, str)
    est_name = cfg.estimator.name
    if instance:  # the instance's own name in summaries; the config is final before the stages are built
        est_name = type(estimator).__name__
        cfg.estimator.name = str(getattr(estimator, "name", None) or est_name)
    stages = build_stages(cfg, layout, dev, estimator=estimator if instance else None, renderer=renderer,
                          controller=controller, progress=not cfg.logging.quiet)
    loop = ClosedLoop(stages, sync_timers=sync_timers)
    meta = _run_meta(cfg, est_name, dev, layout.batch_size, stages.events is not None, stages.estimator)
    cbs = CallbackList([])
    try:
        cbs = CallbackList(default_callbacks(cfg, run_dir, loop, on_step) + list(callbacks))
        write_results_json(run_dir / "results.json", loop.summaries(), **meta)
        setup_s = time.perf_counter() - t_start
        # ---- run
        status, error, exc_to_raise = "complete", None, None
        t_loop = time.perf_counter()
        try:
            cbs.on_start(loop)
            loop.run(cbs.on_step)
        except BaseException as exc:  # noqa: BLE001 - Ctrl-C too: write what we have, then re-raise
            status, error, exc_to_raise = failure_status(exc, run_dir), f"{type(exc).__name__}: {exc}", exc
        loop_s = time.perf_counter() - t_loop
        # ---- write
        result = _write_outputs(loop, run_dir, meta, status, error, t_start,
                                dict(setup=setup_s, loop=loop_s))
        cbs.on_end(loop, result)
        write_results_json(run_dir / "results.json", result.runs, **meta)  # with the callbacks' timings
    finally:
        cbs.close()
    if exc_to_raise is not None:
        raise exc_to_raise
    return result


def _write_outputs(loop: ClosedLoop, run_dir: Path, meta: dict, status: str, error, t_start: float,
                   timings: dict) -> SimulationResult:
    """Final summaries and traces of ``loop`` into results.json and traces.npz; ``meta`` is updated
    in place (status, times, outcomes) and the :class:`SimulationResult` returned."""
    t_out = time.perf_counter()
    if status != "complete":
        loop.mark_interrupted()
        loop.record_final()
    runs = loop.summaries()
    traces = loop.traces_numpy()
    write_traces_npz(run_dir / "traces.npz", traces)
    sim_time_s = float(sum(r["t_end_s"] for r in runs))
    wall = time.perf_counter() - t_start
    all_timings = dict(loop.timer.seconds)
    all_timings.update(timings, outputs=time.perf_counter() - t_out)
    counts = {}
    for r in runs:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    meta.update(status=status, error=error, wall_time_s=wall, sim_time_s=sim_time_s,
                real_time_factor=sim_time_s / wall if wall > 0 else None, n_steps=loop.step_index,
                timings_s=all_timings, outcomes=counts)
    write_results_json(run_dir / "results.json", runs, **meta)
    return SimulationResult(runs=runs, traces=traces, run_dir=run_dir, wall_time_s=wall, status=status,
                            timings_s=all_timings, n_steps=loop.step_index, sim_time_s=sim_time_s, error=error)
