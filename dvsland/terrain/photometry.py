"""Photometry of the lunar surface seen by a nadir camera: lunar-Lambert reflectance, cast
shadows by horizon scan along the sun azimuth, ambient floor.

Shading works on a *sun-aligned* grid (columns point toward the sun's azimuth), where the
shadow test along a sun ray is a reverse running maximum along each row (``torch.cummax``):
exact for any shadow length inside the grid, O(n^2).
"""

from __future__ import annotations

import math
from typing import Tuple

import torch

from .grid import Grid


def lunar_lambert_l(phase_deg: float) -> float:
    """McEwen (1991) lunar-Lambert limb-darkening weight L(alpha) (1 = Lommel-Seeliger, 0 = Lambert)."""
    a = phase_deg
    value = 1.0 - 0.019 * a + 2.42e-4 * a * a - 1.46e-6 * a ** 3
    return min(max(value, 0.0), 1.0)


def cast_shadow(height_m: torch.Tensor, spacing_m: float, sun_elevation_deg: float) -> torch.Tensor:
    """Fraction lit (1 = sunlit, 0 = in cast shadow) on a sun-aligned grid.

    Args:
        height_m: (..., R, C) heights; column index grows toward the sun.
        spacing_m: texel side, m.
        sun_elevation_deg: sun elevation, degrees.

    Returns:
        (..., R, C) in [0, 1]; the edge is softened over one texel (anti-aliasing).
    """
    tan_e = math.tan(math.radians(sun_elevation_deg))
    c = height_m.shape[-1]
    u = torch.arange(c, dtype=height_m.dtype, device=height_m.device) * (spacing_m * tan_e)
    q = height_m - u
    horizon = torch.flip(torch.cummax(torch.flip(q, dims=[-1]), dim=-1).values, dims=[-1])
    # exclude the texel itself: the horizon of column j is the max over columns > j
    blocker = torch.cat([horizon[..., 1:], torch.full_like(horizon[..., :1], -math.inf)], dim=-1)
    depth = (blocker - q).clamp(min=0.0)
    return (1.0 - depth / (spacing_m * tan_e)).clamp(0.0, 1.0)


def shade(height_m: torch.Tensor, albedo: torch.Tensor, spacing_m: float, sun_elevation_deg: float,
          ambient: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """Linear irradiance at a nadir camera on a sun-aligned grid.

    I = albedo * (R_LL(i, e) * lit + ambient), R_LL the lunar-Lambert reflectance
    L * 2 cos i / (cos i + cos e) + (1 - L) cos i with L from the phase angle 90 deg - elevation
    (full sun on a flat surface gives R_LL = 2 sin(el) / (1 + sin(el)) * L + ...).

    Args:
        height_m, albedo: (R, C) on a sun-aligned grid (columns toward the sun).
        spacing_m: texel side, m. sun_elevation_deg: degrees. ambient: fraction of full sun.

    Returns:
        irradiance (R, C) > 0, and the lit fraction (R, C).
    """
    el = math.radians(sun_elevation_deg)
    gu = torch.gradient(height_m, spacing=spacing_m, dim=-1)[0]
    gv = torch.gradient(height_m, spacing=spacing_m, dim=-2)[0]
    norm = torch.sqrt(1.0 + gu * gu + gv * gv)
    cos_i = ((-gu * math.cos(el) + math.sin(el)) / norm).clamp(min=0.0)
    cos_e = 1.0 / norm
    lam = lunar_lambert_l(90.0 - sun_elevation_deg)
    refl = lam * 2.0 * cos_i / (cos_i + cos_e) + (1.0 - lam) * cos_i
    lit = cast_shadow(height_m, spacing_m, sun_elevation_deg)
    return albedo * (refl * lit + ambient), lit


def shaded_sun_grid(terrain, center_xy_m, m: int, spacing_m: float, ambient: float,
                    pad_frac: float = 0.5) -> Tuple[torch.Tensor, torch.Tensor, Grid]:
    """Shade an m x m sun-aligned window of ``terrain`` centred on ``center_xy_m``.

    The heights are sampled ``pad_frac * m`` texels further toward the sun so that features
    outside the window still cast their shadows into it.

    Returns:
        irradiance (m, m) float64, height_m (m, m) float64 (CPU), and the window's :class:`Grid`
        (column axis toward the sun, angle ``terrain.sun_grid_angle_rad``).
    """
    ang = terrain.sun_grid_angle_rad
    pad = int(math.ceil(pad_frac * m))
    ec = (math.cos(ang), math.sin(ang))
    cx = float(center_xy_m[0]) + 0.5 * pad * spacing_m * ec[0]
    cy = float(center_xy_m[1]) + 0.5 * pad * spacing_m * ec[1]
    full = Grid.centered((cx, cy), m, m + pad, spacing_m, ang)
    h, a = terrain.fields(full)
    irr, _ = shade(h, a, spacing_m, terrain.sun_elevation_deg, ambient)
    window = Grid.centered(center_xy_m, m, m, spacing_m, ang)
    return irr[:, :m].contiguous(), h[:, :m].contiguous(), window
