"""Compiled splat-and-sum kernel of ``cmax``'s score (CPU), identical to the torch path.

:func:`dvsland.estimators.contrast.split_contrast` splats every warped event (bilinear, four
corners) into one image per element, candidate and half of the events, and needs per image the
total weight and the sums of squares and cross products. The torch path builds all images at once
(one large canvas, B x G x 2 images); this kernel takes the events element by element (a counting
sort by element), splats them into one small canvas per (element, candidate) that stays in the
cache, and sums only the rows touched. Corner weights are integers (multiples of 2^-12 of an
event, see ``WEIGHT_UNIT`` in contrast.py) and the sums are int64, so the kernel's sums are the
torch path's exactly, in any order and on any number of threads; its float32 arithmetic (warp,
box test, corner weights) is the torch path's operation for operation (the exponential comes in
from torch). Tests pin the two to equality.

Compiled once with the C++ compiler through ``torch.utils.cpp_extension.load_inline`` into
torch's extension folder, under a name that carries a hash of the source, flags and versions.
``DVSLAND_NATIVE_CMAX`` (or :func:`use_native_cmax`) picks the mode:

- ``auto`` (default, also when unset or empty): use the kernel when its build is cached (nothing
  is compiled), else the torch path, silently.
- ``1`` / ``on`` / ``true`` / ``yes``: build on first use when not cached, then use it.
- ``0`` / ``off`` / ``false`` / ``no``: never use it.

Build once with ``python -m dvsland.estimators.build_native``. Without a compiler (or on any build
or load error) the torch path runs, with one warning.
"""

from __future__ import annotations

import platform
from pathlib import Path
from typing import Optional

import torch

from dvsland.native_build import (AUTO, OFF, ON, build_extension, extension_cached, extension_dir, extension_name,
                                  load_or_warn, mode_from_env)

_SRC = r"""
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <vector>

// Per element b and candidate g: n[b,g,h] = sum of the integer corner weights of half h, and
// s[b,g,:] = (sum_p I0^2, sum_p I1^2, sum_p I0 I1) over the canvas pixels p; see the module doc
// of dvsland/estimators/native_cmax.py and split_contrast in contrast.py (the torch path).
std::vector<torch::Tensor> splat_sums(torch::Tensor xc, torch::Tensor yc, torch::Tensor b, torch::Tensor half,
                                      torch::Tensor scale, torch::Tensor ginv, torch::Tensor wt,
                                      double cx, double cy, double x_lo, double x_hi, double y_lo, double y_hi,
                                      int64_t Hc, int64_t Wc, double unit) {
  auto f32 = torch::kFloat32;
  TORCH_CHECK(xc.is_contiguous() && yc.is_contiguous() && wt.is_contiguous() && xc.scalar_type() == f32 &&
              yc.scalar_type() == f32 && wt.scalar_type() == f32, "splat_sums: xc, yc, wt contiguous float32");
  TORCH_CHECK(b.is_contiguous() && half.is_contiguous() && b.scalar_type() == torch::kInt64 &&
              half.scalar_type() == torch::kInt64, "splat_sums: b, half contiguous int64");
  TORCH_CHECK(scale.is_contiguous() && ginv.is_contiguous() && scale.scalar_type() == f32 &&
              ginv.scalar_type() == f32 && scale.dim() == 2 && ginv.dim() == 2, "splat_sums: scale (G,E), ginv (G,B) float32");
  const int64_t E = xc.numel(), G = scale.size(0), B = ginv.size(1), P = Hc * Wc;
  TORCH_CHECK(scale.size(1) == E && ginv.size(0) == G && yc.numel() == E && b.numel() == E && half.numel() == E &&
              wt.numel() == E && Hc >= 2 && Wc >= 2, "splat_sums: shapes");
  const float* X = xc.data_ptr<float>();
  const float* Y = yc.data_ptr<float>();
  const float* S = scale.data_ptr<float>();
  const float* GI = ginv.data_ptr<float>();
  const float* W = wt.data_ptr<float>();
  const int64_t* Bi = b.data_ptr<int64_t>();
  const int64_t* Hf = half.data_ptr<int64_t>();
  std::vector<int64_t> start(B + 1, 0), order(E);
  for (int64_t e = 0; e < E; ++e) {
    TORCH_CHECK(Bi[e] >= 0 && Bi[e] < B && (Hf[e] == 0 || Hf[e] == 1), "splat_sums: b out of [0, B) or half not 0/1");
    start[Bi[e] + 1]++;
  }
  for (int64_t i = 0; i < B; ++i) start[i + 1] += start[i];
  {
    std::vector<int64_t> pos(start.begin(), start.end() - 1);
    for (int64_t e = 0; e < E; ++e) order[pos[Bi[e]]++] = e;
  }
  auto n = torch::zeros({B, G, 2}, torch::kInt64);
  auto s = torch::zeros({B, G, 3}, torch::kInt64);
  int64_t* N = n.data_ptr<int64_t>();
  int64_t* Sq = s.data_ptr<int64_t>();
  const float fcx = (float)cx, fcy = (float)cy, uf = (float)unit;
  const float lox = (float)(x_lo - cx), hix = (float)(x_hi - cx), loy = (float)(y_lo - cy), hiy = (float)(y_hi - cy);
  const float xmax = (float)(Wc - 2), ymax = (float)(Hc - 2);
  at::parallel_for(0, B, 1, [&](int64_t lo, int64_t hi) {
    std::vector<int32_t> canvas32(2 * P, 0);
    std::vector<int64_t> canvas64;
    std::vector<float> ex, ey, ew, es;
    std::vector<int64_t> eh, touched;
    for (int64_t bi = lo; bi < hi; ++bi) {
      const int64_t n_e = start[bi + 1] - start[bi];
      if (n_e == 0) continue;
      // the element's events, contiguous (read G times); an int32 canvas when no pixel can
      // reach 2^31 (every pixel holds at most the element's whole weight), else int64
      ex.resize(n_e); ey.resize(n_e); ew.resize(n_e); eh.resize(n_e); es.resize(n_e);
      double total = 0.0;
      for (int64_t k = 0; k < n_e; ++k) {
        const int64_t e = order[start[bi] + k];
        ex[k] = X[e]; ey[k] = Y[e]; ew[k] = W[e]; eh[k] = Hf[e] * P;
        total += std::fabs((double)W[e]) * unit + 4.0;
      }
      const bool wide = !(total < 2147483647.0);
      if (wide && canvas64.empty()) canvas64.assign(2 * P, 0);
      for (int64_t g = 0; g < G; ++g) {
        const float* Sg = S + g * E;
        for (int64_t k = 0; k < n_e; ++k) es[k] = Sg[order[start[bi] + k]];
        const float gi = GI[g * B + bi];
        const float xl = lox * gi, xh = hix * gi, yl = loy * gi, yh = hiy * gi;
        // the sums are kept as the splat goes: adding q to pixel value v of half h (the other half
        // holding u there) adds q (2 v + q) to sum I_h^2 and q u to sum I0 I1; the touched corners are
        // cleared afterwards (integers: the same sums as a pass over the finished images)
        int64_t acc[5] = {0, 0, 0, 0, 0};  // n0, n1, s0, s1, s01
        touched.clear();
        for (int64_t k = 0; k < n_e; ++k) {
          const float sc = es[k];
          const float xw = (ex[k] - fcx) * sc;
          const float yw = (ey[k] - fcy) * sc;
          if (!(xw >= xl && xw <= xh && yw >= yl && yw <= yh)) continue;  // weight 0: adds nothing
          const float w = ew[k];
          const float xs = xw + fcx, ys = yw + fcy;
          const float x0 = std::min(std::max(std::floor(xs), 0.0f), xmax);
          const float y0 = std::min(std::max(std::floor(ys), 0.0f), ymax);
          const float fx = std::min(std::max(xs - x0, 0.0f), 1.0f);
          const float fy = std::min(std::max(ys - y0, 0.0f), 1.0f);
          const float wy1 = w * fy;
          const float wy0 = w - wy1;
          const float a = wy0 * fx, c = wy1 * fx;
          const float w00 = wy0 - a, w10 = wy1 - c;
          const int64_t q[4] = {(int64_t)std::nearbyint(w00 * uf), (int64_t)std::nearbyint(a * uf),
                                (int64_t)std::nearbyint(w10 * uf), (int64_t)std::nearbyint(c * uf)};
          const int64_t h = eh[k] ? 1 : 0;
          const int64_t at = eh[k] + (int64_t)y0 * Wc + (int64_t)x0;
          const int64_t other = at + (h ? -P : P);
          const int64_t d[4] = {0, 1, Wc, Wc + 1};
          if (wide) {
            int64_t* cv = canvas64.data();
            for (int j = 0; j < 4; ++j) {
              const int64_t v = cv[at + d[j]], u = cv[other + d[j]];
              acc[h] += q[j]; acc[2 + h] += q[j] * (2 * v + q[j]); acc[4] += q[j] * u;
              cv[at + d[j]] = v + q[j];
            }
          } else {
            int32_t* cv = canvas32.data();
            for (int j = 0; j < 4; ++j) {
              const int64_t v = cv[at + d[j]], u = cv[other + d[j]];
              acc[h] += q[j]; acc[2 + h] += q[j] * (2 * v + q[j]); acc[4] += q[j] * u;
              cv[at + d[j]] = (int32_t)(v + q[j]);
            }
          }
          touched.push_back(at);
        }
        for (const int64_t at : touched) {
          if (wide) {
            int64_t* cv = canvas64.data() + at;
            cv[0] = 0; cv[1] = 0; cv[Wc] = 0; cv[Wc + 1] = 0;
          } else {
            int32_t* cv = canvas32.data() + at;
            cv[0] = 0; cv[1] = 0; cv[Wc] = 0; cv[Wc + 1] = 0;
          }
        }
        const int64_t n0 = acc[0], n1 = acc[1], s0 = acc[2], s1 = acc[3], s01 = acc[4];
        const int64_t j = bi * G + g;
        N[j * 2] = n0; N[j * 2 + 1] = n1;
        Sq[j * 3] = s0; Sq[j * 3 + 1] = s1; Sq[j * 3 + 2] = s01;
      }
    }
  });
  return {n, s};
}

// For each event, how many events of its element lie on its pixel: bincount(b * n_px + px)[b * n_px + px]
// computed element by element in a small canvas (b (E,) int64 in [0, B), px (E,) int64 in [0, n_px)).
torch::Tensor pixel_counts(torch::Tensor b, torch::Tensor px, int64_t B, int64_t n_px) {
  TORCH_CHECK(b.is_contiguous() && px.is_contiguous() && b.scalar_type() == torch::kInt64 &&
              px.scalar_type() == torch::kInt64 && b.numel() == px.numel(), "pixel_counts: b, px contiguous int64 (E,)");
  const int64_t E = b.numel();
  const int64_t* Bi = b.data_ptr<int64_t>();
  const int64_t* Px = px.data_ptr<int64_t>();
  std::vector<int64_t> start(B + 1, 0), order(E);
  for (int64_t e = 0; e < E; ++e) {
    TORCH_CHECK(Bi[e] >= 0 && Bi[e] < B && Px[e] >= 0 && Px[e] < n_px, "pixel_counts: b or px out of range");
    start[Bi[e] + 1]++;
  }
  for (int64_t i = 0; i < B; ++i) start[i + 1] += start[i];
  {
    std::vector<int64_t> pos(start.begin(), start.end() - 1);
    for (int64_t e = 0; e < E; ++e) order[pos[Bi[e]]++] = e;
  }
  auto out = torch::empty({E}, torch::kInt64);
  int64_t* O = out.data_ptr<int64_t>();
  std::vector<int32_t> canvas(n_px, 0);
  for (int64_t bi = 0; bi < B; ++bi) {
    for (int64_t k = start[bi]; k < start[bi + 1]; ++k) canvas[Px[order[k]]]++;
    for (int64_t k = start[bi]; k < start[bi + 1]; ++k) O[order[k]] = canvas[Px[order[k]]];
    for (int64_t k = start[bi]; k < start[bi + 1]; ++k) canvas[Px[order[k]]] = 0;
  }
  return out;
}

// cmax's hot-pixel weights (cmax.hot_pixel_weights, the torch path): c = events of the element on
// the event's pixel; two rounds of mean = sum(keep) / sum(keep / c) per element (float64, summed in event order
// as bincount does), keep = c <= factor * mean; weight = 1 where kept, else mean / c (as float32).
torch::Tensor hot_weights(torch::Tensor b, torch::Tensor px, int64_t B, int64_t n_px, double factor) {
  torch::Tensor cnt = pixel_counts(b, px, B, n_px);
  const int64_t E = b.numel();
  const int64_t* Bi = b.data_ptr<int64_t>();
  const int64_t* C = cnt.data_ptr<int64_t>();
  std::vector<double> mean(B, 0.0), n_px_s(B), n_ev_s(B);
  std::vector<unsigned char> keep(E, 1);
  for (int round = 0; round < 2; ++round) {
    std::fill(n_px_s.begin(), n_px_s.end(), 0.0);
    std::fill(n_ev_s.begin(), n_ev_s.end(), 0.0);
    for (int64_t e = 0; e < E; ++e) {
      const double k = keep[e] ? 1.0 : 0.0;
      n_px_s[Bi[e]] += k / (double)C[e];
      n_ev_s[Bi[e]] += k;
    }
    for (int64_t i = 0; i < B; ++i) mean[i] = n_ev_s[i] / std::max(n_px_s[i], 1e-9);
    for (int64_t e = 0; e < E; ++e) keep[e] = (double)C[e] <= factor * mean[Bi[e]];
  }
  auto out = torch::empty({E}, torch::kFloat32);
  float* O = out.data_ptr<float>();
  for (int64_t e = 0; e < E; ++e) O[e] = keep[e] ? 1.0f : (float)(mean[Bi[e]] / (double)C[e]);
  return out;
}

// dvsland.estimators.contrast.event_hash for one event (int64 products wrap as uint64 ones; >> is arithmetic).
static inline int64_t event_hash1(int64_t b, int64_t x, int64_t y, int64_t t, int64_t seed_term) {
  uint64_t u = (uint64_t)b * 0x1F1F1F1FULL + (uint64_t)x * 0x2545F491ULL + (uint64_t)y * 0x9E3779B1ULL +
               (uint64_t)t * 0x6A09E667ULL + (uint64_t)seed_term;
  int64_t h = (int64_t)u;
  h = (int64_t)((uint64_t)(h ^ (h >> 31)) * 0x7FB5D329728EA185ULL);
  h = (int64_t)((uint64_t)(h ^ (h >> 27)) * 0x81DADEF4BC2DD44DULL);
  h = h ^ (h >> 33);
  return h & 0x7FFFFFFF;
}

// cmax's store thinning (cmax.store_keep, the torch path): the indices of the events on the sensor and in the
// batch whose hash (seed_terms[b] = element b's folded seed * 0x3C6EF372) passes (h & 0xFFFF) < p[b] 65536 with
// p = min(cap[b] / max(n[b], 1), 1), n[b] the element's events on the sensor (float64, as bincount).
torch::Tensor store_select(torch::Tensor b, torch::Tensor x, torch::Tensor y, torch::Tensor t, torch::Tensor cap,
                           int64_t W, int64_t H, torch::Tensor seed_terms) {
  auto i64 = torch::kInt64;
  TORCH_CHECK(b.is_contiguous() && x.is_contiguous() && y.is_contiguous() && t.is_contiguous() &&
              b.scalar_type() == i64 && x.scalar_type() == i64 && y.scalar_type() == i64 && t.scalar_type() == i64,
              "store_select: b, x, y, t contiguous int64");
  TORCH_CHECK(cap.is_contiguous() && cap.scalar_type() == torch::kFloat64, "store_select: cap contiguous float64 (B,)");
  const int64_t E = b.numel(), B = cap.numel();
  const int64_t *Bi = b.data_ptr<int64_t>(), *X = x.data_ptr<int64_t>(), *Y = y.data_ptr<int64_t>(),
                *T = t.data_ptr<int64_t>();
  TORCH_CHECK(seed_terms.is_contiguous() && seed_terms.scalar_type() == i64 && seed_terms.numel() == B,
              "store_select: seed_terms contiguous int64 (B,)");
  const double* C = cap.data_ptr<double>();
  const int64_t* ST = seed_terms.data_ptr<int64_t>();
  std::vector<double> n(B, 0.0), p(B);
  for (int64_t e = 0; e < E; ++e)
    if (Bi[e] >= 0 && Bi[e] < B && X[e] >= 0 && X[e] < W && Y[e] >= 0 && Y[e] < H) n[Bi[e]] += 1.0;
  for (int64_t i = 0; i < B; ++i) p[i] = std::min(C[i] / std::max(n[i], 1.0), 1.0);
  std::vector<int64_t> keep;
  keep.reserve(size_t(E));
  for (int64_t e = 0; e < E; ++e) {
    if (!(Bi[e] >= 0 && Bi[e] < B && X[e] >= 0 && X[e] < W && Y[e] >= 0 && Y[e] < H)) continue;
    const int64_t h = event_hash1(Bi[e], X[e], Y[e], T[e], ST[Bi[e]]);
    if ((double)(h & 0xFFFF) < p[Bi[e]] * 65536.0) keep.push_back(e);
  }
  auto out = torch::empty({(int64_t)keep.size()}, i64);
  if (!keep.empty()) std::memcpy(out.data_ptr<int64_t>(), keep.data(), keep.size() * sizeof(int64_t));
  return out;
}
"""

_FUNCTIONS = ["splat_sums", "pixel_counts", "hot_weights", "store_select"]
# SSE4.1 on x86-64 (every x86-64 CPU since about 2008): floor and round-to-nearest-even become one
# instruction instead of a libm call each (the kernel is about 2x faster); the same IEEE results
_CFLAGS = ["-O3", "-ffp-contract=off"] + (["-msse4.1"] if platform.machine().lower() in ("x86_64", "amd64") else [])
_ENV = "DVSLAND_NATIVE_CMAX"
_ON, _OFF, _AUTO = ON, OFF, AUTO
_module = None
_failed = False
_enabled: Optional[bool] = None


def use_native_cmax(on: Optional[bool] = True) -> None:
    """Pick the mode for this process: True = on (build when not cached), False = off, None = back
    to ``DVSLAND_NATIVE_CMAX`` (default auto)."""
    global _enabled
    _enabled = None if on is None else bool(on)


def mode() -> str:
    """``"on"``, ``"off"`` or ``"auto"``: :func:`use_native_cmax`'s choice, else the environment's.

    Raises:
        ValueError naming ``DVSLAND_NATIVE_CMAX`` when it holds another word.
    """
    return mode_from_env(_ENV, _enabled)


def module_name() -> str:
    """The extension's name: a hash of the source, flags, functions, torch and Python versions."""
    return extension_name("dvsland_cmax_native", _SRC, " ".join(_CFLAGS), " ".join(_FUNCTIONS))


def build_dir() -> Path:
    """The folder of the build (torch's extension folder, ``TORCH_EXTENSIONS_DIR`` if set)."""
    return extension_dir(module_name())


def cached() -> bool:
    """Whether the build of this exact source is in the cache (so auto mode uses it)."""
    return extension_cached(module_name())


def enabled() -> bool:
    """Whether ``cmax`` should use the kernel now: mode on, or auto with the build cached (or
    loaded). Never compiles."""
    m = mode()
    return m == _ON or (m == _AUTO and not _failed and (_module is not None or cached()))


def kernel_for(t: torch.Tensor, native: Optional[bool] = None):
    """The compiled module for work on ``t``'s device, or None for the torch path: CPU tensors only;
    ``native`` None = where :func:`enabled` (never compiles in auto mode), True = :func:`load` it
    whatever the mode says, False = never."""
    if native is False or t.device.type != "cpu":
        return None
    return load() if (native or enabled()) else None


def build(verbose: bool = False):
    """Compile (when not cached) and load the kernel; the module. Raises on any build error."""
    return build_extension(module_name(), _SRC, _FUNCTIONS, _CFLAGS, verbose)


def load():
    """The compiled module, or None: mode off; auto without a cached build; or a failed build or
    load (one warning, then the torch path for the rest of the process)."""
    global _module, _failed
    if _module is not None or _failed:
        return _module
    m = mode()
    if m == _OFF or (m == _AUTO and not cached()):
        return None
    _module = load_or_warn(module_name(), cached(), build, "dvsland.estimators.native_cmax")
    _failed = _module is None
    return _module


__all__ = ["use_native_cmax", "enabled", "kernel_for", "mode", "cached", "build", "build_dir", "module_name", "load"]
