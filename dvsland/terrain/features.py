"""Crater and boulder catalogues and their profiles.

Populations follow cumulative power laws N(>D) = density * D^-exponent per m^2. They are drawn
per size octave [D, 2D) in a square of side ``region_factor * D`` around the landing point
(capped at ``region_max_m``): a small feature only needs to exist where a camera low enough to
see it looks. Each octave has its own numpy generator seeded by (site seed, kind, octave), so a
catalogue is identical bit for bit for the same spec.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Catalogue:
    """Features as float64 CPU tensors of shape (M,): centre x_m, y_m, diameter d_m, freshness in
    [0, 1] (1 = fresh: full depth, rim and bright ejecta)."""

    x_m: torch.Tensor
    y_m: torch.Tensor
    d_m: torch.Tensor
    fresh: torch.Tensor

    def __len__(self) -> int:
        return int(self.d_m.numel())


def power_law_catalogue(seed: int, kind: int, density: float, exponent: float, d_min_m: float,
                        d_max_m: float, region_factor: float, region_max_m: float,
                        fresh_min: float = 0.0) -> Catalogue:
    """Draw a feature population octave by octave (see module doc). Returns a :class:`Catalogue`."""
    xs, ys, ds, fs = [], [], [], []
    if density > 0 and d_max_m > d_min_m:
        n_oct = int(math.ceil(math.log2(d_max_m / d_min_m)))
        for k in range(n_oct):
            lo = d_min_m * 2.0 ** k
            hi = min(2 * lo, d_max_m)
            side = min(region_factor * lo, region_max_m)
            mean = density * (lo ** -exponent - hi ** -exponent) * side * side
            rng = np.random.default_rng([int(seed), int(kind), k])
            m = int(rng.poisson(mean))
            if m == 0:
                continue
            u = rng.random(m)
            d = (lo ** -exponent - u * (lo ** -exponent - hi ** -exponent)) ** (-1.0 / exponent)
            x = (rng.random(m) - 0.5) * side
            y = (rng.random(m) - 0.5) * side
            f = fresh_min + (1 - fresh_min) * rng.random(m) ** 2.0  # most craters are degraded
            xs.append(x), ys.append(y), ds.append(d), fs.append(f)
    cat = [np.concatenate(v) if v else np.zeros(0) for v in (xs, ys, ds, fs)]
    return Catalogue(*(torch.from_numpy(np.ascontiguousarray(c, dtype=np.float64)) for c in cat))


def crater_profile(r: torch.Tensor, d_m: torch.Tensor, fresh: torch.Tensor, depth_ratio: float,
                   rim_ratio: float) -> torch.Tensor:
    """Height (m) of a simple crater at normalised radius r = distance / (D/2).

    Paraboloid bowl inside (floor depth ``depth_ratio * D`` below the rim crest), raised rim of
    ``rim_ratio * D`` at r = 1, ejecta blanket falling as r^-3 to zero at r = 2. Depth and rim
    scale with ``fresh`` (degraded craters are shallower).
    """
    depth = depth_ratio * d_m * fresh
    rim = rim_ratio * d_m * fresh
    inside = rim + depth * (r * r - 1.0)
    rr = r.clamp(min=1.0)
    outside = rim * (rr.pow(-3) - 0.125) / 0.875
    h = torch.where(r < 1.0, inside, outside)
    return torch.where(r < 2.0, h, torch.zeros_like(h))


def ejecta_albedo(r: torch.Tensor, fresh: torch.Tensor, boost: float) -> torch.Tensor:
    """Relative albedo change (add to 1) around a crater: bright ejecta of fresh craters."""
    f3 = fresh ** 3
    halo = torch.exp(-((r - 1.0) / 0.5).clamp(min=0.0) ** 2) * (1 - (r / 2.0).clamp(max=1.0) ** 2)
    return boost * f3 * halo


def boulder_profile(r: torch.Tensor, d_m: torch.Tensor) -> torch.Tensor:
    """Height (m) of a boulder (hemisphere, height D/2) at r = distance / (D/2)."""
    return 0.5 * d_m * torch.sqrt((1.0 - r * r).clamp(min=0.0))
