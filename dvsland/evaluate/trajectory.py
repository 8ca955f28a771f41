"""The evaluation descents: the closed-form oracle-controlled descent of every site, sampled per step.

With perfect sensing the controller makes tau(t) = tau0 - c^2 t exactly, so the
oracle-controlled descent is the closed form z = z0 s^(1/c^2), v = v0 s^(1/c^2 - 1),
s = 1 + c^2 v0 t / z0 (:mod:`dvsland.dynamics.closed_form`). The evaluation uses it
(not a simulator run), sampled at the frame rate down to the success altitude.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence

import numpy as np

from dvsland.config import Config
from dvsland.dynamics import closed_form_state, closed_form_time_to_altitude


@dataclass
class Descents:
    """Sampled descents of B sites over K + 1 frame times (k = 0 .. K).

    Attributes:
        sites: site names, length B.
        t_s: (K + 1,) float64 frame times, s.
        altitude_m: (B, K + 1) float64; held at ``z_end_m`` once reached.
        velocity_mps: (B, K + 1) float64; 0 once ``z_end_m`` is reached.
        valid: (B, K + 1) bool, the descent is above ``z_end_m`` at that frame.
    """

    sites: List[str]
    t_s: np.ndarray
    altitude_m: np.ndarray
    velocity_mps: np.ndarray
    valid: np.ndarray

    @property
    def n_steps(self) -> int:
        return len(self.t_s) - 1

    @property
    def divergence(self) -> np.ndarray:
        """True D = v / z, (B, K + 1) float64, 1/s."""
        return self.velocity_mps / self.altitude_m


def closed_form_descents(cfg: Config, sites: Optional[Sequence[str]] = None, z_end_m: Optional[float] = None,
                         max_steps: Optional[int] = None) -> Descents:
    """Closed-form descents of ``sites`` (default: all in ``cfg.simulation.sites``) at ``cfg.dt_s``.

    Args:
        cfg: config (initial conditions from ``simulation.sites``, c^2 from ``controller.c2``).
        sites: names to keep, in that order.
        z_end_m: stop altitude (default ``simulation.success_altitude_m``).
        max_steps: truncate to at most this many steps.
    """
    specs = {s.name: s for s in cfg.simulation.sites}
    names = list(specs) if sites is None else list(sites)
    for n in names:
        if n not in specs:
            raise ValueError(f"site {n!r} is not in the config's simulation.sites {list(specs)}")
    if not names:
        raise ValueError("sites must name at least one site")
    z_end = float(cfg.simulation.success_altitude_m if z_end_m is None else z_end_m)
    c2 = float(cfg.controller.c2)
    dt = float(cfg.dt_s)
    t_end = []
    for n in names:
        s = specs[n]
        if not s.z0_m > z_end:
            raise ValueError(f"site {n}: z0_m = {s.z0_m} must be above z_end_m = {z_end}")
        t_end.append(closed_form_time_to_altitude(z_end, s.z0_m, s.v0_mps, c2))
    K = int(np.ceil(max(t_end) / dt))
    if max_steps is not None:
        if int(max_steps) < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        K = min(K, int(max_steps))
    t = np.arange(K + 1) * dt
    z = np.empty((len(names), K + 1))
    v = np.empty_like(z)
    for i, n in enumerate(names):
        zi, vi = closed_form_state(t, specs[n].z0_m, specs[n].v0_mps, c2)
        z[i], v[i] = zi, vi
    valid = z > z_end
    z = np.where(valid, z, z_end)
    v = np.where(valid, v, 0.0)
    return Descents(names, t, z, v, valid)


def segment_schedule(n_steps: int, segment_steps: int = 0, stride: int = 1) -> List[range]:
    """Which steps to run: every ``stride``-th segment of ``segment_steps`` steps (0 = one segment).

    Steps are numbered 1 .. n_steps (step k covers frames k-1 -> k). Contiguous kept segments merge.
    """
    if int(stride) < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if int(segment_steps) < 0:
        raise ValueError(f"segment_steps must be >= 0, got {segment_steps}")
    if segment_steps == 0 or stride == 1:
        return [range(1, n_steps + 1)]
    out = []
    for i, start in enumerate(range(1, n_steps + 1, segment_steps)):
        if i % stride == 0:
            out.append(range(start, min(n_steps, start + segment_steps - 1) + 1))
    return out
