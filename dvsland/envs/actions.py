"""The action of a :class:`~dvsland.envs.LandingVectorEnv`: what an agent commands, and the thrust
in N that flies.

Three action modes (``action=``), each one float per element:

- ``"thrust"`` (default): a normalised command a in [-1, 1], mapped linearly onto the engine's
  range [thrust_low, thrust_high]: u = thrust_low + (a + 1) / 2 (thrust_high - thrust_low).
  thrust_low = ``controller.thrust_min_n``; thrust_high = ``controller.thrust_max_n`` or, where the
  law has no upper bound (the paper presets: ``thrust_max_n: null``), :data:`UNBOUNDED_HIGH_HOVERS`
  = 3 hover thrusts of the initial mass, 3 m0 g (48.7 kN for the paper's 10 t lander on the Moon).
- ``"thrust_n"``: the thrust itself in N, in [``thrust_min_n``, ``thrust_max_n``] (no upper bound
  where the law has none): the raw mode, e.g. to replay the shipped controller's commands
  (``info["controller_thrust_n"]``).
- ``"divergence_setpoint"``: a divergence set-point D_set in [-c, c] 1/s (c =
  ``simulation.crash_divergence``) fed to a proportional divergence law with hover feed-forward,
  the structure of the ``div_p`` law: u = m g + K (D_set - D_f), clamped to [thrust_low,
  thrust_high], where D_f is the loop filter's output at this step (the ``d_filtered`` of the
  observation) and K = ``setpoint_gain_ns`` (default 4e6 N s, the gain of the paper's second
  setting). Where the filter has no output yet (NaN), u = m g (hover).

A NaN or infinite action always raises ValueError. An action outside its range raises ValueError
naming ``action`` and the range, unless the env was built with ``clip_actions=True`` (then it is
clipped into the range).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np
import torch
from gymnasium import spaces

#: the action modes
ACTIONS = ("thrust", "thrust_n", "divergence_setpoint")
#: upper bound of the normalised thrust where the law has none: this many hover thrusts m0 g
UNBOUNDED_HIGH_HOVERS = 3.0
#: default gain K of the divergence set-point law, N s
SETPOINT_GAIN_NS = 4.0e6


class ActionSpec(NamedTuple):
    """How actions of one mode map to thrust.

    Attributes:
        mode: one of :data:`ACTIONS`.
        low, high: the action's range (the agent's units; ``high`` may be inf for ``thrust_n``).
        thrust_low_n, thrust_high_n: the engine range the normalised modes map onto, N (finite).
        gain_ns: K of the set-point law, N s.
        clip: clip out-of-range actions instead of raising.
    """

    mode: str
    low: float
    high: float
    thrust_low_n: float
    thrust_high_n: float
    gain_ns: float
    clip: bool

    def space(self) -> spaces.Box:
        """The single-element action space: Box (1,) float32."""
        return spaces.Box(np.float32(self.low), np.float32(self.high), (1,), np.float32)


def action_spec(mode: str, cfg, clip: bool = False, setpoint_gain_ns: float = SETPOINT_GAIN_NS) -> ActionSpec:
    """The :class:`ActionSpec` of ``mode`` for config ``cfg`` (``controller.thrust_min_n`` /
    ``thrust_max_n``, ``dynamics.mass_kg`` and ``g_mps2``, ``simulation.crash_divergence``).

    Raises:
        ValueError: an unknown mode (naming ``action`` and the allowed names), or a gain <= 0.
    """
    if mode not in ACTIONS:
        raise ValueError(f"action must be one of {list(ACTIONS)}, got {mode!r}")
    if not (math.isfinite(setpoint_gain_ns) and setpoint_gain_ns > 0):
        raise ValueError(f"setpoint_gain_ns must be finite and > 0, got {setpoint_gain_ns}")
    lo = float(cfg.controller.thrust_min_n)
    tmax = cfg.controller.thrust_max_n
    hi = float(tmax) if tmax is not None else UNBOUNDED_HIGH_HOVERS * cfg.dynamics.mass_kg * cfg.dynamics.g_mps2
    if mode == "thrust":
        a_lo, a_hi = -1.0, 1.0
    elif mode == "thrust_n":
        a_lo, a_hi = lo, (float(tmax) if tmax is not None else math.inf)
    else:
        c = float(cfg.simulation.crash_divergence)
        a_lo, a_hi = -c, c
    return ActionSpec(mode, a_lo, a_hi, lo, hi, float(setpoint_gain_ns), bool(clip))


def check_action(spec: ActionSpec, action, batch_size: int) -> torch.Tensor:
    """The actions as a (B,) float64 tensor, checked (and clipped where ``spec.clip``).

    Args:
        action: (B,), (B, 1) or, for B = 1, a scalar, in the agent's units.

    Raises:
        ValueError: wrong shape, NaN/inf, or out of range without ``clip`` (names ``action``).
    """
    if isinstance(action, torch.Tensor):  # a torch agent's actions stay on their device
        if action.dtype == torch.bool or action.is_complex():
            raise ValueError(f"action must be real numbers (int or float), got dtype {action.dtype}")
        a = action.detach().to(torch.float64)
    else:
        raw = np.asarray(action)
        if raw.dtype.kind not in "iuf":  # a string, complex, bool or object action is refused, not coerced
            raise ValueError(f"action must be real numbers (int or float), got dtype {raw.dtype} ({action!r:.80})")
        a = torch.as_tensor(raw.astype(np.float64))
    if a.numel() != batch_size or a.dim() > 2 or (a.dim() == 2 and a.shape[1] != 1):
        raise ValueError(f"action must have shape ({batch_size},) or ({batch_size}, 1), got {tuple(a.shape)}")
    a = a.reshape(batch_size)
    if not bool(torch.isfinite(a).all()):
        raise ValueError(f"action must be finite (no NaN or inf), got {a.tolist()}")
    # the space is float32: accept what rounds into it
    tol = 1e-6 * max(1.0, abs(spec.low), abs(spec.high) if math.isfinite(spec.high) else 1.0)
    if spec.clip:
        return a.clamp(spec.low, spec.high)
    if bool(((a < spec.low - tol) | (a > spec.high + tol)).any()):
        raise ValueError(f"action ({spec.mode!r}) must be in [{spec.low:g}, {spec.high:g}], got {a.tolist()}")
    return a.clamp(spec.low, spec.high)


def to_thrust(spec: ActionSpec, a: torch.Tensor, mass_kg: torch.Tensor, g_mps2: float,
              d_filtered: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Thrust in N (B,) float64 from checked actions ``a`` (B,) float64.

    Args:
        mass_kg: (B,) float64 current mass, kg (for the set-point law's hover term).
        d_filtered: (B,) float64 loop filter output, 1/s (the set-point law only; NaN = hover).
    """
    if spec.mode == "thrust":
        return spec.thrust_low_n + (a + 1.0) * 0.5 * (spec.thrust_high_n - spec.thrust_low_n)
    if spec.mode == "thrust_n":
        return a.clone()
    a = a.to(mass_kg.device)
    mg = mass_kg * g_mps2
    u = mg + spec.gain_ns * (a - d_filtered)
    u = torch.where(torch.isnan(u), mg, u)
    return u.clamp(spec.thrust_low_n, spec.thrust_high_n)


def hover_fraction(spec: ActionSpec, mass_kg: torch.Tensor, g_mps2: float) -> torch.Tensor:
    """(B,) float64 m g / thrust_high: the hover thrust as a fraction of the normalised range's top."""
    return mass_kg * g_mps2 / spec.thrust_high_n
