"""Starting descents: :func:`init_state` (every descent) and :func:`reset_where` (some of them).

A restarted descent gets its initial conditions, fresh bookkeeping and fresh stage states while
the other descents fly on bit for bit as if nothing had happened; its emulator restarts on the
next rendered frame (its first step shows no events and no estimate, like a descent's step 0).
"""

from __future__ import annotations

from typing import Optional

import torch

from dvsland.pytree import hash_normal, tree_where

from .contracts import stage_fns
from .state import LoopState, StageStates
from .termination import RUNNING


def init_state(stages, z_m=None, v_mps=None, m_kg=None) -> LoopState:
    """The state at step 0: every descent at its initial conditions, every stage at its start.

    Args:
        stages: :class:`dvsland.stages.Stages`.
        z_m, v_mps, m_kg: optional initial altitude (m, > 0), velocity (m/s) and mass (kg, > 0):
            scalars or (B,) values; default the layout's z0, v0 and ``dynamics.mass_kg``. The
            controller's target and the filter's prior keep the configured (planned) start.

    Raises:
        ValueError: a start value of the wrong shape, not finite, or out of range (names it).
    """
    L, dev, f64 = stages.layout, torch.device(stages.device), torch.float64
    B = L.batch_size
    z = _start("z_m", L.tensor("z0_m", dev, f64) if z_m is None else z_m, B, dev, positive=True)
    v = _start("v_mps", L.tensor("v0_mps", dev, f64) if v_mps is None else v_mps, B, dev)
    m = _start("m_kg", stages.settings.mass_kg if m_kg is None else m_kg, B, dev, positive=True)
    fns = stage_fns(stages)
    ss = StageStates(None, fns.estimator.init_state(), fns.filter.init_state(), fns.controller.init_state())
    zeros_i = torch.zeros(B, dtype=torch.int64, device=dev)
    zeros_f = torch.zeros(B, dtype=f64, device=dev)
    return LoopState(step=0, flight_step=zeros_i.clone(), z_m=z, v_mps=v, m_kg=m,
                     active=torch.ones(B, dtype=torch.bool, device=dev),
                     outcome=torch.full((B,), RUNNING, dtype=torch.int8, device=dev), t_end_s=zeros_f,
                     lowest_m=z.clone(), max_thrust_n=zeros_f.clone(), n_held=zeros_i, n_missing=zeros_i.clone(),
                     n_sanitised=zeros_i.clone(), n_positive=zeros_i.clone(), last_thrust_n=None, last_mass_kg=None,
                     last_frames=None, scene_idx=stages.scene_idx.to(dev),
                     noise_seed=L.tensor("seed", dev, torch.int64), restarted=None, stage_state=ss)


def reset_where(stages, state: LoopState, mask, z_m=None, v_mps=None, m_kg=None, seed=None,
                scene_idx=None) -> LoopState:
    """Restart the descents where ``mask`` (B,) bool is True; the others are left bit-identical.

    Args:
        stages: the stages ``state`` flies with.
        state: the current state (not changed).
        mask: (B,) bool (a tensor, numpy array or list).
        z_m, v_mps, m_kg: the restarted descents' initial altitude (m, > 0), velocity (m/s) and mass
            (kg, > 0): scalars or (B,) values (only the masked entries are used); default the
            layout's z0, v0 and ``dynamics.mass_kg``.
        seed: the restarted descents' sensor-noise seeds: an int or (B,) int64 (default: unchanged,
            so a restarted descent meets the same noise draws as its first flight).
        scene_idx: the restarted descents' scenes (the renderer's rows): an int or (B,) int64
            (default: unchanged).

    Returns:
        the new :class:`LoopState`: the masked descents at flight step 0, active, their outcome and
        counts cleared, their estimator, filter and law states fresh; their emulator restarts on
        the next frame.

    Raises:
        ValueError: a mask of the wrong length or dtype, a non-finite or out-of-range start value,
            a seed or scene index of the wrong shape or out of range (each names the argument).
    """
    B, dev = state.batch_size, state.z_m.device
    m = _mask(mask, B, dev)
    L, f64 = stages.layout, torch.float64
    z = _start("z_m", L.tensor("z0_m", dev, f64) if z_m is None else z_m, B, dev, positive=True, where=m)
    v = _start("v_mps", L.tensor("v0_mps", dev, f64) if v_mps is None else v_mps, B, dev, where=m)
    mk = _start("m_kg", stages.settings.mass_kg if m_kg is None else m_kg, B, dev, positive=True, where=m)
    seeds = state.noise_seed if seed is None else _ints("seed", seed, B, dev, 0, 2 ** 63 - 1)
    n_scenes = int(stages.scene_idx.max()) + 1 if stages.scene_idx.numel() else 1
    scenes = state.scene_idx if scene_idx is None else _ints("scene_idx", scene_idx, B, dev, 0, n_scenes - 1)
    fns = stage_fns(stages)
    ss = state.stage_state
    ss = StageStates(ss.emulator, fns.estimator.reset_where(ss.estimator, m), fns.filter.reset_where(ss.filter, m),
                     fns.controller.reset_where(ss.controller, m))
    w = lambda new, old: torch.where(m, new, old)  # noqa: E731
    zi, zf = torch.zeros(B, dtype=torch.int64, device=dev), torch.zeros(B, dtype=f64, device=dev)
    last_u = last_m = None
    if state.last_thrust_n is not None:
        last_u, last_m = w(zf, state.last_thrust_n), w(mk, state.last_mass_kg)
    restarted = m if state.restarted is None else (m | state.restarted)
    return state._replace(
        flight_step=w(zi, state.flight_step), z_m=w(z, state.z_m), v_mps=w(v, state.v_mps), m_kg=w(mk, state.m_kg),
        active=m | state.active, outcome=w(torch.full_like(state.outcome, RUNNING), state.outcome),
        t_end_s=w(zf, state.t_end_s), lowest_m=w(z, state.lowest_m), max_thrust_n=w(zf, state.max_thrust_n),
        n_held=w(zi, state.n_held), n_missing=w(zi, state.n_missing), n_sanitised=w(zi, state.n_sanitised),
        n_positive=w(zi, state.n_positive), last_thrust_n=last_u, last_mass_kg=last_m,
        scene_idx=w(scenes, state.scene_idx), noise_seed=w(seeds, state.noise_seed),
        restarted=restarted, stage_state=ss)


def dispersed_start(stages, keys, z_sigma: float, v_sigma: float, z_clip=(0.5, 1.5), v_clip=(0.5, 1.5)):
    """The layout's start of each descent dispersed by counter-based draws: (z0_m, v0_mps), (B,)
    float64 m and m/s, each the layout's value times ``(1 + sigma N(0, 1)).clamp(*clip)``, with N
    :func:`dvsland.pytree.hash_normal` of ``keys`` (int64 tensors or ints broadcast to (B,)) and a
    stream tag (1 for z, 2 for v). The same keys give the same starts on every device."""
    L, dev, f64 = stages.layout, torch.device(stages.device), torch.float64
    z0 = L.tensor("z0_m", dev, f64) * (1.0 + z_sigma * hash_normal(*keys, 1)).clamp(*z_clip)
    v0 = L.tensor("v0_mps", dev, f64) * (1.0 + v_sigma * hash_normal(*keys, 2)).clamp(*v_clip)
    return z0, v0


def restart_finished(stages, state: LoopState, **kw) -> LoopState:
    """:func:`reset_where` on every finished descent (a no-op, without a copy, when none has)."""
    done = ~state.active
    if not bool(done.any()):
        return state
    return reset_where(stages, state, done, **kw)


def _mask(mask, B: int, dev) -> torch.Tensor:
    m = torch.as_tensor(mask, device=dev)
    if m.dtype != torch.bool or m.shape != (B,):
        raise ValueError(f"reset mask must be a ({B},) bool tensor (one entry per descent), got shape "
                         f"{tuple(m.shape)} dtype {m.dtype}")
    return m


def _ints(name: str, value, B: int, dev, lo: int, hi: int) -> torch.Tensor:
    t = torch.as_tensor(value, device=dev)
    if t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
        raise ValueError(f"{name} must be an integer or ({B},) integers in [{lo}, {hi}], got dtype {t.dtype}")
    t = t.to(torch.int64)
    if t.dim() == 0:
        t = t.expand(B).clone()
    if t.shape != (B,):
        raise ValueError(f"{name} must be an integer or of shape ({B},), got shape {tuple(t.shape)}")
    if bool(((t < lo) | (t > hi)).any()):
        raise ValueError(f"{name} must lie in [{lo}, {hi}], got {t.tolist()}")
    return t


def _start(name: str, value, B: int, dev, positive: bool = False, where: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``value`` as a (B,) float64 tensor; checked (finite, > 0 if ``positive``) where ``where``."""
    t = torch.as_tensor(value, dtype=torch.float64).to(dev)
    if t.dim() == 0:
        t = t.expand(B).clone()
    if t.shape != (B,):
        raise ValueError(f"{name} must be a scalar or of shape ({B},), got shape {tuple(t.shape)}")
    chk = t if where is None else t[where]
    if not bool(torch.isfinite(chk).all()) or (positive and not bool((chk > 0).all())):
        raise ValueError(f"{name} must be finite{' and > 0' if positive else ''}, got {chk.tolist()}")
    return t


__all__ = ["init_state", "reset_where", "restart_finished", "dispersed_start"]
