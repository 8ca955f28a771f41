"""The emulator's step of some descents only: a finished descent's sensor costs nothing.

The closed loop stops flying a descent once it has landed, crashed or timed out, and drops that
descent's events (``simulation.compact``). :func:`emulator_step_rows` goes one step further and
does not emulate it at all: the step runs on the rows still in flight, and their pixels, noise
draws and events are those of the whole batch's step, bit for bit. Every draw is keyed by the
descent's own seed and step counter, and every per-pixel rule is local to its descent, so the
batch-mates change nothing.

The other descents' pixels are left as they were (frozen, no events) and only their clock moves
on, so that the batch still steps at one shared instant; a restart (``reset_where``) re-initialises
them.
"""

from __future__ import annotations

from typing import Tuple

import torch

from dvsland.pytree import tree_map

from .emulator import EmulatorParams, EmulatorState, emulator_step, params_rows, rows_into
from .events import Events


def state_rows(state: EmulatorState, rows: torch.Tensor) -> EmulatorState:
    """``state`` of the descents ``rows`` (K,) int64 (every batch-first leaf taken at those rows)."""
    B = state.lref.shape[0]
    return tree_map(lambda t: t.index_select(0, rows) if t.dim() >= 1 and t.shape[0] == B else t, state)


def _merge(state: EmulatorState, old_rows: EmulatorState, new_rows: EmulatorState, rows: torch.Tensor,
           t_us: int) -> EmulatorState:
    """``state`` with the rows' fields replaced by ``new_rows``'s, every clock at ``t_us``; a field the
    step kept (the same object as in ``old_rows``: thresholds, seeds, leak maps) is kept whole."""
    B = state.lref.shape[0]
    out = {}
    for name, full, was, part in zip(EmulatorState._fields, state, old_rows, new_rows):
        if full is None or part is was:
            out[name] = full
        elif part is None:
            raise ValueError(f"emulator_step_rows: state field {name!r} vanished in the step")
        else:
            out[name] = tree_map(lambda f, p: rows_into(f, rows, p, B), full, part)
    out["t_us"] = torch.full_like(state.t_us, int(t_us))
    return EmulatorState(**out)


def emulator_step_rows(params: EmulatorParams, state: EmulatorState, frames: torch.Tensor, t_us: int,
                       rows: torch.Tensor) -> Tuple[EmulatorState, Events]:
    """:func:`~dvsland.events.emulator.emulator_step` of the descents ``rows`` only.

    Args:
        params, state: the whole batch's (B descents).
        frames: (B, H, W) floating, linear irradiance (the other rows are not read).
        t_us: int µs, > the state's time.
        rows: (K,) int64 ascending descent indices on the state's device (0 <= K <= B).

    Returns:
        (the new state: the rows' fields as after the whole batch's step, the others' as they were
        with the clock at ``t_us``; the rows' events, with their batch indices b, sorted by (b, t) and
        marked checked for the whole batch). ``state`` is not written.
    """
    B, H, W = state.lref.shape
    rows = rows.to(device=state.lref.device, dtype=torch.int64)
    if rows.numel() == 0:  # nothing in flight: only the clock moves
        return state._replace(t_us=torch.full_like(state.t_us, int(t_us))), Events.empty(
            state.lref.device).marked_checked(B, W, H)
    old_rows = state_rows(state, rows)
    new_rows, ev = emulator_step(params_rows(params, rows), old_rows, frames.index_select(0, rows.to(frames.device)),
                                 t_us)
    if ev.b.numel():
        ev = Events(rows.index_select(0, ev.b), ev.x, ev.y, ev.t, ev.p)
    return _merge(state, old_rows, new_rows, rows, t_us), ev.marked_checked(B, W, H)


__all__ = ["emulator_step_rows", "params_rows", "state_rows"]
