"""Optional compiled kernels of the emulator (CPU): the ideal pixel's step, an LSD radix sort of
its int64 event keys fused with their decoding, and the loops of the denoising filters.

The emulator's per-step sort of packed event keys (:class:`dvsland.events.emulator._KeyLayout`)
is about half of a dense step with numpy's sort (158 k keys, B = 18 at 128x128, 0.6 events per
pixel: about 6.5 ms of process CPU on this machine against 1.1 ms for this radix sort). Sorting
integers has one result, so the events are identical with and without it (tests pin it).

It is opt-in because it is compiled on first use with the C++ compiler through
``torch.utils.cpp_extension.load_inline`` (about 80 s once on a busy 2-core machine, then cached
in torch's extension folder): set the environment variable ``DVSLAND_NATIVE_SORT=1`` or call
:func:`use_native_sort`. Without a compiler (or on any build error) the numpy sort is used, with
one warning.
"""

from __future__ import annotations

import os
import warnings
from typing import Optional

import torch

_SRC = r"""
#include <torch/extension.h>
#include <cmath>
#include <cstring>
#include <vector>

// LSD radix sort of non-negative int64 keys below 2^bits, in place; 11-bit digits.
void radix_sort_(torch::Tensor keys, int64_t bits) {
  TORCH_CHECK(keys.is_contiguous() && keys.scalar_type() == torch::kInt64 && keys.device().is_cpu(),
              "radix_sort_: keys must be a contiguous int64 CPU tensor");
  const int64_t n = keys.numel();
  if (n < 2) return;
  int64_t* a = keys.data_ptr<int64_t>();
  std::vector<int64_t> buf(n);
  int64_t* src = a;
  int64_t* dst = buf.data();
  const int D = 11;
  const int64_t M = (int64_t(1) << D) - 1;
  std::vector<int64_t> cnt(size_t(1) << D);
  for (int64_t sh = 0; sh < bits; sh += D) {
    std::fill(cnt.begin(), cnt.end(), 0);
    for (int64_t i = 0; i < n; ++i) cnt[(src[i] >> sh) & M]++;
    if (cnt[(src[0] >> sh) & M] == n) continue;  // one digit value: this pass changes nothing
    int64_t s = 0;
    for (auto& c : cnt) { int64_t t = c; c = s; s += t; }
    for (int64_t i = 0; i < n; ++i) dst[cnt[(src[i] >> sh) & M]++] = src[i];
    std::swap(src, dst);
  }
  if (src != a) std::memcpy(a, src, size_t(n) * sizeof(int64_t));
}

// radix_sort_ then unpack the keys into the Events fields in one pass (see _KeyLayout):
// b, x, y, t = t0 + t_rel (int64) and p = +1 / -1 (int8, OFF bit 1 = -1).
std::vector<torch::Tensor> sort_decode(torch::Tensor keys, int64_t bits, int64_t b_shift, int64_t t_shift,
                                       int64_t y_shift, int64_t x_mask, int64_t y_mask, int64_t t0) {
  radix_sort_(keys, bits);
  const int64_t n = keys.numel();
  const int64_t* k = keys.data_ptr<int64_t>();
  auto opt = torch::TensorOptions().dtype(torch::kInt64);
  auto b = torch::empty({n}, opt), x = torch::empty({n}, opt), y = torch::empty({n}, opt), t = torch::empty({n}, opt);
  auto p = torch::empty({n}, torch::TensorOptions().dtype(torch::kInt8));
  int64_t *pb = b.data_ptr<int64_t>(), *px = x.data_ptr<int64_t>(), *py = y.data_ptr<int64_t>(), *pt = t.data_ptr<int64_t>();
  int8_t* pp = p.data_ptr<int8_t>();
  const int64_t t_mask = (int64_t(1) << (b_shift - t_shift)) - 1;
  for (int64_t i = 0; i < n; ++i) {
    const int64_t v = k[i];
    pp[i] = (v & 1) ? -1 : 1;
    px[i] = (v >> 1) & x_mask;
    py[i] = (v >> y_shift) & y_mask;
    pt[i] = ((v >> t_shift) & t_mask) + t0;
    pb[i] = v >> b_shift;
  }
  return {b, x, y, t, p};
}

// The front-end filters of dvsland.events.denoise as tonic writes them: one loop over the events
// in stream order with a per-pixel memory of the last event time (mem, flat, in/out).
torch::Tensor baf_keep(torch::Tensor pix_t, torch::Tensor x_t, torch::Tensor y_t, torch::Tensor t_t,
                       torch::Tensor mem_t, int64_t H, int64_t W, int64_t window, int64_t neighbours) {
  const int64_t n = pix_t.numel();
  const int64_t *pix = pix_t.data_ptr<int64_t>(), *x = x_t.data_ptr<int64_t>(), *y = y_t.data_ptr<int64_t>();
  const int64_t* t = t_t.data_ptr<int64_t>();
  int64_t* mem = mem_t.data_ptr<int64_t>();
  auto keep_t = torch::empty({n}, torch::TensorOptions().dtype(torch::kBool));
  bool* keep = keep_t.data_ptr<bool>();
  const int DX[8] = {-1, 1, 0, 0, -1, 1, -1, 1}, DY[8] = {0, 0, -1, 1, -1, -1, 1, 1};
  for (int64_t i = 0; i < n; ++i) {
    bool ok = false;
    for (int k = 0; k < neighbours && !ok; ++k) {
      const int64_t xn = x[i] + DX[k], yn = y[i] + DY[k];
      if (xn < 0 || xn >= W || yn < 0 || yn >= H) continue;
      ok = t[i] - mem[pix[i] + DY[k] * W + DX[k]] < window;
    }
    mem[pix[i]] = t[i];
    keep[i] = ok;
  }
  return keep_t;
}

torch::Tensor refractory_keep(torch::Tensor pix_t, torch::Tensor t_t, torch::Tensor mem_t, int64_t period) {
  const int64_t n = pix_t.numel();
  const int64_t *pix = pix_t.data_ptr<int64_t>(), *t = t_t.data_ptr<int64_t>();
  int64_t* mem = mem_t.data_ptr<int64_t>();
  auto keep_t = torch::empty({n}, torch::TensorOptions().dtype(torch::kBool));
  bool* keep = keep_t.data_ptr<bool>();
  for (int64_t i = 0; i < n; ++i) {
    keep[i] = t[i] - mem[pix[i]] > period;
    mem[pix[i]] = t[i];
  }
  return keep_t;
}

// The ideal pixel's step (log interpolation, scalar thresholds and refractory period) in one pass
// over the pixels, the same float64 operations in the same order as EventEmulator._pixel_events /
// _emitted_log / _extra_keys (torch's addcmul is a fused multiply-add: std::fma here). Updates
// lref and t_last in place; returns the unsorted event keys, or an empty tensor and the count in
// n_out[0] when the count exceeds cap (cap < 0: no cap).
static inline double clamp_lo(double x, double lo) { return x < lo ? lo : x; }  // NaN stays NaN, as torch
static inline double clamp_lohi(double x, double lo, double hi) { x = x < lo ? lo : x; return x > hi ? hi : x; }

torch::Tensor pixel_events(torch::Tensor l1_t, torch::Tensor lref_t, torch::Tensor l0_t, torch::Tensor tlast_t,
                           torch::Tensor code_t, double th_on, double th_off, double r, double t0, double dt,
                           bool spacing_may_bind, int64_t t_shift, int64_t cap, torch::Tensor n_out) {
  const double TOL = 1e-9, shrink = 1.0 - 2 * TOL;
  const int64_t P = l1_t.numel();
  const double* l1 = l1_t.data_ptr<double>();
  double* lref = lref_t.data_ptr<double>();
  const double* l0 = l0_t.data_ptr<double>();
  double* tlast = tlast_t.data_ptr<double>();
  const int64_t* code = code_t.data_ptr<int64_t>();
  const bool same = th_on == th_off;
  const double lo_on = th_on * shrink, lo_off = th_off * shrink;
  std::vector<int64_t> idx; std::vector<double> cnt_v, first_v, step_v;
  std::vector<int64_t> off_v;
  idx.reserve(P / 2); cnt_v.reserve(P / 2); first_v.reserve(P / 2); step_v.reserve(P / 2); off_v.reserve(P / 2);
  double total = 0.0;
  for (int64_t k = 0; k < P; ++k) {
    const double d = l1[k] - lref[k];
    if (same ? !(std::fabs(d) >= lo_on) : !(d >= lo_on || d <= -lo_off)) continue;
    double n, th;
    if (same) {
      n = std::floor(std::fabs(d / th_on) + TOL);
      th = (d > 0 ? 1.0 : (d < 0 ? -1.0 : 0.0)) * th_on;
    } else {
      const double n_on = clamp_lo(std::floor(d / th_on + TOL), 0.0);
      const double n_off = clamp_lo(std::floor(-d / th_off + TOL), 0.0);
      n = n_on + n_off;
      th = d > 0 ? th_on : -th_off;
    }
    const double tl = tlast[k] - t0;
    // _emitted_log
    const double dl = l1[k] - l0[k];
    const double scale = (1.0 / dl) * dt;  // torch: scalar / tensor = tensor.reciprocal() * scalar
    const double spacing = th * scale;
    const double base = (lref[k] - l0[k]) * scale;
    double cnt = n, first = base + spacing, step = spacing;
    if (r > 0) {
      const bool near = first < tl + r;
      if (spacing_may_bind ? ((spacing < r) || near) : near) {
        const double j0 = clamp_lo(std::ceil(((tl - base) + r) / spacing), 1.0);
        const double m = clamp_lo(std::ceil((1.0 / spacing) * r), 1.0);  // as r / sp in torch
        double c = clamp_lo(std::floor((n - j0) / m) + 1.0, 0.0);
        if (!std::isfinite(c)) c = 0.0;
        cnt = c;
        first = std::fma(j0, spacing, base);
        step = m * spacing;
      }
    }
    lref[k] = std::fma(n, th, lref[k]);
    if (cnt > 0) {
      tlast[k] = std::fma(cnt - 1.0, step, first) + t0;
      idx.push_back(k); cnt_v.push_back(cnt); first_v.push_back(first); step_v.push_back(step);
      off_v.push_back(std::signbit(th) ? 1 : 0);
      total += cnt;
    }
  }
  n_out.data_ptr<double>()[0] = total;
  if (cap >= 0 && total > double(cap)) return torch::empty({0}, torch::kInt64);
  auto keys = torch::empty({int64_t(total)}, torch::kInt64);
  int64_t* out = keys.data_ptr<int64_t>();
  int64_t w = 0;
  for (size_t a = 0; a < idx.size(); ++a) {
    const int64_t c0 = code[idx[a]] | off_v[a];
    out[w++] = (int64_t(clamp_lohi(std::floor(first_v[a] + 0.5), 1.0, dt)) << t_shift) + c0;
    const int64_t ce = int64_t(cnt_v[a]);
    for (int64_t i = 1; i < ce; ++i) {
      const double tau = step_v[a] * double(i) + first_v[a];
      out[w++] = (int64_t(clamp_lohi(std::floor(tau + 0.5), 1.0, dt)) << t_shift) + c0;
    }
  }
  return keys;
}
"""

_module = None
_failed = False
_enabled: Optional[bool] = None


def use_native_sort(on: bool = True) -> None:
    """Switch the compiled sort on or off for this process (default: ``DVSLAND_NATIVE_SORT``)."""
    global _enabled
    _enabled = bool(on)


def native_sort_enabled() -> bool:
    """Whether the emulator should try the compiled sort."""
    if _enabled is not None:
        return _enabled
    return os.environ.get("DVSLAND_NATIVE_SORT", "0") not in ("", "0", "false", "no")


def load():
    """The compiled module (built on first call), or None when it cannot be built."""
    global _module, _failed
    if _module is not None or _failed:
        return _module
    try:
        from torch.utils.cpp_extension import load_inline

        _module = load_inline("dvsland_events_native", cpp_sources=_SRC, functions=["radix_sort_", "pixel_events", "sort_decode", "baf_keep", "refractory_keep"],
                              extra_cflags=["-O3", "-ffp-contract=off"], verbose=False)
    except Exception as exc:  # no compiler, no headers, ...: the numpy sort stays
        _failed = True
        warnings.warn(f"dvsland.events.native: the compiled sort could not be built ({exc}); "
                      f"using numpy's sort", RuntimeWarning)
    return _module


def radix_sort_(keys: torch.Tensor, bits: int) -> bool:
    """Sort ``keys`` ((N,) int64 CPU, contiguous, values in [0, 2^bits)) in place with the compiled
    kernel; returns False (nothing done) when it is not enabled or not available."""
    if not native_sort_enabled():
        return False
    mod = load()
    if mod is None:
        return False
    mod.radix_sort_(keys, int(bits))
    return True


__all__ = ["use_native_sort", "native_sort_enabled", "load", "radix_sort_"]
