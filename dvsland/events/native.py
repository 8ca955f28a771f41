"""Compiled kernels of the emulator (CPU): the ideal pixel's step, an LSD radix sort of its int64
event keys fused with their decoding, and the loops of the denoising filters.

They give the same events and pixel state as the torch path, which stays the reference (the
operations are the same float64 ones in the same order; sorting integers has one result; tests
pin it). On dense frames (B = 18, 128x128, 0.6 events per pixel) they make a step about 2-3x
cheaper (docs/events.md, "Speed against v2e").

They are compiled once with the C++ compiler through ``torch.utils.cpp_extension.load_inline``
(about 1-2 min of CPU on a busy 2-core machine) into torch's extension folder, under a name that
carries a hash of the source, the flags and the torch version, so a stale build is never loaded.
The environment variable ``DVSLAND_NATIVE_SORT`` (or :func:`use_native_sort`) picks the mode:

- ``auto`` (default, also when unset or empty): use the kernels when their build is already in
  the cache (loaded in milliseconds, nothing is compiled); otherwise the torch path runs, silently.
- ``1`` / ``on`` / ``true`` / ``yes``: build on first use when not cached, then use them.
- ``0`` / ``off`` / ``false`` / ``no``: never use them.

Build once with ``python -m dvsland.events.build_native`` (prints the time and the folder). Without a
compiler (or on any build or load error) the torch path runs, with one warning.

Purity: the kernels that update per-pixel memories (``pixel_events``: the reference and last-event
times; ``baf_keep`` / ``refractory_keep``: the filters' memories) write into the buffers they are
given, and their callers give them fresh or cloned buffers, never a state's own tensors (unless the
caller donated that state, :func:`dvsland.events.emulator.emulator_step`). ``shot_keys`` (the keys of
the former generator-drawn, pre-sorted shot noise) is no longer called: the shot noise is a
counter-based draw now (:mod:`dvsland.events.pixel_model`); it stays in the source so that an
existing build keeps its name (dropping it means one rebuild).
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Optional

import torch

from dvsland.native_build import (AUTO, OFF, ON, build_extension, extension_cached, extension_dir, extension_name,
                                  load_or_warn, mode_from_env)

_SRC = r"""
#include <torch/extension.h>
#include <cmath>
#include <cstring>
#include <vector>

// LSD radix sort of non-negative int64 keys below 2^bits by their bits lo_bit..bits-1, in place, stable;
// 11-bit digits. With lo_bit = 0 the keys end fully sorted; with lo_bit > 0 keys equal in those bits
// keep their input order (the emulator's keys come in pixel order, which is their low bits' order).
void radix_sort_bits_(torch::Tensor keys, int64_t bits, int64_t lo_bit) {
  TORCH_CHECK(keys.is_contiguous() && keys.scalar_type() == torch::kInt64 && keys.device().is_cpu(),
              "radix_sort_: keys must be a contiguous int64 CPU tensor");
  const int64_t n = keys.numel();
  if (n < 2) return;
  int64_t* a = keys.data_ptr<int64_t>();
  // the work buffer is kept across calls up to 2^22 keys (32 MiB): no fresh pages per step
  static thread_local std::vector<int64_t> kept;
  std::vector<int64_t> once;
  std::vector<int64_t>& buf = n <= (int64_t(1) << 22) ? kept : once;
  if (int64_t(buf.size()) < n) buf.resize(size_t(n));
  int64_t* src = a;
  int64_t* dst = buf.data();
  const int D = 11;
  const int64_t M = (int64_t(1) << D) - 1;
  std::vector<int64_t> cnt(size_t(1) << D);
  for (int64_t sh = lo_bit; sh < bits; sh += D) {
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

void radix_sort_(torch::Tensor keys, int64_t bits) { radix_sort_bits_(keys, bits, 0); }

// radix_sort_ then unpack the keys into the Events fields in one pass (see _KeyLayout):
// b, x, y, t = t0 + t_rel (int64) and p = +1 / -1 (int8, OFF bit 1 = -1).
// radix_sort_bits_ then merge in `more` (sorted, may be empty) and unpack all into the Events fields
// in one pass (see _KeyLayout): b, x, y, t = t0 + t_rel (int64) and p = +1 / -1 (int8, OFF bit 1 = -1).
// lo_bit: see radix_sort_bits_ (t_shift when the keys come in pixel order, else 0).
std::vector<torch::Tensor> sort_decode(torch::Tensor keys, int64_t bits, int64_t lo_bit, torch::Tensor more,
                                       int64_t b_shift, int64_t t_shift, int64_t y_shift, int64_t x_mask,
                                       int64_t y_mask, int64_t t0) {
  TORCH_CHECK(more.is_contiguous() && more.scalar_type() == torch::kInt64 && more.device().is_cpu(),
              "sort_decode: more must be a contiguous int64 CPU tensor");
  TORCH_CHECK(keys.is_contiguous() && keys.scalar_type() == torch::kInt64 && keys.device().is_cpu(),
              "sort_decode: keys must be a contiguous int64 CPU tensor");
  const int64_t na = keys.numel(), nb = more.numel(), n = na + nb;
  auto opt = torch::TensorOptions().dtype(torch::kInt64);
  auto b = torch::empty({n}, opt), x = torch::empty({n}, opt), y = torch::empty({n}, opt), t = torch::empty({n}, opt);
  auto p = torch::empty({n}, torch::TensorOptions().dtype(torch::kInt8));
  int64_t *pb = b.data_ptr<int64_t>(), *px = x.data_ptr<int64_t>(), *py = y.data_ptr<int64_t>(), *pt = t.data_ptr<int64_t>();
  int8_t* pp = p.data_ptr<int8_t>();
  const int64_t t_mask = (int64_t(1) << (b_shift - t_shift)) - 1;
  auto put = [&](int64_t w, int64_t v) {
    pp[w] = (v & 1) ? -1 : 1;
    px[w] = (v >> 1) & x_mask;
    py[w] = (v >> y_shift) & y_mask;
    pt[w] = ((v >> t_shift) & t_mask) + t0;
    pb[w] = v >> b_shift;
  };
  radix_sort_bits_(keys, bits, lo_bit);
  const int64_t* ka = keys.data_ptr<int64_t>();
  const int64_t* kb = more.data_ptr<int64_t>();
  int64_t i = 0, j = 0;
  const uint64_t END = ~uint64_t(0);  // above every key (keys are < 2^63)
  for (int64_t w = 0; w < n; ++w) {
    // branch-free merge step (the two streams interleave at random)
    const uint64_t va = i < na ? uint64_t(ka[i]) : END, vb = j < nb ? uint64_t(kb[j]) : END;
    const bool from_a = va <= vb;
    const int64_t v = int64_t(from_a ? va : vb);
    i += from_a;
    j += !from_a;
    put(w, v);
  }
  return {b, x, y, t, p};
}

// Shot-noise candidates (slot, elem, u as pixel_model.sorted_candidates draws them, in (element, time,
// pixel) order) thinned and keyed as pixel_model.draw_shot_noise and EventEmulator.step do, the same
// float64 operations in the same order: q = min(I / I_full, 1) * c + a with I the pixel's irradiance
// (float64); kept when u < q (only if thin), OFF when u < q / 2; key = ((slot + 2^(t_shift-1)) << 1)
// | (elem << b_shift) | OFF. Returns {flat pixel index, key} of the kept ones, in order (sorted keys).
std::vector<torch::Tensor> shot_keys(torch::Tensor slot_t, torch::Tensor elem_t, torch::Tensor u_t, torch::Tensor irr_t,
                                     int64_t H, int64_t W, int64_t x_bits, int64_t y_bits, double inv_full, double a,
                                     double c, bool thin, int64_t t_shift, int64_t b_shift) {
  TORCH_CHECK(irr_t.scalar_type() == torch::kFloat64 && irr_t.is_contiguous() && u_t.scalar_type() == torch::kFloat64,
              "shot_keys: irradiance and u must be contiguous float64");
  const int64_t n = slot_t.numel();
  const int64_t *slot = slot_t.data_ptr<int64_t>(), *elem = elem_t.data_ptr<int64_t>();
  const double *u = u_t.data_ptr<double>(), *irr = irr_t.data_ptr<double>();
  auto flat_t = torch::empty({n}, torch::kInt64), keys_t = torch::empty({n}, torch::kInt64);
  int64_t *flat = flat_t.data_ptr<int64_t>(), *keys = keys_t.data_ptr<int64_t>();
  const int64_t xm = (int64_t(1) << x_bits) - 1, ym = (int64_t(1) << y_bits) - 1, t_one = int64_t(1) << (t_shift - 1);
  int64_t w = 0;
  for (int64_t i = 0; i < n; ++i) {
    const int64_t s = slot[i];
    const int64_t f = (((s >> x_bits) & ym) + elem[i] * H) * W + (s & xm);
    double q = irr[f] * inv_full;
    q = q > 1.0 ? 1.0 : q;
    q = q * c + a;
    // written always, kept by advancing w: no branch on the random u (half of them mispredicted)
    flat[w] = f;
    keys[w] = (((s + t_one) << 1) | (elem[i] << b_shift)) | int64_t(u[i] < q * 0.5);
    w += int64_t(!thin || u[i] < q);
  }
  return {flat_t.narrow(0, 0, w), keys_t.narrow(0, 0, w)};
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

struct Cand { int64_t code; double cnt, first, step; };  // one pixel with >= 1 emitted event

// x86-64: a second copy for CPUs with AVX2/FMA (floor, ceil and fma as single instructions; the
// same IEEE results: no contraction, -ffp-contract=off), picked at load time by the dynamic loader.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define DVS_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define DVS_CLONES
#endif

// th_on_map / th_off_map: per-pixel thresholds (or null: the scalars th_on / th_off); r_elem: per-
// element refractory periods (or null: the scalar r), element = pixel / hw. As the torch path: with
// maps the candidate bounds are th_on * shrink and th_off * -shrink and the general ON/OFF count;
// per-element r is divided as r / spacing, a scalar r as (1 / spacing) * r (torch's scalar / tensor).
DVS_CLONES static double scan_pixels(const double* l1, double* lref, const double* l0, double* tlast,
                                     const int64_t* code, int64_t P, double th_on_s, double th_off_s,
                                     const double* th_on_map, const double* th_off_map, double r_s,
                                     const double* r_elem, int64_t hw, double t0, double dt,
                                     bool spacing_may_bind, std::vector<Cand>& out) {
  const double TOL = 1e-9, shrink = 1.0 - 2 * TOL;
  const bool maps = th_on_map != nullptr;
  const bool same = !maps && th_on_s == th_off_s;
  double total = 0.0;
  for (int64_t k = 0; k < P; ++k) {
    const double d = l1[k] - lref[k];
    const double th_on = maps ? th_on_map[k] : th_on_s, th_off = maps ? th_off_map[k] : th_off_s;
    if (same ? !(std::fabs(d) >= th_on * shrink)
             : !(d >= th_on * shrink || d <= (maps ? th_off * -shrink : -(th_off * shrink)))) continue;
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
    const double r = r_elem ? r_elem[k / hw] : r_s;
    const double tl = tlast[k] - t0;
    // _emitted_log
    const double dl = l1[k] - l0[k];
    const double scale = (1.0 / dl) * dt;  // torch: scalar / tensor = tensor.reciprocal() * scalar
    const double spacing = th * scale;
    const double base = (lref[k] - l0[k]) * scale;
    double cnt = n, first = base + spacing, step = spacing;
    if (r_elem || r > 0) {
      const bool near = first < tl + r;
      if (spacing_may_bind ? ((spacing < r) || near) : near) {
        const double j0 = clamp_lo(std::ceil(((tl - base) + r) / spacing), 1.0);
        const double m = clamp_lo(std::ceil(r_elem ? r / spacing : (1.0 / spacing) * r), 1.0);  // as torch
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
      out.push_back({code[k] | (std::signbit(th) ? 1 : 0), cnt, first, step});
      total += cnt;
    }
  }
  return total;
}

DVS_CLONES static void write_keys(const std::vector<Cand>& cand, double dt, int64_t t_shift, int64_t* out) {
  int64_t w = 0;
  for (const Cand& c : cand) {
    out[w++] = (int64_t(clamp_lohi(std::floor(c.first + 0.5), 1.0, dt)) << t_shift) + c.code;
    const int64_t ce = int64_t(c.cnt);
    for (int64_t i = 1; i < ce; ++i) {
      const double tau = c.step * double(i) + c.first;
      out[w++] = (int64_t(clamp_lohi(std::floor(tau + 0.5), 1.0, dt)) << t_shift) + c.code;
    }
  }
}

// th_on_map, th_off_map, r_elem: empty tensors for the scalars, else contiguous float64 (see scan_pixels).
torch::Tensor pixel_events(torch::Tensor l1_t, torch::Tensor lref_t, torch::Tensor l0_t, torch::Tensor tlast_t,
                           torch::Tensor code_t, double th_on, double th_off, torch::Tensor th_on_map,
                           torch::Tensor th_off_map, double r, torch::Tensor r_elem, int64_t hw, double t0,
                           double dt, bool spacing_may_bind, int64_t t_shift, int64_t cap, torch::Tensor n_out) {
  auto ptr = [](const torch::Tensor& x) -> const double* {
    if (x.numel() == 0) return nullptr;
    TORCH_CHECK(x.is_contiguous() && x.scalar_type() == torch::kFloat64, "pixel_events: maps must be contiguous float64");
    return x.data_ptr<double>();
  };
  const int64_t P = l1_t.numel();
  static thread_local std::vector<Cand> kept;  // kept across calls (no fresh pages per step)
  std::vector<Cand>& cand = kept;
  cand.clear();
  if (cand.capacity() < size_t(P / 2)) cand.reserve(size_t(P / 2));
  const double total = scan_pixels(l1_t.data_ptr<double>(), lref_t.data_ptr<double>(), l0_t.data_ptr<double>(),
                                   tlast_t.data_ptr<double>(), code_t.data_ptr<int64_t>(), P, th_on, th_off,
                                   ptr(th_on_map), ptr(th_off_map), r, ptr(r_elem), hw, t0, dt, spacing_may_bind,
                                   cand);
  n_out.data_ptr<double>()[0] = total;
  if (cap >= 0 && total > double(cap)) return torch::empty({0}, torch::kInt64);
  auto keys = torch::empty({int64_t(total)}, torch::kInt64);
  write_keys(cand, dt, t_shift, keys.data_ptr<int64_t>());
  if (cand.capacity() > (size_t(1) << 22)) std::vector<Cand>().swap(cand);  // do not keep huge buffers
  return keys;
}
"""

_FUNCTIONS = ["radix_sort_", "pixel_events", "sort_decode", "shot_keys", "baf_keep", "refractory_keep"]
_CFLAGS = ["-O3", "-ffp-contract=off"]

_ON, _OFF, _AUTO = ON, OFF, AUTO
_module = None
_failed = False
_absent = False  # auto mode found no cached build in this process (not looked for again)
#: this process's choice (use_native_sort): True = on, False = off, None = the environment's
_enabled: Optional[bool] = None


def use_native_sort(on: Optional[bool] = True) -> None:
    """Pick the mode for this process: True = on (build when not cached), False = off, None = back
    to ``DVSLAND_NATIVE_SORT`` (default auto)."""
    global _enabled
    _enabled = None if on is None else bool(on)


@contextlib.contextmanager
def native_sort_mode(on: Optional[bool]):
    """:func:`use_native_sort` (``on``) inside the block, the process's earlier choice after it
    (how the benchmarks time the torch and the compiled path in one process)."""
    global _enabled
    saved = _enabled
    use_native_sort(on)
    try:
        yield
    finally:
        _enabled = saved


def mode() -> str:
    """``"on"``, ``"off"`` or ``"auto"``: :func:`use_native_sort`'s choice, else the environment's.

    Raises:
        ValueError naming ``DVSLAND_NATIVE_SORT`` when it holds another word.
    """
    return mode_from_env("DVSLAND_NATIVE_SORT", _enabled)


def module_name() -> str:
    """The extension's name: a hash of the source, flags, functions, torch and Python versions."""
    return extension_name("dvsland_events_native", _SRC, " ".join(_CFLAGS), " ".join(_FUNCTIONS))


def build_dir() -> Path:
    """The folder of the build (torch's extension folder, ``TORCH_EXTENSIONS_DIR`` if set)."""
    return extension_dir(module_name())


def cached() -> bool:
    """Whether the build of this exact source is in the cache (so auto mode uses it)."""
    return extension_cached(module_name())


def native_sort_enabled() -> bool:
    """Whether the emulator and the denoiser should use the kernels now: mode on, or auto with the
    build cached (or already loaded). Never compiles. In auto mode the cache is looked at once per
    process (a build made later by another process is used from the next process on)."""
    global _absent
    m = mode()
    if m == _ON:
        return True
    if m == _OFF or _failed:
        return False
    if _module is not None:
        return True
    if _absent:
        return False
    if cached():
        return True
    _absent = True
    return False


def kernels():
    """The compiled module when the kernels are to be used now (:func:`native_sort_enabled`, then
    :func:`load`), else None (the torch path). Never compiles in auto mode."""
    return load() if native_sort_enabled() else None


def build(verbose: bool = False):
    """Compile (when not cached) and load the kernels; the module. Raises on any build error."""
    return build_extension(module_name(), _SRC, _FUNCTIONS, _CFLAGS, verbose)


def load():
    """The compiled module, or None: mode off; auto without a cached build; or a failed build or
    load (one warning, then the torch path for the rest of the process)."""
    global _module, _failed
    if _module is not None or _failed:
        return _module
    m = mode()
    if m == _OFF or (m == _AUTO and not native_sort_enabled()):
        return None
    _module = load_or_warn(module_name(), cached(), build, "dvsland.events.native")
    _failed = _module is None
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


__all__ = ["use_native_sort", "native_sort_enabled", "mode", "cached", "build", "build_dir", "module_name",
           "load", "radix_sort_"]
