"""Reward and episode ends of a :class:`~dvsland.envs.LandingVectorEnv`.

Per step (the action held over [t_k, t_{k+1}), judged at t_{k+1}):

    r = tracking_weight * dt * max(0, 1 - |D(t_{k+1}) - D*(t_{k+1})| / tracking_scale)

with D = v/z the true divergence (1/s) and D*(t) = -1 / max(tau0 - c2 t, tau_min_s) the
paper's time-to-contact target of the descent (tau0 = z0/|v0| of the element, c2 =
``controller.c2``; tau_min_s = 2 / ``simulation.crash_divergence`` = 4 s by default, so
|D*| stays at half the crash divergence once the target's TTC runs out): up to
``tracking_weight`` per second of flight, for flying within ``tracking_scale`` of the target. The
term is never negative, so ending a descent early never pays (with a penalty per step, a quick
crash would be the best return of a policy that tracks poorly).

On the step a descent ends, the terminal term is added:

- success (z <= ``simulation.success_altitude_m``): + success_bonus - speed_penalty * |v| (m/s);
- crash (z <= 0 or |D| >= ``simulation.crash_divergence``) or ascent (v > 0): - failure_penalty;
- timeout (t reaches ``simulation.t_max_s``): nothing more; it is a truncation, not a termination.

``terminated`` is True on success, crash and ascent; ``truncated`` on timeout (the outcomes of
:mod:`dvsland.sim.termination`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from dvsland.sim.termination import ASCENT, CRASH, SUCCESS, TIMEOUT


@dataclass(frozen=True)
class RewardConfig:
    """Weights of the reward (see the module docstring); all >= 0.

    Attributes:
        tracking_weight: tracking reward per second of flight on the target.
        tracking_scale: |D - D*| (1/s) at which the tracking reward falls to 0.
        success_bonus: added at a success.
        speed_penalty: per m/s of |v| at a success.
        failure_penalty: subtracted at a crash or an ascent.
        tau_min_s: floor of the target's time to contact, s (None: 2 / crash_divergence).
    """

    tracking_weight: float = 1.0
    tracking_scale: float = 0.02
    success_bonus: float = 10.0
    speed_penalty: float = 0.2
    failure_penalty: float = 10.0
    tau_min_s: float = None

    def __post_init__(self):
        for k in ("tracking_weight", "success_bonus", "speed_penalty", "failure_penalty"):
            v = float(getattr(self, k))
            if not v >= 0:
                raise ValueError(f"reward.{k} must be >= 0, got {v}")
        if not float(self.tracking_scale) > 0:
            raise ValueError(f"reward.tracking_scale must be > 0, got {self.tracking_scale}")
        if self.tau_min_s is not None and not float(self.tau_min_s) > 0:
            raise ValueError(f"reward.tau_min_s must be > 0, got {self.tau_min_s}")


def divergence_target(t_s, tau0_s: torch.Tensor, c2: float, tau_min_s: float) -> torch.Tensor:
    """D*(t) = -1 / max(tau0 - c2 t, tau_min), (B,) float64 1/s, for ``tau0_s`` (B,) float64 s and
    the flight time ``t_s`` (a float or (B,) float64 s)."""
    t = t_s if isinstance(t_s, torch.Tensor) else float(t_s)
    return -1.0 / (tau0_s - c2 * t).clamp_min(tau_min_s)


def step_reward(rc: RewardConfig, dt_s: float, d_true: torch.Tensor, d_target: torch.Tensor, v_mps: torch.Tensor,
                flying: torch.Tensor, ended: torch.Tensor, outcome: torch.Tensor) -> torch.Tensor:
    """The reward of one step, (B,) float64.

    Args:
        dt_s: the control step, s.
        d_true, d_target: (B,) float64 true and target divergence at t_{k+1}, 1/s.
        v_mps: (B,) float64 velocity at t_{k+1} (the touchdown speed where it ended), m/s.
        flying: (B,) bool, the element flew this step (0 reward elsewhere).
        ended: (B,) bool, the descent ended at this step.
        outcome: (B,) int8 outcome codes after the step.
    """
    err = torch.nan_to_num((d_true - d_target).abs(), nan=math.inf)  # z <= 0 at a crash: no tracking
    r = rc.tracking_weight * dt_s * (1.0 - err / rc.tracking_scale).clamp_min(0.0)
    success = ended & (outcome == SUCCESS)
    failure = ended & ((outcome == CRASH) | (outcome == ASCENT))
    r = r + torch.where(success, rc.success_bonus - rc.speed_penalty * v_mps.abs(), torch.zeros_like(r))
    r = r - torch.where(failure, torch.full_like(r, rc.failure_penalty), torch.zeros_like(r))
    return torch.where(flying, r, torch.zeros_like(r))


def episode_ends(ended: torch.Tensor, outcome: torch.Tensor):
    """(terminated, truncated), (B,) bool each: ended by success/crash/ascent, or by timeout."""
    timeout = outcome == TIMEOUT
    return ended & ~timeout, ended & timeout
