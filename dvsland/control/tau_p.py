"""The paper's proportional TTC law, Eq. 2 read literally in tau-space (controller ``tau_p``).

u = Kp (tau* - tau_hat) + m g,  tau_hat = -1 / D_filtered,  clamped to [thrust_min, thrust_max].

When the filtered divergence is missing (NaN) or has the wrong sign (D >= 0 means the craft
is not approaching, so tau_hat is meaningless) the law does not act on it: it holds the last
thrust command (``missing_policy="hold"``) or commands hover m g (``"hover"``), and reports
which elements did so. The output is always finite.

Params :class:`~dvsland.control.base.LawParams`, state :class:`~dvsland.control.base.HoldLastState`,
pure step :func:`tau_p_step`.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from .base import (ControlOutput, Controller, HoldLastState, LawParams, check_bounds, check_gain_and_target,
                   clamp_thrust, hold_last_finish, hold_last_init, law_inputs, law_params)
from .gain import tau_loop_gain
from .registry import register_controller

Tensor = torch.Tensor


def tau_p_step(p: LawParams, state: HoldLastState, t_s, d_filtered: Tensor, mass_kg: Tensor,
               active: Optional[Tensor] = None) -> Tuple[HoldLastState, ControlOutput]:
    """Pure step of ``tau_p``: (next state, :class:`ControlOutput`).

    Args:
        t_s: flight time of each descent, (B,) float64 s (or a float for all).
        d_filtered: (B,) filtered divergence, 1/s (NaN = none).
        mass_kg: (B,) current mass, kg.
        active: (B,) bool or None (all); inactive descents keep their last command.

    Finite by construction: a usable D < 0 gives tau_hat = -1/D in (0, inf], so
    Kp (tau* - tau_hat) is finite or -inf, and the clamp maps -inf to ``thrust_min_n``.
    """
    d, _, mg, t_s = law_inputs(p, t_s, d_filtered, mass_kg)
    tau_star = p.tau0_s - p.c2 * t_s
    usable = d < 0  # False for NaN and for D >= 0 (not approaching)
    tau_hat = torch.where(usable, -1.0 / d, float("nan"))
    u = clamp_thrust(p, p.kp * (tau_star - tau_hat) + mg)
    state, thrust = hold_last_finish(p, state, usable, u, mg, active)
    return state, ControlOutput(thrust_n=thrust, tau_hat_s=tau_hat, tau_target_s=tau_star, held=~usable)


@register_controller("tau_p")
class TauPController(Controller):
    """Paper Eq. 2, batched with per-element gains.

    Args:
        kp: (B,) float64 gains Kp, N/s.
        tau0_s: (B,) float64 initial TTC z0/|v0|, s.
        c2: c^2 of the target.
        g_mps2: gravity, m/s^2.
        thrust_min_n: lower clamp, N (>= 0).
        thrust_max_n: upper clamp, N, or None for unbounded.
        missing_policy: ``"hold"`` or ``"hover"``.
        z0_m, v0_mps, m0_kg: optional (B,) nominal initial state (only for the reported loop gain).

    Before the first command (and after a reset) the "last thrust" is hover, m g.
    """

    def __init__(self, kp: Tensor, tau0_s: Tensor, c2: float, g_mps2: float, thrust_min_n: float = 0.0,
                 thrust_max_n: Optional[float] = None, missing_policy: str = "hold", z0_m=None, v0_mps=None, m0_kg=None):
        check_bounds(thrust_min_n, thrust_max_n, missing_policy)
        kp, tau0_s = check_gain_and_target(kp, tau0_s, c2)
        self.params = law_params(kp, tau0_s, c2, g_mps2, thrust_min_n, thrust_max_n, missing_policy)
        self.z0_m, self.v0_mps, self.m0_kg = z0_m, v0_mps, m0_kg
        self._template = self.init_state()
        self.state = self.init_state()

    @classmethod
    def from_params(cls, p, **options) -> "TauPController":
        """From the loop's :class:`~dvsland.control.DescentParams` (no law options)."""
        if options:
            raise ValueError(f"controller 'tau_p' takes no options, got {sorted(options)}")
        return cls(p.kp, p.tau0_s, p.c2, p.g_mps2, p.thrust_min_n, p.thrust_max_n, p.missing_policy,
                   z0_m=p.z0_m, v0_mps=p.v0_mps, m0_kg=p.m0_kg)

    def init_state(self) -> HoldLastState:
        return hold_last_init(self.params)

    def step_state(self, state: HoldLastState, t_s, d_filtered: Tensor, mass_kg: Tensor,
                   active: Optional[Tensor] = None, altitude_m: Optional[Tensor] = None):
        """Pure step (:func:`tau_p_step`); ``altitude_m`` is not used."""
        self._check(state)
        return tau_p_step(self.params, state, t_s, d_filtered, mass_kg, active)

    def loop_gain_fields(self, m_kg: Tensor, z_m: Tensor) -> dict:
        """tau-space lambda = Kp z0 / (m0 v0^2) (the initial mass: the paper's figure)."""
        if self.z0_m is None:
            return {}
        m0 = self.m0_kg if self.m0_kg is not None else m_kg
        return {"loop_gain": tau_loop_gain(self.kp, self.z0_m, self.v0_mps, m0), "loop_gain_kind": "tau"}
