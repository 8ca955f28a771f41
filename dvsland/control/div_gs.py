"""A divergence law past the paper (controller ``div_gs``): the gain is scheduled on the
efference-copy altitude estimate, and the divergence target brings the craft to the success
altitude slowly.

The released law u = Kp (D* - D) has loop gain Kp / (m z): sluggish high up, past the sampled
loop's stability limit near the ground (:mod:`dvsland.control.gain`). With an altitude estimate
z_hat from the efference-copy filter (:class:`~dvsland.control.EfferenceFilter`) the gain can be
scheduled, K = lambda m z_hat, so that the divergence loop has the same rate ``lambda`` at every
altitude:

    u = m (g + a_ref) + lambda m z_hat (D*(z_hat) - D_filtered),  clamped to [thrust_min, thrust_max]

The target D* = -v_ref(z_hat) / z_hat follows the lowest of three speed profiles:

- the paper's constant-TTC-decrease descent, v_p(z) = |v0| (z / z0)^(1 - c2) (tau = tau0 (z/z0)^c2);
- a braking curve, v_b(z) = sqrt(v_land^2 + 2 a_brake (z - z_land));
- a final exponential approach, v_f(z) = v_land + k_final (z - z_land);

each clipped below at v_land (below z_land the craft keeps sinking at v_land), and a_ref is that
profile's own deceleration ((1 - c2) v_p^2 / z, a_brake, k_final v_f): the thrust the profile needs.
The constant-tau-decrease descent reaches 50 m at 11-14 m/s on the paper's sites; this one at
about v_land. A missing filtered estimate holds the last thrust (or hovers).
"""

from __future__ import annotations

from typing import Optional

import torch

from .base import ControlOutput, Controller, HoldLast, check_bounds
from .registry import register_controller

Tensor = torch.Tensor


def reference_speed(z_m: Tensor, z0_m: Tensor, v0_mps: Tensor, c2: float, v_land_mps: float, z_land_m: float,
                    a_brake_mps2: float, k_final_per_s: float):
    """Speed profile of ``div_gs`` and its deceleration.

    Args:
        z_m: (B,) float64 altitude, m (> 0).
        z0_m, v0_mps: (B,) float64 nominal start.
        c2, v_land_mps, z_land_m, a_brake_mps2, k_final_per_s: profile constants (see module doc).

    Returns:
        (speed_mps (B,) >= v_land, decel_mps2 (B,) >= 0): the target descent speed |v_ref| and the
        upward acceleration that following the profile needs.
    """
    z = z_m.clamp_min(1e-6)
    above = (z - z_land_m).clamp_min(0.0)
    vp = v0_mps.abs() * (z / z0_m) ** (1.0 - c2)
    vb = torch.sqrt(v_land_mps ** 2 + 2.0 * a_brake_mps2 * above)
    vf = v_land_mps + k_final_per_s * above
    speed = torch.minimum(torch.minimum(vp, vb), vf)
    decel = torch.where(vp <= torch.minimum(vb, vf), (1.0 - c2) * vp * vp / z,
                        torch.where(vb <= vf, torch.full_like(z, a_brake_mps2), k_final_per_s * vf))
    low = speed <= v_land_mps
    return torch.where(low, torch.full_like(speed, v_land_mps), speed), torch.where(low, 0.0, decel)


@register_controller("div_gs")
class DivGSController(Controller):
    """Gain-scheduled divergence law (needs the filter's altitude estimate).

    Args:
        z0_m, v0_mps: (B,) float64 nominal initial state.
        c2: slope of the paper's TTC target (the profile's upper part).
        g_mps2: gravity, m/s^2.
        thrust_min_n, thrust_max_n, missing_policy: as for ``tau_p``.
        lambda_per_s: divergence-loop rate, 1/s (> 0; lambda dt well below 2).
        v_land_mps: target speed at ``z_land_m``, m/s (> 0).
        z_land_m: altitude where the profile reaches v_land, m (>= 0).
        a_brake_mps2: deceleration of the braking curve, m/s^2 (> 0).
        k_final_per_s: rate of the final exponential approach, 1/s (> 0).
    """

    needs_altitude = True

    def __init__(self, z0_m: Tensor, v0_mps: Tensor, c2: float, g_mps2: float, thrust_min_n: float = 0.0,
                 thrust_max_n: Optional[float] = None, missing_policy: str = "hold", lambda_per_s: float = 1.0,
                 v_land_mps: float = 1.0, z_land_m: float = 50.0, a_brake_mps2: float = 1.5,
                 k_final_per_s: float = 0.2):
        check_bounds(thrust_min_n, thrust_max_n, missing_policy)
        for name, val in (("lambda_per_s", lambda_per_s), ("v_land_mps", v_land_mps),
                          ("a_brake_mps2", a_brake_mps2), ("k_final_per_s", k_final_per_s)):
            if not val > 0:
                raise ValueError(f"{name} must be > 0, got {val}")
        if not z_land_m >= 0:
            raise ValueError(f"z_land_m must be >= 0, got {z_land_m}")
        if not 0 < c2 < 1:
            raise ValueError(f"c2 must be in (0, 1), got {c2}")
        self.z0_m = torch.as_tensor(z0_m, dtype=torch.float64)
        self.v0_mps = torch.as_tensor(v0_mps, dtype=torch.float64, device=self.z0_m.device)
        self.c2, self.g_mps2 = float(c2), float(g_mps2)
        self.missing_policy = missing_policy
        self.lambda_per_s, self.v_land_mps, self.z_land_m = float(lambda_per_s), float(v_land_mps), float(z_land_m)
        self.a_brake_mps2, self.k_final_per_s = float(a_brake_mps2), float(k_final_per_s)
        self._mem = HoldLast(thrust_min_n, thrust_max_n)

    @classmethod
    def from_params(cls, p, **options) -> "DivGSController":
        """From the loop's :class:`~dvsland.control.DescentParams` and the ``controller.div_gs`` options
        (the settings' Kp is not used: the gain is lambda m z_hat)."""
        return cls(p.z0_m, p.v0_mps, p.c2, p.g_mps2, p.thrust_min_n, p.thrust_max_n, p.missing_policy, **options)

    def reset(self, mask: Optional[Tensor] = None) -> None:
        self._mem.reset(mask)

    def loop_gain_fields(self, m_kg: Tensor, z_m: Tensor) -> dict:
        """The scheduled divergence-loop gain is lambda at every altitude: it never crosses the limit."""
        return {"loop_gain": torch.full_like(m_kg, self.lambda_per_s), "loop_gain_kind": "div"}

    def __call__(self, t_s, d_filtered: Tensor, mass_kg: Tensor, active: Optional[Tensor] = None,
                 altitude_m: Optional[Tensor] = None) -> ControlOutput:
        if altitude_m is None:
            raise ValueError("controller 'div_gs' needs altitude_m (use the 'efference' filter)")
        d = d_filtered.to(torch.float64)
        m = mass_kg.to(torch.float64)
        mg = m * self.g_mps2
        z = altitude_m.to(torch.float64).clamp_min(1.0)
        speed, decel = reference_speed(z, self.z0_m, self.v0_mps, self.c2, self.v_land_mps, self.z_land_m,
                                       self.a_brake_mps2, self.k_final_per_s)
        d_star = -speed / z
        usable = ~torch.isnan(d)
        u = m * (self.g_mps2 + decel) + self.lambda_per_s * m * z * (d_star - torch.where(usable, d, 0.0))
        u = self._mem.clamp(u)
        self._mem.before(mg)
        thrust = self._mem.finish(usable, u, mg, self.missing_policy, active)
        tau_hat = torch.where(d < 0, -1.0 / d, float("nan"))
        return ControlOutput(thrust_n=thrust, tau_hat_s=tau_hat, tau_target_s=-1.0 / d_star, held=~usable)
