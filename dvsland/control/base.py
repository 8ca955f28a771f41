"""The controller interface under the stage contract, its output record and the 'hold last' memory.

A built-in law is three things (:mod:`dvsland.pytree`): frozen :class:`LawParams` (the loop's
per-descent gains and targets, the controller section's bounds and the law's own config section),
a state (:class:`HoldLastState`: the last command of each descent) and a pure module-level step.
The :class:`Controller` base class turns ``init_state`` / ``step_state`` / ``reset_where`` into
the object API (``__call__``, ``reset``) that holds one state in ``self.state``.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional, Tuple

import torch

from dvsland.pytree import check_state_like, tree_leaves, tree_where

Tensor = torch.Tensor


class ControlOutput(NamedTuple):
    """One control step's result, all (B,).

    Attributes:
        thrust_n: float64 commanded thrust, N (finite, clamped).
        tau_hat_s: float64 TTC used, s (NaN where the estimate was not used).
        tau_target_s: float64 tau*(t), s.
        held: bool, True where the estimate was missing / wrong-signed and the policy acted.
        residual: float64 a residual law's correction as a share of its reach, in [-1, 1] (the
            ``policy`` law on ``div_gs``: tanh(net)); None for every other law.
    """

    thrust_n: Tensor
    tau_hat_s: Tensor
    tau_target_s: Tensor
    held: Tensor
    residual: Optional[Tensor] = None


class LawParams(NamedTuple):
    """What a built-in law flies with; frozen in flight.

    Attributes:
        kp: (B,) float64 gain of each descent's setting (the law's units), or None (``div_gs``).
        tau0_s: (B,) float64 initial time to contact of the target, s.
        c2: slope of the TTC target tau*(t) = tau0 - c2 t.
        g_mps2: gravity, m/s^2.
        thrust_min_n: lower thrust bound, N (>= 0).
        thrust_max_n: upper thrust bound, N, or None (unbounded).
        missing_policy: ``"hold"`` or ``"hover"``.
        options: the law's own config section (:class:`dvsland.config.schema.DivPConfig`,
            :class:`~dvsland.config.schema.DivGSConfig`) or None.
    """

    kp: Optional[Tensor]
    tau0_s: Tensor
    c2: float
    g_mps2: float
    thrust_min_n: float
    thrust_max_n: Optional[float]
    missing_policy: str
    options: Any = None


class HoldLastState(NamedTuple):
    """State of a built-in law for B descents.

    Attributes:
        last_thrust_n: (B,) float64 the last command, N; NaN = none yet (hover m g is used).
    """

    last_thrust_n: Tensor


def _defines(cls: type, name: str, stop: type) -> bool:
    """True when a class of ``cls``'s MRO below ``stop`` defines ``name``."""
    for k in cls.__mro__:
        if k is stop:
            return False
        if name in k.__dict__:
            return True
    return False


def mark_object_api_only(cls: type, base: type, call_name: str) -> None:
    """A subclass of ``base`` that implements the object API (``call_name``) but not the contract
    gets ``init_state`` / ``step_state`` / ``reset_where`` = None, so
    :func:`dvsland.pytree.has_stage_contract` says False and the loop runs it as an object stage."""
    if _defines(cls, call_name, base) and not _defines(cls, "step_state", base):
        cls.init_state = cls.step_state = cls.reset_where = None


def batch_of(state) -> Tuple[int, torch.device]:
    """(B, device) of a state: the first dim and device of its first tensor leaf."""
    leaf = next(iter(tree_leaves(state).values()))
    return int(leaf.shape[0]), leaf.device


def as_mask(mask, batch_size: int, device, stage: str) -> Tensor:
    """``mask`` as a (B,) bool tensor on ``device`` (None = every descent); ValueError naming ``stage``."""
    if mask is None:
        return torch.ones(batch_size, dtype=torch.bool, device=device)
    mask = torch.as_tensor(mask, device=device)
    if mask.shape != (batch_size,) or mask.dtype != torch.bool:
        raise ValueError(f"{stage}: mask must be a (B,) = ({batch_size},) bool tensor, "
                         f"got shape {tuple(mask.shape)} dtype {mask.dtype}")
    return mask


class Controller:
    """Base class of batched thrust laws.

    The stage contract: a built-in law holds only settings (``self.params``) and implements
    ``init_state() -> State``, the pure ``step_state(state, t_s, d_filtered, mass_kg, active,
    altitude_m=None) -> (State, ControlOutput)`` and (optionally; the default restarts the masked
    descents from ``init_state()``) ``reset_where(state, mask) -> State``. The object API
    ``__call__(t_s, d_filtered, mass_kg, active=None, altitude_m=None) -> ControlOutput`` and
    ``reset(mask=None)`` is provided here on top of them, holding one state in ``self.state``.

    Inputs of a step: the flight time ``t_s`` ((B,) float64 per descent, s; a float is taken for
    all), the filtered divergence (B,) (1/s, NaN = none), the current mass (B,) kg, the active mask
    (B,) bool (None = all; inactive descents keep their last command). A law that sets the class
    attribute ``needs_altitude = True`` is also given ``altitude_m=`` (B,) float64, the filter's
    altitude estimate in m (see :mod:`dvsland.control.efference`).

    A third-party law may implement the object API alone (``__call__`` and ``reset``);
    it then has no contract methods (they are None) and the loop runs it as an object stage.
    Subclass a built-in law by overriding ``step_state``, not ``__call__``.

    Optional: ``loop_gain_fields(m_kg, z_m)`` returning per-descent loop-gain figures for the
    summary (see :mod:`dvsland.control.gain`); laws without it report no loop gain.
    """

    needs_altitude: bool = False

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        mark_object_api_only(cls, Controller, "__call__")

    # ------------------------------------------------------------------ the contract
    def init_state(self):
        """The state of B descents before their first command."""
        raise NotImplementedError(f"{type(self).__name__} implements neither the contract nor __call__")

    def step_state(self, state, t_s, d_filtered: Tensor, mass_kg: Tensor, active: Optional[Tensor] = None,
                   altitude_m: Optional[Tensor] = None) -> Tuple[Any, ControlOutput]:
        """Pure step: (next state, :class:`ControlOutput`); ``state`` is left unchanged."""
        raise NotImplementedError(f"{type(self).__name__} implements neither the contract nor __call__")

    def reset_where(self, state, mask: Tensor):
        """``state`` with the descents where ``mask`` (B,) bool is True restarted, the others bit-identical."""
        fresh = self.init_state()
        return tree_where(as_mask(mask, *batch_of(fresh), f"controller {type(self).__name__}"), fresh, state)

    # ------------------------------------------------------------------ the object API over it
    def _check(self, state) -> None:
        """ValueError naming the law and the field when ``state`` is not one of this law's states."""
        check_state_like(f"controller {type(self).__name__}", state, self._template)

    def reset(self, mask: Optional[Tensor] = None) -> None:
        """Restart the descents where ``mask`` (B,) bool is True (all when None): no command yet."""
        if mask is None or getattr(self, "state", None) is None:
            self.state = self.init_state()
        if mask is not None:
            self.state = self.reset_where(self.state, mask)

    def __call__(self, t_s, d_filtered: Tensor, mass_kg: Tensor, active: Optional[Tensor] = None,
                 altitude_m: Optional[Tensor] = None, **inputs) -> ControlOutput:
        """One command for each descent (see the class doc); the state advances in ``self.state``.
        ``inputs``: what a law reads besides (e.g. ``velocity_sigma_mps`` for ``div_gs`` with
        ``v_min_sigma`` > 0), passed to its ``step_state``."""
        if getattr(self, "state", None) is None:
            self.state = self.init_state()
        self.state, out = self.step_state(self.state, t_s, d_filtered, mass_kg, active, altitude_m=altitude_m, **inputs)
        return out

    def __getattr__(self, name: str):
        """Read access to the settings: the fields of ``self.params`` and of its ``options`` section."""
        d = self.__dict__
        if not name.startswith("__") and "params" in d:
            p = d["params"]
            if name in getattr(p, "_fields", ()):
                return getattr(p, name)
            options = getattr(p, "options", None)
            if name in getattr(type(options), "__dataclass_fields__", {}):
                return getattr(options, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")


# ------------------------------------------------------------------ the 'hold last' memory
def hold_last_init(p: LawParams) -> HoldLastState:
    """No command yet for any of the B descents of ``p``."""
    return HoldLastState(torch.full(p.tau0_s.shape, float("nan"), dtype=torch.float64, device=p.tau0_s.device))


def clamp_thrust(p: LawParams, u: Tensor) -> Tensor:
    """``u`` clamped to [thrust_min_n, thrust_max_n] (-inf -> thrust_min_n; NaN stays NaN)."""
    u = u.clamp_min(p.thrust_min_n)  # also maps -inf to thrust_min
    if p.thrust_max_n is not None:
        u = u.clamp_max(p.thrust_max_n)
    return u


def hold_last_finish(p: LawParams, state: HoldLastState, usable: Tensor, u: Tensor, mg: Tensor,
                     active: Optional[Tensor]) -> Tuple[HoldLastState, Tensor]:
    """(next state, thrust (B,) float64 N): ``u`` where ``usable``, else the missing policy (the last
    command, or hover ``mg`` clamped); the last command where not ``active``. A descent with no
    command yet counts hover (clamped) as its last one."""
    hover = clamp_thrust(p, mg)
    last = state.last_thrust_n
    last = torch.where(torch.isnan(last), hover, last)
    fallback = last if p.missing_policy == "hold" else hover
    thrust = torch.where(usable, u, fallback)
    if active is not None:
        thrust = torch.where(active, thrust, last)
    return HoldLastState(thrust), thrust


def divergence_law_finish(p: LawParams, state: HoldLastState, d: Tensor, u: Tensor, mg: Tensor,
                          active: Optional[Tensor], tau_target_s: Tensor) -> Tuple[HoldLastState, ControlOutput]:
    """The end of a law on the filtered divergence ``d`` (B,) 1/s: the command ``u`` (B,) N where ``d``
    is known, the missing policy where it is NaN (:func:`hold_last_finish`), and the
    :class:`ControlOutput` with tau_hat = -1/d (NaN unless d < 0) and the target ``tau_target_s`` (B,) s."""
    usable = ~torch.isnan(d)
    state, thrust = hold_last_finish(p, state, usable, u, mg, active)
    tau_hat = torch.where(d < 0, -1.0 / d, float("nan"))
    return state, ControlOutput(thrust_n=thrust, tau_hat_s=tau_hat, tau_target_s=tau_target_s, held=~usable)


def law_inputs(p: LawParams, t_s, d_filtered: Tensor, mass_kg: Tensor):
    """(d (B,) float64, m (B,) float64, m g (B,) float64, t_s as float or float64 tensor)."""
    if isinstance(t_s, Tensor):
        t_s = t_s.to(device=p.tau0_s.device, dtype=torch.float64)
    m = mass_kg.to(torch.float64)
    return d_filtered.to(torch.float64), m, m * p.g_mps2, t_s


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


def law_params(kp, tau0_s, c2: float, g_mps2: float, thrust_min_n: float, thrust_max_n: Optional[float],
               missing_policy: str, options: Any = None) -> LawParams:
    """:class:`LawParams` from a law constructor's arguments (bounds as floats)."""
    return LawParams(kp, tau0_s, float(c2), float(g_mps2), float(thrust_min_n),
                     None if thrust_max_n is None else float(thrust_max_n), missing_policy, options)
