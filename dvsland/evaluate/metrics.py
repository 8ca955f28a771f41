"""Error metrics of divergence estimates (defined in :mod:`dvsland.estimators.metrics`, where
training code can reach them without importing the evaluation)."""

from dvsland.estimators.metrics import BANDS, band_metrics, divergence_metrics

__all__ = ["BANDS", "band_metrics", "divergence_metrics"]
