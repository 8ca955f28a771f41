"""Controllers: the interface, and the paper's proportional TTC law (Eq. 2).

u = Kp (tau* - tau_hat) + m g,  tau_hat = -1 / D_filtered,  clamped to [thrust_min, thrust_max].

When the filtered divergence is missing (NaN) or has the wrong sign (D >= 0 means the craft
is not approaching, so tau_hat is meaningless) the law does not act on it: it holds the last
thrust command (``missing_policy="hold"``) or commands hover m g (``"hover"``), and reports
which elements did so. The output is always finite.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from .target import tau_target

Tensor = torch.Tensor


@dataclass
class ControlOutput:
    """One control step's result, all (B,).

    Attributes:
        thrust_n: float64 commanded thrust, N (finite, clamped).
        tau_hat_s: float64 TTC used, s (NaN where the estimate was not used).
        tau_target_s: float64 tau*(t), s.
        held: bool, True where the estimate was missing / wrong-signed and the policy acted.
    """

    thrust_n: Tensor
    tau_hat_s: Tensor
    tau_target_s: Tensor
    held: Tensor


class Controller:
    """Interface of a batched thrust law. Subclasses implement :meth:`reset` and :meth:`__call__`.

    ``__call__(t_s, d_filtered, mass_kg, active)`` gets the flight time (scalar or (B,)
    float64, s), the filtered divergence (B,) (1/s, NaN = none), the current mass (B,) kg and
    the active mask, and returns a :class:`ControlOutput`.
    """

    def reset(self, mask: Optional[Tensor] = None) -> None:
        raise NotImplementedError

    def __call__(self, t_s, d_filtered: Tensor, mass_kg: Tensor, active: Optional[Tensor] = None) -> ControlOutput:
        raise NotImplementedError


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

    Before the first command (and after a reset) the "last thrust" is hover, m g.
    """

    def __init__(self, kp: Tensor, tau0_s: Tensor, c2: float, g_mps2: float, thrust_min_n: float = 0.0,
                 thrust_max_n: Optional[float] = None, missing_policy: str = "hold"):
        if missing_policy not in ("hold", "hover"):
            raise ValueError(f"missing_policy must be 'hold' or 'hover', got {missing_policy!r}")
        if not 0 < c2 < 1:
            raise ValueError(f"c2 must be in (0, 1), got {c2}")
        if thrust_min_n < 0:
            raise ValueError(f"thrust_min_n must be >= 0, got {thrust_min_n}")
        if thrust_max_n is not None and thrust_max_n < thrust_min_n:
            raise ValueError(f"thrust_max_n must be >= thrust_min_n={thrust_min_n}, got {thrust_max_n}")
        self.kp = torch.as_tensor(kp, dtype=torch.float64)
        if bool((self.kp <= 0).any()):
            raise ValueError("kp must be > 0 for every element")
        self.tau0_s = torch.as_tensor(tau0_s, dtype=torch.float64, device=self.kp.device)
        self.c2 = float(c2)
        self.g_mps2 = float(g_mps2)
        self.thrust_min_n = float(thrust_min_n)
        self.thrust_max_n = None if thrust_max_n is None else float(thrust_max_n)
        self.missing_policy = missing_policy
        self._last: Optional[Tensor] = None
        self._pending_reset = False

    def reset(self, mask: Optional[Tensor] = None) -> None:
        """Forget the last command (hover is used until a command exists)."""
        self._pending_reset = True
        if mask is None or self._last is None:
            self._last = None
        else:
            self._last = torch.where(mask, float("nan"), self._last)  # NaN = hover at the next call

    def _clamp(self, u: Tensor) -> Tensor:
        u = u.clamp_min(self.thrust_min_n)  # also maps -inf (D_hat -> 0-) to thrust_min
        if self.thrust_max_n is not None:
            u = u.clamp_max(self.thrust_max_n)
        return u

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
        u = self._clamp(self.kp * (tau_star - tau_hat) + mg)
        if self._last is None:
            self._last = self._clamp(mg)
        elif self._pending_reset:
            self._last = torch.where(torch.isnan(self._last), self._clamp(mg), self._last)
        self._pending_reset = False
        if self.missing_policy == "hold":
            fallback = self._last
        else:
            fallback = self._clamp(mg)
        thrust = torch.where(usable, u, fallback)
        if active is not None:
            thrust = torch.where(active, thrust, self._last)
        self._last = thrust
        return ControlOutput(thrust_n=thrust, tau_hat_s=tau_hat, tau_target_s=tau_star, held=~usable)
