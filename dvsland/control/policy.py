"""A thrust law that is a small network (controller ``policy``), trained through the closed loop
(``dvsland train-loop --what policy``) and flown by path like any other law.

Observation (B, 4) float64 of each descent, from what every law is given:

- the filtered divergence D_f (NaN -> 0) and the paper's TTC target D*(t) = -1 / max(tau0 - c2 t,
  tau_min), both scaled by 1 / ``D_SCALE``;
- their difference D_f - D*, scaled by 1 / ``ERR_SCALE``;
- the hover thrust m g as a fraction of the engine's top (``thrust_max_n``, or 3 m0 g unbounded).

Action: thrust = sigmoid(net(obs)) x the engine's top, clamped to the controller's bounds. A
missing filtered estimate holds the last command (or hovers), as the other laws do.

Params :class:`~dvsland.control.base.LawParams` whose ``options`` is a :class:`PolicyOptions`
(the network and the observation's constants), state
:class:`~dvsland.control.base.HoldLastState`, pure step :func:`policy_law_step`. The network is
the law's frozen params in flight; training replaces its weights between flights.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional, Tuple

import torch
from torch import nn

from dvsland.estimators.state_dict_check import check_state_dict, read_checkpoint_file, short_path

from .base import (ControlOutput, Controller, HoldLastState, LawParams, check_bounds, clamp_thrust,
                   divergence_law_finish, hold_last_init, law_inputs, law_params)
from .registry import register_controller

Tensor = torch.Tensor

#: observation scales: divergence 1/s, tracking error 1/s
D_SCALE, ERR_SCALE = 0.05, 0.01
#: ``kind`` of a policy checkpoint
POLICY_KIND = "dvsland-loop-policy"


class PolicyNet(nn.Module):
    """obs (B, 4) float64 -> thrust-fraction logit (B,); initialised near hover (1/3 of the top)."""

    def __init__(self, hidden: int = 32, hover_fraction: float = 1.0 / 3.0):
        super().__init__()
        if not (isinstance(hidden, int) and hidden >= 1):
            raise ValueError(f"controller.policy.hidden must be an integer >= 1, got {hidden!r}")
        self.hidden = hidden
        self.net = nn.Sequential(nn.Linear(4, hidden), nn.Tanh(), nn.Linear(hidden, 1)).double()
        with torch.no_grad():
            self.net[2].weight.mul_(0.1)
            self.net[2].bias.fill_(math.log(hover_fraction / (1.0 - hover_fraction)))

    def forward(self, obs: Tensor) -> Tensor:
        return self.net(obs).squeeze(-1)


class PolicyOptions(NamedTuple):
    """The ``policy`` law's own params: the network, the engine's top (B,) N and tau_min (s)."""

    net: PolicyNet
    thrust_high_n: Tensor
    tau_min_s: float


def load_policy(path, param: str = "controller.policy.checkpoint") -> PolicyNet:
    """The :class:`PolicyNet` of a ``dvsland train-loop --what policy`` checkpoint.

    Raises:
        ValueError: naming ``param`` and the file: missing, unreadable, another kind of file, or
            weights that do not fit or are not finite.
    """
    hint = "write one with dvsland train-loop CONFIG --what policy"
    ck = read_checkpoint_file(path, param, "dvsland policy checkpoint", hint)
    where = f"{param} {short_path(path)}"
    if ck.get("kind") != POLICY_KIND:
        raise ValueError(f"{where}: not a policy checkpoint (kind {ck.get('kind')!r}, expected {POLICY_KIND!r}; "
                         f"{hint})")
    hidden = ck.get("hidden")
    if not (isinstance(hidden, int) and 1 <= hidden <= 4096):
        raise ValueError(f"{where}: 'hidden' must be an integer in [1, 4096], got {hidden!r}")
    net = PolicyNet(hidden)
    check_state_dict(ck.get("state_dict"), net, where)
    net.load_state_dict(ck["state_dict"])
    return net


def policy_observation(p: LawParams, t_s, d: Tensor, m: Tensor) -> Tensor:
    """The observation (B, 4) float64 (see the module doc) of filtered divergence ``d`` (B,) 1/s
    (NaN allowed) and mass ``m`` (B,) kg at flight time ``t_s`` (B,) s."""
    o = p.options
    d_star = -1.0 / (p.tau0_s - p.c2 * t_s).clamp_min(o.tau_min_s)
    d0 = torch.nan_to_num(d, nan=0.0)
    hover = m * p.g_mps2 / o.thrust_high_n
    return torch.stack((d0 / D_SCALE, d_star / D_SCALE, (d0 - d_star) / ERR_SCALE, hover), dim=1), d_star


def policy_law_step(p: LawParams, state: HoldLastState, t_s, d_filtered: Tensor, mass_kg: Tensor,
                    active: Optional[Tensor], altitude_m: Optional[Tensor] = None
                    ) -> Tuple[HoldLastState, ControlOutput]:
    """Pure step of ``policy``: (next state, :class:`ControlOutput`); inputs as for every law
    (t_s (B,) s, d_filtered (B,) 1/s NaN = none, mass_kg (B,) kg, active (B,) bool or None).
    The command keeps its autograd graph to the network's weights and the inputs."""
    d, m, mg, t_s = law_inputs(p, t_s, d_filtered, mass_kg)
    if not isinstance(t_s, Tensor):
        t_s = torch.full_like(d, float(t_s))
    obs, d_star = policy_observation(p, t_s, d, m)
    u = clamp_thrust(p, torch.sigmoid(p.options.net(obs)) * p.options.thrust_high_n)
    return divergence_law_finish(p, state, d, u, mg, active, -1.0 / d_star)


@register_controller("policy")
class PolicyController(Controller):
    """A network's thrust (see the module doc).

    Args:
        tau0_s: (B,) float64 initial TTC z0/|v0|, s.
        c2: slope of the observed TTC target.
        g_mps2: gravity, m/s^2.
        m0_kg: (B,) initial masses, kg (the engine's top is 3 m0 g when ``thrust_max_n`` is None).
        thrust_min_n, thrust_max_n, missing_policy: as for ``tau_p``.
        net: the :class:`PolicyNet` (None: ``checkpoint``'s, or an untrained one of ``hidden`` units).
        checkpoint: a policy checkpoint's path ('' = none).
        hidden: hidden units of an untrained network.
        tau_min_s: lowest TTC of the observed target, s.
    """

    def __init__(self, tau0_s: Tensor, c2: float, g_mps2: float, m0_kg: Tensor, thrust_min_n: float = 0.0,
                 thrust_max_n: Optional[float] = None, missing_policy: str = "hold", net: Optional[PolicyNet] = None,
                 checkpoint: str = "", hidden: int = 32, tau_min_s: float = 4.0):
        check_bounds(thrust_min_n, thrust_max_n, missing_policy)
        if not (isinstance(tau_min_s, (int, float)) and tau_min_s > 0):
            raise ValueError(f"controller.policy.tau_min_s must be > 0 s, got {tau_min_s!r}")
        if net is None:  # frozen in flight: a loop that flies it keeps no graph (training unfreezes it)
            net = load_policy(checkpoint) if str(checkpoint).strip() else PolicyNet(int(hidden))
            net.requires_grad_(False)
        tau0 = torch.as_tensor(tau0_s, dtype=torch.float64)
        m0 = torch.as_tensor(m0_kg, dtype=torch.float64, device=tau0.device).expand_as(tau0)
        high = torch.full_like(tau0, float(thrust_max_n)) if thrust_max_n is not None else 3.0 * m0 * g_mps2
        net = net.to(tau0.device)
        self.params = law_params(None, tau0, c2, g_mps2, thrust_min_n, thrust_max_n, missing_policy,
                                 PolicyOptions(net, high, float(tau_min_s)))
        self.checkpoint = str(checkpoint)
        self._template = self.init_state()
        self.state = self.init_state()

    @classmethod
    def from_params(cls, p, **options) -> "PolicyController":
        """From the loop's :class:`~dvsland.control.DescentParams` and the ``controller.policy`` options."""
        return cls(p.tau0_s, p.c2, p.g_mps2, p.m0_kg, p.thrust_min_n, p.thrust_max_n, p.missing_policy, **options)

    @property
    def net(self) -> PolicyNet:
        """The network (its weights are what ``dvsland train-loop --what policy`` trains)."""
        return self.params.options.net

    def init_state(self) -> HoldLastState:
        return hold_last_init(self.params)

    def step_state(self, state: HoldLastState, t_s, d_filtered: Tensor, mass_kg: Tensor,
                   active: Optional[Tensor] = None, altitude_m: Optional[Tensor] = None):
        """Pure step (:func:`policy_law_step`)."""
        self._check(state)
        return policy_law_step(self.params, state, t_s, d_filtered, mass_kg, active, altitude_m)


__all__ = ["PolicyNet", "PolicyOptions", "PolicyController", "policy_law_step", "policy_observation", "load_policy",
           "POLICY_KIND", "D_SCALE", "ERR_SCALE"]
