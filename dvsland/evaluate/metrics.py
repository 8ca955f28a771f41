"""Error metrics of divergence estimates and the target sites (defined in
:mod:`dvsland.estimators.metrics`, where training code and the TensorBoard writer of
:mod:`dvsland.report` reach them without importing the evaluation)."""

from dvsland.estimators.metrics import BANDS, TARGET_SITES, band_metrics, divergence_metrics

__all__ = ["BANDS", "TARGET_SITES", "band_metrics", "divergence_metrics"]
