"""The controller interface and its output record."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

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

    A law that sets the class attribute ``needs_altitude = True`` is also given
    ``altitude_m=`` (B,) float64, the filter's altitude estimate in m (the efference-copy filter
    provides one; see :mod:`dvsland.control.efference`).

    Optional: ``loop_gain_fields(m_kg, z_m)`` returning per-descent loop-gain figures for the
    summary (see :mod:`dvsland.control.gain`); laws without it report no loop gain.
    """

    needs_altitude: bool = False

    def reset(self, mask: Optional[Tensor] = None) -> None:
        raise NotImplementedError

    def __call__(self, t_s, d_filtered: Tensor, mass_kg: Tensor, active: Optional[Tensor] = None) -> ControlOutput:
        raise NotImplementedError


class HoldLast:
    """The 'last thrust' memory shared by the built-in laws (hover m g before any command)."""

    def __init__(self, thrust_min_n: float, thrust_max_n: Optional[float]):
        self.thrust_min_n = float(thrust_min_n)
        self.thrust_max_n = None if thrust_max_n is None else float(thrust_max_n)
        self.last: Optional[Tensor] = None
        self._pending_reset = False

    def clamp(self, u: Tensor) -> Tensor:
        u = u.clamp_min(self.thrust_min_n)  # also maps -inf to thrust_min
        if self.thrust_max_n is not None:
            u = u.clamp_max(self.thrust_max_n)
        return u

    def reset(self, mask: Optional[Tensor] = None) -> None:
        self._pending_reset = True
        if mask is None or self.last is None:
            self.last = None
        else:
            self.last = torch.where(mask, float("nan"), self.last)  # NaN = hover at the next call

    def before(self, mg: Tensor) -> None:
        """Make ``last`` defined (hover where unknown) before a command is chosen."""
        if self.last is None:
            self.last = self.clamp(mg)
        elif self._pending_reset:
            self.last = torch.where(torch.isnan(self.last), self.clamp(mg), self.last)
        self._pending_reset = False

    def finish(self, usable: Tensor, u: Tensor, mg: Tensor, policy: str, active: Optional[Tensor]) -> Tensor:
        """Thrust: ``u`` where usable, else the missing policy; frozen where not ``active``."""
        fallback = self.last if policy == "hold" else self.clamp(mg)
        thrust = torch.where(usable, u, fallback)
        if active is not None:
            thrust = torch.where(active, thrust, self.last)
        self.last = thrust
        return thrust


def check_bounds(thrust_min_n: float, thrust_max_n: Optional[float], missing_policy: str) -> None:
    """ValueError naming the parameter when a bound or the policy is invalid."""
    if missing_policy not in ("hold", "hover"):
        raise ValueError(f"missing_policy must be 'hold' or 'hover', got {missing_policy!r}")
    if thrust_min_n < 0:
        raise ValueError(f"thrust_min_n must be >= 0, got {thrust_min_n}")
    if thrust_max_n is not None and thrust_max_n < thrust_min_n:
        raise ValueError(f"thrust_max_n must be >= thrust_min_n={thrust_min_n}, got {thrust_max_n}")


def check_gain_and_target(kp, tau0_s, c2: float):
    """``(kp, tau0_s)`` as float64 tensors on kp's device after the checks every tau*-tracking law
    shares: c2 in (0, 1) and every Kp > 0 (ValueError naming the parameter).

    Args:
        kp: (B,) proportional gains, N/s (or anything ``torch.as_tensor`` takes).
        tau0_s: (B,) initial time-to-contact of the target, s.
        c2: the target's slope in tau*(t) = tau0 - c2 t.
    """
    if not 0 < c2 < 1:
        raise ValueError(f"c2 must be in (0, 1), got {c2}")
    kp = torch.as_tensor(kp, dtype=torch.float64)
    if bool((kp <= 0).any()):
        raise ValueError("kp must be > 0 for every element")
    return kp, torch.as_tensor(tau0_s, dtype=torch.float64, device=kp.device)
