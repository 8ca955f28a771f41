"""Fly a prescribed altitude profile on the loop: the thrust that makes ``loop_step`` follow it.

The open-loop evaluation (the closed-form oracle descent of every site) and the spiking
estimator's training sequences (constant-divergence climbs and descents) fly an altitude profile
given in advance, not one the controller chooses. They run on :func:`dvsland.sim.loop_step` like
every other flight, with ``thrust`` given: :func:`tracking_thrust` is the thrust that brings the
loop's own dynamics (``dynamics.integrator``) onto the profile's next altitude.

- Where the altitude after a step depends on the thrust held over it (``exact``, ``substeps``),
  the thrust is solved so that it lands on ``z_ref[k + 1]`` (to ~1e-12 relative).
- Where it does not (``euler``: z1 = z0 + v0 dt), the thrust sets the velocity that lands the
  *next* step on ``z_ref[k + 2]``; :func:`start_velocity` gives the start velocity that lands
  the first one on ``z_ref[1]``. The velocity is then the profile's forward difference.

Either way the altitudes the renderer sees are the profile's (the evaluation reports the largest
deviation, ``trajectory_max_rel_dz``), and the truth an estimator is scored against is the loop's
own ``d_true = v / z`` of those steps.
"""

from __future__ import annotations

from typing import Callable, Iterator, Optional

import torch

Tensor = torch.Tensor

#: Newton-secant rounds of :func:`tracking_thrust` (it converges in 1-3 on the shipped integrators)
_ROUNDS = 8


#: does the altitude after one step depend on the thrust held over it, per LanderDynamics integrator
_FOLLOWS = {"exact": True, "substeps": True, "euler": False}


def _as(x, like: Tensor) -> Tensor:
    return torch.as_tensor(x, dtype=torch.float64).to(like.device).reshape(like.shape)


def altitude_follows_thrust(dynamics, z: Tensor, v: Tensor, m: Tensor, dt_s: float) -> bool:
    """True when the altitude after one step depends on the thrust held over it (False for the
    explicit Euler step, whose z1 = z0 + v0 dt). Known for :class:`dvsland.dynamics.LanderDynamics`'
    integrators, probed with two steps otherwise."""
    known = _FOLLOWS.get(getattr(dynamics, "integrator", None))
    if known is not None:
        return known
    zero = torch.zeros_like(z)
    probe = m * 1.0  # 1 m/s^2: well above rounding, far from burnout
    za = dynamics.step(z, v, m, zero, dt_s)[0]
    zb = dynamics.step(z, v, m, probe, dt_s)[0]
    return bool(((zb - za).abs() > 1e-12 * (za.abs() + 1.0)).any())


def start_velocity(dynamics, z0: Tensor, v0: Tensor, z1: Tensor, m: Tensor, dt_s: float) -> Tensor:
    """The velocity to start a profile (z0 -> z1 after one step) with: ``v0`` where the thrust can
    steer the first step's altitude; the forward difference (z1 - z0) / dt where it cannot."""
    z0 = torch.as_tensor(z0, dtype=torch.float64)
    v0, z1, m = (_as(x, z0) for x in (v0, z1, m))
    if altitude_follows_thrust(dynamics, z0, v0, m, dt_s):
        return v0
    return (z1 - z0) / dt_s


def tracking_thrust(stages, state, z_next, z_after: Optional[Tensor] = None) -> Tensor:
    """The (B,) thrust, N, that brings ``state`` onto the profile.

    Args:
        stages: :class:`dvsland.stages.Stages` (its ``dynamics`` and ``settings.dt_s``).
        state: the :class:`dvsland.sim.LoopState` about to be stepped.
        z_next: (B,) the profile's altitude one step ahead, m.
        z_after: (B,) the profile's altitude two steps ahead, m; needed when the altitude after a
            step does not depend on the thrust (``euler``), ignored otherwise.

    Returns:
        (B,) float64 thrust >= 0, finite (0 where no finite thrust reaches the profile, e.g. a
        finished descent or an empty tank); pass it to ``loop_step(..., thrust=...)``.
    """
    dyn, dt = stages.dynamics, float(stages.settings.dt_s)
    z, v, m = state.z_m, state.v_mps, state.m_kg
    z_next = _as(z_next, z)
    zero = torch.zeros_like(z)
    z0u, v0u = dyn.step(z, v, m, zero, dt)[:2]
    if altitude_follows_thrust(dyn, z, v, m, dt):
        target, pick = z_next, 0
        # constant-mass guess: z1 = z + v dt + (u/m - g) dt^2 / 2
        guess = m * (stages.settings.g_mps2 + 2.0 * (z_next - z - v * dt) / dt ** 2)
    else:
        if z_after is None:
            raise ValueError("tracking_thrust: this integrator's next altitude does not depend on the thrust; "
                             "give z_after (the profile two steps ahead)")
        target, pick = (_as(z_after, z) - z0u) / dt, 1  # the velocity that lands the next step on z_after
        guess = m * (stages.settings.g_mps2 + (target - v) / dt)
    # secant on f(u) = state after one step (monotone increasing in u), from u = 0 and the guess
    u0, f0 = zero, (z0u, v0u)[pick]
    u1 = torch.where(torch.isfinite(guess), guess, zero).clamp_min(0.0)
    f1 = dyn.step(z, v, m, u1, dt)[pick]
    for _ in range(_ROUNDS):
        err = target - f1
        # done: on target, finished (its thrust is not flown), or below it at zero thrust
        open_ = (err.abs() > 1e-12 * (target.abs() + 1.0)) & state.active & ~((u1 <= 0) & (err < 0))
        if not bool(open_.any()):
            break
        slope = (f1 - f0) / (u1 - u0)
        ok = torch.isfinite(slope) & (slope > 0)
        u2 = torch.where(ok, u1 + err / torch.where(ok, slope, torch.ones_like(slope)), u1).clamp_min(0.0)
        u0, f0, u1 = u1, f1, u2
        f1 = dyn.step(z, v, m, u1, dt)[pick]
    return torch.where(torch.isfinite(u1), u1, zero)


def fly_profile(stages, z_ref, v0, m_kg=None, timer: Optional[Callable] = None,
                keep_flying: bool = False) -> Iterator:
    """Fly B descents along the altitude profile ``z_ref`` on :func:`dvsland.sim.loop_step`.

    Starts a new flight (:func:`dvsland.sim.init_state`: every stage reset) at ``z_ref[:, 0]`` and
    steps ``N = z_ref.shape[1] - 2`` times with :func:`tracking_thrust` (the last two samples are
    its look-ahead): step ``k`` renders ``z_ref[:, k]`` and reports the events of
    ``(t_{k-1}, t_k]``.

    Args:
        stages: :class:`dvsland.stages.Stages`.
        z_ref: (B, N + 2) altitudes at the loop's steps, m.
        v0: (B,) the profile's velocity at its start, m/s (replaced by :func:`start_velocity`'s).
        m_kg: start mass (default the configured one).
        timer: ``loop_step``'s per-stage timer.
        keep_flying: end no descent (``loop_step(..., terminate=False)``): a profile that climbs
            or goes below the success altitude keeps flying.

    Yields:
        the :class:`dvsland.sim.StepOutput` of each step.
    """
    from dvsland.sim import init_state, loop_step

    dev = torch.device(stages.device)
    z_ref = torch.as_tensor(z_ref, dtype=torch.float64).to(dev)
    B, n = z_ref.shape[0], z_ref.shape[1] - 2
    if n < 1:
        raise ValueError(f"z_ref must have at least 3 samples per element (1 step + the look-ahead), got {n + 2}")
    m = torch.full((B,), float(stages.settings.mass_kg), dtype=torch.float64, device=dev) if m_kg is None \
        else _as(m_kg, z_ref[:, 0])
    v = start_velocity(stages.dynamics, z_ref[:, 0], _as(v0, z_ref[:, 0]), z_ref[:, 1], m, stages.settings.dt_s)
    state = init_state(stages, z_m=z_ref[:, 0], v_mps=v, m_kg=m)
    for k in range(n):
        u = tracking_thrust(stages, state, z_ref[:, k + 1], z_ref[:, k + 2])
        state, out = loop_step(stages, state, thrust=u, timer=timer, terminate=not keep_flying,
                               donate=True)  # the profile's own state
        yield out


__all__ = ["tracking_thrust", "start_velocity", "altitude_follows_thrust", "fly_profile"]
