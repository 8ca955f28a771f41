"""A thrust law that is a small network (controller ``policy``), trained through the closed loop
(``dvsland train-loop --what policy``) and flown by path like any other law.

Observation, float64 (B, 4), (B, 7) or (B, 10) per descent (``controller.policy.observation``):

- ``basic`` (4), from what every law is given: the filtered divergence D_f (NaN -> 0) and the
  paper's TTC target D*(t) = -1 / max(tau0 - c2 t, tau_min), both scaled by 1 / ``D_SCALE``; their
  difference D_f - D*, scaled by 1 / ``ERR_SCALE``; the hover thrust m g as a fraction of the
  engine's top (``thrust_max_n``, or 3 m0 g unbounded);
- ``efference`` (7): the four above, then the estimator's raw estimate D_hat of this step
  (NaN -> 0) scaled by 1 / ``D_SCALE``, its confidence in [0, 1] (0 where there is none), and
  the filter's altitude estimate as ln(max(z_hat, 1 m) / ``Z_REF_M``). It needs a filter that
  gives an altitude (``efference``, ``efference_fit``); the loop hands the law the estimate
  (:attr:`PolicyController.needs_estimate`);
- ``efference_doubt`` (10): the seven above, then how far the ``efference_fit`` filter has moved
  from its plan (``FilterOut.doubt``): the fitted offsets of the initial altitude and velocity in
  prior standard deviations, each clamped to +-``DOUBT_CLAMP``, and the share of the descent's
  estimates the fit rejected. A fit that has walked several prior sigmas from the dead-reckoned
  start is one that biased estimates have pulled; the other inputs cannot show that. It needs
  ``controller.filter=efference_fit`` (:attr:`PolicyController.needs_doubt`).

Action (``controller.policy.base``):

- ``none``: thrust = sigmoid(net(obs)) x the engine's top, clamped to the controller's bounds;
- ``div_gs``: a residual on ``div_gs`` (its constants from ``controller.div_gs``): thrust =
  u_div_gs + a m g tanh(net(obs)), clamped, with ``a`` = ``controller.policy.authority`` (the
  residual's reach in units of m g; 1 by default). The network's output layer starts at zero, so
  the untrained policy flies exactly ``div_gs``.

A missing filtered estimate holds the last command (or hovers), as the other laws do. A
checkpoint records its observation, base and authority; flying it under other settings is refused,
naming the key.

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

from dvsland.checks import check_choice, check_range
from dvsland.config.schema import DivGSConfig
from dvsland.estimators.state_dict_check import check_state_dict, read_checkpoint_file, short_path

from .base import (ControlOutput, Controller, HoldLastState, LawParams, check_bounds, clamp_thrust,
                   divergence_law_finish, hold_last_init, law_inputs, law_params)
from .div_gs import div_gs_step
from .registry import register_controller

Tensor = torch.Tensor

#: observation scales: divergence 1/s, tracking error 1/s, reference altitude m (of ln z_hat / Z_REF_M)
D_SCALE, ERR_SCALE, Z_REF_M = 0.05, 0.01, 100.0
#: ``kind`` of a policy checkpoint
POLICY_KIND = "dvsland-loop-policy"
#: the doubt's offsets (prior standard deviations) are clamped to +- this in the observation
DOUBT_CLAMP = 10.0
#: observation name -> its width
OBSERVATIONS = {"basic": 4, "efference": 7, "efference_doubt": 10}
#: laws a policy can be a residual on (``controller.policy.base``)
BASES = ("none", "div_gs")
#: the residual's largest reach, in units of m g (``controller.policy.authority``)
AUTHORITY_MAX = 3.0


def _check_kind(observation: str, base: str, authority: float = 1.0) -> None:
    """ValueError naming ``controller.policy.observation`` / ``.base`` / ``.authority`` when one is not
    allowed (an authority other than 1 needs ``base=div_gs``: only a residual has one)."""
    check_choice("controller.policy.observation", observation, OBSERVATIONS)
    check_choice("controller.policy.base", base, BASES)
    check_range("controller.policy.authority", authority, 0.0, AUTHORITY_MAX, open_lo=True)
    if base == "none" and authority != 1.0:
        raise ValueError(f"controller.policy.authority={authority!r} needs controller.policy.base=div_gs "
                         "(it scales the residual; base=none has none)")


class PolicyNet(nn.Module):
    """obs (B, n_obs) float64 -> (B,) float64: the thrust-fraction logit (``base="none"``; starts near
    hover, 1/3 of the top) or the residual's pre-tanh output (``base="div_gs"``; starts at exactly 0).

    Args:
        hidden: hidden tanh units.
        hover_fraction: the untrained thrust fraction of ``base="none"``.
        observation: a key of :data:`OBSERVATIONS` (the input width).
        base: one of :data:`BASES`.
        authority: the residual's reach in units of m g (``base="div_gs"``; 1 for ``none``).
    """

    def __init__(self, hidden: int = 32, hover_fraction: float = 1.0 / 3.0, observation: str = "basic",
                 base: str = "none", authority: float = 1.0):
        super().__init__()
        if not (isinstance(hidden, int) and hidden >= 1):
            raise ValueError(f"controller.policy.hidden must be an integer >= 1, got {hidden!r}")
        _check_kind(observation, base, authority)
        self.hidden, self.observation, self.base, self.authority = hidden, observation, base, float(authority)
        self.net = nn.Sequential(nn.Linear(OBSERVATIONS[observation], hidden), nn.Tanh(),
                                 nn.Linear(hidden, 1)).double()
        with torch.no_grad():
            if base == "none":
                self.net[2].weight.mul_(0.1)
                self.net[2].bias.fill_(math.log(hover_fraction / (1.0 - hover_fraction)))
            else:  # a residual starts as its base law, exactly
                self.net[2].weight.zero_()
                self.net[2].bias.zero_()

    def forward(self, obs: Tensor) -> Tensor:
        return self.net(obs).squeeze(-1)


class PolicyOptions(NamedTuple):
    """The ``policy`` law's own params: the network, the engine's top (B,) N, tau_min (s) and, for
    ``base="div_gs"``, the base law's params (:class:`LawParams` with :class:`DivGSConfig` options)."""

    net: PolicyNet
    thrust_high_n: Tensor
    tau_min_s: float
    base: Optional[LawParams] = None


def checkpoint_observation_base(ck: dict, where: str, observation: Optional[str] = None,
                                base: Optional[str] = None, authority: Optional[float] = None) -> dict:
    """``{"observation": ..., "base": ..., "authority": ...}`` of a policy checkpoint's dict ``ck``
    (``basic`` / ``none`` / 1.0 when it predates them), checked: ValueError naming ``where`` for an
    unknown value, and naming ``controller.policy.<key>`` when ``observation`` / ``base`` /
    ``authority`` (the flown config's; None = any) differ from the checkpoint's."""
    got = {"observation": ck.get("observation", "basic"), "base": ck.get("base", "none"),
           "authority": ck.get("authority", 1.0)}
    if not (isinstance(got["authority"], (int, float)) and 0.0 < got["authority"] <= AUTHORITY_MAX):
        raise ValueError(f"{where}: authority {got['authority']!r} is not in (0, {AUTHORITY_MAX}]")
    got["authority"] = float(got["authority"])
    for key, want, known in (("observation", observation, OBSERVATIONS), ("base", base, BASES),
                             ("authority", None if authority is None else float(authority), None)):
        if known is not None and got[key] not in known:
            raise ValueError(f"{where}: {key} {got[key]!r} is not one of {list(known)}")
        if want is not None and want != got[key]:
            raise ValueError(f"controller.policy.{key} is {want!r} but {where} was trained with {key} "
                             f"{got[key]!r}; set --set controller.policy.{key}={got[key]}")
    return got


def load_policy(path, param: str = "controller.policy.checkpoint", observation: Optional[str] = None,
                base: Optional[str] = None, authority: Optional[float] = None) -> PolicyNet:
    """The :class:`PolicyNet` of a ``dvsland train-loop --what policy`` checkpoint. A checkpoint
    without ``observation`` / ``base`` / ``authority`` (written before they existed) is ``basic`` /
    ``none`` / 1.

    Args:
        observation, base, authority: the flown config's ``controller.policy.observation`` /
            ``.base`` / ``.authority`` (None: take the checkpoint's).

    Raises:
        ValueError: naming ``param`` and the file: missing, unreadable, another kind of file, or
            weights that do not fit or are not finite; naming ``controller.policy.observation`` /
            ``.base`` / ``.authority`` when the checkpoint was trained with another one.
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
    got = checkpoint_observation_base(ck, where, observation, base, authority)
    net = PolicyNet(hidden, observation=got["observation"], base=got["base"], authority=got["authority"])
    check_state_dict(ck.get("state_dict"), net, where)
    net.load_state_dict(ck["state_dict"])
    return net


def policy_observation(p: LawParams, t_s, d: Tensor, m: Tensor, altitude_m: Optional[Tensor] = None,
                       estimate: Optional[Tuple[Tensor, Tensor]] = None,
                       doubt: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
    """The observation (see the module doc) and the target D*(t) (B,) float64 1/s.

    Args:
        p: the law's params (``p.options.net.observation`` picks the observation).
        t_s: (B,) float64 flight time, s.
        d: (B,) float64 filtered divergence, 1/s (NaN allowed).
        m: (B,) float64 mass, kg.
        altitude_m: (B,) the filter's altitude estimate z_hat, m (``efference`` only).
        estimate: (D_hat (B,) 1/s NaN = none, confidence (B,) in [0, 1]) of this step (``efference``,
            ``efference_doubt``).
        doubt: (B, 3) float64 the filter's ``FilterOut.doubt`` (``efference_doubt`` only).

    Returns:
        (obs (B, 4), (B, 7) or (B, 10) float64, D* (B,) float64 1/s).
    """
    o = p.options
    d_star = -1.0 / (p.tau0_s - p.c2 * t_s).clamp_min(o.tau_min_s)
    d0 = torch.nan_to_num(d, nan=0.0)
    hover = m * p.g_mps2 / o.thrust_high_n
    cols = [d0 / D_SCALE, d_star / D_SCALE, (d0 - d_star) / ERR_SCALE, hover]
    if o.net.observation in ("efference", "efference_doubt"):
        if altitude_m is None or estimate is None:
            raise ValueError(f"controller.policy.observation={o.net.observation} needs the filter's altitude and "
                             "the estimate (fly it in the loop with controller.filter=efference_fit"
                             + (")" if o.net.observation == "efference_doubt" else " or efference)"))
        d_hat, conf = estimate
        d_hat = d_hat.to(d.dtype)
        ok = torch.isfinite(d_hat)
        z = altitude_m.to(d.dtype).clamp_min(1.0)
        cols += [torch.where(ok, d_hat, 0.0) / D_SCALE,
                 torch.where(ok, torch.nan_to_num(conf.to(d.dtype), nan=0.0), 0.0).clamp(0.0, 1.0),
                 torch.log(z / Z_REF_M)]
    if o.net.observation == "efference_doubt":
        if doubt is None:
            raise ValueError("controller.policy.observation=efference_doubt needs the filter's doubt (fly it in the "
                             "loop with controller.filter=efference_fit)")
        doubt = doubt.to(d.dtype)
        cols += [doubt[:, 0].clamp(-DOUBT_CLAMP, DOUBT_CLAMP), doubt[:, 1].clamp(-DOUBT_CLAMP, DOUBT_CLAMP),
                 doubt[:, 2]]
    return torch.stack(cols, dim=1), d_star


def policy_law_step(p: LawParams, state: HoldLastState, t_s, d_filtered: Tensor, mass_kg: Tensor,
                    active: Optional[Tensor], altitude_m: Optional[Tensor] = None,
                    estimate: Optional[Tuple[Tensor, Tensor]] = None,
                    doubt: Optional[Tensor] = None,
                    velocity_sigma_mps: Optional[Tensor] = None) -> Tuple[HoldLastState, ControlOutput]:
    """Pure step of ``policy``: (next state, :class:`ControlOutput`); inputs as for every law
    (t_s (B,) s, d_filtered (B,) 1/s NaN = none, mass_kg (B,) kg, active (B,) bool or None,
    altitude_m (B,) m the filter's z_hat), and ``estimate`` = (D_hat (B,) 1/s, confidence (B,))
    for the ``efference`` observations, the filter's ``doubt`` (B, 3) for ``efference_doubt``, and its
    velocity standard deviation (B,) m/s for a ``div_gs`` base with ``v_min_sigma`` > 0. The
    command keeps its autograd graph to the network's weights and the inputs."""
    d, m, mg, t_s = law_inputs(p, t_s, d_filtered, mass_kg)
    if not isinstance(t_s, Tensor):
        t_s = torch.full_like(d, float(t_s))
    o = p.options
    obs, d_star = policy_observation(p, t_s, d, m, altitude_m, estimate, doubt)
    out = o.net(obs)
    if o.base is None:
        u = clamp_thrust(p, torch.sigmoid(out) * o.thrust_high_n)
        return divergence_law_finish(p, state, d, u, mg, active, -1.0 / d_star)
    # residual on div_gs: its command where it has one, plus authority x m g tanh(net)
    _, base = div_gs_step(o.base, state, t_s, d_filtered, mass_kg, active, altitude_m, velocity_sigma_mps)
    r = torch.tanh(out)  # x 1.0 is exact: authority 1 gives the bits of m g tanh(net)
    state, ctl = divergence_law_finish(p, state, d, clamp_thrust(p, base.thrust_n + o.net.authority * mg * r), mg,
                                       active, base.tau_target_s)
    return state, ctl._replace(residual=r)


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
        observation: ``basic``, ``efference`` or ``efference_doubt`` (see the module doc).
        base: ``none`` or ``div_gs`` (a residual on div_gs).
        authority: the residual's reach in units of m g (``base="div_gs"`` only).
        base_options: the base law's constants (``controller.div_gs`` as a dict; None = its defaults).
    """

    def __init__(self, tau0_s: Tensor, c2: float, g_mps2: float, m0_kg: Tensor, thrust_min_n: float = 0.0,
                 thrust_max_n: Optional[float] = None, missing_policy: str = "hold", net: Optional[PolicyNet] = None,
                 checkpoint: str = "", hidden: int = 32, tau_min_s: float = 4.0, observation: str = "basic",
                 base: str = "none", base_options: Optional[dict] = None, authority: float = 1.0):
        check_bounds(thrust_min_n, thrust_max_n, missing_policy)
        if not (isinstance(tau_min_s, (int, float)) and tau_min_s > 0):
            raise ValueError(f"controller.policy.tau_min_s must be > 0 s, got {tau_min_s!r}")
        _check_kind(observation, base, authority)
        if net is None:  # frozen in flight: a loop that flies it keeps no graph (training unfreezes it)
            if str(checkpoint).strip():
                net = load_policy(checkpoint, observation=observation, base=base, authority=authority)
            else:
                net = PolicyNet(int(hidden), observation=observation, base=base, authority=authority)
            net.requires_grad_(False)
        elif (net.observation, net.base, net.authority) != (observation, base, float(authority)):
            raise ValueError(f"controller.policy.observation/base/authority {observation!r}/{base!r}/{authority!r} do "
                             f"not match the network's {net.observation!r}/{net.base!r}/{net.authority!r}")
        tau0 = torch.as_tensor(tau0_s, dtype=torch.float64)
        m0 = torch.as_tensor(m0_kg, dtype=torch.float64, device=tau0.device).expand_as(tau0)
        high = torch.full_like(tau0, float(thrust_max_n)) if thrust_max_n is not None else 3.0 * m0 * g_mps2
        net = net.to(tau0.device)
        base_p = None
        if base == "div_gs":
            if not 0 < c2 < 1:
                raise ValueError(f"c2 must be in (0, 1), got {c2}")
            gs = DivGSConfig(**(base_options or {}))
            base_p = law_params(None, tau0, c2, g_mps2, thrust_min_n, thrust_max_n, missing_policy, gs)
        self.params = law_params(None, tau0, c2, g_mps2, thrust_min_n, thrust_max_n, missing_policy,
                                 PolicyOptions(net, high, float(tau_min_s), base_p))
        self.checkpoint = str(checkpoint)
        #: the loop gives the law the filter's altitude / this step's (D_hat, confidence) / the
        #: filter's doubt (``FilterOut.doubt``) when True
        self.needs_altitude = observation != "basic" or base != "none"
        self.needs_estimate = observation != "basic"
        self.needs_doubt = observation == "efference_doubt"
        #: ... and its velocity standard deviation (a div_gs base whose floor grows with it)
        self.needs_velocity_sigma = base != "none" and base_p.options.v_min_sigma > 0
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
                   active: Optional[Tensor] = None, altitude_m: Optional[Tensor] = None,
                   estimate: Optional[Tuple[Tensor, Tensor]] = None, doubt: Optional[Tensor] = None,
                   velocity_sigma_mps: Optional[Tensor] = None):
        """Pure step (:func:`policy_law_step`)."""
        self._check(state)
        return policy_law_step(self.params, state, t_s, d_filtered, mass_kg, active, altitude_m, estimate, doubt,
                               velocity_sigma_mps)


__all__ = ["PolicyNet", "PolicyOptions", "PolicyController", "policy_law_step", "policy_observation", "load_policy",
           "checkpoint_observation_base", "POLICY_KIND", "D_SCALE", "ERR_SCALE", "Z_REF_M", "DOUBT_CLAMP", "OBSERVATIONS",
           "BASES", "AUTHORITY_MAX"]
