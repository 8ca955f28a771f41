"""Open-loop evaluation: run estimators side by side on the evaluation event streams.

The evaluation set (deterministic): for every site, the closed-form oracle-controlled descent
(:mod:`.trajectory`) sampled at the frame rate down to the success altitude; frames from the
renderer (``render.renderer`` of the config, default "fast"); events from the configured
:class:`~dvsland.events.EventEmulator` (seeded with ``simulation.seed``). Every estimator sees
the same events in the same order; ``update`` is timed (with a device sync).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

from dvsland.config import Config, build, config_to_dict
from dvsland.config.validate import check_config
from dvsland.estimators import Truth
from dvsland.stages import FrameSource, build_estimator, build_event_source

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
        ms_per_step: {estimator: (n_run,) float64 wall time of each ``update`` for the batch, ms}.
        n_events: (B, K + 1) int64 events per step and site (-1 = step not run).
        summary: JSON-ready dict of all metrics (see :func:`summarise`).
    """

    descents: Descents
    d_hat: Dict[str, np.ndarray]
    scored: np.ndarray
    ms_per_step: Dict[str, np.ndarray]
    n_events: np.ndarray
    summary: dict = field(default_factory=dict)


def _parse_value(text: str):
    import yaml

    return yaml.safe_load(text)


def parse_estimator_spec(spec) -> tuple:
    """``"dpr"`` -> ("dpr", "dpr", {}); ``"cmax[window_ms=500;n_grid=21]"`` -> (label, "cmax",
    {"window_ms": 500, "n_grid": 21}) with the whole text as label; a tuple (label, name, dict)
    passes through. Values are parsed as YAML scalars; :func:`variant_config` applies them as
    ``--set estimator.cmax.window_ms=500`` would (one override syntax, one validation)."""
    if isinstance(spec, (tuple, list)):
        label, name, over = spec
        return str(label), str(name), dict(over)
    spec = str(spec).strip()
    if "[" not in spec:
        return spec, spec, {}
    if not spec.endswith("]"):
        raise ValueError(f"estimator spec {spec!r}: expected NAME or NAME[key=value;key=value]")
    name, body = spec[:-1].split("[", 1)
    over = {}
    for item in filter(None, (x.strip() for x in body.split(";"))):
        if "=" not in item:
            raise ValueError(f"estimator spec {spec!r}: {item!r} is not key=value")
        k, v = item.split("=", 1)
        over[k.strip()] = _parse_value(v.strip())
    return spec, name.strip(), over


def variant_config(cfg: Config, name: str, overrides: dict, label: str = "") -> Config:
    """``cfg`` with estimator ``name``'s parameters updated by ``overrides``, validated as
    ``--set estimator.<name>.<key>=<value>`` would be (typed by the schema's field, range-checked,
    unknown keys rejected with the allowed ones); an estimator without a config section takes
    them in ``estimator.params``."""
    if not overrides:
        return cfg
    section = name if dataclasses.is_dataclass(getattr(cfg.estimator, name, None)) else "params"
    data = config_to_dict(cfg)
    data["estimator"][section].update(overrides)
    source = f"estimator spec {label or name}"
    return check_config(build(Config, data, source=source), source=source)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def summarise(res: EvaluationResult, info: Optional[dict] = None) -> dict:
    """Metrics per estimator: per site, per altitude band, over sites A-G and over all sites."""
    desc = res.descents
    d_true = desc.divergence
    alt = desc.altitude_m
    sites = desc.sites
    target = np.array([s in TARGET_SITES for s in sites])
    out = dict(info or {})
    out["sites"] = sites
    out["steps_scored"] = int(res.scored.sum())
    out["events_per_step_mean"] = {s: float(res.n_events[i][res.n_events[i] >= 0].mean())
                                   if (res.n_events[i] >= 0).any() else 0.0 for i, s in enumerate(sites)}
    ests = {}
    for name, dh in res.d_hat.items():
        sc = res.scored
        e = {"ms_per_step_mean": float(np.mean(res.ms_per_step[name])) if len(res.ms_per_step[name]) else None,
             "ms_per_step_median": float(np.median(res.ms_per_step[name])) if len(res.ms_per_step[name]) else None,
             "batch_size": len(sites)}
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


def evaluate(cfg: Config, estimators: Sequence[str] = ("dpr", "cmax"), sites: Optional[Sequence[str]] = None,
             *, segment_steps: int = 0, stride: int = 1, max_steps: Optional[int] = None, warmup_steps: int = 10,
             device="cpu", frame_source: Optional[FrameSource] = None, progress: bool = True) -> EvaluationResult:
    """Run ``estimators`` open loop on the evaluation streams of ``sites``.

    Args:
        cfg: config (sites, camera, render, emulator, estimator parameters, seed).
        estimators: names (see :func:`dvsland.estimators.available_estimators`); parameters from
            ``cfg.estimator.<name>`` (or ``cfg.estimator.params`` for third-party ones). A name
            may carry overrides, ``"cmax[window_ms=500;n_grid=21]"`` (see
            :func:`parse_estimator_spec`), to compare variants side by side.
        sites: site names (default: all of ``cfg.simulation.sites``); they form one batch.
        segment_steps, stride: quick runs: keep every ``stride``-th segment of ``segment_steps``
            steps, resetting emulator and estimators at each kept segment (0 / 1 = the whole
            descent in one go).
        max_steps: truncate the descents.
        warmup_steps: steps at the start of each segment left out of the metrics.
        device: torch device of renderer, emulator and estimators.
        frame_source: ``f(altitude_m (B,), site_idx (B,)) -> (B, H, W)`` frames; default the
            config's renderer for ``sites``.
        progress: tqdm progress bar.
    """
    from dvsland.config import validate_config

    cfg = validate_config(cfg)  # the same check as a config file (a hand-edited Config included)
    device = torch.device(device)
    if not estimators:
        raise ValueError("estimators must name at least one estimator")
    if int(warmup_steps) < 0:
        raise ValueError(f"warmup_steps must be >= 0, got {warmup_steps}")
    desc = closed_form_descents(cfg, sites, max_steps=max_steps)
    B, K = len(desc.sites), desc.n_steps
    source = build_event_source(cfg, desc.sites, device, renderer=frame_source)
    site_idx = torch.arange(B, device=device)
    specs = [parse_estimator_spec(e) for e in estimators]
    ests = {}
    for label, name, over in specs:
        if label in ests:
            raise ValueError(f"estimator label {label!r} given twice")
        # built once, from its variant config (the plain config may not even construct)
        ests[label] = build_estimator(variant_config(cfg, name, over, label), B, device, name=name)
    estimators = list(ests)
    d_hat = {n: np.full((B, K + 1), np.nan) for n in estimators}
    times: Dict[str, List[float]] = {n: [] for n in estimators}
    scored = np.zeros((B, K + 1), dtype=bool)
    n_events = np.full((B, K + 1), -1, dtype=np.int64)
    alt = torch.as_tensor(desc.altitude_m, dtype=torch.float32)
    t_us = np.round(desc.t_s * 1e6).astype(np.int64)
    segs = segment_schedule(K, segment_steps, stride)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(len(s) for s in segs), desc="evaluate", unit="step")
    for seg in segs:
        k0 = seg.start - 1
        source.reset(alt[:, k0].to(device), site_idx, int(t_us[k0]))
        for est in ests.values():
            est.reset()
        for k in seg:
            _, ev = source.step(alt[:, k].to(device), site_idx, int(t_us[k]))
            n_events[:, k] = ev.batch_counts(B).cpu().numpy()
            truth = Truth(torch.as_tensor(desc.altitude_m[:, k], device=device),
                          torch.as_tensor(desc.velocity_mps[:, k], device=device))
            for name, est in ests.items():
                _sync(device)
                t0 = time.perf_counter()
                d = est.update(ev, int(t_us[k]), truth)
                _sync(device)
                times[name].append((time.perf_counter() - t0) * 1e3)
                d_hat[name][:, k] = d.detach().double().cpu().numpy()
            scored[:, k] = desc.valid[:, k] & (k - seg.start >= warmup_steps)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    res = EvaluationResult(desc, d_hat, scored, {n: np.asarray(v) for n, v in times.items()}, n_events)
    info = dict(trajectory="closed_form", n_steps=K, steps_run=int(sum(len(s) for s in segs)),
                segment_steps=int(segment_steps), stride=int(stride), warmup_steps=int(warmup_steps),
                device=str(device), torch_threads=torch.get_num_threads(), estimators_run=list(estimators))
    res.summary = summarise(res, info)
    return res
