"""Open-loop evaluation: run estimators side by side on the evaluation event streams.

The evaluation set (deterministic): for every site, the closed-form oracle-controlled descent
(:mod:`.trajectory`) flown on :func:`dvsland.sim.loop_step` with the thrust that tracks it
(:func:`dvsland.evaluate.reference.tracking_thrust`) down to the success altitude. Each estimator
flies it in its own loop (the stages of :func:`dvsland.stages.build_stages`: the config's renderer,
built once and shared, default "fast"; the configured :class:`~dvsland.events.EventEmulator`,
seeded with ``simulation.seed``): the thrust does not depend on the estimate, so every estimator
sees the same altitudes and the same events, and its ``D_hat`` is the loop's ``d_est``, scored
against the loop's ``d_true``. The estimate stage is timed (with a device sync): process CPU time,
as ``dvsland bench`` measures (the report's time base on the CPU; wall time on CUDA, where the
work runs on the device), with the wall time beside it.
"""

from __future__ import annotations

import copy
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

from dvsland.config import Config
from dvsland.estimators.calibrate import STRUCTURE_KEY
from dvsland.report.checkpoint import estimator_checkpoint
from dvsland.stages import FrameSource, build_estimator, build_stages

from .flight import flight_config, parse_estimator_spec, variant_config  # noqa: F401 (re-exported)
from .metrics import band_metrics, divergence_metrics
from .trajectory import Descents, closed_form_descents, segment_schedule

#: the sites the issue's accuracy target applies to (H and I are nearly featureless)
TARGET_SITES = ("A", "B", "C", "D", "E", "F", "G")

@dataclass
class EvaluationResult:
    """Estimates and metrics of an open-loop evaluation.

    Attributes:
        descents: the sampled :class:`Descents` (truth).
        d_hat: {estimator: (B, K + 1) float64 estimates, NaN = none or step not run}.
        scored: (B, K + 1) bool, steps that count in the metrics (run, descent valid, after warm-up).
        ms_per_step: {estimator: (n_run,) float64 time of each ``update`` for the batch, ms, in the
            report's time base ``time_base``: process CPU time on the CPU, wall time on CUDA}.
        n_events: (B, K + 1) int64 events per step and site (-1 = step not run).
        summary: JSON-ready dict of all metrics (see :func:`summarise`); with hard scenarios its
            ``scenarios`` holds their descriptions and per-phase metrics.
        scenarios: what :func:`dvsland.evaluate.scenario_run.run_scenarios` returned (traces
            included), or {} without scenarios.
        wall_ms_per_step: {estimator: (n_run,) float64 wall time of each ``update``, ms}.
        time_base: "CPU" or "wall": what ``ms_per_step`` measures.
        checkpoints: {estimator: :func:`dvsland.report.checkpoint.checkpoint_identity`} of the
            estimators that read a trained checkpoint (``learned``, ``snn``).
        confidence: {estimator: (B, K + 1) float64 confidence in [0, 1] of each estimate (0 where
            none or not run)}; read by the calibration report (:mod:`dvsland.evaluate.calibration`).
        structure: {estimator: (B, K + 1) float64 its ``structure`` diagnostic per step (NaN where
            none)}, for the estimators that give one (``cmax``): a calibration feature.
    """

    descents: Descents
    d_hat: Dict[str, np.ndarray]
    scored: np.ndarray
    ms_per_step: Dict[str, np.ndarray]
    n_events: np.ndarray
    summary: dict = field(default_factory=dict)
    scenarios: dict = field(default_factory=dict)
    wall_ms_per_step: Dict[str, np.ndarray] = field(default_factory=dict)
    time_base: str = "CPU"
    checkpoints: Dict[str, dict] = field(default_factory=dict)
    confidence: Dict[str, np.ndarray] = field(default_factory=dict)
    structure: Dict[str, np.ndarray] = field(default_factory=dict)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def target_label(sites: Sequence[str]) -> str:
    """Label of the aggregate over the target sites actually run: "A-G" only when all of A..G ran,
    else the sites joined by commas ("A,D"); "none" when no target site ran."""
    run = [s for s in TARGET_SITES if s in set(sites)]
    if not run:
        return "none"
    if len(run) == len(TARGET_SITES):
        return f"{TARGET_SITES[0]}-{TARGET_SITES[-1]}"
    return ",".join(run)


def time_base(device) -> str:
    """The time base of a report on ``device``: "CPU" (process CPU time, as ``dvsland bench``) on
    the CPU, "wall" on CUDA (the work runs on the device; its CPU time is only the launches)."""
    return "wall" if torch.device(device).type == "cuda" else "CPU"


def _stats_ms(ms) -> dict:
    """{"median", "mean"} of per-update times, ms (None without any)."""
    a = np.asarray(ms if ms is not None else [], dtype=np.float64)
    return {"median": float(np.median(a)) if a.size else None, "mean": float(np.mean(a)) if a.size else None}


def _timing_summary(res: EvaluationResult, name: str) -> dict:
    """The per-update time fields of one estimator: ``time_base``, ``ms_per_step_median`` /
    ``_mean`` (in that base), ``cpu_ms_per_step_*`` and ``wall_ms_per_step_*`` (ms)."""
    base = res.time_base
    own = _stats_ms(res.ms_per_step.get(name))
    wall = _stats_ms(res.wall_ms_per_step.get(name)) if name in res.wall_ms_per_step else \
        (own if base == "wall" else _stats_ms(None))
    cpu = own if base == "CPU" else _stats_ms(None)
    return {"time_base": base, "ms_per_step_median": own["median"], "ms_per_step_mean": own["mean"],
            "cpu_ms_per_step_median": cpu["median"], "cpu_ms_per_step_mean": cpu["mean"],
            "wall_ms_per_step_median": wall["median"], "wall_ms_per_step_mean": wall["mean"]}


def summarise(res: EvaluationResult, info: Optional[dict] = None) -> dict:
    """Metrics per estimator: per site, per altitude band, over sites A-G and over all sites; the
    time per update (:func:`_timing_summary`) and, for a trained estimator, its ``checkpoint``
    (file, sha256, path)."""
    desc = res.descents
    d_true = desc.divergence
    alt = desc.altitude_m
    sites = desc.sites
    target = np.array([s in TARGET_SITES for s in sites])
    out = dict(info or {})
    out["sites"] = sites
    out["target_label"] = target_label(sites)
    out["steps_scored"] = int(res.scored.sum())
    out["events_per_step_mean"] = {s: float(res.n_events[i][res.n_events[i] >= 0].mean())
                                   if (res.n_events[i] >= 0).any() else 0.0 for i, s in enumerate(sites)}
    out["time_base"] = res.time_base
    if res.checkpoints:
        from dvsland.report.checkpoint import checkpoint_text

        out["checkpoints"] = {n: checkpoint_text(c) for n, c in res.checkpoints.items()}
    ests = {}
    for name, dh in res.d_hat.items():
        sc = res.scored
        e = dict(_timing_summary(res, name), batch_size=len(sites))
        if name in res.checkpoints:
            e["checkpoint"] = res.checkpoints[name]
        e["sites"] = {s: divergence_metrics(dh[i][sc[i]], d_true[i][sc[i]]) for i, s in enumerate(sites)}
        m_all = sc
        m_t = sc & target[:, None]
        e["all_sites"] = divergence_metrics(dh[m_all], d_true[m_all])
        e["sites_A_G"] = divergence_metrics(dh[m_t], d_true[m_t])
        e["bands_all_sites"] = band_metrics(dh[m_all], d_true[m_all], alt[m_all])
        e["bands_A_G"] = band_metrics(dh[m_t], d_true[m_t], alt[m_t])
        ests[name] = e
    out["estimators"] = ests
    return out


class _EstimateTimer:
    """``loop_step`` timer of each ``estimate`` stage (device synchronised), the others untimed:
    ``last_cpu_ms`` (process CPU time) and ``last_ms`` (wall time), ms."""

    def __init__(self, device: torch.device):
        self.device = device
        self.last_ms = 0.0
        self.last_cpu_ms = 0.0

    def __call__(self, stage: str):
        return _Timed(self) if stage == "estimate" else nullcontext()


class _Timed:
    def __init__(self, owner: _EstimateTimer):
        self.owner = owner

    def __enter__(self):
        _sync(self.owner.device)
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        _sync(self.owner.device)
        self.owner.last_ms = (time.perf_counter() - self.t0) * 1e3
        self.owner.last_cpu_ms = (time.process_time() - self.c0) * 1e3
        return False


def record_structure(structure: Dict[str, np.ndarray], name: str, diagnostics, k: int, shape) -> None:
    """Step ``k``'s ``structure`` diagnostic (B,) of estimator ``name`` into ``structure[name]`` (an
    array of ``shape``, made on its first value, NaN elsewhere), where ``diagnostics`` (the step's
    dict, or None) hold one."""
    st = (diagnostics or {}).get(STRUCTURE_KEY)
    if isinstance(st, torch.Tensor):
        structure.setdefault(name, np.full(shape, np.nan))[:, k] = st.detach().double().cpu().numpy()


def evaluate(cfg: Config, estimators: Sequence[str] = ("dpr", "cmax"), sites: Optional[Sequence[str]] = None,
             *, segment_steps: int = 0, stride: int = 1, max_steps: Optional[int] = None, warmup_steps: int = 10,
             device="cpu", frame_source: Optional[FrameSource] = None, progress: bool = True,
             scenarios=()) -> EvaluationResult:
    """Run ``estimators`` open loop on the evaluation streams of ``sites``.

    Args:
        cfg: config (sites, camera, render, emulator, dynamics, estimator parameters, seed).
        estimators: names (see :func:`dvsland.estimators.available_estimators`); parameters from
            ``cfg.estimator.<name>`` (or ``cfg.estimator.params`` for third-party ones). A name
            may carry overrides, ``"cmax[window_ms=500;n_grid=21]"`` (see
            :func:`parse_estimator_spec`), to compare variants side by side.
        sites: site names (default: all of ``cfg.simulation.sites``); they form one batch.
        segment_steps, stride: quick runs: keep every ``stride``-th segment of ``segment_steps``
            steps; each kept segment starts a new flight (:func:`dvsland.sim.init_state` at the
            descent's state there: emulator and estimator reset) (0 / 1 = the whole descent in one go).
        max_steps: truncate the descents.
        warmup_steps: steps at the start of each segment left out of the metrics.
        device: torch device of renderer, emulator and estimators.
        frame_source: ``f(altitude_m (B,), site_idx (B,)) -> (B, H, W)`` frames; default the
            config's renderer for ``sites``.
        progress: tqdm progress bar.
        scenarios: hard scenarios flown after the descents, each a named segment of the report
            (:mod:`dvsland.evaluate.scenarios`: "all", "none", names, or Scenario objects).

    The returned ``descents`` hold the flown altitudes and velocities (the truth of the scores);
    ``summary['trajectory_max_rel_dz']`` is their largest relative deviation from the closed form.
    """
    from dvsland.config import validate_config
    from dvsland.dynamics import closed_form_state
    from dvsland.layout import build_layout

    from .reference import fly_profile

    cfg = validate_config(cfg)  # the same check as a config file (a hand-edited Config included)
    device = torch.device(device)
    if not estimators:
        raise ValueError("estimators must name at least one estimator")
    if int(warmup_steps) < 0:
        raise ValueError(f"warmup_steps must be >= 0, got {warmup_steps}")
    desc = closed_form_descents(cfg, sites, max_steps=max_steps)
    B, K = len(desc.sites), desc.n_steps
    specs = [parse_estimator_spec(e) for e in estimators]
    ests, checkpoints = {}, {}
    for label, name, over in specs:
        if label in ests:
            raise ValueError(f"estimator label {label!r} given twice")
        # built once, from its variant config (the plain config may not even construct)
        vcfg = variant_config(cfg, name, over, label)
        ests[label] = build_estimator(vcfg, B, device, name=name)
        ck = estimator_checkpoint(vcfg, name, ests[label])
        if ck is not None:
            checkpoints[label] = ck
    estimators = list(ests)
    # the profile, two steps past the end (the tracking thrust looks ahead), unclamped
    site_cfg = {s.name: s for s in cfg.simulation.sites}
    t_ref = np.arange(K + 3) * float(cfg.dt_s)
    z_ref = np.stack([closed_form_state(t_ref, site_cfg[n].z0_m, site_cfg[n].v0_mps, float(cfg.controller.c2))[0]
                      for n in desc.sites])
    f64 = dict(dtype=torch.float64, device=device)
    z_ref_t = torch.as_tensor(z_ref, **f64)
    fcfg = flight_config(cfg, desc.sites, K)
    layout = build_layout(fcfg, desc.sites)
    renderer = frame_source
    if renderer is None and any(getattr(e, "needs_events", True) for e in ests.values()):
        from dvsland.render import get_renderer  # one renderer shared by every estimator's stages

        renderer = get_renderer(cfg.render.renderer, desc.sites, cfg.camera, cfg.render, device=device)
    d_hat = {n: np.full((B, K + 1), np.nan) for n in estimators}
    conf = {n: np.zeros((B, K + 1)) for n in estimators}
    structure: Dict[str, np.ndarray] = {}  # the estimators whose diagnostics give it
    base = time_base(device)
    times: Dict[str, List[float]] = {n: [] for n in estimators}  # in the time base
    walls: Dict[str, List[float]] = {n: [] for n in estimators}
    scored = np.zeros((B, K + 1), dtype=bool)
    n_events = np.full((B, K + 1), -1, dtype=np.int64)
    alt, vel, valid = desc.altitude_m.copy(), desc.velocity_mps.copy(), desc.valid.copy()
    z_end = float(cfg.simulation.success_altitude_m)
    segs = segment_schedule(K, segment_steps, stride)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(estimators) * sum(len(s) for s in segs), desc="evaluate", unit="step")
    timer = _EstimateTimer(device)
    m0 = torch.full((B,), float(fcfg.dynamics.mass_kg), **f64)
    have_events = False
    for i_est, (name, est) in enumerate(ests.items()):
        ecfg = copy.deepcopy(fcfg)
        ecfg.estimator.name = dict((lab, n) for lab, n, _ in specs)[name]  # the loop's messages name it
        stages = build_stages(ecfg, layout, device, estimator=est, renderer=renderer)
        first = i_est == 0  # the flight does not depend on the estimator: recorded once
        count = stages.events is not None and not have_events  # events counted once
        for seg in segs:
            k0 = seg.start - 1  # each segment: a new flight from the descent's state at frame k0
            z_seg = z_ref_t[:, k0:seg.stop + 2].clone()
            z_seg[:, 0] = torch.as_tensor(desc.altitude_m[:, k0], **f64)  # held at z_end past the end
            v_seg = torch.as_tensor(desc.velocity_mps[:, k0], **f64)
            for k, out in zip(range(k0, seg.stop), fly_profile(stages, z_seg, v_seg, m0, timer=timer)):
                if k == k0:
                    continue  # the first frame of a segment: no events yet, not scored
                times[name].append(timer.last_cpu_ms if base == "CPU" else timer.last_ms)
                walls[name].append(timer.last_ms)
                d_hat[name][:, k] = out.d_est.detach().cpu().numpy()
                conf[name][:, k] = out.d_conf.detach().cpu().numpy()
                record_structure(structure, name, out.diagnostics(), k, (B, K + 1))
                if first:
                    alt[:, k], vel[:, k] = out.z_m.cpu().numpy(), out.v_mps.cpu().numpy()
                    valid[:, k] = (out.active & (out.z_m > z_end)).cpu().numpy()
                    scored[:, k] = valid[:, k] & (k - seg.start >= warmup_steps)
                if count:
                    n_events[:, k] = out.events.batch_counts(B).cpu().numpy()
                if bar is not None:
                    bar.update(1)
        have_events = have_events or count
    if bar is not None:
        bar.close()
    if not have_events:  # no estimator needed events: none were made
        for seg in segs:
            n_events[:, seg.start:seg.stop] = 0
    run = np.zeros(K + 1, dtype=bool)
    for seg in segs:
        run[seg.start:seg.stop] = True
    flown = valid & run[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):  # z_ref is 0 past a descent's end: not read there
        rel_dz = np.abs(alt - z_ref[:, :K + 1]) / z_ref[:, :K + 1]
    flown_desc = Descents(desc.sites, desc.t_s, alt, vel, valid)
    res = EvaluationResult(flown_desc, d_hat, scored, {n: np.asarray(v) for n, v in times.items()}, n_events,
                           wall_ms_per_step={n: np.asarray(v) for n, v in walls.items()}, time_base=base,
                           checkpoints=checkpoints, confidence=conf, structure=structure)
    info = dict(trajectory="closed_form", flight="loop_step, tracking thrust",
                integrator=str(cfg.dynamics.integrator),
                trajectory_max_rel_dz=float(rel_dz[flown].max()) if flown.any() else 0.0,
                n_steps=K, steps_run=int(sum(len(s) for s in segs)),
                segment_steps=int(segment_steps), stride=int(stride), warmup_steps=int(warmup_steps),
                device=str(device), torch_threads=torch.get_num_threads(), estimators_run=list(estimators))
    res.summary = summarise(res, info)
    if scenarios:
        from .scenario_run import run_scenarios

        res.scenarios = run_scenarios(cfg, {lab: (n, o) for lab, n, o in specs}, scenarios, device=device,
                                      frame_source=frame_source, progress=progress)
        if res.scenarios:
            res.summary["scenarios"] = {k: res.scenarios[k] for k in ("scenarios", "metrics")}
    return res
