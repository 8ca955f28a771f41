"""The batched closed-loop descent simulator.

Public names: :func:`simulate`, :class:`SimulationResult`, :class:`ClosedLoop`,
:func:`build_layout`, :class:`BatchLayout`, :func:`termination_code`, :data:`OUTCOMES`.
"""

from .api import simulate
from dvsland.layout import BatchLayout, build_layout, expand_seeds, setting_label
from .loop import ClosedLoop
from .result import TRACE_FIELDS, SimulationResult, TraceRecorder
from .termination import OUTCOMES, termination_code

__all__ = ["simulate", "SimulationResult", "ClosedLoop", "BatchLayout", "build_layout", "expand_seeds",
           "setting_label", "termination_code", "OUTCOMES", "TRACE_FIELDS", "TraceRecorder"]
