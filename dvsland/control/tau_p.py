"""The paper's proportional TTC law, Eq. 2 read literally in tau-space (controller ``tau_p``).

u = Kp (tau* - tau_hat) + m g,  tau_hat = -1 / D_filtered,  clamped to [thrust_min, thrust_max].

When the filtered divergence is missing (NaN) or has the wrong sign (D >= 0 means the craft
is not approaching, so tau_hat is meaningless) the law does not act on it: it holds the last
thrust command (``missing_policy="hold"``) or commands hover m g (``"hover"``), and reports
which elements did so. The output is always finite.
"""

from __future__ import annotations

from typing import Optional

import torch

from .base import ControlOutput, Controller, HoldLast, check_bounds, check_gain_and_target
from .gain import tau_loop_gain
from .registry import register_controller

Tensor = torch.Tensor


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
        self.kp, self.tau0_s = check_gain_and_target(kp, tau0_s, c2)
        self.c2 = float(c2)
        self.g_mps2 = float(g_mps2)
        self.thrust_min_n = float(thrust_min_n)
        self.thrust_max_n = None if thrust_max_n is None else float(thrust_max_n)
        self.missing_policy = missing_policy
        self.z0_m, self.v0_mps, self.m0_kg = z0_m, v0_mps, m0_kg
        self._mem = HoldLast(thrust_min_n, thrust_max_n)

    @classmethod
    def from_params(cls, p, **options) -> "TauPController":
        """From the loop's :class:`~dvsland.control.DescentParams` (no law options)."""
        if options:
            raise ValueError(f"controller 'tau_p' takes no options, got {sorted(options)}")
        return cls(p.kp, p.tau0_s, p.c2, p.g_mps2, p.thrust_min_n, p.thrust_max_n, p.missing_policy,
                   z0_m=p.z0_m, v0_mps=p.v0_mps, m0_kg=p.m0_kg)

    def reset(self, mask: Optional[Tensor] = None) -> None:
        """Forget the last command (hover is used until a command exists)."""
        self._mem.reset(mask)

    def loop_gain_fields(self, m_kg: Tensor, z_m: Tensor) -> dict:
        """tau-space lambda = Kp z0 / (m0 v0^2) (the initial mass: the paper's figure)."""
        if self.z0_m is None:
            return {}
        m0 = self.m0_kg if self.m0_kg is not None else m_kg
        return {"loop_gain": tau_loop_gain(self.kp, self.z0_m, self.v0_mps, m0), "loop_gain_kind": "tau"}

    def __call__(self, t_s, d_filtered: Tensor, mass_kg: Tensor, active: Optional[Tensor] = None) -> ControlOutput:
        """Thrust for filtered divergence ``d_filtered`` (B,) at flight time ``t_s`` (float or (B,)).

        Finite by construction: a usable D < 0 gives tau_hat = -1/D in (0, inf], so
        Kp (tau* - tau_hat) is finite or -inf, and the clamp maps -inf to ``thrust_min_n``.
        """
        d = d_filtered.to(torch.float64)
        mg = mass_kg.to(torch.float64) * self.g_mps2
        tau_star = self.tau0_s - self.c2 * t_s
        usable = d < 0  # False for NaN and for D >= 0 (not approaching)
        tau_hat = torch.where(usable, -1.0 / d, float("nan"))
        u = self._mem.clamp(self.kp * (tau_star - tau_hat) + mg)
        self._mem.before(mg)
        thrust = self._mem.finish(usable, u, mg, self.missing_policy, active)
        return ControlOutput(thrust_n=thrust, tau_hat_s=tau_hat, tau_target_s=tau_star, held=~usable)
