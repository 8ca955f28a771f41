"""A divergence law past the paper (controller ``div_gs``): the gain is scheduled on the
efference-copy altitude estimate, and the target ends in a slow constant-divergence approach.

The released law u = Kp (D* - D) has loop gain Kp / (m z): sluggish high up, past the sampled
loop's stability limit near the ground (:mod:`dvsland.control.gain`). With an altitude estimate
z_hat from the efference-copy filter (:class:`~dvsland.control.EfferenceFilter`) the gain can be
scheduled, K = lambda m z_hat, so that the divergence loop has the same rate ``lambda`` at every
altitude:

    u = m (g + a_ref) + lambda m z_hat (D*(t) - D_filtered),  clamped to [thrust_min, thrust_max]

The target follows the paper's TTC profile until its divergence reaches ``d_final_per_s``, then
holds that divergence (an exponential approach, v = -d_final z):

    D*(t) = -min(1 / tau*(t), d_final),   tau*(t) = tau0 - c2 t

so the speed at the success altitude z_s is d_final z_s (0.03 1/s x 50 m = 1.5 m/s) whatever the
altitude estimate says: z_hat only scales the gain and the feed-forward a_ref (the deceleration
the target needs: (1 - c2) D*^2 z_hat on the TTC part, D*^2 z_hat on the constant-divergence part).
With ``v_min_mps`` > 0 the final approach is floored at that sink rate (constant velocity below
z_hat = v_min / d_final). With ``v_min_sigma`` > 0 the floor grows with what the filter does not
know about its own velocity: v_min + v_min_sigma sigma_v, sigma_v the filter's posterior standard
deviation of the velocity (``FilterOut.velocity_sigma_mps``). A craft whose filter fused no
estimate flies on its prior (sigma_v = the dispersion of v0, 3 m/s on ``montecarlo_efference``);
its velocity may be off by that much, and a floor of 2 m/s alone then lets the true velocity reach
0, so the craft hovers and climbs away. The floor falls back to v_min as estimates come in.
The constant-TTC-decrease descent alone reaches 50 m at 11-14 m/s on the paper's sites. A
missing filtered estimate holds the last thrust (or hovers).

Params :class:`~dvsland.control.base.LawParams` (options: :class:`dvsland.config.schema.DivGSConfig`),
state :class:`~dvsland.control.base.HoldLastState`, pure step :func:`div_gs_step`.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from dvsland.config.schema import DivGSConfig

from .base import (ControlOutput, Controller, HoldLastState, LawParams, check_bounds, clamp_thrust,
                   divergence_law_finish, hold_last_init, law_inputs, law_params)
from .registry import register_controller

Tensor = torch.Tensor


def divergence_target(t_s, tau0_s: Tensor, c2: float, d_final_per_s: float):
    """Target of ``div_gs`` and the deceleration coefficient of its phase.

    Args:
        t_s: flight time, s (float or (B,)).
        tau0_s: (B,) float64 initial TTC, s.
        c2: slope of tau*(t) = tau0 - c2 t.
        d_final_per_s: divergence of the final approach, 1/s (> 0; a float or a 0-dim float64 tensor).

    Returns:
        (d_star (B,) float64 < 0, 1/s; coef (B,) float64: a_ref = coef d_star^2 z, i.e. 1 - c2 on the
        TTC part and 1 on the constant-divergence part).
    """
    tau_star = tau0_s - c2 * t_s
    inv = torch.where(tau_star > 0, 1.0 / tau_star.clamp_min(1e-9), float("inf"))
    final = inv >= d_final_per_s
    d_star = -torch.where(final, d_final_per_s, inv)  # a tensor d_final keeps its graph
    coef = torch.where(final, 1.0, 1.0 - c2)
    return d_star, coef


def floored_target(t_s, tau0_s: Tensor, c2: float, d_final_per_s: float, v_min_mps, z_m: Tensor):
    """:func:`divergence_target` with the final approach floored at the sink rate ``v_min_mps``
    (m/s; 0 = no floor): where the final approach's d_final z is below it the target becomes
    -v_min / z (constant velocity, coef 0).

    Args:
        v_min_mps: the floor, m/s: a float (0 = none) or (B,) float64 (one per descent, >= 0).
        z_m: (B,) float64 altitude, m, at least 1 m (the law's z_hat; the loss's true z).

    Returns:
        (d_star (B,) float64 1/s, coef (B,) float64), as :func:`divergence_target`.
    """
    d_star, coef = divergence_target(t_s, tau0_s, c2, d_final_per_s)
    if isinstance(v_min_mps, Tensor) or v_min_mps > 0:  # final approach (coef 1) floored: constant velocity, a_ref = 0
        floor = -v_min_mps / z_m
        use = (coef == 1.0) & (floor < d_star)
        d_star = torch.where(use, floor, d_star)
        coef = torch.where(use, 0.0, coef)
    return d_star, coef


def div_gs_step(p: LawParams, state: HoldLastState, t_s, d_filtered: Tensor, mass_kg: Tensor,
                active: Optional[Tensor], altitude_m: Optional[Tensor],
                velocity_sigma_mps: Optional[Tensor] = None) -> Tuple[HoldLastState, ControlOutput]:
    """Pure step of ``div_gs``: (next state, :class:`ControlOutput`).

    Args:
        t_s: flight time of each descent, (B,) float64 s (or a float for all).
        d_filtered: (B,) filtered divergence, 1/s (NaN = none).
        mass_kg: (B,) current mass, kg.
        active: (B,) bool or None (all); inactive descents keep their last command.
        altitude_m: (B,) the filter's altitude estimate z_hat, m (required).
        velocity_sigma_mps: (B,) the filter's posterior standard deviation of the velocity, m/s
            (required where ``v_min_sigma`` > 0, else not read).
    """
    if altitude_m is None:
        raise ValueError("controller 'div_gs' needs altitude_m (use the 'efference' filter)")
    o = p.options
    d, m, mg, t_s = law_inputs(p, t_s, d_filtered, mass_kg)
    z = altitude_m.to(torch.float64).clamp_min(1.0)
    d_star, coef = floored_target(t_s, p.tau0_s, p.c2, o.d_final_per_s, sink_floor(o, velocity_sigma_mps), z)
    usable = ~torch.isnan(d)
    a_ref = coef * d_star * d_star * z
    u = m * (p.g_mps2 + a_ref) + o.lambda_per_s * m * z * (d_star - torch.where(usable, d, 0.0))
    u = clamp_thrust(p, u)
    return divergence_law_finish(p, state, d, u, mg, active, -1.0 / d_star)


def sink_floor(o: DivGSConfig, velocity_sigma_mps: Optional[Tensor]):
    """The final approach's sink-rate floor, m/s: ``v_min_mps`` (a float), or with ``v_min_sigma`` > 0
    v_min + v_min_sigma sigma_v (B,) float64 (a NaN sigma counts as 0)."""
    if not o.v_min_sigma > 0:
        return o.v_min_mps
    if velocity_sigma_mps is None:
        raise ValueError("controller.div_gs.v_min_sigma > 0 needs the filter's velocity standard deviation "
                         "(velocity_sigma_mps; controller.filter=efference_fit or efference gives it)")
    sig = torch.nan_to_num(velocity_sigma_mps.to(torch.float64), nan=0.0).clamp_min(0.0)
    return o.v_min_mps + o.v_min_sigma * sig


@register_controller("div_gs")
class DivGSController(Controller):
    """Gain-scheduled divergence law (needs the filter's altitude estimate).

    Args:
        tau0_s: (B,) float64 initial TTC z0/|v0|, s.
        c2: slope of the TTC target.
        g_mps2: gravity, m/s^2.
        thrust_min_n, thrust_max_n, missing_policy: as for ``tau_p``.
        lambda_per_s: divergence-loop rate, 1/s (> 0; lambda dt well below 2).
        d_final_per_s: divergence of the final approach, 1/s (> 0): the speed at altitude z is
            then d_final z.
        v_min_mps: lowest sink rate of the final approach, m/s (>= 0; 0 = none): the target becomes
            D* = -max(d_final, v_min / z_hat), a constant-velocity descent once d_final z_hat < v_min.
            An altitude estimate that is too low then cannot stop the craft above the ground (it
            would hover, then climb, at v_hat = -d_final z_hat -> 0).
        v_min_sigma: the floor grows by this many of the filter's posterior velocity standard
            deviations (>= 0; 0 = off): v_min + v_min_sigma sigma_v (the module doc).
    """

    needs_altitude = True

    def __init__(self, tau0_s: Tensor, c2: float, g_mps2: float, thrust_min_n: float = 0.0,
                 thrust_max_n: Optional[float] = None, missing_policy: str = "hold", lambda_per_s: float = 1.0,
                 d_final_per_s: float = 0.03, v_min_mps: float = 0.0, v_min_sigma: float = 0.0):
        check_bounds(thrust_min_n, thrust_max_n, missing_policy)
        for name, val in (("v_min_mps", v_min_mps), ("v_min_sigma", v_min_sigma)):
            if not val >= 0:
                raise ValueError(f"controller.div_gs.{name} must be >= 0, got {val}")
        for name, val in (("lambda_per_s", lambda_per_s), ("d_final_per_s", d_final_per_s)):
            if not val > 0:
                raise ValueError(f"{name} must be > 0, got {val}")
        if not 0 < c2 < 1:
            raise ValueError(f"c2 must be in (0, 1), got {c2}")
        options = DivGSConfig(lambda_per_s=float(lambda_per_s), d_final_per_s=float(d_final_per_s),
                              v_min_mps=float(v_min_mps), v_min_sigma=float(v_min_sigma))
        self.params = law_params(None, torch.as_tensor(tau0_s, dtype=torch.float64), c2, g_mps2, thrust_min_n,
                                 thrust_max_n, missing_policy, options)
        self._template = self.init_state()
        self.state = self.init_state()

    @classmethod
    def from_params(cls, p, **options) -> "DivGSController":
        """From the loop's :class:`~dvsland.control.DescentParams` and the ``controller.div_gs`` options
        (the settings' Kp is not used: the gain is lambda m z_hat)."""
        return cls(p.tau0_s, p.c2, p.g_mps2, p.thrust_min_n, p.thrust_max_n, p.missing_policy, **options)

    def init_state(self) -> HoldLastState:
        return hold_last_init(self.params)

    @property
    def needs_velocity_sigma(self) -> bool:
        """Whether the step reads the filter's velocity standard deviation (``v_min_sigma`` > 0)."""
        return self.params.options.v_min_sigma > 0

    def step_state(self, state: HoldLastState, t_s, d_filtered: Tensor, mass_kg: Tensor,
                   active: Optional[Tensor] = None, altitude_m: Optional[Tensor] = None,
                   velocity_sigma_mps: Optional[Tensor] = None):
        """Pure step (:func:`div_gs_step`); ``altitude_m`` (B,) m is required, ``velocity_sigma_mps``
        (B,) m/s where ``v_min_sigma`` > 0."""
        self._check(state)
        return div_gs_step(self.params, state, t_s, d_filtered, mass_kg, active, altitude_m, velocity_sigma_mps)

    def loop_gain_fields(self, m_kg: Tensor, z_m: Tensor) -> dict:
        """The scheduled divergence-loop gain is lambda at every altitude: it never crosses the limit."""
        return {"loop_gain": torch.full_like(m_kg, self.lambda_per_s), "loop_gain_kind": "div"}
