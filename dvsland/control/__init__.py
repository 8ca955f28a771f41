"""Control: the TTC target, the NaN-aware moving-average filter and thrust laws.

Public names: :func:`tau_target`, :func:`initial_ttc`, :func:`nan_moving_average`,
:class:`MovingAverageFilter`, :class:`Controller`, :class:`ControlOutput`, :class:`TauPController`.
"""

from .filter import MovingAverageFilter, nan_moving_average
from .target import initial_ttc, tau_target
from .tau_p import ControlOutput, Controller, TauPController

__all__ = ["tau_target", "initial_ttc", "nan_moving_average", "MovingAverageFilter", "Controller",
           "ControlOutput", "TauPController"]
