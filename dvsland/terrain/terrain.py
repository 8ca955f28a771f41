"""A continuous, seeded, multi-scale Moon-like terrain (one landing site).

Height (m) = band-limited fBm relief + simple craters + boulders; albedo = mean x exp(fBm) x
ejecta / boulder brightening. Everything is a function of world position (x east, y north,
metres; the landing point is (0, 0)) and the sampling texel: a grid only holds features at
least ~2 texels across (they fade in between 2 and 4 texels), so sampling is band-limited.

Fields are computed on CPU in float64 (fixed summation order: same seed -> same terrain bit for
bit) and then cast and moved to the requested device and dtype.
"""

from __future__ import annotations

import math
from functools import cached_property
from typing import Optional, Tuple

import numpy as np
import torch
import torch.nn.functional as F

from .features import Catalogue, boulder_profile, crater_profile, ejecta_albedo, power_law_catalogue
from .grid import Grid, compute_threads
from .noise import band_weight, fbm
from .spec import SiteSpec, load_spec

#: features fade in between these sizes in texels (diameter for craters / boulders)
FEATURE_FADE_TEXELS = (2.0, 4.0)
#: noise octaves fade in between these wavelengths in texels
NOISE_FADE_TEXELS = (4.0, 8.0)
#: octaves at least this many texels long are evaluated on a 4x coarser grid, cubic-upsampled
_COARSE_TEXELS = 64.0
_ALBEDO_HURST = 0.2
_ALBEDO_MAX_WAVELENGTH_M = 20000.0


class Terrain:
    """One landing site's terrain (see module doc).

    Attributes:
        spec: the :class:`SiteSpec`; ``name``, ``seed`` mirror it.
        craters, boulders: :class:`Catalogue` of features (float64 CPU tensors).
    """

    def __init__(self, spec: SiteSpec):
        self.spec = spec
        self.name = spec.name
        self.seed = int(spec.seed)
        c, b = spec.craters, spec.boulders
        self.craters: Catalogue = power_law_catalogue(
            self.seed, 1, c.density, c.exponent, c.d_min_m, c.d_max_m, spec.region_factor,
            spec.region_max_m, fresh_min=c.freshness_min)
        cr = self.craters
        clear = (cr.d_m >= spec.landing_clear_d_m) & (torch.hypot(cr.x_m, cr.y_m) < 0.75 * cr.d_m)
        if bool(clear.any()):
            keep = ~clear
            self.craters = Catalogue(cr.x_m[keep], cr.y_m[keep], cr.d_m[keep], cr.fresh[keep])
        self.boulders: Catalogue = power_law_catalogue(
            self.seed, 2, b.density, b.exponent, b.d_min_m, b.d_max_m, spec.region_factor,
            spec.region_max_m, fresh_min=1.0)

    def __repr__(self) -> str:
        return (f"Terrain({self.name!r}, seed={self.seed}, craters={len(self.craters)}, "
                f"boulders={len(self.boulders)}, sun=({self.sun_elevation_deg:.1f} deg el, "
                f"{self.spec.sun.azimuth_deg:.1f} deg az))")

    # ---------------------------------------------------------------- sun
    @property
    def sun_elevation_deg(self) -> float:
        return float(self.spec.sun.elevation_deg)

    @property
    def sun_azimuth_deg(self) -> float:
        """Compass azimuth TO the sun, clockwise from north."""
        return float(self.spec.sun.azimuth_deg)

    @cached_property
    def sun_direction(self) -> np.ndarray:
        """(3,) float64 unit vector pointing TO the sun, world frame (x east, y north, z up)."""
        el = math.radians(self.sun_elevation_deg)
        az = math.radians(self.sun_azimuth_deg)
        return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])

    @property
    def sun_grid_angle_rad(self) -> float:
        """Angle (from east, counter-clockwise) of the horizontal direction to the sun."""
        d = self.sun_direction
        return math.atan2(d[1], d[0])

    # ---------------------------------------------------------------- fields
    def fields(self, grid: Grid) -> Tuple[torch.Tensor, torch.Tensor]:
        """Height (m) and albedo on a grid, each (n_rows, n_cols) float64 on CPU (see _fields)."""
        with compute_threads():
            return self._fields(grid)

    def _fields(self, grid: Grid) -> Tuple[torch.Tensor, torch.Tensor]:
        """Height (m) and albedo on a grid, each (n_rows, n_cols) float64 on CPU.

        Two tiers for the noise: octaves shorter than 64 texels are evaluated at every texel,
        longer ones on a 4x coarser grid and Catmull-Rom-upsampled (16+ samples per wavelength).
        Craters and boulders are always evaluated at every texel (sharp rims).
        """
        s = grid.spacing_m
        split_noise = _COARSE_TEXELS * s
        height = self._noise(grid, "height", lam_below=split_noise)
        log_alb = self._noise(grid, "albedo", lam_below=split_noise)
        rel_alb = torch.zeros_like(height)
        self._features(grid, height, rel_alb, s)
        # coarse tier: texel (I, J) sits at fine index 4 I + 1.5 - 4 m (m coarse texels of margin)
        m = 2
        nrc = -(-grid.n_rows // 4) + 2 * m
        ncc = -(-grid.n_cols // 4) + 2 * m
        ox, oy = grid.world(torch.tensor(1.5 - 4 * m, dtype=torch.float64),
                            torch.tensor(1.5 - 4 * m, dtype=torch.float64))
        coarse = Grid(float(ox), float(oy), grid.angle_rad, nrc, ncc, 4 * s)
        ch = self._noise(coarse, "height", lam_from=split_noise, texel_m=s)
        ca = self._noise(coarse, "albedo", lam_from=split_noise, texel_m=s)
        ur = _catmull_rom_up(grid.n_rows, nrc, 4, 1.5 - 4 * m)
        uc = _catmull_rom_up(grid.n_cols, ncc, 4, 1.5 - 4 * m)
        up = ur @ torch.stack([ch, ca]) @ uc.T
        height = height + up[0]
        log_alb = log_alb + up[1]
        albedo = self.spec.albedo.mean * torch.exp(log_alb) * (1.0 + rel_alb).clamp(min=0.2)
        return height, albedo.clamp(max=1.0)

    def _features(self, grid: Grid, height: torch.Tensor, rel_alb: torch.Tensor, texel_m: float,
                  d_from: float = 0.0, d_below: float = math.inf) -> None:
        """Add craters and boulders with ``d_from <= D < d_below`` (weights from ``texel_m``)."""
        from .stamp import stamp
        spec = self.spec
        lo, hi = FEATURE_FADE_TEXELS
        c = spec.craters
        outs = [height.view(-1), rel_alb.view(-1)]
        for cat, reach, fn in ((self.craters, 2.0, None), (self.boulders, 1.0, None)):
            if not len(cat):
                continue
            w = band_weight(cat.d_m / texel_m, lo, hi) * ((cat.d_m >= d_from) & (cat.d_m < d_below))
            if cat is self.craters:
                def fn(r, d, f):
                    return (crater_profile(r, d, f, c.depth_ratio, c.rim_ratio),
                            ejecta_albedo(r, f, spec.albedo.ejecta_boost))
            else:
                boost = spec.albedo.boulder_boost

                def fn(r, d, f):
                    return boulder_profile(r, d), boost * (r < 1.0).to(r.dtype)
            stamp(outs, grid, cat.x_m, cat.y_m, cat.d_m, cat.fresh, w, reach, fn)

    def _noise(self, grid: Grid, which: str, lam_from: float = 0.0, lam_below: float = math.inf,
               texel_m: Optional[float] = None) -> torch.Tensor:
        """Band-limited fBm (height in m, or log-albedo) on a grid (octaves in [lam_from, lam_below))."""
        r = self.spec.relief
        if which == "height":
            args = dict(seed=self.seed * 2 + 1, max_wavelength_m=r.max_wavelength_m,
                        min_wavelength_m=r.min_wavelength_m, amplitude_at_1km=r.amplitude_m, hurst=r.hurst)
        else:
            args = dict(seed=self.seed * 2 + 2, max_wavelength_m=_ALBEDO_MAX_WAVELENGTH_M,
                        min_wavelength_m=r.min_wavelength_m, amplitude_at_1km=self.spec.albedo.variation,
                        hurst=_ALBEDO_HURST)
        lo, hi = NOISE_FADE_TEXELS
        x, y = grid.coords()
        return fbm(x, y, texel_m=texel_m or grid.spacing_m, lo_texels=lo, hi_texels=hi,
                   lam_from=lam_from, lam_below=lam_below, **args)

    # ---------------------------------------------------------------- public sampling
    def heightmap(self, extent_m: float, n: int, center_xy_m=(0.0, 0.0), device="cpu",
                  dtype: torch.dtype = torch.float32) -> Tuple[torch.Tensor, torch.Tensor]:
        """Height (m) and albedo on an n x n grid of texel centres covering a square of side
        ``extent_m`` centred on ``center_xy_m`` (map view: row 0 = north edge, row i -> y
        decreasing; column j -> x increasing), band-limited to the texel ``extent_m / n``.

        Returns:
            height_m: (n, n) ``dtype`` on ``device``, metres above the datum z = 0.
            albedo: (n, n) ``dtype`` on ``device``, normal albedo in (0, 1].
        """
        _check_extent(extent_m, n)
        grid = Grid.centered(center_xy_m, n, n, extent_m / n, 0.0)
        h, a = self.fields(grid)
        return h.to(device=device, dtype=dtype), a.to(device=device, dtype=dtype)

    def height_at_origin(self, texel_m: float) -> float:
        """Terrain height (m) at the landing point, band-limited to ``texel_m`` (4x4 grid mean of
        the four centre texels)."""
        grid = Grid.centered((0.0, 0.0), 2, 2, texel_m, 0.0)
        h, _ = self.fields(grid)
        return float(h.mean())

    def irradiance(self, extent_m: float, n: int, center_xy_m=(0.0, 0.0), ambient: float = 0.02,
                   device="cpu", dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """Shaded linear irradiance seen by a nadir camera, map view like :meth:`heightmap`.

        Lunar-Lambert photometry, cast shadows, ambient floor (see
        :func:`dvsland.terrain.photometry.shade`). Computed on a sun-aligned grid, then resampled.

        Returns:
            (n, n) ``dtype`` on ``device``, > 0.
        """
        from .photometry import shaded_sun_grid
        _check_extent(extent_m, n)
        s = extent_m / n
        m = int(math.ceil(n * math.sqrt(2))) + 4
        with compute_threads():
            irr, _, sgrid = shaded_sun_grid(self, center_xy_m, m, s, ambient)
        # resample onto the map-view grid
        ii, jj = torch.meshgrid(torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64),
                                indexing="ij")
        x, y = Grid.centered(center_xy_m, n, n, s, 0.0).world(ii, jj)
        ti, tj = sgrid.texel(x, y)
        gx = (tj + 0.5) / sgrid.n_cols * 2 - 1
        gy = (ti + 0.5) / sgrid.n_rows * 2 - 1
        g = torch.stack([gx, gy], dim=-1)[None].to(torch.float64)
        out = F.grid_sample(irr[None, None], g, mode="bilinear", align_corners=False)[0, 0]
        return out.to(device=device, dtype=dtype)


def _catmull_rom_up(n_fine: int, n_coarse: int, factor: int, first: float) -> torch.Tensor:
    """(n_fine, n_coarse) float64 Catmull-Rom interpolation matrix for coarse samples at fine
    index ``factor * I + first``. Exact for quadratics: no periodic slope ripple (PyTorch's bicubic
    with a = -0.75 leaves one, visible in the shading of smooth relief)."""
    c = (torch.arange(n_fine, dtype=torch.float64) - first) / factor
    i0 = torch.floor(c)
    t = c - i0
    t2, t3 = t * t, t * t * t
    w = torch.stack([(-t3 + 2 * t2 - t) / 2, (3 * t3 - 5 * t2 + 2) / 2, (-3 * t3 + 4 * t2 + t) / 2,
                     (t3 - t2) / 2], dim=1)
    idx = i0.to(torch.int64)[:, None] + torch.arange(-1, 3)[None, :]
    if int(idx.min()) < 0 or int(idx.max()) >= n_coarse:
        raise RuntimeError("coarse grid margin too small for cubic interpolation")
    out = torch.zeros(n_fine, n_coarse, dtype=torch.float64)
    out.scatter_add_(1, idx, w)
    return out


def _check_extent(extent_m: float, n: int) -> None:
    if not (extent_m > 0 and math.isfinite(extent_m)):
        raise ValueError(f"extent_m must be a positive finite length in metres, got {extent_m}")
    if not (isinstance(n, int) and 2 <= n <= 16384):
        raise ValueError(f"n must be an int in [2, 16384], got {n!r}")


_CACHE: dict = {}


def load_site(name: str, sun_elevation_deg: Optional[float] = None) -> Terrain:
    """The terrain of site ``name`` (configs/sites/<name>.yaml), optionally with the sun elevation
    overridden (degrees, [1, 90]). Cached per process. Unknown name -> ValueError listing A-I."""
    spec = load_spec(name).with_sun_elevation(sun_elevation_deg)
    key = spec.digest()
    if key not in _CACHE:
        _CACHE[key] = Terrain(spec)
    return _CACHE[key]
