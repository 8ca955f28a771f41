"""The loop's state as one typed object: :class:`LoopState`, and how to copy, save and load it.

A :class:`LoopState` holds everything that changes while B descents fly: the physical state
(altitude, velocity, mass), the step counter, the ``active`` mask and outcome bookkeeping, the
efference copy (the thrust held over the last step) and the state of each stage (emulator,
estimator, filter, controller).

The stages keep their working buffers in memory between steps (reused for speed, an allocator
detail). A state returned by :func:`dvsland.sim.loop_step` therefore refers to the stages' live
buffers (``stage_state`` is a :class:`LiveStages` handle) until it is copied: stepping from it
*consumes* it, like a donated buffer in JAX. To keep a state (to branch, to resume later, to save)
call :func:`clone_state` first; a cloned state holds a :class:`StageSnapshot` (deep copies of the
stages' state) and can be stepped from any number of times. Stepping from a consumed live state
raises :class:`StaleStateError` rather than flying from the wrong buffers.
"""

from __future__ import annotations

import copy
import itertools
from pathlib import Path
from typing import Any, Dict, NamedTuple, Optional, Tuple, Union

import torch

#: the stages whose state a :class:`StageSnapshot` holds, in this order
STATEFUL_STAGES = ("emulator", "estimator", "filter", "controller")

#: file format version of :func:`save_state`
STATE_FORMAT = 1

_stage_ids = itertools.count(1)


class StaleStateError(RuntimeError):
    """A live :class:`LoopState` was stepped from after the stages had moved past it."""


class LiveStages(NamedTuple):
    """Handle to the stages' in-memory state right after step ``generation`` of stages ``owner``."""

    owner: int
    generation: int


class StageSnapshot(NamedTuple):
    """Deep copies of each stateful stage's attributes (a dict per stage; None where the stage is
    absent, e.g. the emulator when the estimator needs no events)."""

    emulator: Optional[Dict[str, Any]]
    estimator: Optional[Dict[str, Any]]
    filter: Optional[Dict[str, Any]]
    controller: Optional[Dict[str, Any]]


class LoopState(NamedTuple):
    """The state of B descents between two control steps.

    Tensors are (B,) on the loop's device unless stated.

    Attributes:
        step: control steps flown so far (int); the flight time is ``step * dt_s``.
        z_m: altitude, float64 m (z = 0 the surface).
        v_mps: vertical velocity, float64 m/s (< 0 descending).
        m_kg: mass, float64 kg.
        active: bool, still flying.
        outcome: int8 outcome code (:mod:`dvsland.sim.termination`; RUNNING while active).
        t_end_s: float64 s, end time of a finished descent (the time flown so far while active).
        lowest_m: float64 m, lowest altitude reached.
        max_thrust_n: float64 N, largest thrust commanded.
        n_held, n_missing, n_sanitised, n_positive: int64 counts of held commands, missing
            estimates, estimates replaced by NaN and positive (wrong-sign) estimates.
        last_thrust_n, last_mass_kg: float64, the command held over the last step and the mass at
            its start (the efference copy; None before the first step).
        last_frames: (B, H, W) float32, the last rendered frames (None before the first step or when
            the estimator needs no events); finished descents keep theirs.
        stage_state: :class:`LiveStages` (the stages' buffers, consumed by the next step) or
            :class:`StageSnapshot` (an independent copy).
    """

    step: int
    z_m: torch.Tensor
    v_mps: torch.Tensor
    m_kg: torch.Tensor
    active: torch.Tensor
    outcome: torch.Tensor
    t_end_s: torch.Tensor
    lowest_m: torch.Tensor
    max_thrust_n: torch.Tensor
    n_held: torch.Tensor
    n_missing: torch.Tensor
    n_sanitised: torch.Tensor
    n_positive: torch.Tensor
    last_thrust_n: Optional[torch.Tensor]
    last_mass_kg: Optional[torch.Tensor]
    last_frames: Optional[torch.Tensor]
    stage_state: Union[LiveStages, StageSnapshot]

    @property
    def batch_size(self) -> int:
        return int(self.z_m.shape[0])

    @property
    def done(self) -> bool:
        """True when no descent is active (one host sync)."""
        return not bool(self.active.any())


# ------------------------------------------------------------------ stage snapshots
def stage_objects(stages) -> Tuple[Any, ...]:
    """The stateful stage objects of ``stages`` in :data:`STATEFUL_STAGES` order (None where absent)."""
    return (stages.emulator, stages.estimator, stages.filter, stages.controller)


def _shared_memo(stages) -> dict:
    """A deepcopy memo that maps the live stage objects (and what never changes in flight: the
    renderer, torch modules' weights, the config and layout) to themselves, so a copy of one stage's
    attributes keeps pointing at the other live stages instead of duplicating them."""
    memo: dict = {}
    keep = [*stage_objects(stages), stages.renderer, stages.layout, getattr(stages, "cfg", None),
            getattr(stages, "dynamics", None), getattr(stages, "params", None)]
    for obj in keep:
        if obj is not None:
            memo[id(obj)] = obj
    for obj in stage_objects(stages):
        for v in vars(obj).values() if obj is not None else ():
            if isinstance(v, torch.nn.Module):  # weights are constant in flight: shared, not copied
                memo[id(v)] = v
    return memo


def _copy_vars(obj, memo: dict) -> Optional[Dict[str, Any]]:
    if obj is None:
        return None
    get = getattr(obj, "get_state", None)  # a stage may define its own (smaller) state
    if callable(get):
        return {"__state__": copy.deepcopy(get(), dict(memo))}
    return copy.deepcopy(dict(vars(obj)), dict(memo))


def _load_vars(obj, saved: Optional[Dict[str, Any]], memo: dict) -> None:
    if obj is None or saved is None:
        if (obj is None) != (saved is None):
            raise ValueError("stage_state: the saved state and the stages disagree on which stages exist "
                             "(an estimator that needs events against one that does not?)")
        return
    if "__state__" in saved:
        obj.set_state(copy.deepcopy(saved["__state__"], dict(memo)))
        return
    fresh = copy.deepcopy(saved, dict(memo))
    vars(obj).clear()
    vars(obj).update(fresh)


def snapshot_stages(stages) -> StageSnapshot:
    """Deep copies of the stages' current state (see :class:`StageSnapshot`)."""
    memo = _shared_memo(stages)
    return StageSnapshot(*(_copy_vars(o, memo) for o in stage_objects(stages)))


def restore_stages(stages, snap: StageSnapshot) -> None:
    """Put copies of ``snap`` into the stages (``snap`` itself stays unchanged and reusable)."""
    memo = _shared_memo(stages)
    for obj, saved in zip(stage_objects(stages), snap):
        _load_vars(obj, saved, memo)


def live_handle(stages) -> LiveStages:
    """The handle of the stages' current in-memory state."""
    owner = getattr(stages, "_state_owner", None)
    if owner is None:
        owner = next(_stage_ids)
        stages._state_owner = owner
    return LiveStages(owner, int(getattr(stages, "_state_generation", 0)))


def advance_generation(stages) -> LiveStages:
    """Mark the stages' state as moved on by one step; returns the new handle."""
    stages._state_generation = int(getattr(stages, "_state_generation", 0)) + 1
    return live_handle(stages)


def adopt_state(stages, state: LoopState) -> None:
    """Make the stages hold ``state``'s stage state before a step.

    Raises:
        StaleStateError: ``state`` is a live state of these stages that a later step consumed, or a
            live state of other stages.
    """
    ss = state.stage_state
    if isinstance(ss, StageSnapshot):
        restore_stages(stages, ss)
        advance_generation(stages)  # every live handle issued before this point is now stale
        return
    if ss != live_handle(stages):
        raise StaleStateError(
            f"state at step {state.step} refers to stage buffers that have since moved on (or to other "
            "stages): a live LoopState can be stepped from once; use clone_state(stages, state) to keep one")


# ------------------------------------------------------------------ clone, save, load
def _clone_tensors(state: LoopState) -> dict:
    return {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in state._asdict().items()}


def clone_state(stages, state: LoopState) -> LoopState:
    """An independent copy of ``state`` (tensors cloned, stage state snapshotted) that can be
    stepped from, saved or kept while the original flies on."""
    fields = _clone_tensors(state)
    ss = state.stage_state
    if isinstance(ss, StageSnapshot):
        fields["stage_state"] = StageSnapshot(*(copy.deepcopy(s) for s in ss))
    else:
        adopt_state(stages, state)  # raises if stale
        fields["stage_state"] = snapshot_stages(stages)
    return LoopState(**fields)


def save_state(path: Union[str, Path], stages, state: LoopState) -> Path:
    """Write ``state`` (cloned) to ``path`` with :func:`torch.save`.

    The file is a pickle: load only files you wrote (:func:`load_state`). It is written to a
    temporary name and renamed, so a failure leaves the previous file or none.
    """
    path = Path(path)
    snap = clone_state(stages, state)
    blob = {"format": STATE_FORMAT, "batch_size": state.batch_size, "state": snap}
    tmp = path.with_name(path.name + ".tmp")
    torch.save(blob, tmp)
    tmp.replace(path)
    return path


def load_state(path: Union[str, Path], device: Any = "cpu") -> LoopState:
    """Read a state written by :func:`save_state`, every tensor (stage buffers too) on ``device``
    (the device of the stages it will be stepped with).

    Raises:
        ValueError: ``path`` is not a dvsland loop-state file (names the file and what is wrong).
    """
    path = Path(path)
    try:
        blob = torch.load(path, map_location=torch.device(device), weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is one clear error
        raise ValueError(f"state file {str(path)!r}: not a readable loop state ({type(exc).__name__}: {exc})") from None
    if not isinstance(blob, dict) or blob.get("format") != STATE_FORMAT or not isinstance(blob.get("state"), LoopState):
        raise ValueError(f"state file {str(path)!r}: not a dvsland loop state of format {STATE_FORMAT}")
    return blob["state"]


__all__ = ["LoopState", "StageSnapshot", "LiveStages", "StaleStateError", "STATEFUL_STAGES", "clone_state",
           "save_state", "load_state", "snapshot_stages", "restore_stages", "adopt_state"]
