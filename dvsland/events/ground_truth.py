"""The ground truth of a recording: a time series of divergence (and altitude and velocity where
known). A plain container at the bottom of :mod:`dvsland.events`, so that dvsland's own event files
(:mod:`dvsland.events.io`) and the recordings of other tools (:mod:`dvsland.events.recording`)
both store and read it without importing each other."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np


@dataclass
class GroundTruth:
    """A ground-truth time series of a recording.

    Attributes:
        t_us: (K,) int64 µs, increasing.
        divergence: (K,) float64, D = v / z, 1/s (negative while descending).
        altitude_m, velocity_mps: (K,) float64 or None (when only D is known).
    """

    t_us: np.ndarray
    divergence: np.ndarray
    altitude_m: Optional[np.ndarray] = None
    velocity_mps: Optional[np.ndarray] = None

    def __post_init__(self):
        self.t_us = np.asarray(self.t_us).astype(np.int64).reshape(-1)
        self.divergence = np.asarray(self.divergence, dtype=np.float64).reshape(-1)
        K = len(self.t_us)
        for name in ("divergence", "altitude_m", "velocity_mps"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.float64).reshape(-1)
                setattr(self, name, v)
                if len(v) != K:
                    raise ValueError(f"ground truth {name} has {len(v)} samples, t_us has {K}")
        if K == 0:
            raise ValueError("ground truth needs at least one sample")
        if K > 1 and np.any(np.diff(self.t_us) <= 0):
            raise ValueError("ground truth t_us must be strictly increasing")

    @classmethod
    def from_altitude(cls, t_us, altitude_m, velocity_mps) -> "GroundTruth":
        z = np.asarray(altitude_m, dtype=np.float64)
        v = np.asarray(velocity_mps, dtype=np.float64)
        if np.any(z <= 0):
            raise ValueError("ground truth altitude_m must be > 0 (D = v / z)")
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
