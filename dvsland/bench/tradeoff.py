"""Speed against error: every registered estimator (and its main knobs) and the settings that trade
speed for accuracy, each as open-loop error against time per control step.

A *configuration* is an estimator spec (``"dpr"``, ``"cmax[n_grid=11]"``) plus config overrides
(contrast threshold, resolution, renderer). For each one:

- error: :func:`dvsland.evaluate.evaluate` on the closed-form oracle descents of the sites
  (sampled segments in ``--quick``): median and 90th percentile of |relative error| of D over the
  scored steps with an estimate, and coverage (fraction of scored steps with an estimate), over
  sites A-G (H and I are nearly featureless; their coverage is reported apart);
- speed: :func:`dvsland.bench.stages.time_stages` at B = 18 (render + emulate + estimate +
  control/dynamics per control step).

Configurations that share a scene (same overrides) share one evaluation (the estimators see the
same events).
"""

from __future__ import annotations

import copy
import math
import time
import traceback
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np

from dvsland.config import Config, apply_overrides, build, config_to_dict
from dvsland.estimators import available_estimators
from dvsland.estimators.registry import check_estimator_names

from .stages import time_stages

#: variants of the known estimators (their main knobs); other registered estimators run with defaults
VARIANTS_FULL = {
    "dpr": ["dpr", "dpr[pair_weighting=length]", "dpr[n_max=30]", "dpr[memory_ms=300]"],
    "cmax": ["cmax", "cmax[n_grid=11;n_refine=1]", "cmax[max_events=1000]", "cmax[n_grid=41]"],
    "snn": ["snn"],
    "oracle": ["oracle", "oracle[noise_rel=0.1]", "oracle[noise_rel=0.3]", "oracle[noise_rel=0.1;delay_steps=3]"],
}
VARIANTS_QUICK = {
    "dpr": ["dpr", "dpr[pair_weighting=length]"],
    "cmax": ["cmax", "cmax[n_grid=11;n_refine=1]"],
    "snn": ["snn"],
    "oracle": ["oracle", "oracle[noise_rel=0.1]", "oracle[noise_rel=0.3]"],
}
#: settings that trade speed for accuracy, flown with ``dpr``: (label, overrides)
SETTINGS = [
    ("threshold 0.05", ["emulator.threshold=0.05"]),
    ("threshold 0.2", ["emulator.threshold=0.2"]),
    ("half resolution 64x64", ["camera.width_px=64", "camera.height_px=64"]),
]
TARGET = ("A", "B", "C", "D", "E", "F", "G")


@dataclass
class Configuration:
    """One point of the speed/error plot."""

    label: str
    family: str
    estimator: str
    overrides: List[str] = field(default_factory=list)
    sites: Optional[List[str]] = None  # None: all configured sites


def configurations(quick: bool, estimators: Optional[Sequence[str]] = None,
                   pyrender: bool = True) -> List[Configuration]:
    """The configurations to measure: each registered estimator's variants, then the settings."""
    names = list(estimators) if estimators else available_estimators()
    check_estimator_names(names)
    table = VARIANTS_QUICK if quick else VARIANTS_FULL
    out = []
    for name in names:
        for spec in table.get(name, [name]):
            out.append(Configuration(spec, name, spec))
    if not estimators or "dpr" in names:
        for label, over in SETTINGS:
            out.append(Configuration(f"dpr, {label}", "setting", "dpr", list(over)))
        if pyrender:
            sub = ["A", "E"]
            out.append(Configuration("dpr, fast renderer (A, E)", "renderer", "dpr", [], sub))
            out.append(Configuration("dpr, pyrender (A, E)", "renderer", "dpr", ["render.renderer=pyrender"], sub))
    return out


def error_metrics(d_hat: np.ndarray, d_true: np.ndarray, scored: np.ndarray) -> Dict[str, float]:
    """Median and p90 |relative error| over scored steps with an estimate, and coverage.

    Args:
        d_hat, d_true: (B, K) estimates and truth, 1/s (NaN = no estimate).
        scored: (B, K) bool, steps that count.
    """
    dh, dt = d_hat[scored], d_true[scored]
    ok = np.isfinite(dh)
    nan = float("nan")
    if dh.size == 0:
        return dict(n_scored=0, coverage=nan, median_abs_rel_err=nan, p90_abs_rel_err=nan, within_10=nan)
    rel = np.abs(dh[ok] - dt[ok]) / np.abs(dt[ok])
    return dict(n_scored=int(dh.size), coverage=float(ok.mean()),
                median_abs_rel_err=float(np.median(rel)) if rel.size else nan,
                p90_abs_rel_err=float(np.percentile(rel, 90)) if rel.size else nan,
                within_10=float((rel <= 0.10).sum() / dh.size))


def config_with(cfg: Config, overrides: Sequence[str]) -> Config:
    """A validated copy of ``cfg`` with ``section.key=value`` overrides applied."""
    if not overrides:
        return copy.deepcopy(cfg)
    from dvsland.config.validate import check_config

    data = apply_overrides(config_to_dict(cfg), list(overrides))
    return check_config(build(Config, data, source="bench"), source="bench")


def run_tradeoff(cfg: Config, confs: Sequence[Configuration], device="cpu", quick: bool = True,
                 batch_size: int = 18, progress: bool = False, log=print) -> List[dict]:
    """Measure every configuration; returns one dict per configuration (error, timing, or error text)."""
    from dvsland.evaluate import evaluate

    seg = dict(segment_steps=12, stride=12, warmup_steps=5) if quick else dict(segment_steps=30, stride=4,
                                                                              warmup_steps=5)
    n_steps, warmup = (4, 3) if quick else (10, 5)
    groups: Dict[tuple, List[Configuration]] = {}
    for c in confs:
        groups.setdefault((tuple(c.overrides), tuple(c.sites or ())), []).append(c)
    rows = []
    for (over, sites), members in groups.items():
        vcfg = config_with(cfg, list(over))
        site_list = list(sites) or None
        specs = list(dict.fromkeys(m.estimator for m in members))
        t0 = time.perf_counter()
        res, err = None, None
        try:
            kw = dict(seg)
            if vcfg.render.renderer == "pyrender":  # about 0.1-0.3 s per frame: a short sample
                kw = dict(segment_steps=8, stride=60 if quick else 10, warmup_steps=5)
            res = evaluate(vcfg, specs, sites=site_list, device=device, progress=progress, **kw)
        except Exception as exc:  # noqa: BLE001 - one failing configuration must not end the report
            err = f"{type(exc).__name__}: {exc}"
            log(f"bench: evaluation of {specs} with {list(over)} failed: {err}")
            traceback.print_exc()
        eval_s = time.perf_counter() - t0
        for m in members:
            row = dict(label=m.label, family=m.family, estimator=m.estimator, overrides=list(m.overrides),
                       sites=m.sites, batch_size=batch_size, eval_seconds=eval_s)
            if res is not None:
                desc = res.descents
                d_true = desc.divergence
                tgt = np.array([s in TARGET for s in desc.sites])
                sc = res.scored
                if not tgt.any():
                    tgt[:] = True
                row["error"] = error_metrics(res.d_hat[m.estimator], d_true, sc & tgt[:, None])
                row["error_all_sites"] = error_metrics(res.d_hat[m.estimator], d_true, sc)
                if (~tgt).any():  # coverage on the nearly featureless sites left out above (H, I)
                    row["coverage_H_I"] = error_metrics(res.d_hat[m.estimator], d_true, sc & ~tgt[:, None])["coverage"]
                row["error_sites"] = [s for s in desc.sites if s in TARGET] or list(desc.sites)
                row["steps_run"] = res.summary.get("steps_run")
                row["events_per_step"] = float(np.mean(res.n_events[res.n_events >= 0])) / len(desc.sites)
            else:
                row["failed"] = err
            try:
                tcfg = copy.deepcopy(vcfg)
                ns, wu = n_steps, warmup
                if tcfg.render.renderer == "pyrender" and quick:  # about 0.3-0.6 s per frame here
                    ns, wu = 1, 0
                row["timing"] = time_stages(tcfg, batch_size, device, m.estimator, n_steps=ns, warmup=wu,
                                            sites=site_list)
            except Exception as exc:  # noqa: BLE001
                row["failed"] = (row.get("failed", "") + f" timing {type(exc).__name__}: {exc}").strip()
                log(f"bench: timing of {m.label} failed: {exc}")
            rows.append(row)
            e = row.get("error", {})
            tm = row.get("timing", {})
            log(f"  {m.label:<40} med|rel| {_pct(e.get('median_abs_rel_err'))}  p90 {_pct(e.get('p90_abs_rel_err'))}"
                f"  cover {_pct(e.get('coverage'))}  {tm.get('cpu_ms_total', math.nan):8.2f} CPU ms/step"
                f" ({tm.get('ms_total', math.nan):.2f} wall)")
    return rows


def _pct(x) -> str:
    return "   -  " if x is None or not math.isfinite(x) else f"{100 * x:5.1f}%"


def pareto_front(points: Sequence[tuple]) -> List[int]:
    """Indices of the points (x, y) not dominated by another (lower x and lower y are better),
    sorted by x. Points with a non-finite coordinate are never on the front."""
    idx = [i for i, (x, y) in enumerate(points) if math.isfinite(x) and math.isfinite(y)]
    idx.sort(key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in idx:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front
