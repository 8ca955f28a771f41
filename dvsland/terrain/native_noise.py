"""Compiled octaves of the terrain's gradient noise (CPU), identical to the torch path.

An octave of :func:`dvsland.terrain.noise.fbm` is, per world point, the lattice coordinates
(x / lambda + offset, float64), the Perlin noise there (:func:`~dvsland.terrain.noise.perlin`: the
four corners' gradients from the seed's tables, two fades and three blends, float32) and its
weighted sum into the field (float64). The torch path runs that as about forty tensor passes per
octave; this kernel runs it point by point in one. Its arithmetic is the torch path's, operation for
operation: every multiply and add rounded on its own (``-ffp-contract=off``), and ``lerp`` as
PyTorch's CPU kernel computes it (a fused multiply-add from the nearer end), so the terrain is the
same to the bit (tests compare fields and prepared levels).

Plain C++ behind a C interface, built on first use where a C++ compiler is found
(:class:`dvsland.native_build.NativeLibrary`). ``DVSLAND_NATIVE_TERRAIN`` (or
:func:`use_native_noise`) picks the mode: ``auto`` (default), ``1`` / ``on``, ``0`` / ``off``.
"""

from __future__ import annotations

import ctypes
from typing import Optional

import torch

from dvsland.native_build import CLONES, NativeLibrary, bind_functions, tensor_address

_SRC = r"""
#include <cmath>
#include <cstdint>

""" + CLONES + r"""
// torch.lerp on a CPU: from the nearer end, one fused multiply-add
DVS_INLINE float lerp(float a, float b, float w) {
  return __builtin_fabsf(w) < 0.5f ? __builtin_fmaf(w, b - a, a) : __builtin_fmaf(w - 1.0f, b - a, b);
}
DVS_INLINE float fade(float t) { return t * t * t * (t * (t * 6.0f - 15.0f) + 10.0f); }

DVS_CLONES static void octave(const double* __restrict x, const double* __restrict y, int64_t n, double lam,
                              double off, float a, const int32_t* __restrict perm, const float* __restrict gx,
                              const float* __restrict gy, int32_t m, double* __restrict out) {
  for (int64_t i = 0; i < n; ++i) {
    const double px = x[i] / lam + off, py = y[i] / lam - off;
    const double x0 = __builtin_floor(px), y0 = __builtin_floor(py);
    const float fx = float(px - x0), fy = float(py - y0);
    const int32_t ix = int32_t(x0) & m, iy = int32_t(y0) & m;
    const float fx1 = fx - 1.0f, fy1 = fy - 1.0f;
    const int32_t j0 = perm[ix] + iy, j1 = perm[ix + 1] + iy;
    const float u = fade(fx);
    const float n0 = lerp(gx[j0] * fx + gy[j0] * fy, gx[j1] * fx1 + gy[j1] * fy, u);
    const float n1 = lerp(gx[j0 + 1] * fx + gy[j0 + 1] * fy1, gx[j1 + 1] * fx1 + gy[j1 + 1] * fy1, u);
    out[i] += double(a * lerp(n0, n1, fade(fy)));
  }
}

extern "C" {

// out[i] += float(amp) * perlin(x[i] / lam + off, y[i] / lam - off) for n points (float64 x, y, out);
// perm (2 P,) int32, gx, gy (2 P,) float32 the seed's tables, P a power of two. Returns 0, or -1 (nothing
// written; the torch path raises the error) where a lattice coordinate lies outside +-2^31 cells.
int64_t noise_octave(const double* x, const double* y, int64_t n, double lam, double off, double amp,
                     const int32_t* perm, const float* gx, const float* gy, int64_t period, double* out) {
  for (int64_t i = 0; i < n; ++i) {
    const double x0 = std::floor(x[i] / lam + off), y0 = std::floor(y[i] / lam - off);
    if (!(std::fabs(x0) < 2147483648.0 && std::fabs(y0) < 2147483648.0)) return -1;
  }
  octave(x, y, n, lam, off, float(amp), perm, gx, gy, int32_t(period - 1), out);
  return 0;
}

}
"""

# every operation rounded on its own, as the torch path's separate passes (the fma above are lerp's own);
# -fno-trapping-math lets the compiler vectorise lerp's two-sided select (no value changes, only whether
# floating-point exception flags could be raised)
_CFLAGS = ["-O3", "-ffp-contract=off", "-fno-trapping-math", "-std=c++17"]
_ENV = "DVSLAND_NATIVE_TERRAIN"
_I64, _F64, _P = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
#: the C function's (argument types, result type)
_SIGNATURES = {"noise_octave": ([_P, _P, _I64, _F64, _F64, _F64, _P, _P, _P, _I64, _P], _I64)}


class Kernels:
    """The loaded library's octave on torch tensors (CPU)."""

    def __init__(self, lib: ctypes.CDLL):
        self._f = bind_functions(lib, _SIGNATURES).noise_octave

    def add_octave(self, x_m: torch.Tensor, y_m: torch.Tensor, lam: float, off: float, amp: float, tables,
                   period: int, out: torch.Tensor) -> bool:
        """``out += amp * perlin(x_m / lam + off, y_m / lam - off)`` in place (float64, contiguous, CPU,
        one shape); ``tables`` = (perm int32, gx, gy float32) of the octave's seed. False (``out``
        untouched) where a lattice coordinate is out of range."""
        perm, gx, gy = tables
        if not (x_m.shape == y_m.shape == out.shape) or perm.numel() != 2 * period:
            raise RuntimeError("noise_octave: x_m, y_m and out must share a shape; perm holds 2 x period entries")
        ptr = {name: tensor_address(t, dt, f"noise_octave: {name}") for name, t, dt in (
            ("x_m", x_m, torch.float64), ("y_m", y_m, torch.float64), ("out", out, torch.float64),
            ("perm", perm, torch.int32), ("gx", gx, torch.float32), ("gy", gy, torch.float32))}
        return self._f(ptr["x_m"], ptr["y_m"], out.numel(), float(lam), float(off), float(amp), ptr["perm"],
                       ptr["gx"], ptr["gy"], int(period), ptr["out"]) == 0


#: the library (its mode, cache and build)
LIBRARY = NativeLibrary("dvsland_terrain_native", _SRC, _CFLAGS, _ENV, "dvsland.terrain.native_noise", Kernels)


def use_native_noise(on: Optional[bool] = True) -> None:
    """Pick the mode for this process: True = on, False = off, None = back to ``DVSLAND_NATIVE_TERRAIN``."""
    LIBRARY.use(on)


def kernel_for(t: torch.Tensor) -> Optional[Kernels]:
    """The kernel for work on ``t``'s device where enabled (built once when needed), else None."""
    return LIBRARY.kernel_for(t)


__all__ = ["Kernels", "LIBRARY", "use_native_noise", "kernel_for"]
