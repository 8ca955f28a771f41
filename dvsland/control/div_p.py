"""The law the paper's released implementation flies (controller ``div_p``): proportional
control in divergence space.

    e = D*(t) - mean(last n_bin D_hat),   D*(t) = -1 / tau*(t),   tau*(t) = tau0 - c2 t
    u = Kp e  (+ m g with ``feedforward_mg``),  clamped to [thrust_min, thrust_max]

With the released code's constants there is no m g term, negative u becomes 0 and no upper
bound is applied. The mean of the last n_bin estimates is the loop's filter output
(``d_filtered``). Its loop gain is Kp / (m z) (see :mod:`dvsland.control.gain`).

A missing filtered estimate (NaN) triggers ``missing_policy`` (hold the last thrust, or hover);
a non-negative D is used as it is (the error is then negative and the thrust drops to the
lower bound). Past t = tau0 / c2 the target tau* is <= 0 and -1/tau* changes sign, as in the
formula; descents end long before that in practice.

Params :class:`~dvsland.control.base.LawParams` (options: :class:`dvsland.config.schema.DivPConfig`),
state :class:`~dvsland.control.base.HoldLastState`, pure step :func:`div_p_step`.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from dvsland.config.schema import DivPConfig

from .base import (ControlOutput, Controller, HoldLastState, LawParams, check_bounds, check_gain_and_target,
                   clamp_thrust, divergence_law_finish, hold_last_init, law_inputs, law_params)
from .gain import div_loop_gain, gain_limit_altitude_m
from .registry import register_controller

Tensor = torch.Tensor


def div_p_step(p: LawParams, state: HoldLastState, t_s, d_filtered: Tensor, mass_kg: Tensor,
               active: Optional[Tensor] = None) -> Tuple[HoldLastState, ControlOutput]:
    """Pure step of ``div_p``: (next state, :class:`ControlOutput`).

    Args:
        t_s: flight time of each descent, (B,) float64 s (or a float for all).
        d_filtered: (B,) filtered divergence, 1/s (NaN = none).
        mass_kg: (B,) current mass, kg.
        active: (B,) bool or None (all); inactive descents keep their last command.
    """
    d, _, mg, t_s = law_inputs(p, t_s, d_filtered, mass_kg)
    tau_star = p.tau0_s - p.c2 * t_s
    usable = ~torch.isnan(d)
    e = -1.0 / tau_star - torch.where(usable, d, 0.0)
    u = p.kp * e
    if p.options.feedforward_mg:
        u = u + mg
    u = clamp_thrust(p, torch.nan_to_num(u, nan=0.0))
    return divergence_law_finish(p, state, d, u, mg, active, tau_star)


@register_controller("div_p")
class DivPController(Controller):
    """u = Kp (-1/tau*(t) - D_filtered) [+ m g], batched with per-element gains.

    Args:
        kp: (B,) float64 gains Kp, N s (thrust per unit divergence error, 1/s).
        tau0_s: (B,) float64 initial TTC z0/|v0|, s.
        c2: slope of tau*(t) = tau0 - c2 t (released code: c*c = 0.25 with c = 0.5).
        g_mps2: gravity, m/s^2.
        thrust_min_n: lower clamp, N (>= 0; the released code: 0).
        thrust_max_n: upper clamp, N, or None (the released code: none applied).
        missing_policy: ``"hold"`` or ``"hover"`` when the filtered D is NaN.
        feedforward_mg: add m g to the command (the released code: no).
        n_bin: optional (B,) int filter lengths, for the reported stability altitude.
        dt_s: control interval, s (for the reported stability altitude).
    """

    def __init__(self, kp: Tensor, tau0_s: Tensor, c2: float, g_mps2: float, thrust_min_n: float = 0.0,
                 thrust_max_n: Optional[float] = None, missing_policy: str = "hold", feedforward_mg: bool = False,
                 n_bin: Optional[Tensor] = None, dt_s: float = 0.1):
        check_bounds(thrust_min_n, thrust_max_n, missing_policy)
        kp, tau0_s = check_gain_and_target(kp, tau0_s, c2)
        self.params = law_params(kp, tau0_s, c2, g_mps2, thrust_min_n, thrust_max_n, missing_policy,
                                 DivPConfig(feedforward_mg=bool(feedforward_mg)))
        self.n_bin = n_bin
        self.dt_s = float(dt_s)
        self._template = self.init_state()
        self.state = self.init_state()

    @classmethod
    def from_params(cls, p, feedforward_mg: bool = False) -> "DivPController":
        """From the loop's :class:`~dvsland.control.DescentParams`; option ``feedforward_mg``."""
        return cls(p.kp, p.tau0_s, p.c2, p.g_mps2, p.thrust_min_n, p.thrust_max_n, p.missing_policy,
                   feedforward_mg=feedforward_mg, n_bin=p.n_bin, dt_s=p.dt_s)

    def init_state(self) -> HoldLastState:
        return hold_last_init(self.params)

    def step_state(self, state: HoldLastState, t_s, d_filtered: Tensor, mass_kg: Tensor,
                   active: Optional[Tensor] = None, altitude_m: Optional[Tensor] = None):
        """Pure step (:func:`div_p_step`); ``altitude_m`` is not used."""
        self._check(state)
        return div_p_step(self.params, state, t_s, d_filtered, mass_kg, active)

    def loop_gain_fields(self, m_kg: Tensor, z_m: Tensor) -> dict:
        """Kp / (m z) at the given (final) state, and the altitude where Kp / (m z) dt crosses the
        sampled loop's limit g_crit(n_bin) (no estimator lag counted)."""
        out = {"loop_gain": div_loop_gain(self.kp, m_kg, z_m.clamp_min(1e-9)), "loop_gain_kind": "div"}
        if self.n_bin is not None:
            out["gain_limit_altitude_m"] = gain_limit_altitude_m(self.kp, m_kg, self.dt_s, self.n_bin)
        return out
