"""The estimator extension point: anything that turns events into divergence D = v/z.

A :class:`DivergenceEstimator` holds the state of B independent descents. The simulator calls
``reset(mask)`` when descents (re)start and ``update(events, t_us, truth)`` once per control
step with the events of the last frame interval; it returns D_hat (B,) in 1/s with the
paper's sign (negative while descending) and NaN where it has no estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Dict, NamedTuple, Optional, Sequence, Tuple

import torch

from .abstain import DEFAULT_ABSTAIN, EVIDENCE_KEY, AbstainParams, gate_output, motion_evidence
from .calibrate import (STRUCTURE_KEY, CalibrationParams, calibrate_confidence, calibrate_output, feature_values,
                        params_to, window_event_counts)


@dataclass
class Truth:
    """Ground truth handed to estimators that need it (oracle, training); others ignore it.

    Attributes:
        altitude_m: (B,) float64, altitude above the landing point, m.
        velocity_mps: (B,) float64, vertical velocity, m/s (negative = descending).
    """

    altitude_m: torch.Tensor
    velocity_mps: torch.Tensor

    @property
    def divergence(self) -> torch.Tensor:
        """True D = v / z, (B,) float64, 1/s."""
        return self.velocity_mps / self.altitude_m


class EstimateOut(NamedTuple):
    """What an estimator's pure step returns besides its next state.

    Attributes:
        d_hat: (B,) float32 D_hat, 1/s (negative while descending), NaN = no estimate.
        confidence: (B,) float32 in [0, 1], 0 where there is no estimate.
        diagnostics: what the estimator tracks at this step, for logging (tensors, e.g.
            ``centroids`` (B, N, 2)); every built-in includes ``confidence``.
    """

    d_hat: torch.Tensor
    confidence: torch.Tensor
    diagnostics: Dict[str, torch.Tensor]


def resolve_principal_point(principal_point_px: Optional[Sequence[float]],
                            sensor_size: Tuple[int, int]) -> Tuple[float, float]:
    """(cx, cy) floats, px: ``principal_point_px`` checked to lie on the sensor, or the sensor
    centre ((W - 1) / 2, (H - 1) / 2) when None. sensor_size is (W, H)."""
    W, H = int(sensor_size[0]), int(sensor_size[1])
    if principal_point_px is None:
        return ((W - 1) / 2.0, (H - 1) / 2.0)
    try:
        cx, cy = (float(v) for v in principal_point_px)
    except (TypeError, ValueError):
        raise ValueError(f"principal_point_px must be [cx, cy] (two numbers, px) or None, "
                         f"got {principal_point_px!r}") from None
    if not (math.isfinite(cx) and math.isfinite(cy) and 0.0 <= cx <= W - 1 and 0.0 <= cy <= H - 1):
        raise ValueError(f"principal_point_px must lie on the sensor, cx in [0, {W - 1}] and cy in "
                         f"[0, {H - 1}] px, got [{cx}, {cy}]")
    return (cx, cy)


def confidence_from_rel_std(rel_std: torch.Tensor, d_hat: torch.Tensor) -> torch.Tensor:
    """1 / (1 + (rel_std / 0.1)^2) as float32 in [0, 1]; 0 where d_hat or rel_std is not finite."""
    c = 1.0 / (1.0 + (rel_std.to(torch.float32) / 0.1) ** 2)
    ok = torch.isfinite(d_hat) & torch.isfinite(c)
    return torch.where(ok, c, torch.zeros_like(c)).clamp(0.0, 1.0)


def confidence_rel_sigma(confidence: torch.Tensor) -> torch.Tensor:
    """Relative standard error sigma_rel = 0.1 sqrt(1/c - 1) of an estimate with confidence c,
    the inverse of the estimators' c = 1 / (1 + (sigma_rel / 0.1)^2).

    Args:
        confidence: (B,) float in [0, 1].

    Returns:
        (B,) same dtype: 0 at c = 1, inf at c = 0 or where c is not finite (no information).
    """
    c = confidence.clamp(0.0, 1.0)
    ok = torch.isfinite(confidence) & (c > 0)
    return torch.where(ok, 0.1 * (1.0 / torch.where(ok, c, 1.0) - 1.0).clamp_min(0.0).sqrt(), float("inf"))


class DivergenceEstimator:
    """Base class of divergence estimators (batched).

    The stage contract (:mod:`dvsland.pytree`): a built-in estimator holds only settings and offers
    ``init_state() -> State``, the pure ``step_state(state, events, t_us, truth) -> (State,
    EstimateOut)`` and ``reset_where(state, mask) -> State``. The object API (``reset``, ``update``,
    ``confidence``, ``diagnostics``) is then provided here on top of them, holding one state in
    ``self.state``; a third-party estimator may implement the object API alone.

    Args:
        batch_size: B, number of independent descents.
        sensor_size: (W, H) in pixels.
        device: torch device of the state and the returned estimate.
        dt_s: control / frame interval, s.
        principal_point_px: (cx, cy) focus of expansion in pixel coordinates (pixel centres at
            integers), inside [0, W - 1] x [0, H - 1]; None = the sensor centre.
    """

    #: Whether ``update`` needs events; an estimator that says False lets the simulator skip
    #: rendering and event emulation.
    needs_events: bool = True

    #: The shared motion-evidence test (:mod:`dvsland.estimators.abstain`) run on every step of an
    #: estimator that takes events: where the window shows no moving scene (noise, flicker) D_hat
    #: becomes NaN and the confidence 0, where it shows little the confidence is scaled down, where
    #: it shows a scene nothing changes. None turns it off (for a class or one instance);
    #: another :class:`~dvsland.estimators.abstain.AbstainParams` tunes it.
    abstain: Optional[AbstainParams] = DEFAULT_ABSTAIN

    #: Post-hoc confidence calibration (:mod:`dvsland.estimators.calibrate`) applied to every step's
    #: confidence after the motion-evidence test: None (the default) = the estimator's own confidence;
    #: a :class:`~dvsland.estimators.calibrate.CalibrationParams` table (``estimator.calibration``)
    #: rescales its predicted sigma. D_hat is never changed.
    calibration: Optional[CalibrationParams] = None

    #: Whether ``step_state`` takes ``donate=True``: the caller gives the input state up, and the step
    #: may write its buffers in place (as JAX's donated arguments). The loop runners donate the states
    #: they made (:func:`dvsland.sim.loop_step` ``donate``); a plug-in without the keyword says False.
    accepts_donate: bool = False

    def __init_subclass__(cls, **kwargs):
        """Every subclass's ``update`` runs behind :func:`_checked_update`: events are checked
        (b, x, y, p in range: a clear error, never an index error deep in an estimator) and
        sorted by (b, t) when they are not, before the estimator sees them."""
        super().__init_subclass__(**kwargs)
        upd = cls.__dict__.get("update")
        if upd is not None and not getattr(upd, "_dvsland_checked", False):
            cls.update = _checked_update(upd)
        stp = cls.__dict__.get("step_state")
        if stp is not None and not getattr(stp, "_dvsland_checked", False):
            cls.step_state = _checked_step_state(stp)
        conf = cls.__dict__.get("confidence")
        if callable(conf) and not getattr(conf, "_dvsland_checked", False):
            cls.confidence = _gated_confidence(conf)

    def _gate(self, out: "EstimateOut", events, t_us: int) -> "EstimateOut":
        """``out`` after the motion-evidence test of ``events`` (unchanged for an estimator without
        events, with ``abstain = None``, or when ``out`` was gated already)."""
        if not getattr(self, "needs_events", True) or getattr(self, "abstain", None) is None:
            return out
        return gate_output(out, events, self.batch_size, self.sensor_size, t_us, self.abstain)

    def _calibrate(self, out: "EstimateOut", events) -> "EstimateOut":
        """``out`` with its confidence calibrated (unchanged with ``calibration = None`` or when
        ``out`` was calibrated already)."""
        return calibrate_output(out, events, self.batch_size, getattr(self, "calibration", None))

    def __init__(self, batch_size: int, sensor_size: Tuple[int, int], device: Any = "cpu",
                 dt_s: float = 0.1, principal_point_px: Optional[Sequence[float]] = None, **params):
        if int(batch_size) < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if len(sensor_size) != 2 or min(sensor_size) < 1:
            raise ValueError(f"sensor_size must be (W, H) with W, H >= 1, got {sensor_size}")
        if not dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        self.batch_size = int(batch_size)
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        self.device = torch.device(device)
        self.dt_s = float(dt_s)
        self.principal_point_px = resolve_principal_point(principal_point_px, self.sensor_size)

    def _mask(self, mask: Optional[torch.Tensor]) -> torch.Tensor:
        """Normalise a reset mask: None -> all True; checks shape (B,) bool."""
        if mask is None:
            return torch.ones(self.batch_size, dtype=torch.bool, device=self.device)
        mask = torch.as_tensor(mask, device=self.device)
        if mask.shape != (self.batch_size,) or mask.dtype != torch.bool:
            raise ValueError(f"mask must be a (B,) = ({self.batch_size},) bool tensor, "
                             f"got shape {tuple(mask.shape)} dtype {mask.dtype}")
        return mask

    # ------------------------------------------------------------------ the object API over the contract
    def _has_contract(self) -> bool:
        return type(self).step_state is not DivergenceEstimator.step_state

    def init_state(self):
        """The state of B descents that have seen nothing (contract; built-ins implement it)."""
        raise NotImplementedError(f"{type(self).__name__} implements the object API only (reset/update)")

    def step_state(self, state, events, t_us: int, truth: Optional[Truth] = None):
        """Pure step: (next state, :class:`EstimateOut`); ``state`` is left unchanged."""
        raise NotImplementedError(f"{type(self).__name__} implements the object API only (reset/update)")

    def reset_where(self, state, mask: torch.Tensor):
        """``state`` with the descents where ``mask`` (B,) bool is True restarted."""
        raise NotImplementedError(f"{type(self).__name__} implements the object API only (reset/update)")

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        """Start over the batch elements where ``mask`` (B,) bool is True (all when None)."""
        if not self._has_contract():
            raise NotImplementedError
        st = getattr(self, "state", None)
        if mask is None or st is None:
            self.state = self.init_state()
            if mask is None:
                self._last = None
                return
        self.state = self.reset_where(self.state, self._mask(mask))
        last = getattr(self, "_last", None)
        if last is not None:  # a restarted descent has no estimate until its next update
            m = self._mask(mask)
            nan = torch.full_like(last.d_hat, float("nan"))
            self._last = last._replace(d_hat=torch.where(m, nan, last.d_hat),
                                       confidence=torch.where(m, torch.zeros_like(last.confidence), last.confidence))

    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        """Take the events of the last interval (up to ``t_us``, int µs) and return D_hat.

        Args:
            events: :class:`dvsland.events.Events` of the interval (may be empty or None for
                estimators with ``needs_events = False``).
            t_us: time of the end of the interval, int microseconds.
            truth: optional :class:`Truth`.

        Returns:
            (B,) float32 tensor, D_hat in 1/s (negative while descending), NaN = no estimate.
        """
        if not self._has_contract():
            raise NotImplementedError
        if getattr(self, "state", None) is None:
            self.state = self.init_state()
        self.state, self._last = self.step_state(self.state, events, t_us, truth)
        return self._last.d_hat.clone()

    def confidence(self) -> torch.Tensor:
        """How much the last estimate can be trusted, (B,) float32 in [0, 1]: 0 = no estimate (NaN)
        or no information, 1 = as good as it gets. The default is 1 where the last estimate is
        finite; estimators override it with their own measure (see the module doc)."""
        last = getattr(self, "_last", None)
        if last is not None:
            return last.confidence
        d = getattr(self, "_d", None)
        if d is None:
            return torch.zeros(self.batch_size, dtype=torch.float32, device=self.device)
        return _times_factor(self, torch.isfinite(d).to(torch.float32))

    def diagnostics(self) -> Dict[str, torch.Tensor]:
        """What the estimator tracks, for logging (e.g. ``centroids`` (B, N, 2), ``n_tracked`` (B,)).
        Every built-in estimator includes ``confidence`` (B,) float32 in [0, 1]."""
        last = getattr(self, "_last", None)
        if last is not None:
            return dict(last.diagnostics)
        return {"confidence": self.confidence()}


def _checked_update(update):
    """Wrap an estimator's ``update`` with the shared input check of
    :func:`dvsland.events.validate.checked_for_estimator`."""
    import functools

    @functools.wraps(update)
    def wrapper(self, events, t_us, *args, **kwargs):
        if events is not None and hasattr(events, "b"):
            from dvsland.events.validate import checked_for_estimator

            W, H = self.sensor_size
            events = checked_for_estimator(events, self.batch_size, W, H, what=f"{type(self).__name__}.update events")
        d = update(self, events, t_us, *args, **kwargs)
        if not self._has_contract():
            self._motion_factor = None  # a factor belongs to the update that measured it
            self._calibration_input = None
        if not isinstance(d, torch.Tensor):
            return d
        gated = getattr(self, "needs_events", True) and getattr(self, "abstain", None) is not None
        if self._has_contract():  # an update that bypasses step_state (e.g. learned's in-place ring)
            last = getattr(self, "_last", None)
            if isinstance(last, EstimateOut):
                out = self._gate(last, events, t_us) if gated and EVIDENCE_KEY not in last.diagnostics else last
                out = self._calibrate(out, events)
                if out is not last:
                    self._last = out
                    return out.d_hat.clone()
            return d
        # the object API alone: the factor (and the calibration's inputs) are kept for confidence()
        if getattr(self, "calibration", None) is not None:
            self._calibration_input = (window_event_counts(events, self.batch_size, d.device), d.detach().clone(),
                                       _structure_of(self) if self.calibration.feature == "structure" else None)
        if not gated:
            return d
        ev = motion_evidence(events, self.batch_size, self.sensor_size, t_us, self.abstain, device=d.device)
        self._motion_factor = ev.factor
        return torch.where(ev.factor > 0, d, torch.full_like(d, float("nan")))

    wrapper._dvsland_checked = True
    return wrapper


def _times_factor(self, c: torch.Tensor) -> torch.Tensor:
    """An object-API estimator's confidence ``c`` (B,) times the factor of its last update's
    motion evidence (0 where the factor is 0), then calibrated (``calibration``); unchanged for
    estimators under the contract (their step's output is gated and calibrated)."""
    if not isinstance(c, torch.Tensor) or self._has_contract():
        return c
    f = getattr(self, "_motion_factor", None)
    if f is not None:
        f = f.to(device=c.device)
        c = torch.where(f > 0, c * f.to(c.dtype), torch.zeros_like(c))
    params, inp = getattr(self, "calibration", None), getattr(self, "_calibration_input", None)
    if params is not None and inp is not None:
        p = params_to(params, c.device)
        n, d, st = inp
        f = feature_values(p.feature, n_events=n.to(c.device), d_hat=d.to(c.device),
                           structure=None if st is None else st.to(c.device))
        c = calibrate_confidence(c, p, f).to(c.dtype)
    return c


def _structure_of(est) -> Optional[torch.Tensor]:
    """The ``structure`` diagnostic (B,) of an object-API estimator's last update, or None."""
    diag = est.diagnostics() if callable(getattr(est, "diagnostics", None)) else None
    st = diag.get(STRUCTURE_KEY) if isinstance(diag, dict) else None
    return st.detach().clone() if isinstance(st, torch.Tensor) else None


def _gated_confidence(confidence):
    """Wrap an object-API estimator's own ``confidence`` with its last motion-evidence factor."""
    import functools

    @functools.wraps(confidence)
    def wrapper(self, *args, **kwargs):
        return _times_factor(self, confidence(self, *args, **kwargs))

    wrapper._dvsland_checked = True
    return wrapper


def _checked_step_state(step_state):
    """Wrap an estimator's ``step_state`` with the same input check as ``update``."""
    import functools

    @functools.wraps(step_state)
    def wrapper(self, state, events, t_us, *args, **kwargs):
        if events is not None and hasattr(events, "b"):
            from dvsland.events.validate import checked_for_estimator

            W, H = self.sensor_size
            events = checked_for_estimator(events, self.batch_size, W, H,
                                           what=f"{type(self).__name__}.step_state events")
        state, out = step_state(self, state, events, t_us, *args, **kwargs)
        if isinstance(out, EstimateOut):
            out = self._calibrate(self._gate(out, events, t_us), events)
        return state, out

    wrapper._dvsland_checked = True
    return wrapper
