"""Seeded 2-D gradient (Perlin) noise and band-limited fBm, evaluated at world points.

Lattice gradients come from a seeded permutation table (period 4096 cells, one table per
octave) and a fixed table of 16 unit vectors, so a value depends only on the point, the wavelength
and the seed: the terrain is continuous and any grid over it is reproducible bit for bit (float64 on
CPU). On the CPU each octave of :func:`fbm` runs as one compiled pass where a C++ compiler is found
(:mod:`dvsland.terrain.native_noise`), with the same bits as the torch passes here.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from . import native_noise

_PERIOD = 4096  # lattice period in cells (per octave; octaves have their own tables)
_ANG = torch.arange(16, dtype=torch.float64) * (2 * math.pi / 16) + math.pi / 16
_GRAD = torch.stack([torch.cos(_ANG), torch.sin(_ANG)], dim=-1).to(torch.float32)  # (16, 2)
_PERMS: dict = {}


def _tables(seed: int):
    """(perm (2 P,) int32, gx (2 P,) float32, gy (2 P,) float32) of ``seed``'s lattice, cached: the
    permutation table and the gradient of the cell each of its entries names (``_GRAD[perm & 15]``),
    so that a corner's gradient is one look-up (P = the lattice period)."""
    t = _PERMS.get(seed)
    if t is None:
        p = np.random.default_rng([0x5EED, int(seed) & 0xFFFFFFFF]).permutation(_PERIOD)
        perm = torch.from_numpy(np.concatenate([p, p]).astype(np.int64))
        g = _GRAD.index_select(0, perm & 15)
        t = (perm.to(torch.int32), g[:, 0].contiguous(), g[:, 1].contiguous())
        _PERMS[seed] = t
    return t


def _fade(t: torch.Tensor) -> torch.Tensor:
    return t * t * t * (t * (t * 6 - 15) + 10)


def perlin(x: torch.Tensor, y: torch.Tensor, seed: int) -> torch.Tensor:
    """Gradient noise at lattice coordinates (x, y) (float64, any shape) -> float32, about [-0.7, 0.7].

    Integer work in int32 and flat ``index_select`` look-ups (a third of the passes of indexing
    ``perm`` and then the gradient table per corner; the same values bit for bit)."""
    shape = x.shape
    x0 = torch.floor(x)
    y0 = torch.floor(y)
    fx = (x - x0).to(torch.float32).reshape(-1)  # fractions in float32: 4x less memory traffic
    fy = (y - y0).to(torch.float32).reshape(-1)
    m = _PERIOD - 1
    if x0.numel() and max(max(-float(v[0]), float(v[1])) for v in (torch.aminmax(x0), torch.aminmax(y0))) >= 2.0 ** 31:
        raise ValueError("perlin: lattice coordinates must lie within +-2^31 cells (a point too far away, "
                         "or a wavelength too small for it)")
    ix = x0.to(torch.int32).bitwise_and_(m).reshape(-1)  # exact below 2^31 cells (checked above)
    iy = y0.to(torch.int32).bitwise_and_(m).reshape(-1)
    perm, gxt, gyt = (t.to(x.device) for t in _tables(seed))
    fx1, fy1 = fx - 1, fy - 1

    def corner(i: torch.Tensor, ax: torch.Tensor, ay: torch.Tensor) -> torch.Tensor:
        # the gradient of lattice corner perm[i] dotted with the offset (ax, ay) from it
        return gxt.index_select(0, i) * ax + gyt.index_select(0, i) * ay

    j0 = perm.index_select(0, ix).add_(iy)  # perm[ix] + iy: corner (0, 0); + 1 for (0, 1)
    j1 = perm.index_select(0, ix.add_(1)).add_(iy)  # perm[ix + 1] + iy: corner (1, 0)
    u = _fade(fx)
    n0 = torch.lerp(corner(j0, fx, fy), corner(j1, fx1, fy), u)
    n1 = torch.lerp(corner(j0.add_(1), fx, fy1), corner(j1.add_(1), fx1, fy1), u)
    return torch.lerp(n0, n1, _fade(fy)).view(shape)


def band_weight(size_over_texel: torch.Tensor | float, lo: float, hi: float):
    """Smooth fade-in of a feature of size ``size`` on a grid of spacing ``texel``: 0 below ``lo``
    texels, 1 above ``hi`` texels (smoothstep), so features appear gradually across levels."""
    if isinstance(size_over_texel, torch.Tensor):
        t = ((size_over_texel - lo) / (hi - lo)).clamp(0.0, 1.0)
    else:
        t = min(max((size_over_texel - lo) / (hi - lo), 0.0), 1.0)
    return t * t * (3 - 2 * t)


def fbm(x_m: torch.Tensor, y_m: torch.Tensor, seed: int, texel_m: float, max_wavelength_m: float,
        min_wavelength_m: float, amplitude_at_1km: float, hurst: float,
        lo_texels: float = 4.0, hi_texels: float = 8.0, lam_from: float = 0.0,
        lam_below: float = float("inf")) -> torch.Tensor:
    """Band-limited fractional Brownian motion at world points (float64, metres).

    Octaves of wavelength lambda = max_wavelength / 2^k down to ``min_wavelength``, amplitude
    ``amplitude_at_1km * (lambda / 1000)^hurst``; an octave fades in between ``lo_texels`` and
    ``hi_texels`` texels per wavelength, so nothing finer than the grid can show is added.
    Only octaves with ``lam_from <= lambda < lam_below`` are summed (to split the work in tiers).
    """
    out = torch.zeros_like(x_m)
    kern = _octave_kernel(x_m, y_m, out)
    lam = max_wavelength_m
    k = 0
    while lam >= min_wavelength_m * 0.999:
        w = band_weight(lam / texel_m, lo_texels, hi_texels)
        if w <= 0.0:
            break
        if lam_from <= lam < lam_below:
            amp = amplitude_at_1km * (lam / 1000.0) ** hurst * w
            # per-octave offset decorrelates the lattices of neighbouring octaves
            off = 0.5 + 0.37 * k
            s = seed * 131 + k
            # the compiled octave where it runs (native_noise: the same bits), else torch's passes
            if kern is None or not kern.add_octave(x_m, y_m, lam, off, amp, _tables(s), _PERIOD, out):
                out += amp * perlin(x_m / lam + off, y_m / lam - off, s)
        lam *= 0.5
        k += 1
    return out


def _octave_kernel(x_m: torch.Tensor, y_m: torch.Tensor, out: torch.Tensor):
    """:mod:`dvsland.terrain.native_noise`'s kernels where they take these points (contiguous CPU
    float64 of one shape) and are enabled, else None."""
    ok = (x_m.dtype == y_m.dtype == torch.float64 and x_m.device.type == "cpu" and y_m.device.type == "cpu"
          and x_m.shape == y_m.shape and x_m.is_contiguous() and y_m.is_contiguous())
    return native_noise.kernel_for(out) if ok else None
