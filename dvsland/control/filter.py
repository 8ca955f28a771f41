"""Divergence filters under the stage contract, and the NaN-aware moving average (filter ``moving_average``).

Every filter is params (frozen), a State of (B, ...) tensors and a pure step (:mod:`dvsland.pytree`):
``init_state()``, ``step_state(state, d_hat, active, accel_mps2=None, thrust_accel_mps2=None,
confidence=None) -> (State, FilterOut)``, ``reset_where(state, mask)``. The object API (``update``,
``reset``) is :class:`DivergenceFilter`'s, on top of them, holding one state in ``self.state``.

The paper averages the last n_bin estimates of D before inverting to TTC. Here every batch
element may have its own n_bin (controller settings side by side in one batch): the filter
keeps the last max(n_bin) estimates of each descent and a per-element mask of which count.
Missing estimates (NaN) are skipped; the filter reports how many it used.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional, Tuple

import torch

from dvsland.pytree import check_state_like, tree_where

from .base import as_mask, batch_of, mark_object_api_only

Tensor = torch.Tensor


class FilterOut(NamedTuple):
    """What a filter's pure step returns besides its next state.

    Attributes:
        d_filtered: (B,) float64 filtered divergence, 1/s (NaN where there is none).
        n_used: (B,) int64 estimates used (the moving average: in its window; the efference
            filters: 1 where this step's estimate was fused).
        altitude_m: (B,) float64 the filter's altitude estimate, m, or None (no estimate: the moving
            average).
        doubt: (B, 3) float64 how far the filter has moved from its plan, or None (only
            ``efference_fit`` gives it): the fitted offsets of the initial altitude and velocity in
            prior standard deviations (dz / sigma_z0, dv / sigma_v0), and the share of this descent's
            estimates the fit rejected (weight 0) so far, in [0, 1].
        velocity_sigma_mps: (B,) float64 the filter's posterior standard deviation of the velocity,
            m/s, or None (the moving average). The efference filters give it: how far the velocity
            they report may be off, from their prior and every estimate they fused.
    """

    d_filtered: Tensor
    n_used: Tensor
    altitude_m: Optional[Tensor]
    doubt: Optional[Tensor] = None
    velocity_sigma_mps: Optional[Tensor] = None


class DivergenceFilter:
    """Base class of the divergence filters: the object API over the stage contract.

    A filter holds only settings (``self.params``) and implements ``init_state()``, the pure
    ``step_state(state, d_hat, active, accel_mps2=None, thrust_accel_mps2=None, confidence=None)
    -> (State, FilterOut)`` and, when a per-descent ``tree_where`` restart is not enough,
    ``reset_where(state, mask)``. ``update`` and ``reset`` are provided here; the fields of the held
    state and of the params (and of their ``cfg`` section) read as attributes (``f.z``,
    ``f.n_rejected``, ``f.gate_sigma``).

    Inputs of a step: ``d_hat`` (B,) float estimates, 1/s (NaN = missing); ``active`` (B,) bool or
    None (all): only these descents advance, the others keep their state; ``accel_mps2`` (B,)
    float64 the known acceleration u/m - g over the last step, m/s^2, or None (the first step; NaN
    for the descents without one: their first step after a restart);
    ``thrust_accel_mps2`` (B,) float64 u/m over the last step; ``confidence`` (B,) float in [0, 1],
    the estimator's confidence.
    """

    #: whether :class:`FilterOut` carries an altitude estimate
    provides_altitude = False
    #: whether :class:`FilterOut` carries the velocity's posterior standard deviation
    provides_velocity_sigma = False

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        mark_object_api_only(cls, DivergenceFilter, "update")

    # ------------------------------------------------------------------ the contract
    def init_state(self):
        """The state of B descents that have seen nothing."""
        raise NotImplementedError(f"{type(self).__name__} implements neither the contract nor update")

    def step_state(self, state, d_hat: Tensor, active: Optional[Tensor] = None, accel_mps2: Optional[Tensor] = None,
                   thrust_accel_mps2: Optional[Tensor] = None, confidence: Optional[Tensor] = None):
        """Pure step: (next state, :class:`FilterOut`); ``state`` is left unchanged."""
        raise NotImplementedError(f"{type(self).__name__} implements neither the contract nor update")

    def reset_where(self, state, mask: Tensor):
        """``state`` with the descents where ``mask`` (B,) bool is True restarted, the others bit-identical."""
        fresh = self.init_state()
        return tree_where(self._mask(mask, fresh), fresh, state)

    # ------------------------------------------------------------------ helpers of the steps
    def _mask(self, mask, like) -> Tensor:
        """``mask`` as a (B,) bool tensor for the descents of state ``like`` (None = all)."""
        return as_mask(mask, *batch_of(like), f"filter {type(self).__name__}")

    def _check_inputs(self, state, d_hat: Tensor, confidence: Optional[Tensor] = None) -> None:
        """ValueError naming the filter and the field: a state unlike this filter's, a d_hat or a
        confidence of the wrong shape (host-side metadata only, no sync)."""
        check_state_like(f"filter {type(self).__name__}", state, self._template)
        B = batch_of(self._template)[0]
        if d_hat.shape != (B,):
            raise ValueError(f"d_hat must have shape ({B},), got {tuple(d_hat.shape)}")
        if confidence is not None and confidence.shape != (B,):
            raise ValueError(f"confidence must have shape ({B},), got {tuple(confidence.shape)}")

    # ------------------------------------------------------------------ the object API
    def reset(self, mask: Optional[Tensor] = None) -> None:
        """Forget the descents where ``mask`` (B,) bool is True (all when None)."""
        if mask is None or getattr(self, "state", None) is None:
            self.state = self.init_state()
        if mask is not None:
            self.state = self.reset_where(self.state, mask)

    def update(self, d_hat: Tensor, mask: Optional[Tensor] = None, accel_mps2: Optional[Tensor] = None,
               thrust_accel_mps2: Optional[Tensor] = None, confidence: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """One control step (see the class doc; ``mask`` is ``active``).

        Returns:
            (d_filtered (B,) float64 1/s, n_used (B,) int64).
        """
        if getattr(self, "state", None) is None:
            self.state = self.init_state()
        self.state, out = self.step_state(self.state, d_hat, mask, accel_mps2=accel_mps2,
                                          thrust_accel_mps2=thrust_accel_mps2, confidence=confidence)
        return out.d_filtered, out.n_used

    def __getattr__(self, name: str) -> Any:
        """Read access to the held state's fields, then the params' fields and their ``cfg`` section's."""
        d = self.__dict__
        if not name.startswith("__"):
            st = d.get("state")
            if name in getattr(st, "_fields", ()):
                return getattr(st, name)
            p = d.get("params")
            if name in getattr(p, "_fields", ()):
                return getattr(p, name)
            cfg = getattr(p, "cfg", None)
            if name in getattr(type(cfg), "__dataclass_fields__", {}):
                return getattr(cfg, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")


# ------------------------------------------------------------------ the moving average
def nan_moving_average(history: Tensor, n_bin: Tensor) -> Tuple[Tensor, Tensor]:
    """Mean of the newest ``n_bin`` finite entries window per element (NaN where none).

    Args:
        history: (N, B) float, newest first (row 0 = latest); NaN = missing.
        n_bin: (B,) int64 window lengths, 1 <= n_bin <= N.

    Returns:
        (mean, n_used): (B,) float (NaN where no finite value in the window) and (B,) int64.
    """
    n = history.shape[0]
    rows = torch.arange(n, device=history.device).unsqueeze(1)
    return _masked_mean(history, rows < n_bin.to(history.device).unsqueeze(0))


def _masked_mean(history: Tensor, in_window: Tensor) -> Tuple[Tensor, Tensor]:
    valid = in_window & torch.isfinite(history)
    n_used = valid.sum(0)
    mean = torch.where(valid, history, 0.0).sum(0) / n_used  # 0 / 0 = NaN where none
    return mean, n_used


class MovingAverageParams(NamedTuple):
    """Settings of the moving average of B descents.

    Attributes:
        n_bin: (B,) int64 window lengths, estimates (>= 1).
        in_window: (N, B) bool, N = max(n_bin): which of the newest-first estimates count.
        dtype: dtype of the kept estimates.
    """

    n_bin: Tensor
    in_window: Tensor
    dtype: torch.dtype


class MovingAverageState(NamedTuple):
    """State of the moving average for B descents.

    Attributes:
        hist: (B, N) the last N = max(n_bin) estimates of each descent, newest first, 1/s (NaN = missing).
    """

    hist: Tensor


def moving_average_step(p: MovingAverageParams, state: MovingAverageState, d_hat: Tensor,
                        active: Optional[Tensor] = None) -> Tuple[MovingAverageState, FilterOut]:
    """Pure step of the moving average: push ``d_hat`` (B,) where ``active`` (all when None) and
    return the mean of each descent's window (NaN where it holds no finite estimate)."""
    h = state.hist
    new = torch.cat([d_hat.to(h.dtype).unsqueeze(1), h[:, :-1]], 1)
    if active is not None:
        new = torch.where(active.unsqueeze(1), new, h)
    mean, n_used = _masked_mean(new.t().contiguous(), p.in_window)  # summed over a newest-first (N, B) history
    return MovingAverageState(new), FilterOut(mean, n_used, None)


class MovingAverageFilter(DivergenceFilter):
    """Batched NaN-aware moving average (params :class:`MovingAverageParams`, state
    :class:`MovingAverageState`, pure step :func:`moving_average_step`).

    Args:
        n_bin: (B,) int window lengths (or a sequence of ints), each >= 1.
        device: torch device.
        dtype: dtype of the stored history (float64 default).

    Example::

        f = MovingAverageFilter(torch.tensor([5, 10]))
        d_f, n_used = f.update(d_hat)   # d_hat (2,), NaN = missing
    """

    def __init__(self, n_bin, device="cpu", dtype: torch.dtype = torch.float64):
        n_bin = torch.as_tensor(n_bin, dtype=torch.int64, device=device).reshape(-1)
        if n_bin.numel() < 1 or bool((n_bin < 1).any()):
            raise ValueError(f"n_bin must be >= 1 for every element, got {n_bin.tolist()}")
        rows = torch.arange(int(n_bin.max()), device=device).unsqueeze(1)
        self.params = MovingAverageParams(n_bin, rows < n_bin.unsqueeze(0), dtype)
        self._template = self.init_state()
        self.state = self.init_state()

    @property
    def batch_size(self) -> int:
        return int(self.params.n_bin.numel())

    @property
    def n_max(self) -> int:
        return int(self.params.in_window.shape[0])

    @property
    def device(self) -> torch.device:
        return self.params.n_bin.device

    @classmethod
    def from_params(cls, p, **options) -> "MovingAverageFilter":
        """From the loop's :class:`~dvsland.control.DescentParams` (window = each setting's n_bin)."""
        if options:
            raise ValueError(f"filter 'moving_average' takes no options, got {sorted(options)}")
        return cls(p.n_bin, device=p.device)

    def init_state(self) -> MovingAverageState:
        return MovingAverageState(torch.full((self.batch_size, self.n_max), float("nan"), dtype=self.params.dtype,
                                             device=self.device))

    def step_state(self, state: MovingAverageState, d_hat: Tensor, active: Optional[Tensor] = None,
                   accel_mps2: Optional[Tensor] = None, thrust_accel_mps2: Optional[Tensor] = None,
                   confidence: Optional[Tensor] = None) -> Tuple[MovingAverageState, FilterOut]:
        """Pure step (:func:`moving_average_step`); ``accel_mps2``, ``thrust_accel_mps2`` and
        ``confidence`` are ignored (the efference filters' inputs: one call serves every filter)."""
        self._check_inputs(state, d_hat)
        return moving_average_step(self.params, state, d_hat, active)
