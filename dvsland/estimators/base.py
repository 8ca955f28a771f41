"""The estimator extension point: anything that turns events into divergence D = v/z.

A :class:`DivergenceEstimator` holds the state of B independent descents. The simulator calls
``reset(mask)`` when descents (re)start and ``update(events, t_us, truth)`` once per control
step with the events of the last frame interval; it returns D_hat (B,) in 1/s with the
paper's sign (negative while descending) and NaN where it has no estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

import torch


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


class DivergenceEstimator:
    """Base class of divergence estimators (stateful, batched).

    Args:
        batch_size: B, number of independent descents.
        sensor_size: (W, H) in pixels.
        device: torch device of the state and the returned estimate.
        dt_s: control / frame interval, s.
    """

    #: Whether ``update`` needs events; an estimator that says False lets the simulator skip
    #: rendering and event emulation.
    needs_events: bool = True

    def __init_subclass__(cls, **kwargs):
        """Every subclass's ``update`` runs behind :func:`_checked_update`: events are checked
        (b, x, y, p in range: a clear error, never an index error deep in an estimator) and
        sorted by (b, t) when they are not, before the estimator sees them."""
        super().__init_subclass__(**kwargs)
        upd = cls.__dict__.get("update")
        if upd is not None and not getattr(upd, "_dvsland_checked", False):
            cls.update = _checked_update(upd)

    def __init__(self, batch_size: int, sensor_size: Tuple[int, int], device: Any = "cpu",
                 dt_s: float = 0.1, **params):
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

    def _mask(self, mask: Optional[torch.Tensor]) -> torch.Tensor:
        """Normalise a reset mask: None -> all True; checks shape (B,) bool."""
        if mask is None:
            return torch.ones(self.batch_size, dtype=torch.bool, device=self.device)
        mask = torch.as_tensor(mask, device=self.device)
        if mask.shape != (self.batch_size,) or mask.dtype != torch.bool:
            raise ValueError(f"mask must be a (B,) = ({self.batch_size},) bool tensor, "
                             f"got shape {tuple(mask.shape)} dtype {mask.dtype}")
        return mask

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        """Start over the batch elements where ``mask`` (B,) bool is True (all when None)."""
        raise NotImplementedError

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
        raise NotImplementedError

    def diagnostics(self) -> Dict[str, torch.Tensor]:
        """What the estimator tracks, for logging (e.g. ``centroids`` (B, N, 2), ``n_tracked`` (B,))."""
        return {}


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
        return update(self, events, t_us, *args, **kwargs)

    wrapper._dvsland_checked = True
    return wrapper
