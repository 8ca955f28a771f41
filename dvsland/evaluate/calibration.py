"""Calibration of an estimator's confidence: does its predicted error match its real error?

Every estimator returns ``(D_hat, confidence)`` per step. The filters read the confidence c as a
relative standard error (:func:`dvsland.estimators.base.confidence_rel_sigma`, the inverse of
:func:`dvsland.estimators.base.confidence_from_rel_std`)::

    sigma_rel(c) = 0.1 * sqrt(1 / c - 1)        (0 at c = 1, 0.1 at c = 0.5, inf at c = 0)
    sigma(c)     = max(sigma_rel(c), 1e-6) * max(|D_hat|, |D|)   1/s

the scale being the efference filter's ``max(|D_hat|, |h|)`` with its prediction h taken as the true
D (an ideal filter). A calibrated estimator has |D_hat - D| <= sigma on 68.3 % and <= 2 sigma on
95.4 % of its estimates. Steps without an estimate (D_hat NaN) or with confidence 0 (sigma = inf:
the filter ignores them) are abstentions, counted apart and left out of the coverage.

Everything here is pure NumPy over flat arrays of N steps (no loop over steps):
:func:`predicted_sigma`, :func:`coverage_table`, :func:`reliability_bins`,
:func:`risk_coverage`, and :func:`calibration_summary` which gathers them per estimator.
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence

import numpy as np
import torch

from dvsland.estimators.base import confidence_rel_sigma
from dvsland.estimators.calibrate import flat_sample
from dvsland.estimators.snn.data import SITE_TYPES

#: Gaussian coverage of +-1 sigma and +-2 sigma
TARGET_1S, TARGET_2S = 0.6827, 0.9545
#: smallest relative sigma: float32 round-off of D_hat (confidence 1 claims no error at all)
REL_SIGMA_FLOOR = 1e-6
#: edges of the reliability bins in predicted relative sigma (c = 0.99, 0.96, 0.8, 0.5, 0.2, 0.04, 0.01)
REL_SIGMA_EDGES = (0.0, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, np.inf)
#: shares of kept steps at which the risk-coverage curve is reported
RISK_GRID = tuple(np.round(np.linspace(0.05, 1.0, 20), 2))


def site_type(site: str) -> str:
    """The type of a site name ("A" -> "craters", "F~1" -> "rocky"; types of
    :data:`dvsland.estimators.snn.data.SITE_TYPES`), "other" for a name outside them."""
    base = str(site).split("~")[0]
    for kind, names in SITE_TYPES.items():
        if len(base) == 1 and base in names:
            return kind
    return "other"


def rel_sigma(confidence) -> np.ndarray:
    """Predicted relative standard error of each estimate: the filters' mapping
    (:func:`~dvsland.estimators.base.confidence_rel_sigma`).

    Args:
        confidence: (N,) float in [0, 1].

    Returns:
        (N,) float64, 0 at c = 1, inf at c = 0 or where c is not finite.
    """
    c = torch.as_tensor(np.asarray(confidence, dtype=np.float64))
    return confidence_rel_sigma(c).numpy()


def predicted_sigma(confidence, d_hat, d_true) -> np.ndarray:
    """Predicted standard error of each estimate, 1/s: ``rel_sigma(c) * max(|D_hat|, |D|)``.

    Args:
        confidence: (N,) float in [0, 1].
        d_hat: (N,) float estimates, 1/s (NaN = none).
        d_true: (N,) float true divergence, 1/s.

    Returns:
        (N,) float64 sigma, 1/s, at least :data:`REL_SIGMA_FLOOR` times the scale (the float32
        round-off of D_hat); inf where c = 0, NaN where D_hat is NaN.
    """
    d_hat = np.asarray(d_hat, dtype=np.float64)
    scale = np.maximum(np.abs(d_hat), np.abs(np.asarray(d_true, dtype=np.float64)))
    with np.errstate(invalid="ignore"):
        return np.maximum(rel_sigma(confidence), REL_SIGMA_FLOOR) * scale


def _check(d_true, d_hat, confidence):
    d_true, d_hat, conf = flat_sample(d_true, d_hat, confidence)
    if not np.isfinite(d_true).all():
        raise ValueError("d_true must be finite (the scored steps' true divergence)")
    return d_true, d_hat, conf


def _z_scores(d_true, d_hat, confidence):
    """(|err| / sigma (N,), answered (N,) bool, nan (N,) bool, zero_conf (N,) bool)."""
    d_true, d_hat, conf = _check(d_true, d_hat, confidence)
    nan = ~np.isfinite(d_hat)
    sig = predicted_sigma(conf, d_hat, d_true)
    zero = ~nan & ~np.isfinite(sig)
    answered = ~nan & ~zero
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.abs(d_hat - d_true) / sig
    z = np.where(sig == 0, np.where(d_hat == d_true, 0.0, np.inf), z)  # c = 1: covered only when exact
    return np.where(answered, z, np.nan), answered, nan, zero


def _coverage_row(z, answered, nan, zero) -> dict:
    n, n_ans = int(z.size), int(answered.sum())
    zc = z[answered]
    c1 = float((zc <= 1.0).mean()) if n_ans else None
    c2 = float((zc <= 2.0).mean()) if n_ans else None
    return {"n_steps": n, "n_estimates": n_ans, "n_nan": int(nan.sum()), "n_zero_confidence": int(zero.sum()),
            "abstain_share": float(1.0 - n_ans / n) if n else None, "cover_1sigma": c1, "cover_2sigma": c2,
            "gap_1sigma": None if c1 is None else c1 - TARGET_1S, "gap_2sigma": None if c2 is None else c2 - TARGET_2S,
            "within_5_points": None if c1 is None else bool(abs(c1 - TARGET_1S) <= 0.05 and abs(c2 - TARGET_2S) <= 0.05)}


def coverage_table(d_true, d_hat, confidence, groups: Optional[Sequence[str]] = None) -> Dict[str, dict]:
    """Share of estimates inside their predicted 1 sigma and 2 sigma, per group and over all.

    Args:
        d_true, d_hat, confidence: (N,) arrays (1/s, 1/s, [0, 1]); D_hat NaN = no estimate.
        groups: (N,) labels (e.g. site types), or None for the overall row only.

    Returns:
        {group: row, ..., "all": row}; a row holds ``n_steps``, ``n_estimates`` (the coverage's
        denominator), ``n_nan`` and ``n_zero_confidence`` (the abstentions), ``abstain_share``,
        ``cover_1sigma``, ``cover_2sigma`` (None without estimates), their gaps to 68.3 % / 95.4 %
        and ``within_5_points`` (both gaps within 0.05).
    """
    z, ans, nan, zero = _z_scores(d_true, d_hat, confidence)
    out = {}
    if groups is not None:
        g = np.asarray(groups).ravel()
        if g.size != z.size:
            raise ValueError(f"groups must have one label per step ({z.size}), got {g.size}")
        for name in dict.fromkeys(g.tolist()):
            m = g == name
            out[str(name)] = _coverage_row(z[m], ans[m], nan[m], zero[m])
    out["all"] = _coverage_row(z, ans, nan, zero)
    return out


def reliability_bins(d_true, d_hat, confidence, edges: Sequence[float] = REL_SIGMA_EDGES) -> list:
    """Reliability diagram data: estimates binned by predicted relative sigma, each bin's RMS
    predicted relative sigma against its observed RMS relative error (both divided by the same
    scale max(|D_hat|, |D|)); a calibrated estimator lies on the diagonal.

    Args:
        d_true, d_hat, confidence: (N,) arrays; abstentions are left out.
        edges: increasing bin edges of the relative sigma (the last may be inf).

    Returns:
        [{"lo", "hi", "n", "pred_rms_rel_sigma", "obs_rms_rel_err", "cover_1sigma"}] for the
        bins holding estimates.
    """
    d_true, d_hat, conf = _check(d_true, d_hat, confidence)
    e = np.asarray(edges, dtype=np.float64)
    if e.ndim != 1 or e.size < 2 or np.any(np.diff(e) <= 0):
        raise ValueError(f"edges must be at least two increasing numbers, got {list(edges)}")
    z, ans, _, _ = _z_scores(d_true, d_hat, conf)
    rs = rel_sigma(conf)[ans]
    scale = np.maximum(np.abs(d_hat), np.abs(d_true))[ans]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_err = np.where(scale > 0, np.abs(d_hat[ans] - d_true[ans]) / scale, 0.0)
    idx = np.clip(np.searchsorted(e, rs, side="right") - 1, 0, e.size - 2)
    nb = e.size - 1
    n = np.bincount(idx, minlength=nb)
    pred = np.bincount(idx, weights=rs ** 2, minlength=nb)
    obs = np.bincount(idx, weights=rel_err ** 2, minlength=nb)
    cov = np.bincount(idx, weights=(z[ans] <= 1.0).astype(np.float64), minlength=nb)
    keep = np.flatnonzero(n)
    return [{"lo": float(e[i]), "hi": float(e[i + 1]), "n": int(n[i]),
             "pred_rms_rel_sigma": float(np.sqrt(pred[i] / n[i])), "obs_rms_rel_err": float(np.sqrt(obs[i] / n[i])),
             "cover_1sigma": float(cov[i] / n[i])} for i in keep]


def risk_coverage(d_true, d_hat, confidence, grid: Sequence[float] = RISK_GRID) -> dict:
    """Risk-coverage curve: steps sorted by confidence, highest first (abstentions last, never
    kept); at each share kept, the mean and median |relative error| of the kept steps. A useful
    confidence gives a curve that rises from left to right.

    Args:
        d_true, d_hat, confidence: (N,) arrays.
        grid: shares of all N steps kept, in (0, 1]; shares beyond the answered share are None.

    Returns:
        {"share_kept": [...], "mean_abs_rel_err": [...], "median_abs_rel_err": [...],
        "min_confidence": [...] (the confidence of the last kept step), "answered_share": float}.
    """
    d_true, d_hat, conf = _check(d_true, d_hat, confidence)
    _, ans, _, _ = _z_scores(d_true, d_hat, conf)
    n, n_ans = d_true.size, int(ans.sum())
    rel = np.abs(d_hat - d_true) / np.maximum(np.abs(d_true), 1e-12)
    key = np.where(ans, conf, -np.inf)
    order = np.argsort(-key, kind="stable")
    r, c = rel[order][:n_ans], conf[order][:n_ans]
    mean = np.cumsum(r) / np.arange(1, n_ans + 1) if n_ans else np.zeros(0)
    g = np.asarray(grid, dtype=np.float64)
    if np.any((g <= 0) | (g > 1)):
        raise ValueError(f"grid shares must lie in (0, 1], got {list(grid)}")
    k = np.ceil(g * n).astype(int)  # steps kept at each share
    ok = (k >= 1) & (k <= n_ans)
    med = [float(np.median(r[:kk])) if o else None for kk, o in zip(k, ok)]  # one per grid point
    return {"share_kept": [float(x) for x in g],
            "mean_abs_rel_err": [float(mean[kk - 1]) if o else None for kk, o in zip(k, ok)],
            "median_abs_rel_err": med,
            "min_confidence": [float(c[kk - 1]) if o else None for kk, o in zip(k, ok)],
            "answered_share": float(n_ans / n) if n else 0.0}


def calibration_summary(d_true, d_hat: Dict[str, np.ndarray], confidence: Dict[str, np.ndarray],
                        scored, sites: Sequence[str]) -> dict:
    """The calibration report of every estimator of an evaluation.

    Args:
        d_true: (B, K) float true divergence, 1/s.
        d_hat: {estimator: (B, K) float estimates, 1/s, NaN = none}.
        confidence: {estimator: (B, K) float in [0, 1]}.
        scored: (B, K) bool, the steps that count.
        sites: B site names; their types (:func:`site_type`) group the coverage table.

    Returns:
        JSON-ready {"sigma_mapping", "targets", "site_types", "estimators": {name: {"coverage",
        "reliability", "risk_coverage"}}}.
    """
    sc = np.asarray(scored, dtype=bool)
    types = np.broadcast_to(np.array([site_type(s) for s in sites])[:, None], sc.shape)
    dt, ty = np.asarray(d_true, dtype=np.float64)[sc], types[sc]
    ests = {}
    for name, dh in d_hat.items():
        if name not in confidence:
            raise ValueError(f"no confidence recorded for estimator {name!r}")
        h, c = np.asarray(dh, dtype=np.float64)[sc], np.asarray(confidence[name], dtype=np.float64)[sc]
        ests[name] = {"coverage": coverage_table(dt, h, c, ty), "reliability": reliability_bins(dt, h, c),
                      "risk_coverage": risk_coverage(dt, h, c)}
    return {"sigma_mapping": "sigma = max(0.1 sqrt(1/c - 1), 1e-6) * max(|D_hat|, |D|) (the filters' confidence_rel_sigma; "
                             "1e-6: float32 round-off)",
            "targets": {"cover_1sigma": TARGET_1S, "cover_2sigma": TARGET_2S, "tolerance": 0.05},
            "site_types": {s: site_type(s) for s in sites}, "estimators": ests}
