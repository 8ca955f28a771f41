"""Divergence estimators behind one interface (docs/estimators.md).

Public names: :class:`DivergenceEstimator`, :class:`Truth`, :func:`get_estimator`,
:func:`register_estimator`, :func:`available_estimators`, :func:`estimator_label` (the alias of
``alias=name``), and the built-in estimators
(``dpr``, ``cmax``, ``oracle``, ``snn``, ``learned``, and ``fused``, which combines others).
"""

from .base import DivergenceEstimator, EstimateOut, Truth
from .registry import (available_estimators, estimator_label, get_estimator, refresh_entry_points,
                       register_estimator)
from . import oracle  # noqa: F401  (registers 'oracle')
from . import dpr  # noqa: F401  (registers 'dpr')
from . import cmax  # noqa: F401  (registers 'cmax')
from . import snn  # noqa: F401  (registers 'snn')
from . import learned  # noqa: F401  (registers 'learned')
from . import fused  # noqa: F401  (registers 'fused')
from .factory import estimator_params, make_estimator

__all__ = ["DivergenceEstimator", "EstimateOut", "Truth", "get_estimator", "register_estimator", "available_estimators",
           "estimator_label",
           "refresh_entry_points", "make_estimator", "estimator_params"]
