"""The stages as the loop calls them: each stateful stage under the stage contract.

A built-in stage offers the contract itself (:mod:`dvsland.pytree`: ``init_state``,
``step_state``, ``reset_where``). A third-party object that only has the object API (an estimator
with ``update``/``reset``, a law with ``__call__``, a filter with ``update``) is run through a
:class:`dvsland.pytree.ObjectStage` adapter built here, so ``--estimator file.py:Class`` keeps
working unchanged. Everything a plug-in returns is checked at this boundary
(:mod:`dvsland.plugins`): one :class:`~dvsland.plugins.PluginError` naming it when it breaks its
contract.

The loop reads :func:`stage_fns` (built once per :class:`dvsland.stages.Stages`):

- ``emulator``: ``init_state(frames, t_us, seed)``, ``step_state(st, frames, t_us) -> (st, Events)``,
  ``reset_where(st, mask, frames, t_us, seed)``;
- ``estimator``: ``init_state()``, ``step_state(st, events, t_us, truth) -> (st, EstimateOut)``,
  ``reset_where(st, mask)``;
- ``filter``: ``init_state()``, ``step_state(st, d_hat, active, accel_mps2, thrust_accel_mps2,
  confidence) -> (st, (d_filtered, n_used, altitude_m or None))``, ``reset_where(st, mask)``;
- ``controller``: ``init_state()``, ``step_state(st, t_s (B,), d_filtered, mass_kg, active,
  altitude_m) -> (st, ControlOutput)``, ``reset_where(st, mask)``.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional

import torch

from dvsland.compiled import CompiledFn
from dvsland.estimators import EstimateOut
from dvsland.plugins import PluginError, call_plugin, check_batch_tensor
from dvsland.pytree import ObjectStage, ObjectState, check_state_like, has_stage_contract, tree_leaves


class StageFns(NamedTuple):
    """The stateful stages under the contract (``emulator`` None when the estimator needs no events)."""

    emulator: Any
    estimator: Any
    filter: Any
    controller: Any
    estimator_name: str
    controller_name: str


def controller_name(stages) -> str:
    """The law's name for messages and results."""
    ctl = stages.controller
    return str(getattr(ctl, "controller_name", None) or stages.cfg.controller.name)


def stage_fns(stages) -> StageFns:
    """The contract objects of ``stages`` (built on first use and kept with them)."""
    fns = getattr(stages, "_stage_fns", None)
    if fns is None or fns[0] is not stages.estimator:
        fns = (stages.estimator, _build(stages))
        stages._stage_fns = fns
    return fns[1]


def _build(stages) -> StageFns:
    est_name, ctl_name = stages.settings.estimator_name, controller_name(stages)
    emu = stages.emulator
    if emu is not None and not has_stage_contract(emu):
        emu = ObjectStage(emu, call=lambda o, frames, t_us: o.step(frames, int(t_us)),
                          reset=_emulator_restart, init=lambda o, frames, t_us, seed=None: o.reset(frames, int(t_us)))
    est = stages.estimator
    if not has_stage_contract(est) or _object_api_only(est):
        est = ObjectStage(est, call=_estimator_call(est_name), reset=_reset_call(est_name))
    filt = stages.filter
    if not has_stage_contract(filt):
        filt = ObjectStage(filt, call=_filter_call, reset=_reset_call("filter"))
    ctl = stages.controller
    if not has_stage_contract(ctl):
        ctl = ObjectStage(ctl, call=_controller_call(ctl_name), reset=_reset_call(ctl_name))
    if getattr(stages.settings, "compile", False):  # simulation.compile: the pure filter and law, fused
        filt = filt if isinstance(filt, ObjectStage) else CompiledStage(filt)
        ctl = ctl if isinstance(ctl, ObjectStage) else CompiledStage(ctl)
    return StageFns(emu, est, filt, ctl, est_name, ctl_name)


#: torch.compile's backend for :class:`CompiledStage` ("inductor": fused kernels; tests use "eager",
#: which traces and guards the same way without generating code)
COMPILE_BACKEND = "inductor"


class CompiledStage:
    """A contract stage whose ``step_state`` runs through ``torch.compile`` (``simulation.compile``):
    the filter's and the law's hundreds of small elementwise ops per step become a few fused
    kernels (on a GPU the step is otherwise bound by kernel launches). Everything else (init,
    reset, parameters) is the wrapped stage's. The first step compiles (about 10 s on an H200), with
    every size symbolic, so another batch size or a longer history reuses it; results equal the eager
    path's within float rounding (tests/test_compile_stages.py). Where compiling fails, the step warns
    once and runs eagerly from then on (:class:`dvsland.compiled.CompiledFn`).

    Args:
        stage: a stage under the contract (not an :class:`~dvsland.pytree.ObjectStage`).
    """

    def __init__(self, stage: Any):
        self.stage = stage
        self._fn = CompiledFn(stage.step_state, "simulation.compile", type(stage).__name__, backend=COMPILE_BACKEND)

    def step_state(self, *args, **kwargs):
        return self._fn(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stage, name)


def _object_api_only(est) -> bool:
    """An estimator subclass that inherits the base's contract methods but only implements the
    object API (``update``/``reset``), or an instance whose ``update``/``reset`` was replaced (a
    wrapped or patched estimator: its object API is what the user asked for)."""
    from dvsland.estimators.base import DivergenceEstimator

    if any(k in vars(est) for k in ("update", "reset", "confidence")):
        return True
    return isinstance(est, DivergenceEstimator) and not est._has_contract()


def _emulator_restart(obj, mask, frames=None, t_us=None, seed=None):
    if mask is not None and not bool(torch.as_tensor(mask).all()):
        raise ValueError(f"{type(obj).__name__}: an object emulator can only restart every descent at once")
    obj.reset(frames, int(t_us))


def _reset_call(name: str):
    def reset(obj, mask):
        call_plugin(name, "reset", obj.reset, mask)
    return reset


def _estimator_call(name: str):
    def call(obj, events, t_us, truth):
        B = truth.altitude_m.shape[0]
        dev = truth.altitude_m.device
        d = call_plugin(name, "update", obj.update, events, t_us, truth=truth)
        d = check_batch_tensor(d, B, dev, name, "update")
        fn = getattr(obj, "confidence", None)
        c = None if not callable(fn) else call_plugin(name, "confidence", fn)
        c = check_batch_tensor(c, B, dev, name, "confidence", allow_none=True)
        diag = getattr(obj, "diagnostics", None)
        dg = {}
        if callable(diag):
            dg = call_plugin(name, "diagnostics", diag) or {}
        if c is None:
            c = torch.isfinite(d).to(torch.float32)
        return EstimateOut(d, c, dict(dg))
    return call


def _filter_call(obj, d_hat, active, accel_mps2=None, thrust_accel_mps2=None, confidence=None):
    d_f, n_used = obj.update(d_hat, mask=active, accel_mps2=accel_mps2, thrust_accel_mps2=thrust_accel_mps2,
                             confidence=confidence)
    return d_f, n_used, getattr(obj, "altitude_m", None)


def _controller_call(name: str):
    def call(obj, t_s, d_f, m_kg, active, altitude_m=None):
        kw = {"altitude_m": altitude_m} if getattr(obj, "needs_altitude", False) else {}
        return call_plugin(name, "__call__", obj, t_s, d_f, m_kg, active, **kw)
    return call


def checked_thrust_out(out, B: int, dev, name: str) -> torch.Tensor:
    """The law's ``thrust_n`` (B,) checked (a :class:`PluginError` naming the law otherwise)."""
    thrust = getattr(out, "thrust_n", None)
    thrust = check_batch_tensor(thrust, B, dev, name, "__call__ (thrust_n)")
    return thrust


def check_no_nan_thrust(thrust: torch.Tensor, name: str) -> None:
    """A law must command a number; one host sync."""
    if bool(torch.isnan(thrust).any()):
        raise PluginError(name, "__call__", "thrust_n is NaN; a law must command a number (hover or hold when "
                                            "its input is missing)")




# ------------------------------------------------------------------ a state against its stages
#: the LoopState's per-descent fields and their dtypes
LOOP_FIELDS = {"flight_step": torch.int64, "z_m": torch.float64, "v_mps": torch.float64, "m_kg": torch.float64,
               "active": torch.bool, "outcome": torch.int8, "t_end_s": torch.float64, "lowest_m": torch.float64,
               "max_thrust_n": torch.float64, "n_held": torch.int64, "n_missing": torch.int64,
               "n_sanitised": torch.int64, "n_positive": torch.int64, "scene_idx": torch.int64,
               "noise_seed": torch.int64}


def reference_states(stages) -> dict:
    """Fresh states of the estimator, filter and law (built once per stages): what a state's stage
    parts are checked against. Object stages (plug-ins without the contract) are not checked."""
    ref = getattr(stages, "_reference_states", None)
    if ref is None:
        fns = stage_fns(stages)
        ref = {k: getattr(fns, k).init_state() for k in ("estimator", "filter", "controller")
               if not isinstance(getattr(fns, k), ObjectStage)}
        stages._reference_states = ref
    return ref


def check_loop_state(stages, state) -> None:
    """Check that ``state`` fits ``stages``: every per-descent field (B,) with its dtype on the loop's
    device, each stage's state of the structure, shapes, dtypes and devices that stage makes. No
    host synchronisation.

    Raises:
        ValueError: one message naming the stage (or ``LoopState``), the field, what was expected
            and what came.
    """
    B, dev = stages.batch_size, torch.device(stages.device)
    for name, dtype in LOOP_FIELDS.items():
        t = getattr(state, name)
        got = (tuple(t.shape), t.dtype, t.device.type) if isinstance(t, torch.Tensor) else type(t).__name__
        if got != ((B,), dtype, dev.type):
            raise ValueError(f"LoopState: field {name!r} must be a ({B},) {dtype} tensor on {dev}, got {got}")
    for name, ref in reference_states(stages).items():
        check_state_like(name, getattr(state.stage_state, name), ref)
    emu = state.stage_state.emulator
    if emu is not None and not isinstance(emu, ObjectState):
        for k, t in tree_leaves(emu).items():
            if t.device.type != dev.type or (t.dim() >= 1 and t.shape[0] != B and not k.endswith("_packed")):
                raise ValueError(f"emulator: state field {k!r} must be batch first ({B}, ...) on {dev}, got shape "
                                 f"{tuple(t.shape)} on {t.device}")


__all__ = ["StageFns", "stage_fns", "controller_name", "checked_thrust_out", "check_no_nan_thrust", "check_loop_state",
           "reference_states", "LOOP_FIELDS"]
