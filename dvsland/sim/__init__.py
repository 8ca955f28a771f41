"""The batched closed-loop descent simulator.

The loop is one typed state and one step: :func:`init_state` gives the :class:`LoopState` of B
descents, :func:`loop_step` flies one control step and returns the next state and the step's
:class:`StepOutput`. Everything that flies descents runs on it: :func:`simulate` (through the
:class:`ClosedLoop` driver and its callbacks), campaigns, the bench, the open-loop evaluation, the
datasets of :mod:`dvsland.data` and the environment of :mod:`dvsland.envs`.

Public names: :func:`simulate`, :class:`SimulationResult`, :class:`ClosedLoop`, :class:`LoopState`,
:class:`StepOutput`, :func:`init_state`, :func:`loop_step` (and its halves :func:`sense_step`,
:func:`act_step`, and its pure parts :func:`render`, :func:`sense`, :func:`estimate`, :func:`act`,
:func:`advance`), :func:`reset_where` (restart some descents), :func:`fly_fleet` (many descents
through B slots that restart as theirs end), :func:`clone_state`, :func:`save_state`,
:func:`load_state`, :class:`StageStates`, :func:`build_layout`, :class:`BatchLayout`,
:func:`termination_code`, :data:`OUTCOMES`.
"""

from dvsland.layout import BatchLayout, build_layout, expand_seeds, setting_label

from .api import simulate
from .fleet import FleetResult, fly_fleet
from .loop import ClosedLoop, run_summaries
from .result import TRACE_FIELDS, SimulationResult, TraceRecorder
from .reset import dispersed_start, init_state, reset_where, restart_finished
from .state import LoopState, StageStates, clone_state, load_state, save_state
from .step import Sensed, StepOutput, act, act_step, advance, estimate, fly_steps, loop_step, render, sense, sense_step
from .termination import OUTCOMES, termination_code

__all__ = ["simulate", "SimulationResult", "ClosedLoop", "LoopState", "StepOutput", "init_state", "loop_step",
           "fly_steps", "sense_step", "act_step", "Sensed", "render", "sense", "estimate", "act", "advance", "reset_where",
           "restart_finished", "fly_fleet", "FleetResult", "dispersed_start", "StageStates", "clone_state", "save_state", "load_state", "run_summaries", "BatchLayout",
           "build_layout", "expand_seeds", "setting_label", "termination_code", "OUTCOMES", "TRACE_FIELDS",
           "TraceRecorder"]
