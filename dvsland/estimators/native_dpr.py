"""Compiled flat-kernel mean-shift and Density Peaks Ranking scores of ``dpr`` (CPU), identical to the
torch path.

:func:`dvsland.estimators.meanshift.meanshift_flat` moves each seed to the count-weighted mean of
the pixels within R of it until it moves less than the tolerance. Its torch path runs a dozen small
tensor operations per iteration, which on a CPU cost far more than the arithmetic. This kernel runs
the same iterations seed by seed. It is used where the window's counts are whole numbers and every
patch sum stays below 2^24 (the paper's settings: ``hot_pixel_factor = 0``): then every sum of the
torch path is exact in float32, whatever its order, and the kernel's per-seed arithmetic is the
torch path's operation for operation (float32 fractions, squared offsets, the division, the clamp,
and the step length as ``sqrt(fma(dy, dy, dx dx))``, as torch's ``vector_norm`` computes it). Anywhere
else (fractional counts from the hot-pixel cap, larger sums) it reports so and the torch path runs.
Tests pin the two to equality.

``peak_scores`` is Density Peaks Ranking's blur, local maxima and scores in one pass per image
(:func:`dvsland.estimators.density_peaks.density_peaks` uses it after checking its bits against the
torch path's once per process).

Plain C++ behind a C interface, compiled on first use where a C++ compiler is found (about a second;
:class:`dvsland.native_build.NativeLibrary`). ``DVSLAND_NATIVE_DPR`` (or :func:`use_native_dpr`) picks
the mode: ``auto`` (default), ``1`` / ``on``, ``0`` / ``off`` (as ``DVSLAND_NATIVE_CMAX``).
"""

from __future__ import annotations

import ctypes
import math
from typing import Optional, Tuple

import torch

from dvsland.native_build import CLONES, NativeLibrary, bind_functions, tensor_address

_SRC = r"""
#include <cmath>
#include <cstdint>
#include <vector>

""" + CLONES + r"""
// Density Peaks Ranking's scores of B images (H x W float32, contiguous): the separable Gaussian blur
// (rows with kx, then columns with ky, k taps each, zero border) as a chain in tap order from 0 of
// fused multiply-adds (how oneDNN's depthwise convolution of two images or more sums; the torch path
// blurs a single image as the first of two), checked against torch at first use; the k_nms x k_nms
// running maximum (-inf outside), and score = blurred where it is a local maximum above min_density,
// else -1. tmp: (H, W) and row: (2 W + k,) float32 scratch.
DVS_INLINE float madd(float x, float w, float acc) { return __builtin_fmaf(x, w, acc); }

DVS_INLINE void blur_rows_cols(const float* img, int64_t H, int64_t W, const float* kx, const float* ky, int64_t k,
                               float* o, float* tmp, float* pad) {
  const int64_t r = k / 2;
  constexpr int64_t BJ = 64;  // outputs per block: four AVX-512 accumulators held in registers over the taps
  const float* __restrict x = img;
  for (int64_t y = 0; y < H; ++y) {  // rows: tmp[y][j] = sum_t x[y][j + t - r] kx[t] (a border tap adds +0)
    for (int64_t j = 0; j < W; ++j) pad[r + j] = x[y * W + j];
    float* __restrict h = tmp + y * W;
    int64_t j = 0;
    for (; j + BJ <= W; j += BJ) {
      float acc[BJ] = {};
      for (int64_t t = 0; t < k; ++t) {
        const float w = kx[t];
        for (int64_t u = 0; u < BJ; ++u) acc[u] = madd(pad[j + u + t], w, acc[u]);
      }
      for (int64_t u = 0; u < BJ; ++u) h[j + u] = acc[u];
    }
    for (; j < W; ++j) {
      float a = 0.0f;
      for (int64_t t = 0; t < k; ++t) a = madd(pad[j + t], kx[t], a);
      h[j] = a;
    }
  }
  for (int64_t y = 0; y < H; ++y) {  // columns: o[y][j] = sum_t tmp[y + t - r][j] ky[t] (rows outside: +0)
    const int64_t t0 = y - r < 0 ? r - y : 0, t1 = y + r >= H ? H - 1 - y + r + 1 : k;
    float* __restrict oy = o + y * W;
    int64_t j = 0;
    for (; j + BJ <= W; j += BJ) {
      float acc[BJ] = {};
      for (int64_t t = t0; t < t1; ++t) {
        const float* __restrict hr = tmp + (y + t - r) * W + j;
        const float w = ky[t];
        for (int64_t u = 0; u < BJ; ++u) acc[u] = madd(hr[u], w, acc[u]);
      }
      for (int64_t u = 0; u < BJ; ++u) oy[j + u] = acc[u];
    }
    for (; j < W; ++j) {
      float a = 0.0f;
      for (int64_t t = t0; t < t1; ++t) a = madd(tmp[(y + t - r) * W + j], ky[t], a);
      oy[j] = a;
    }
  }
}

DVS_CLONES static void peak_scores(const float* img, int64_t B, int64_t H, int64_t W, const float* kx, const float* ky,
                                   int64_t k, int64_t k_nms, float min_density, float* blur, float* score, float* tmp,
                                   float* row) {
  const int64_t r = k / 2, rn = k_nms / 2;
  float* __restrict pad = row + W;  // one zero-bordered input row (W + 2 r)
  for (int64_t j = 0; j < r; ++j) pad[j] = pad[W + r + j] = 0.0f;
  for (int64_t b = 0; b < B; ++b) {
    float* __restrict o = blur + b * H * W;
    blur_rows_cols(img + b * H * W, H, W, kx, ky, k, o, tmp, pad);
    // the running maximum (exact in any order), separably: along rows into tmp, then down the columns
    for (int64_t y = 0; y < H; ++y) {
      const float* __restrict oy = o + y * W;
      float* __restrict hm = tmp + y * W;
      for (int64_t j = 0; j < W; ++j) hm[j] = oy[j];
      for (int64_t d = 1; d <= rn && d < W; ++d) {
        for (int64_t j = 0; j < W - d; ++j) hm[j] = std::max(hm[j], oy[j + d]);
        for (int64_t j = d; j < W; ++j) hm[j] = std::max(hm[j], oy[j - d]);
      }
    }
    for (int64_t y = 0; y < H; ++y) {
      float* __restrict m = row;
      const float* __restrict t0 = tmp + y * W;
      for (int64_t j = 0; j < W; ++j) m[j] = t0[j];
      for (int64_t yy = y - rn; yy <= y + rn; ++yy) {
        if (yy < 0 || yy >= H || yy == y) continue;
        const float* __restrict t = tmp + yy * W;
        for (int64_t j = 0; j < W; ++j) m[j] = std::max(m[j], t[j]);
      }
      const float* __restrict v = o + y * W;
      float* __restrict sc = score + b * H * W + y * W;
      for (int64_t j = 0; j < W; ++j) sc[j] = (v[j] >= m[j] && v[j] > min_density) ? v[j] : -1.0f;
    }
  }
}

extern "C" void dpr_peak_scores(const float* img, int64_t B, int64_t H, int64_t W, const float* kx, const float* ky,
                                int64_t k, int64_t k_nms, float min_density, float* blur, float* score) {
  std::vector<float> tmp(size_t(H * W)), row(static_cast<size_t>(2 * W + k));
  peak_scores(img, B, H, W, kx, ky, k, k_nms, min_density, blur, score, tmp.data(), row.data());
}

// The window of seed (cx, cy) on image img (Hp x Wp, float32): the sums (w, w dx, w dy) of the counts
// of the P x P patch from row/column s0 + floor(c) whose pixel centres lie within r2 (squared, float32)
// of c, as float32 (exact: checked whole numbers with |sums| < 2^24). Returns false where that does
// not hold (the torch path then runs).
static bool window(const float* img, int64_t Wp, int64_t s0, int64_t P, int64_t r_int, float cx, float cy, float r2,
                   float out[3]) {
  if (!(std::isfinite(cx) && std::isfinite(cy))) return false;
  const float bx = std::floor(cx), by = std::floor(cy);
  const float fx = cx - bx, fy = cy - by;
  float d2x[64], d2y[64];
  for (int64_t k = 0; k < P; ++k) {
    const float off = float(k - r_int);
    const float ex = off - fx, ey = off - fy;
    d2x[k] = ex * ex;
    d2y[k] = ey * ey;
  }
  const float* row0 = img + (s0 + int64_t(by)) * Wp + s0 + int64_t(bx);
  double s = 0.0, sx = 0.0, sy = 0.0;
  for (int64_t i = 0; i < P; ++i) {
    const float* row = row0 + i * Wp;
    for (int64_t j = 0; j < P; ++j) {
      if (!(d2x[j] + d2y[i] <= r2)) continue;
      const float v = row[j];
      if (v != 0.0f && v != std::nearbyint(v)) return false;  // not a whole number
      s += v;
      sx += double(v) * double(j - r_int);
      sy += double(v) * double(i - r_int);
    }
  }
  const double lim = 16777216.0;  // 2^24
  if (!(std::fabs(s) < lim && std::fabs(sx) < lim && std::fabs(sy) < lim)) return false;
  out[0] = float(s); out[1] = float(sx); out[2] = float(sy);
  return true;
}

// Mean-shift of B x N seeds (xy, float32, in/out) on B images of Hp x Wp (the sensor W x H inside a zero
// border of `have` px); valid (B N) bytes; counts (B N) float32 out. Returns the iterations run, or -1
// (outputs unspecified) where the window sums are not exact (see window).
extern "C" int64_t dpr_meanshift(const float* img, int64_t B, int64_t Hp, int64_t Wp, int64_t have, int64_t W,
                                 int64_t H, float* xy, const uint8_t* valid, int64_t N, double radius, int64_t iters,
                                 double tol_px, float* counts) {
  const int64_t r_int = int64_t(std::ceil(radius)), P = 2 * r_int + 2, s0 = have - r_int;
  if (P > 64 || s0 < 1) return -1;
  const float r2 = float(radius * radius), tol = float(tol_px), hx = float(W - 1), hy = float(H - 1);
  const bool tol_pos = tol_px > 0;
  auto clampc = [](float v, float hi) { v = v < 0.0f ? 0.0f : v; return v > hi ? hi : v; };
  std::vector<int64_t> act, next;
  for (int64_t k = 0; k < B * N; ++k) {
    float* c = xy + 2 * k;
    c[0] = valid[k] ? clampc(c[0], hx) : 0.0f;
    c[1] = valid[k] ? clampc(c[1], hy) : 0.0f;
    if (valid[k]) act.push_back(k);
  }
  int64_t n_iter = 0;
  float m[3];
  for (int64_t it = 0; it < iters && !act.empty(); ++it) {
    ++n_iter;
    next.clear();
    for (const int64_t k : act) {
      float* c = xy + 2 * k;
      if (!window(img + (k / N) * Hp * Wp, Wp, s0, P, r_int, c[0], c[1], r2, m)) return -1;
      const bool empty = m[0] <= 0.0f;
      const float sc = m[0] < 1e-12f ? 1e-12f : m[0];
      float nx = std::floor(c[0]) + m[1] / sc, ny = std::floor(c[1]) + m[2] / sc;
      nx = empty ? c[0] : clampc(nx, hx);
      ny = empty ? c[1] : clampc(ny, hy);
      const float dx = nx - c[0], dy = ny - c[1];
      const bool still = std::sqrt(std::fma(dy, dy, dx * dx)) >= tol && (tol_pos || !empty);
      c[0] = nx; c[1] = ny;
      if (still) next.push_back(k);
    }
    act.swap(next);
  }
  for (int64_t k = 0; k < B * N; ++k) {
    float* c = xy + 2 * k;
    if (!window(img + (k / N) * Hp * Wp, Wp, s0, P, r_int, c[0], c[1], r2, m)) return -1;
    counts[k] = valid[k] ? m[0] : 0.0f;
    if (!(valid[k] && counts[k] > 0.0f)) { c[0] = NAN; c[1] = NAN; }
  }
  return n_iter;
}
"""

_CFLAGS = ["-O3", "-ffp-contract=off", "-std=c++17"]
_I64, _F64, _P = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
#: the C function's (argument types, result type)
_SIGNATURES = {"dpr_meanshift": ([_P] + [_I64] * 6 + [_P, _P, _I64, _F64, _I64, _F64, _P], _I64),
               "dpr_peak_scores": ([_P, _I64, _I64, _I64, _P, _P, _I64, _I64, ctypes.c_float, _P, _P], None)}


class Kernels:
    """The loaded library's mean-shift and peak scores on torch tensors (CPU)."""

    def __init__(self, lib: ctypes.CDLL):
        lib = bind_functions(lib, _SIGNATURES)
        self._f, self._scores = lib.dpr_meanshift, lib.dpr_peak_scores

    def peak_scores(self, img: torch.Tensor, kx: torch.Tensor, ky: torch.Tensor, nms_px: int,
                    min_density: float) -> Tuple[torch.Tensor, torch.Tensor]:
        """(blurred (B, H, W), score (B, H, W)) float32 of images ``img`` (B, H, W) float32: the blur
        with the 1-d kernels ``kx`` (along W) and ``ky`` (along H), (1, k) float32 each, zero border, the
        ``nms_px`` running maximum and score = blurred at a local maximum above ``min_density``, else -1
        (:func:`~dvsland.estimators.density_peaks.density_peaks`' steps). The blur's sums run in tap
        order as fused multiply-adds."""
        B, H, W = img.shape
        k = kx.numel()
        if ky.numel() != k or k % 2 != 1 or int(nms_px) % 2 != 1:
            raise RuntimeError(f"peak_scores: odd kernels of one length and an odd nms_px, got {kx.numel()}, "
                               f"{ky.numel()}, {nms_px}")
        ptr = [tensor_address(t, torch.float32, f"peak_scores: {n}") for n, t in (("img", img), ("kx", kx), ("ky", ky))]
        blur, score = torch.empty(B, H, W, dtype=torch.float32), torch.empty(B, H, W, dtype=torch.float32)
        self._scores(ptr[0], B, H, W, ptr[1], ptr[2], k, int(nms_px), float(min_density), blur.data_ptr(),
                     score.data_ptr())
        return blur, score

    def meanshift(self, img: torch.Tensor, have: int, W: int, H: int, seeds: torch.Tensor, valid: torch.Tensor,
                  radius_px: float, iters: int, tol_px: float) -> Optional[Tuple[torch.Tensor, torch.Tensor, int]]:
        """:func:`~dvsland.estimators.meanshift.meanshift_flat` on ``img`` (B, Hp, Wp) float32 holding
        the W x H sensor inside a zero border of ``have`` px; (centroids (B, N, 2), counts (B, N),
        iterations), or None where the window sums are not exact (the torch path must run)."""
        B, N = valid.shape
        img = img.to(torch.float32).contiguous()
        xy = seeds.to(torch.float32).contiguous().clone()
        ok = valid.to(torch.uint8).contiguous()
        counts = torch.empty(B, N, dtype=torch.float32)
        n = self._f(img.data_ptr(), B, img.shape[1], img.shape[2], int(have), int(W), int(H), xy.data_ptr(),
                    ok.data_ptr(), N, float(radius_px), int(iters), float(tol_px), counts.data_ptr())
        return None if n < 0 else (xy, counts, int(n))


#: the library (its mode, cache and build: ``LIBRARY.build()``, ``LIBRARY.cached()``, ``LIBRARY.build_dir()``)
LIBRARY = _LIB = NativeLibrary("dvsland_dpr_native", _SRC, _CFLAGS, "DVSLAND_NATIVE_DPR",
                               "dvsland.estimators.native_dpr", Kernels)


def use_native_dpr(on: Optional[bool] = True) -> None:
    """Pick the mode for this process: True = on, False = off, None = back to ``DVSLAND_NATIVE_DPR``."""
    _LIB.use(on)


def kernel_for(t: torch.Tensor) -> Optional[Kernels]:
    """The kernel for work on ``t``'s device where enabled (built once when needed), else None."""
    return _LIB.kernel_for(t)


def fits(radius_px: float, image_pad_px: int) -> bool:
    """Whether the kernel takes this radius and border (patches up to 64 px, a border of ceil(R) + 1 px)."""
    r_int = int(math.ceil(radius_px))
    return 2 * r_int + 2 <= 64 and image_pad_px >= r_int + 1


__all__ = ["Kernels", "LIBRARY", "use_native_dpr", "kernel_for", "fits"]
