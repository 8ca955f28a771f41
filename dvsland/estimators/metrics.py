"""Error metrics of divergence estimates against the truth (pure numpy)."""

from __future__ import annotations

from typing import Dict, Sequence, Tuple

import numpy as np

#: the sites the accuracy target applies to (H and I are nearly featureless): the "sites A-G" of
#: the evaluation's summary and of its TensorBoard histograms
TARGET_SITES: Tuple[str, ...] = ("A", "B", "C", "D", "E", "F", "G")

#: altitude bands (label, low m, high m): error is also reported per band
BANDS: Tuple[Tuple[str, float, float], ...] = (("> 2 km", 2000.0, np.inf), ("2 km - 500 m", 500.0, 2000.0),
                                               ("< 500 m", 0.0, 500.0))


def divergence_metrics(d_hat: np.ndarray, d_true: np.ndarray) -> Dict[str, float]:
    """Metrics over N steps.

    Args:
        d_hat: (N,) estimates, 1/s, NaN = no estimate.
        d_true: (N,) true D, 1/s (non-zero).

    Returns:
        n_steps; coverage (fraction of steps with a finite estimate); median_abs_rel_err and
        rmse (1/s) over steps with an estimate; within_10 and within_20: fraction of ALL steps
        whose estimate is within 10 % / 20 % of the truth (a missing estimate counts as a miss);
        bias_rel: median relative error (signed). NaN where undefined (no steps or no estimate).
    """
    d_hat = np.asarray(d_hat, dtype=np.float64).ravel()
    d_true = np.asarray(d_true, dtype=np.float64).ravel()
    if d_hat.shape != d_true.shape:
        raise ValueError(f"d_hat and d_true must have the same shape, got {d_hat.shape} and {d_true.shape}")
    n = d_hat.size
    ok = np.isfinite(d_hat)
    nan = float("nan")
    if n == 0:
        return dict(n_steps=0, coverage=nan, median_abs_rel_err=nan, rmse=nan, within_10=nan, within_20=nan,
                    bias_rel=nan)
    rel = (d_hat - d_true) / np.abs(d_true)
    rel_ok = rel[ok]
    return dict(
        n_steps=int(n),
        coverage=float(ok.mean()),
        median_abs_rel_err=float(np.median(np.abs(rel_ok))) if ok.any() else nan,
        rmse=float(np.sqrt(np.mean((d_hat[ok] - d_true[ok]) ** 2))) if ok.any() else nan,
        within_10=float(np.sum(np.abs(rel_ok) <= 0.10) / n),
        within_20=float(np.sum(np.abs(rel_ok) <= 0.20) / n),
        bias_rel=float(np.median(rel_ok)) if ok.any() else nan,
    )


def band_metrics(d_hat: np.ndarray, d_true: np.ndarray, altitude_m: np.ndarray,
                 bands: Sequence[Tuple[str, float, float]] = BANDS) -> Dict[str, Dict[str, float]]:
    """:func:`divergence_metrics` per altitude band (altitude_m (N,) at each step)."""
    altitude_m = np.asarray(altitude_m, dtype=np.float64).ravel()
    out = {}
    for label, lo, hi in bands:
        m = (altitude_m >= lo) & (altitude_m < hi)
        out[label] = divergence_metrics(np.asarray(d_hat).ravel()[m], np.asarray(d_true).ravel()[m])
    return out
