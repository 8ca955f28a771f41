"""The ground truth of a recording: a time series of divergence (and altitude and velocity where
known). A plain container at the bottom of :mod:`dvsland.events`, so that dvsland's own event files
(:mod:`dvsland.events.io`) and the recordings of other tools (:mod:`dvsland.events.recording`)
both store and read it without importing each other."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np


def _check_finite(name: str, v: np.ndarray) -> None:
    """ValueError naming the column, the first non-finite value and its row (0-based sample index)."""
    bad = ~np.isfinite(v)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"ground truth column {name!r} holds {v[i]} at row {i} ({int(bad.sum())} of {v.size} "
                         f"values are not finite); it must be finite")


def _times_us(t) -> np.ndarray:
    """Sample times as (K,) int64 µs: integers, or floats that are finite whole numbers within int64."""
    t = np.asarray(t).reshape(-1)
    if t.dtype.kind == "f":
        _check_finite("t_us", t)
        if t.size and (np.abs(t).max() >= 2.0 ** 63 or (t != np.round(t)).any()):
            raise ValueError("ground truth column 't_us' must hold whole numbers of µs within int64")
    elif t.dtype.kind == "u" and t.size and int(t.max()) > np.iinfo(np.int64).max:
        raise ValueError("ground truth column 't_us' reaches 2^63 µs or more: it does not fit int64")
    elif t.dtype.kind not in "iub":
        raise ValueError(f"ground truth column 't_us' must be numeric, got dtype {t.dtype}")
    return t.astype(np.int64)


@dataclass
class GroundTruth:
    """A ground-truth time series of a recording.

    Attributes:
        t_us: (K,) int64 µs, increasing.
        divergence: (K,) float64, D = v / z, 1/s (negative while descending).
        altitude_m, velocity_mps: (K,) float64 or None (when only D is known).

    Every value must be finite: NaN or inf (or t_us beyond int64) is a ValueError naming the column
    and the row, so that no unknown truth reaches the scores.
    """

    t_us: np.ndarray
    divergence: np.ndarray
    altitude_m: Optional[np.ndarray] = None
    velocity_mps: Optional[np.ndarray] = None

    def __post_init__(self):
        self.t_us = _times_us(self.t_us)
        self.divergence = np.asarray(self.divergence, dtype=np.float64).reshape(-1)
        K = len(self.t_us)
        for name in ("altitude_m", "velocity_mps", "divergence"):  # the measured columns first
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.float64).reshape(-1)
                setattr(self, name, v)
                if len(v) != K:
                    raise ValueError(f"ground truth {name} has {len(v)} samples, t_us has {K}")
                _check_finite(name, v)
        if K == 0:
            raise ValueError("ground truth needs at least one sample")
        back = self.t_us[1:] <= self.t_us[:-1]  # comparisons: no overflow
        if back.any():
            i = int(np.argmax(back)) + 1
            raise ValueError(f"ground truth t_us must be strictly increasing: row {i} ({int(self.t_us[i])}) "
                             f"follows {int(self.t_us[i - 1])}")

    @classmethod
    def from_altitude(cls, t_us, altitude_m, velocity_mps) -> "GroundTruth":
        z = np.asarray(altitude_m, dtype=np.float64)
        v = np.asarray(velocity_mps, dtype=np.float64)
        if np.any(z <= 0):
            i = int(np.argmax(np.reshape(z, -1) <= 0))
            raise ValueError(f"ground truth altitude_m must be > 0 (D = v / z), got {np.reshape(z, -1)[i]} at row {i}")
        return cls(t_us, v / z, z, v)

    def at(self, t_us) -> Dict[str, np.ndarray]:
        """Linear interpolation at ``t_us`` (M,); NaN outside [t_us[0], t_us[-1]]. Returns
        {"divergence", "altitude_m", "velocity_mps"} ((M,) float64; the last two NaN if unknown)."""
        t = np.asarray(t_us, dtype=np.float64).reshape(-1)
        out = {}
        tt = self.t_us.astype(np.float64)
        for name in ("divergence", "altitude_m", "velocity_mps"):
            v = getattr(self, name)
            out[name] = (np.interp(t, tt, v, left=np.nan, right=np.nan) if v is not None
                         else np.full(t.shape, np.nan))
        return out

    def arrays(self, prefix: str = "") -> Dict[str, np.ndarray]:
        out = {f"{prefix}t_us": self.t_us, f"{prefix}divergence": self.divergence}
        if self.altitude_m is not None:
            out[f"{prefix}altitude_m"] = self.altitude_m
            out[f"{prefix}velocity_mps"] = self.velocity_mps
        return out


__all__ = ["GroundTruth"]
