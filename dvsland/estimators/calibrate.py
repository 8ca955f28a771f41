"""Post-hoc confidence calibration: a small fitted table that makes an estimator's confidence a
calibrated probability.

Every estimator returns a confidence c per estimate; the filters and the calibration report read it
as a relative standard error ``sigma_rel(c) = 0.1 sqrt(1/c - 1)``
(:func:`dvsland.estimators.base.confidence_rel_sigma`). An estimator whose errors are larger
(or smaller) than that claims is over- (under-) confident. Calibration rescales the claimed sigma
by a factor read from a table, and turns the result back into a confidence::

    log10 sigma_cal = log10 sigma_raw + S(log10 sigma_raw, f)
    c_cal           = 1 / (1 + (sigma_cal / 0.1)^2) = c / (c + s^2 (1 - c)),   s = 10^S

``S`` is bilinear in (log10 sigma_raw, f) between the knots of the table and constant beyond
them; ``f`` is one optional cheap per-step feature the estimator already has: ``events``
(log10(1 + events of the descent in the step's window)), ``abs_d_hat`` (log10 |D_hat|),
``structure`` (log10 of the step's ``structure`` diagnostic: how far ``cmax``'s score stands above
the score of structureless events), or none. The site, which a flight computer does not know, is
never a feature. The fitter (:func:`fit_calibration`) makes ``log10 sigma_raw + S`` non-decreasing
in ``sigma_raw`` along every feature knot (weighted isotonic regression), so the calibrated
confidence keeps the estimator's ranking: a higher raw confidence never gives a lower calibrated one
at the same feature.

- :class:`CalibrationParams` and :func:`calibrate_confidence`: the table and the pure, batched map
  (torch, no loop over the batch, no host sync; CPU or CUDA). Where S = 0 the confidence passes
  bit for bit; c = 0 (no estimate) stays 0.
- :func:`calibrate_output`: the map applied to an estimator's :class:`~.base.EstimateOut` (the raw
  confidence kept in its diagnostics under :data:`RAW_KEY`), as
  :class:`~.base.DivergenceEstimator` does on every step when ``calibration`` is set.
- :func:`fit_calibration`: the fitter (NumPy), from a sample of (D, D_hat, c, feature).
- :func:`load_calibration`, :func:`calibration_to_json`, :func:`resolve_calibration`: the JSON
  files (the shipped ones live in ``dvsland/estimators/calibration/``) and the config key
  ``estimator.calibration`` (``none``, a shipped name, or a path to a .json).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Dict, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch

from dvsland.checks import file_sha256

#: the features a table may use besides the raw confidence
FEATURES = ("none", "events", "abs_d_hat", "structure")
#: the diagnostic key the ``structure`` feature reads (``cmax`` gives it)
STRUCTURE_KEY = "structure"
#: the key of the confidence before calibration in a calibrated estimator's diagnostics
RAW_KEY = "confidence_raw"
#: the config key that selects a table (named in every error)
CONFIG_KEY = "estimator.calibration"
#: the JSON format tag and version of a table file
FORMAT = "dvsland-confidence-calibration"
VERSION = 1
#: the folder of the shipped tables (package data)
SHIPPED_DIR = Path(__file__).resolve().parent / "calibration"
#: the sensors the shipped tables were fitted on (``estimator.calibration: ideal`` picks ``<estimator>_ideal.json``)
SHIPPED_SETS = ("ideal", "realistic")
#: lowest raw relative sigma (c = 1 claims no error at all: the float32 round-off of D_hat instead)
LOG10_SIGMA_FLOOR = -6.0
#: Gaussian coverage of +-1 sigma and +-2 sigma (the report's targets)
TARGET_1S, TARGET_2S = 0.6827, 0.9545


class CalibrationParams(NamedTuple):
    """A calibration table.

    Attributes:
        sigma_knots: (K,) float32, strictly increasing knots in log10 of the raw relative sigma.
        feature_knots: (M,) float32, strictly increasing knots of the feature (M = 1 without one).
        log10_scale: (M, K) float32, log10 of the factor on the raw sigma at each knot.
        feature: one of :data:`FEATURES`.
    """

    sigma_knots: torch.Tensor
    feature_knots: torch.Tensor
    log10_scale: torch.Tensor
    feature: str = "none"


def identity_params(device=None) -> CalibrationParams:
    """The table that changes nothing (S = 0 everywhere)."""
    z = torch.zeros(1, dtype=torch.float32, device=device)
    return CalibrationParams(z, z.clone(), torch.zeros(1, 1, dtype=torch.float32, device=device), "none")


def check_params(p: CalibrationParams, what: str = "calibration") -> None:
    """Raise ValueError naming ``what`` when ``p`` is no usable table (shapes, order, finiteness)."""
    if not isinstance(p, CalibrationParams):
        raise ValueError(f"{what} must be a CalibrationParams, got {type(p).__name__}")
    if p.feature not in FEATURES:
        raise ValueError(f"{what}: feature must be one of {', '.join(FEATURES)}, got {p.feature!r}")
    sk, fk, ls = p.sigma_knots, p.feature_knots, p.log10_scale
    if sk.ndim != 1 or fk.ndim != 1 or sk.numel() < 1 or fk.numel() < 1:
        raise ValueError(f"{what}: sigma_knots and feature_knots must be non-empty 1-D, got shapes "
                         f"{tuple(sk.shape)} and {tuple(fk.shape)}")
    if tuple(ls.shape) != (fk.numel(), sk.numel()):
        raise ValueError(f"{what}: log10_scale must have shape (feature knots, sigma knots) = "
                         f"({fk.numel()}, {sk.numel()}), got {tuple(ls.shape)}")
    if p.feature == "none" and fk.numel() != 1:
        raise ValueError(f"{what}: a table without a feature has one feature knot, got {fk.numel()}")
    for name, t in (("sigma_knots", sk), ("feature_knots", fk), ("log10_scale", ls)):
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{what}: {name} must be finite")
    for name, t in (("sigma_knots", sk), ("feature_knots", fk)):
        if t.numel() > 1 and not bool((t[1:] > t[:-1]).all()):
            raise ValueError(f"{what}: {name} must be strictly increasing")


def params_to(p: CalibrationParams, device) -> CalibrationParams:
    """``p`` with its tensors as float32 on ``device``."""
    kw = dict(dtype=torch.float32, device=device)
    return p._replace(sigma_knots=p.sigma_knots.to(**kw), feature_knots=p.feature_knots.to(**kw),
                      log10_scale=p.log10_scale.to(**kw))


def _interp_index(knots: torch.Tensor, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Linear interpolation weights of ``x`` (B,) between ``knots`` (K,), constant beyond the ends:
    (i0, i1, w) with value = (1 - w) v[i0] + w v[i1]."""
    K = knots.numel()
    if K == 1:
        z = torch.zeros(x.shape, dtype=torch.long, device=x.device)
        return z, z, torch.zeros_like(x)
    i1 = torch.searchsorted(knots, x.contiguous()).clamp(1, K - 1)
    i0 = i1 - 1
    k0, k1 = knots[i0], knots[i1]
    w = ((x - k0) / (k1 - k0)).clamp(0.0, 1.0)
    return i0, i1, w


def log10_scale_at(params: CalibrationParams, log10_sigma: torch.Tensor,
                   feature: Optional[torch.Tensor] = None) -> torch.Tensor:
    """S (B,) float32: the table's log10 factor at (``log10_sigma``, ``feature``) (bilinear, constant
    beyond the knots; a table with a feature reads ``feature`` (B,), which must then be given)."""
    ls = params.log10_scale
    x = log10_sigma.to(torch.float32)
    i0, i1, w = _interp_index(params.sigma_knots, x)
    if params.feature_knots.numel() == 1:
        row = ls[0]
        return _lerp(row[i0], row[i1], w)
    if feature is None:
        raise ValueError(f"this calibration table reads the feature {params.feature!r}: pass feature=")
    f = feature.to(device=x.device, dtype=torch.float32)
    j0, j1, v = _interp_index(params.feature_knots, f)
    K = ls.shape[1]
    flat = ls.reshape(-1)
    return _lerp(_lerp(flat[j0 * K + i0], flat[j0 * K + i1], w), _lerp(flat[j1 * K + i0], flat[j1 * K + i1], w), v)


def _lerp(a: torch.Tensor, b: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """a + w (b - a): exactly a where b = a (a table of zeros stays exactly zero)."""
    return a + w * (b - a)


def raw_log10_sigma(confidence: torch.Tensor) -> torch.Tensor:
    """log10 of the relative sigma 0.1 sqrt(1/c - 1) (B,) float32, at least :data:`LOG10_SIGMA_FLOOR`
    (c = 1); +inf at c = 0."""
    c = confidence.to(torch.float32)
    return (0.5 * torch.log10((1.0 - c) / c) - 1.0).clamp_min(LOG10_SIGMA_FLOOR)


def feature_values(kind: str, n_events: Optional[torch.Tensor] = None, d_hat: Optional[torch.Tensor] = None,
                   structure: Optional[torch.Tensor] = None) -> Optional[torch.Tensor]:
    """The feature (B,) float32 of a table: ``events`` -> log10(1 + n_events), ``abs_d_hat`` ->
    log10 |D_hat| (at least -6; 0 where D_hat is NaN: such steps have c = 0 and pass unchanged),
    ``structure`` -> log10 of the ``structure`` diagnostic (at least -3; 0 where NaN: no estimate),
    ``none`` -> None."""
    if kind == "none":
        return None
    if kind == "events":
        if n_events is None:
            raise ValueError("the 'events' calibration feature needs the window's event counts")
        return torch.log10(1.0 + n_events.to(torch.float32).clamp_min(0.0))
    if kind == "abs_d_hat":
        if d_hat is None:
            raise ValueError("the 'abs_d_hat' calibration feature needs D_hat")
        a = torch.log10(d_hat.to(torch.float32).abs().clamp_min(1e-6))
        return torch.nan_to_num(a, nan=0.0)
    if kind == "structure":
        if structure is None:
            raise ValueError(f"the 'structure' calibration feature needs the estimator's {STRUCTURE_KEY!r} "
                             f"diagnostic (cmax gives it)")
        return torch.nan_to_num(torch.log10(structure.to(torch.float32).clamp_min(1e-3)), nan=0.0)
    raise ValueError(f"unknown calibration feature {kind!r}; use one of {', '.join(FEATURES)}")


def calibrate_confidence(confidence: torch.Tensor, params: CalibrationParams,
                         feature: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The calibrated confidence (B,) float32 in [0, 1] (module doc), all descents at once.

    Args:
        confidence: (B,) raw confidence in [0, 1] (0 = no estimate).
        params: :class:`CalibrationParams` on the confidence's device (:func:`params_to`).
        feature: (B,) the table's feature (:func:`feature_values`), None for a table without one.

    Returns:
        (B,) float32: ``c / (c + s^2 (1 - c))`` with s = 10^S; exactly ``c`` where S = 0; 0 where
        c = 0; 1 where c = 1; NaN stays NaN.
    """
    c = confidence.to(torch.float32)
    S = log10_scale_at(params, raw_log10_sigma(c), feature)
    s2 = torch.pow(10.0, 2.0 * S)
    cal = c / (c + s2 * (1.0 - c))
    cal = torch.where(S == 0, c, cal)
    cal = torch.where(c > 0, cal, c)  # c = 0 (no estimate) stays 0 (and 0/0 never appears)
    return cal.clamp(0.0, 1.0)


def window_event_counts(events, batch_size: int, device) -> torch.Tensor:
    """(B,) float32 events of each descent in ``events`` (None / empty: 0), without a host sync."""
    n = torch.zeros(int(batch_size), dtype=torch.float32, device=device)
    if events is None or not hasattr(events, "b") or events.b.numel() == 0:
        return n
    b = events.b.to(device)
    return n.index_add_(0, b, torch.ones(b.shape, dtype=torch.float32, device=device))


def calibrate_output(out, events, batch_size: int, params: Optional[CalibrationParams]):
    """``out`` (:class:`~dvsland.estimators.base.EstimateOut`) with its confidence calibrated by
    ``params`` and the raw one in its diagnostics under :data:`RAW_KEY` (unchanged when ``params``
    is None or ``out`` was calibrated already). D_hat is never changed."""
    if params is None or RAW_KEY in out.diagnostics:
        return out
    raw = out.confidence
    p = params_to(params, raw.device)
    n = window_event_counts(events, batch_size, raw.device) if p.feature == "events" else None
    st = out.diagnostics.get(STRUCTURE_KEY) if p.feature == "structure" else None
    f = feature_values(p.feature, n_events=n, d_hat=out.d_hat, structure=None if st is None else st.to(raw.device))
    conf = calibrate_confidence(raw, p, f).to(raw.dtype)
    diag = dict(out.diagnostics)
    diag[RAW_KEY] = raw
    if "confidence" in diag:
        diag["confidence"] = conf
    return out._replace(confidence=conf, diagnostics=diag)


# ---------------------------------------------------------------------------------------------- fitting
def flat_sample(d_true, d_hat, confidence) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d_true, d_hat, confidence) of a calibration sample as flat float64 NumPy arrays (N,);
    ValueError naming them when their lengths differ."""
    d_true = np.asarray(d_true, dtype=np.float64).ravel()
    d_hat = np.asarray(d_hat, dtype=np.float64).ravel()
    conf = np.asarray(confidence, dtype=np.float64).ravel()
    if not (d_true.shape == d_hat.shape == conf.shape):
        raise ValueError(f"d_true, d_hat and confidence must have the same length, got {d_true.size}, "
                         f"{d_hat.size}, {conf.size}")
    return d_true, d_hat, conf


def _z0(d_true, d_hat, conf):
    """|D_hat - D| over the raw predicted sigma (the report's scale max(|D_hat|, |D|)), the raw
    log10 relative sigma, and the answered mask (D_hat finite, c > 0), as float64 NumPy (N,)."""
    d_true, d_hat, conf = flat_sample(d_true, d_hat, conf)
    ans = np.isfinite(d_hat) & np.isfinite(d_true) & (conf > 0) & np.isfinite(conf)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.maximum(0.5 * np.log10((1.0 - conf) / conf) - 1.0, LOG10_SIGMA_FLOOR)
        scale = np.maximum(np.abs(d_hat), np.abs(d_true))
        z0 = np.abs(d_hat - d_true) / (10.0 ** x * scale)
    z0 = np.where(scale > 0, z0, 0.0)
    return z0, x, ans


#: the log10 factors a cell's fit chooses from (1/1000 to 1000, 0.005 decades apart)
_GRID = np.round(np.arange(-3.0, 3.0 + 1e-9, 0.005), 6)


def best_log10_scale(z0: np.ndarray) -> Tuple[float, float]:
    """The log10 factor S on the raw sigma that brings the share of ``z0`` (|error| / raw sigma)
    inside 1 and 2 calibrated sigmas closest to 68.3 % / 95.4 % (the smaller of the two gaps'
    maximum; the middle of a tie), and that largest gap."""
    z = np.sort(np.asarray(z0, dtype=np.float64))
    if z.size == 0:
        return 0.0, float("nan")
    s = 10.0 ** _GRID
    c1 = np.searchsorted(z, s, side="right") / z.size
    c2 = np.searchsorted(z, 2.0 * s, side="right") / z.size
    loss = np.maximum(np.abs(c1 - TARGET_1S), np.abs(c2 - TARGET_2S))
    best = loss.min()
    ties = np.flatnonzero(loss <= best + 1e-12)
    return float(_GRID[ties[len(ties) // 2]]), float(best)


def _pav(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted isotonic (non-decreasing) regression of ``y`` (pool adjacent violators)."""
    vals, wts, cnt = [], [], []
    for yi, wi in zip(y.tolist(), w.tolist()):
        vals.append(yi)
        wts.append(wi)
        cnt.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            wsum = wts[-2] + wts[-1]
            v = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / wsum if wsum > 0 else 0.5 * (vals[-2] + vals[-1])
            n = cnt[-2] + cnt[-1]
            vals[-2:], wts[-2:], cnt[-2:] = [v], [wsum], [n]
    return np.repeat(np.asarray(vals), cnt)


def _edges(v: np.ndarray, n_bins: int) -> np.ndarray:
    """Quantile edges of ``v`` into at most ``n_bins`` bins (duplicates dropped)."""
    e = np.unique(np.quantile(v, np.linspace(0.0, 1.0, n_bins + 1)))
    return e if e.size >= 2 else np.array([v.min(), v.min() + 1e-6])


def _bin(v, e):
    return np.clip(np.searchsorted(e, v, side="right") - 1, 0, e.size - 2)


def fit_calibration(d_true, d_hat, confidence, feature: str = "none", n_events=None, *, structure=None,
                    sigma_bins: int = 6, feature_bins: int = 4, min_count: int = 40) -> Tuple[CalibrationParams, dict]:
    """Fit a calibration table to a sample of estimates (NumPy; N steps, pooled over sites).

    Cells: the answered steps (D_hat finite, c > 0) split at quantiles of the raw log10 sigma
    (``sigma_bins``) and of the feature (``feature_bins``); each cell's knot is the median of its
    steps. In each cell the factor is the one that brings its 1-sigma and 2-sigma shares closest to
    68.3 % / 95.4 % (:func:`best_log10_scale`); a cell with fewer than ``min_count`` steps takes the
    factor of its whole feature row (and a row with too few, that of the whole sample). Along each
    row the calibrated log10 sigma is then made non-decreasing (weighted isotonic regression), so
    the map is monotone in the raw confidence.

    Args:
        d_true, d_hat, confidence: (N,) true divergence, estimates (NaN = none), raw confidence.
        feature: one of :data:`FEATURES`.
        n_events: (N,) events of each step's window (``events``).
        structure: (N,) the estimator's ``structure`` diagnostic at each step (``structure``).

    Returns:
        (:class:`CalibrationParams`, {"n_estimates", "cells": [[count per cell]], "max_gap_cells"}).
    """
    if feature not in FEATURES:
        raise ValueError(f"feature must be one of {', '.join(FEATURES)}, got {feature!r}")
    z0, x, ans = _z0(d_true, d_hat, confidence)
    if ans.sum() < max(int(min_count), 1):
        raise ValueError(f"too few estimates to fit a calibration: {int(ans.sum())} (need >= {min_count})")
    if feature == "none":
        f = np.zeros_like(x)
    else:
        f = _feature_np(feature, d_hat, n_events, structure)
    z0, x, f = z0[ans], x[ans], f[ans]
    ex = _edges(x, int(sigma_bins))
    ef = _edges(f, int(feature_bins)) if feature != "none" else np.array([0.0, 1.0])
    bx, bf = _bin(x, ex), _bin(f, ef)
    K, M = ex.size - 1, ef.size - 1
    s_all, _ = best_log10_scale(z0)
    sk = np.array([np.median(x[bx == k]) if (bx == k).any() else 0.5 * (ex[k] + ex[k + 1]) for k in range(K)])
    fk = np.array([np.median(f[bf == m]) if (bf == m).any() else 0.5 * (ef[m] + ef[m + 1]) for m in range(M)])
    if feature == "none":
        fk = np.zeros(1)
    table = np.zeros((M, K))
    counts = np.zeros((M, K), dtype=int)
    gaps = np.full((M, K), np.nan)
    for m in range(M):
        row = bf == m
        s_row = best_log10_scale(z0[row])[0] if row.sum() >= min_count else s_all
        for k in range(K):
            cell = row & (bx == k)
            counts[m, k] = int(cell.sum())
            if counts[m, k] >= min_count:
                table[m, k], gaps[m, k] = best_log10_scale(z0[cell])
            else:
                table[m, k] = s_row
        y = _pav(sk + table[m], np.maximum(counts[m], 1).astype(np.float64))
        table[m] = y - sk
    # strictly increasing knots (medians of neighbouring bins can coincide on a discrete confidence)
    sk = _strict(sk)
    fk = _strict(fk)
    p = CalibrationParams(torch.tensor(sk, dtype=torch.float32), torch.tensor(fk, dtype=torch.float32),
                          torch.tensor(table, dtype=torch.float32), feature)
    check_params(p)
    return p, {"n_estimates": int(ans.sum()), "cell_counts": counts.tolist(),
               "max_gap_cells": None if np.isnan(gaps).all() else float(np.nanmax(gaps))}


def _strict(k: np.ndarray) -> np.ndarray:
    out = np.asarray(k, dtype=np.float64).copy()
    for i in range(1, out.size):
        if out[i] <= out[i - 1] + 1e-4:
            out[i] = out[i - 1] + 1e-4
    return out


def _flat(v, dtype=np.float64) -> Optional[torch.Tensor]:
    """A NumPy-like sample ``v`` as a flat (N,) tensor of ``dtype`` (None stays None)."""
    return None if v is None else torch.as_tensor(np.asarray(v, dtype=dtype).ravel())


def _feature_np(kind: str, d_hat, n_events=None, structure=None) -> np.ndarray:
    """:func:`feature_values` over a flat NumPy sample (N,), float64."""
    f = feature_values(kind, n_events=_flat(n_events), d_hat=_flat(d_hat), structure=_flat(structure))
    return f.double().numpy()


def apply_calibration_np(params: CalibrationParams, d_hat, confidence, n_events=None, structure=None) -> np.ndarray:
    """:func:`calibrate_confidence` over a flat NumPy sample (N,) (the fitter's and the report's
    offline check), float64."""
    f = feature_values(params.feature, n_events=_flat(n_events), d_hat=_flat(d_hat, np.float32),
                       structure=_flat(structure))
    return calibrate_confidence(_flat(confidence, np.float32), params_to(params, "cpu"), f).double().numpy()


# ---------------------------------------------------------------------------------------------- files
def calibration_to_json(params: CalibrationParams, estimator: str, fit: Optional[dict] = None) -> dict:
    """The JSON object of a table: format, version, estimator, feature, knots, table, and ``fit``
    (where and on what it was fitted: config, sensor, seeds, coverage before / after, ...)."""
    check_params(params)
    return {"format": FORMAT, "version": VERSION, "estimator": str(estimator), "feature": params.feature,
            "sigma_knots_log10": [round(float(v), 6) for v in params.sigma_knots.tolist()],
            "feature_knots": [round(float(v), 6) for v in params.feature_knots.tolist()],
            "log10_scale": [[round(float(v), 6) for v in row] for row in params.log10_scale.tolist()],
            "fit": dict(fit or {})}


def params_from_json(obj: dict, what: str = CONFIG_KEY) -> Tuple[CalibrationParams, dict]:
    """(:class:`CalibrationParams`, the whole object) of a table's JSON object; ValueError naming
    ``what`` when it is not one."""
    if not isinstance(obj, dict) or obj.get("format") != FORMAT:
        raise ValueError(f"{what}: not a dvsland calibration table (format must be {FORMAT!r})")
    if obj.get("version") != VERSION:
        raise ValueError(f"{what}: calibration table version {obj.get('version')!r} is not supported (use {VERSION})")
    for key in ("estimator", "feature", "sigma_knots_log10", "feature_knots", "log10_scale"):
        if key not in obj:
            raise ValueError(f"{what}: calibration table lacks {key!r}")
    try:
        p = CalibrationParams(torch.tensor(obj["sigma_knots_log10"], dtype=torch.float32),
                              torch.tensor(obj["feature_knots"], dtype=torch.float32),
                              torch.tensor(obj["log10_scale"], dtype=torch.float32), str(obj["feature"]))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: calibration table numbers are malformed: {exc}") from None
    try:
        check_params(p, what)
    except ValueError as exc:
        raise ValueError(str(exc) if str(exc).startswith(what) else f"{what}: {exc}") from None
    return p, obj


def shipped_calibrations() -> Dict[str, Path]:
    """{name: path} of the shipped tables (``cmax_ideal``, ...)."""
    if not SHIPPED_DIR.is_dir():
        return {}
    return {p.stem: p for p in sorted(SHIPPED_DIR.glob("*.json"))}


def load_calibration(path, what: str = CONFIG_KEY) -> Tuple[CalibrationParams, dict]:
    """Read a table file: (:class:`CalibrationParams`, its JSON object); ValueError naming ``what``."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{what}: no such calibration file: {str(path)!r}")
    try:
        obj = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{what}: cannot read calibration file {str(path)!r}: {exc}") from None
    return params_from_json(obj, f"{what} ({p.name})")


def _base_name(name: str) -> str:
    """'fast=cmax[n_grid=21]' -> 'cmax'."""
    s = str(name)
    if "=" in s.split("[")[0]:
        s = s.split("=", 1)[1]
    return s.split("[")[0].strip()


def calibration_off(value) -> bool:
    """Whether an ``estimator.calibration`` value asks for no table (``none``, empty or None)."""
    return value is None or str(value).strip().lower() in ("", "none")


def resolve_calibration(value: str, estimator: str, checkpoint: Optional[str] = None) -> Optional[Tuple[CalibrationParams, dict]]:
    """The table that ``estimator.calibration = value`` selects for ``estimator``, or None.

    ``none`` (or empty): None. A shipped set (``ideal``, ``realistic``): the shipped
    ``<checkpoint file's stem>_<set>.json`` where one ships for the checkpoint the estimator reads
    and was fitted for this estimator (``learned_cnn_both_realistic.json`` for ``learned_cnn_both.pt``),
    else ``<estimator>_<set>.json``.
    A shipped name (``cmax_realistic``) or a path to a ``.json`` file:
    that table. A table fitted for another estimator, or (``checkpoint``: the text
    ``"<file> sha256:<digits>"`` of the checkpoint the estimator reads) for another checkpoint, is
    refused. Errors (ValueError) name ``estimator.calibration``, and list the shipped names.
    """
    if calibration_off(value):
        return None
    v = str(value).strip()
    est = _base_name(estimator)
    shipped = shipped_calibrations()
    names = ", ".join(sorted(shipped)) or "none"
    if v in SHIPPED_SETS:
        own = f"{_checkpoint_stem(checkpoint)}_{v}" if checkpoint else None
        key = own if own in shipped and _fitted_for(shipped[own]) == est else f"{est}_{v}"
        if key not in shipped:
            raise ValueError(f"{CONFIG_KEY}: no shipped {v!r} calibration for estimator {est!r} (shipped: {names}); "
                             f"fit one (docs/estimators.md) and give its path")
        path = shipped[key]
    elif v in shipped:
        path = shipped[v]
    elif v.endswith(".json") or "/" in v or "\\" in v:
        path = Path(v).expanduser()
    else:
        raise ValueError(f"{CONFIG_KEY}: {v!r} is neither 'none', a shipped set ({', '.join(SHIPPED_SETS)}), a shipped "
                         f"table ({names}) nor a path to a .json file")
    params, obj = load_calibration(path)
    fitted = _base_name(obj.get("estimator", ""))
    if fitted != est:
        raise ValueError(f"{CONFIG_KEY}: {v!r} was fitted for estimator {fitted!r}, not {est!r}")
    fit_ck = (obj.get("fit") or {}).get("checkpoint")
    if checkpoint and fit_ck and _sha(fit_ck) != _sha(checkpoint):
        raise ValueError(f"{CONFIG_KEY}: {v!r} was fitted on the checkpoint {fit_ck}, but this {est} reads "
                         f"{checkpoint}; fit a table for it (docs/estimators.md)")
    return params, obj


def _fitted_for(path: Path) -> str:
    """The estimator a table file was fitted for ('' where it cannot be read): a checkpoint's own
    table (``learned_cnn_dagger_realistic``) serves the estimator that reads the checkpoint, not a
    ``fused`` one that holds it."""
    try:
        return _base_name(load_calibration(path)[1].get("estimator", ""))
    except ValueError:
        return ""


def _sha(text: str) -> str:
    """The sha256 digits of a checkpoint text ``"file sha256:abc..."`` (the text itself without one),
    cut to the 12 digits the reports keep."""
    t = str(text)
    return (t.split("sha256:", 1)[1].strip() if "sha256:" in t else t.strip())[:12]


def _checkpoint_stem(text: str) -> str:
    """The file stem of a checkpoint text ``"file sha256:abc..."`` (``learned_cnn_both`` of
    ``"learned_cnn_both.pt sha256:aac95e06d692"``), the other half of what :func:`_sha` reads."""
    return Path(str(text).split("sha256:", 1)[0].strip()).stem


def checkpoint_sha256(estimator) -> Optional[str]:
    """``"<file> sha256:<12 hex digits>"`` of the checkpoint file a built estimator reads (its
    ``checkpoint`` attribute), None when it reads none."""
    ck = getattr(estimator, "checkpoint", None)
    if not isinstance(ck, (str, os.PathLike)) or not str(ck) or not Path(ck).is_file():
        return None
    return f"{Path(ck).name} sha256:{file_sha256(ck)}"


__all__ = ["FEATURES", "STRUCTURE_KEY", "RAW_KEY", "CONFIG_KEY", "SHIPPED_SETS", "CalibrationParams", "identity_params",
           "check_params", "params_to", "log10_scale_at", "raw_log10_sigma", "feature_values", "calibrate_confidence",
           "window_event_counts", "calibrate_output", "best_log10_scale", "fit_calibration", "apply_calibration_np",
           "calibration_to_json", "params_from_json", "shipped_calibrations", "load_calibration", "resolve_calibration"]
