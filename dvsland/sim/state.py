"""The loop's state as data: :class:`LoopState`, and how to copy, save and load it.

A :class:`LoopState` holds everything that changes while B descents fly: the physics (altitude,
velocity, mass), the clock, the ``active`` mask and outcome bookkeeping, the efference copy (the
thrust held over the last step) and each stage's own ``State`` (:class:`StageStates`; see the
stage contract in :mod:`dvsland.pytree`). Every leaf is a tensor (or None, or a plain value shared
by the batch), so copying a state is a tree copy of tensors (:func:`clone_state`), and the states
the loop returns are new objects: a state can be kept, branched from or saved at any step.
"""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Any, NamedTuple, Optional, Union

import torch

from dvsland.pytree import tree_clone, tree_to

#: file format version of :func:`save_state`
STATE_FORMAT = 2


class StageStates(NamedTuple):
    """The State of each stateful stage (their types are the stages' own, e.g. ``OracleState``).

    Attributes:
        emulator: the emulator's state (None when the estimator needs no events, and before the
            first frame).
        estimator, filter, controller: their states.
    """

    emulator: Any
    estimator: Any
    filter: Any
    controller: Any


class LoopState(NamedTuple):
    """The state of B descents between two control steps.

    Tensors are (B,) on the loop's device unless stated.

    Attributes:
        step: control steps since :func:`dvsland.sim.init_state` (int); the clock shared by the
            batch (events are stamped ``step * dt_s`` in µs).
        flight_step: int64 control steps since each descent's (re)start; its flight time is
            ``flight_step * dt_s`` (a finished descent's end time is ``t_end_s``).
        z_m: altitude, float64 m (z = 0 the surface).
        v_mps: vertical velocity, float64 m/s (< 0 descending).
        m_kg: mass, float64 kg.
        active: bool, still flying.
        outcome: int8 outcome code (:mod:`dvsland.sim.termination`; RUNNING while active).
        t_end_s: float64 s, flight time at the end of a finished descent (the time flown so far
            while active).
        lowest_m: float64 m, lowest altitude reached.
        max_thrust_n: float64 N, largest thrust commanded.
        n_held, n_missing, n_sanitised, n_positive: int64 counts of held commands, missing
            estimates, estimates replaced by NaN and positive (wrong-sign) estimates.
        last_thrust_n, last_mass_kg: float64, the command held over the last step and the mass at
            its start (the efference copy; None before the first step).
        last_frames: (B, H, W) float32, the last rendered frames (None before the first step or when
            the estimator needs no events); finished descents keep theirs.
        scene_idx: int64, the renderer's scene of each descent.
        noise_seed: int64, the seed of each descent's sensor noise (counter-based draws).
        restarted: bool, descents restarted by :func:`dvsland.sim.reset_where` since the last step
            (their emulator restarts on the next frame), or None when none was.
        stage_state: :class:`StageStates`.
    """

    step: int
    flight_step: torch.Tensor
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
    scene_idx: torch.Tensor
    noise_seed: torch.Tensor
    restarted: Optional[torch.Tensor]
    stage_state: StageStates

    @property
    def batch_size(self) -> int:
        return int(self.z_m.shape[0])

    @property
    def done(self) -> bool:
        """True when no descent is active (one host sync)."""
        return not bool(self.active.any())


def clone_state(stages_or_state, state: Optional[LoopState] = None) -> LoopState:
    """An independent copy of a state (every tensor cloned), ``clone_state(state)``.

    ``clone_state(stages, state)`` (the older form) is accepted too; ``stages`` is not needed.
    """
    st = stages_or_state if state is None else state
    if not isinstance(st, LoopState):
        raise ValueError(f"clone_state: expected a LoopState, got {type(st).__name__}")
    return tree_clone(st)


def save_state(path: Union[str, Path], stages_or_state, state: Optional[LoopState] = None) -> Path:
    """Write a state with :func:`torch.save`: ``save_state(path, state)`` (or ``(path, stages, state)``).

    The file is a pickle: load only files you wrote (:func:`load_state`). It is written to a
    temporary name and renamed, so a failure leaves the previous file or none (and no temporary).

    Raises:
        ValueError: not a LoopState, ``path`` a folder or in a folder that does not exist.
        OSError: the file cannot be written (names it; a full disk keeps its errno).
    """
    st = stages_or_state if state is None else state
    if not isinstance(st, LoopState):
        raise ValueError(f"save_state: expected a LoopState, got {type(st).__name__}")
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"save_state: {str(path)!r} is a folder; give the state file's name")
    if not path.parent.is_dir():
        raise ValueError(f"save_state: the folder of {str(path)!r} does not exist")
    blob = {"format": STATE_FORMAT, "batch_size": st.batch_size, "state": tree_to(st, "cpu")}
    tmp = path.with_name(path.name + ".tmp")
    try:
        torch.save(blob, tmp)
        tmp.replace(path)
    except (OSError, RuntimeError) as exc:  # torch reports a failed open or write as RuntimeError
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        reason = getattr(exc, "strerror", None) or str(exc).splitlines()[0][:200]
        raise OSError(getattr(exc, "errno", None) or errno.EIO, f"save_state: cannot write the state file ({reason})",
                      str(path)) from None
    return path


#: fields that are finite in every state the loop makes (a damaged file is refused on load)
_FINITE_FIELDS = ("z_m", "v_mps", "m_kg")


def load_state(path: Union[str, Path], device: Any = "cpu") -> LoopState:
    """Read a state written by :func:`save_state`, every tensor (stage states too) on ``device``
    (the device of the stages it will be stepped with).

    Raises:
        ValueError: ``path`` is not a dvsland loop-state file, or holds a non-finite altitude,
            velocity or mass (names the file and what is wrong); ``device`` not available here.
    """
    from dvsland.checks import check_device

    device = check_device(device, "device")
    path = Path(path)
    try:
        blob = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is one clear error
        reason = str(exc).splitlines()[0][:200] if str(exc) else ""
        raise ValueError(f"state file {str(path)!r}: not a readable loop state ({type(exc).__name__}: {reason})") from None
    if not isinstance(blob, dict) or blob.get("format") != STATE_FORMAT or not isinstance(blob.get("state"), LoopState):
        raise ValueError(f"state file {str(path)!r}: not a dvsland loop state of format {STATE_FORMAT}")
    st = blob["state"]
    for name in _FINITE_FIELDS:
        value = getattr(st, name)
        if not isinstance(value, torch.Tensor) or not bool(torch.isfinite(value).all()):
            raise ValueError(f"state file {str(path)!r}: field {name!r} is not a finite tensor (a damaged state)")
    return tree_to(st, device)


__all__ = ["LoopState", "StageStates", "clone_state", "save_state", "load_state", "STATE_FORMAT"]
