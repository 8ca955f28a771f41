"""Compiled kernels of the emulator (CPU): the ideal pixel's step, an LSD radix sort of its int64
event keys fused with their decoding, the loops of the denoising filters, and the counts and sums
of the estimators' motion-evidence test (:mod:`dvsland.estimators.abstain`).

They give the same events and pixel state as the torch path, which stays the reference (the
operations are the same float64 ones in the same order; sorting integers has one result; tests
pin it). On dense frames (B = 18, 128x128, 0.6 events per pixel) they make a step about 2-3x
cheaper (docs/events.md, "Speed against v2e").

They are plain C++ behind a C interface (no torch headers), called through ``ctypes`` on the
tensors' memory, and compiled with the system's C++ compiler in a second or two into a cache
folder (:func:`dvsland.native_build.library_dir`), under a name that carries a hash of the source,
the flags, the compiler and the machine, so a stale build is never loaded. The environment
variable ``DVSLAND_NATIVE_SORT`` (or :func:`use_native_sort`) picks the mode:

- ``auto`` (default, also when unset or empty): use the kernels; when they are not in the cache,
  build them on first use if a C++ compiler is found (``$CXX``, ``c++``, ``g++`` or ``clang++``),
  else run the torch path, silently.
- ``1`` / ``on`` / ``true`` / ``yes``: the same, but a missing compiler is warned about.
- ``0`` / ``off`` / ``false`` / ``no``: never use them.

``python -m dvsland.events.build_native`` (or ``dvsland build-native``) builds them ahead and prints
the time and the folder. On any build or load error the torch path runs, with one warning.

Purity: the kernels that update per-pixel memories (``pixel_events``: the reference and last-event
times; ``baf_keep`` / ``refractory_keep``: the filters' memories) write into the buffers they are
given, and their callers give them fresh or cloned buffers, never a state's own tensors (unless the
caller donated that state, :func:`dvsland.events.emulator.emulator_step`).
"""

from __future__ import annotations

import contextlib
import ctypes
from pathlib import Path
from typing import Optional

import torch

from dvsland.native_build import NativeLibrary, bind_functions, tensor_address as _ptr

_SRC = r"""
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

// x86-64: a second copy for CPUs with AVX2/FMA (floor, ceil and fma as single instructions; the
// same IEEE results: no contraction, -ffp-contract=off), picked at load time by the dynamic loader.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define DVS_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define DVS_CLONES
#endif
#define DVS_INLINE __attribute__((always_inline)) static inline  // inlined into each clone

// LSD radix sort of non-negative int64 keys below 2^bits by their bits lo_bit..bits-1, in place, stable;
// 11-bit digits. With lo_bit = 0 the keys end fully sorted; with lo_bit > 0 keys equal in those bits
// keep their input order (the emulator's keys come in pixel order, which is their low bits' order).
static void radix_sort_bits(int64_t* a, int64_t n, int64_t bits, int64_t lo_bit) {
  if (n < 2) return;
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

extern "C" void dvs_radix_sort(int64_t* keys, int64_t n, int64_t bits) { radix_sort_bits(keys, n, bits, 0); }

// One run of keys equal in their bits >= seg_bit, sorted by their bits lo_bit..seg_bit-1 (LSD, stable):
// insertion sort for short runs, else passes of at most 9-bit digits with every pass's histogram
// taken in one read. buf holds at least n keys.
static void sort_run(int64_t* a, int64_t n, int64_t seg_bit, int64_t lo_bit, int64_t* buf) {
  if (n < 2) return;
  if (n <= 24) {
    for (int64_t i = 1; i < n; ++i) {  // the keys' high bits are equal: comparing them whole is stable
      const int64_t v = a[i];
      int64_t j = i;
      for (; j > 0 && (a[j - 1] >> lo_bit) > (v >> lo_bit); --j) a[j] = a[j - 1];
      a[j] = v;
    }
    return;
  }
  const int64_t w = seg_bit - lo_bit;
  const int passes = int((w + 8) / 9);
  const int D = int((w + passes - 1) / passes);
  const int64_t M = (int64_t(1) << D) - 1, K = int64_t(1) << D;
  if (passes == 2 && n < (int64_t(1) << 31)) {  // the emulator's case (17 bits of time): two plain passes
    uint32_t c0[512], c1[512];
    std::memset(c0, 0, sizeof(uint32_t) * size_t(K));
    std::memset(c1, 0, sizeof(uint32_t) * size_t(K));
    for (int64_t i = 0; i < n; ++i) { const int64_t v = a[i] >> lo_bit; c0[v & M]++; c1[(v >> D) & M]++; }
    uint32_t s0 = 0, s1 = 0;
    for (int64_t d = 0; d < K; ++d) {
      uint32_t t = c0[d]; c0[d] = s0; s0 += t;
      t = c1[d]; c1[d] = s1; s1 += t;
    }
    for (int64_t i = 0; i < n; ++i) { const int64_t v = a[i]; buf[c0[(v >> lo_bit) & M]++] = v; }
    const int64_t sh = lo_bit + D;
    for (int64_t i = 0; i < n; ++i) { const int64_t v = buf[i]; a[c1[(v >> sh) & M]++] = v; }
    return;
  }
  int64_t cnt[4][512];
  std::memset(cnt, 0, sizeof(int64_t) * size_t(passes) * 512);
  for (int64_t i = 0; i < n; ++i) {
    const int64_t v = a[i] >> lo_bit;
    for (int q = 0; q < passes; ++q) cnt[q][(v >> (q * D)) & M]++;
  }
  int64_t* src = a;
  int64_t* dst = buf;
  for (int q = 0; q < passes; ++q) {
    const int64_t sh = lo_bit + int64_t(q) * D;
    int64_t* c = cnt[q];
    if (c[(src[0] >> sh) & M] == n) continue;  // one digit value: this pass changes nothing
    int64_t s = 0;
    for (int64_t d = 0; d < K; ++d) { const int64_t t = c[d]; c[d] = s; s += t; }
    for (int64_t i = 0; i < n; ++i) dst[c[(src[i] >> sh) & M]++] = src[i];
    std::swap(src, dst);
  }
  if (src != a) std::memcpy(a, src, size_t(n) * sizeof(int64_t));
}

// The same order as radix_sort_bits(a, n, bits, lo_bit) for keys that come ordered by their bits
// >= seg_bit (the descent, as the pixel kernel emits them): each descent's run sorted alone, in
// cache. Falls back to radix_sort_bits where the keys are not so ordered.
static void radix_sort_runs(int64_t* a, int64_t n, int64_t bits, int64_t seg_bit, int64_t lo_bit) {
  if (n < 2) return;
  if (seg_bit - lo_bit > 36 || seg_bit <= lo_bit) { radix_sort_bits(a, n, bits, lo_bit); return; }
  for (int64_t i = 1; i < n; ++i) {
    if ((a[i] >> seg_bit) < (a[i - 1] >> seg_bit)) { radix_sort_bits(a, n, bits, lo_bit); return; }
  }
  static thread_local std::vector<int64_t> buf;
  int64_t i = 0;
  while (i < n) {
    const int64_t hi = a[i] >> seg_bit;
    int64_t j = i + 1;
    while (j < n && (a[j] >> seg_bit) == hi) ++j;
    if (int64_t(buf.size()) < j - i) buf.resize(size_t(j - i));
    sort_run(a + i, j - i, seg_bit, lo_bit, buf.data());
    i = j;
  }
  if (buf.size() > (size_t(1) << 22)) std::vector<int64_t>().swap(buf);  // do not keep huge buffers
}

// The Events fields of n sorted keys (see dvs_sort_decode): one vectorised pass.
DVS_CLONES static void decode_keys(const int64_t* __restrict k, int64_t n, int64_t b_shift, int64_t t_shift,
                                   int64_t y_shift, int64_t x_mask, int64_t y_mask, int64_t t_mask, int64_t t0,
                                   int64_t* __restrict pb, int64_t* __restrict px, int64_t* __restrict py,
                                   int64_t* __restrict pt, int8_t* __restrict pp) {
  for (int64_t w = 0; w < n; ++w) {
    const int64_t v = k[w];
    pp[w] = (v & 1) ? -1 : 1;
    px[w] = (v >> 1) & x_mask;
    py[w] = (v >> y_shift) & y_mask;
    pt[w] = ((v >> t_shift) & t_mask) + t0;
    pb[w] = v >> b_shift;
  }
}

// radix_sort_bits (lo_bit: t_shift when the keys come in pixel order, else 0) then merge in `more`
// (nb sorted keys, may be 0) and unpack all into the Events fields in one pass (see _KeyLayout):
// b, x, y, t = t0 + t_rel (int64) and p = +1 / -1 (int8, OFF bit 1 = -1); outputs of na + nb entries.
extern "C" void dvs_sort_decode(int64_t* keys, int64_t na, int64_t bits, int64_t lo_bit, const int64_t* more,
                                int64_t nb, int64_t b_shift, int64_t t_shift, int64_t y_shift, int64_t x_mask,
                                int64_t y_mask, int64_t t0, int64_t* pb, int64_t* px, int64_t* py, int64_t* pt,
                                int8_t* pp) {
  const int64_t n = na + nb;
  const int64_t t_mask = (int64_t(1) << (b_shift - t_shift)) - 1;
  auto put = [&](int64_t w, int64_t v) {
    pp[w] = (v & 1) ? -1 : 1;
    px[w] = (v >> 1) & x_mask;
    py[w] = (v >> y_shift) & y_mask;
    pt[w] = ((v >> t_shift) & t_mask) + t0;
    pb[w] = v >> b_shift;
  };
  // keys in pixel order (lo_bit > 0) come ordered by descent: each descent's run is sorted alone
  if (lo_bit > 0) radix_sort_runs(keys, na, bits, b_shift, lo_bit); else radix_sort_bits(keys, na, bits, 0);
  if (nb == 0) {  // nothing to merge (no noise events): decoded in one vectorised pass
    decode_keys(keys, na, b_shift, t_shift, y_shift, x_mask, y_mask, t_mask, t0, pb, px, py, pt, pp);
    return;
  }
  int64_t i = 0, j = 0;
  const uint64_t END = ~uint64_t(0);  // above every key (keys are < 2^63)
  for (int64_t w = 0; w < n; ++w) {
    // branch-free merge step (the two streams interleave at random)
    const uint64_t va = i < na ? uint64_t(keys[i]) : END, vb = j < nb ? uint64_t(more[j]) : END;
    const bool from_a = va <= vb;
    const int64_t v = int64_t(from_a ? va : vb);
    i += from_a;
    j += !from_a;
    put(w, v);
  }
}

// The frames (B, P) float32 widened to float64 into out, and each row's range lo[b], hi[b] (float64; NaN where
// the row holds a NaN), in one pass (EventEmulator's float64 copy and its amin / amax). Sixteen running
// minima and maxima per row (x < m ? x : m is the IEEE min instruction's rule), merged at the end.
DVS_CLONES static void widen_row(const float* __restrict f, double* __restrict out, int64_t P, double* lo,
                                 double* hi) {
  float mn[16], mx[16];
  int32_t nan[16];
  for (int j = 0; j < 16; ++j) { mn[j] = INFINITY; mx[j] = -INFINITY; nan[j] = 0; }
  int64_t k = 0;
  for (; k + 16 <= P; k += 16) {
    for (int j = 0; j < 16; ++j) {
      const float v = f[k + j];
      out[k + j] = double(v);
      mn[j] = v < mn[j] ? v : mn[j];
      mx[j] = v > mx[j] ? v : mx[j];
      nan[j] |= v != v;
    }
  }
  for (; k < P; ++k) {
    const float v = f[k];
    out[k] = double(v);
    mn[0] = v < mn[0] ? v : mn[0];
    mx[0] = v > mx[0] ? v : mx[0];
    nan[0] |= v != v;
  }
  float a = mn[0], b = mx[0];
  int32_t any = nan[0];
  for (int j = 1; j < 16; ++j) { a = mn[j] < a ? mn[j] : a; b = mx[j] > b ? mx[j] : b; any |= nan[j]; }
  *lo = any ? NAN : double(a);
  *hi = any ? NAN : double(b);
}

extern "C" void dvs_widen_range(const float* f, int64_t B, int64_t P, double* out, double* lo, double* hi) {
  for (int64_t b = 0; b < B; ++b) widen_row(f + b * P, out + b * P, P, lo + b, hi + b);
}

// The front-end filters of dvsland.events.denoise as tonic writes them: one loop over the events
// in stream order with a per-pixel memory of the last event time (mem, flat, in/out).
extern "C" void dvs_baf_keep(const int64_t* pix, const int64_t* x, const int64_t* y, const int64_t* t, int64_t n,
                             int64_t* mem, int64_t H, int64_t W, int64_t window, int64_t neighbours, bool* keep) {
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
}

extern "C" void dvs_refractory_keep(const int64_t* pix, const int64_t* t, int64_t n, int64_t* mem, int64_t period,
                                    bool* keep) {
  for (int64_t i = 0; i < n; ++i) {
    keep[i] = t[i] - mem[pix[i]] > period;
    mem[pix[i]] = t[i];
  }
}

// The active pixels, those with an active 8-neighbour and the cells' active pixels of one element's
// occupancy image img ((H + 2) x (W + 2), zero border; 0 = no event), added to its outputs: a dense pass
// over the pixels, three rows at a time (vectorised), for windows with many events.
// (inlined into each clone of dvs_motion_counts)
__attribute__((always_inline)) static inline void dense_counts(const uint8_t* img, int64_t H, int64_t W,
                                                               int64_t cell, int64_t Hc, int64_t Wc, float* cells,
                                                               float* active, float* with_nb,
                                                               std::vector<int32_t>& col) {
  const int64_t Wp = W + 2;
  int64_t n_act = 0, n_nb = 0;
  col.assign(size_t(W), 0);
  for (int64_t y = 0; y < H; ++y) {
    const uint8_t* __restrict r0 = img + y * Wp;  // the rows above, at and below sensor row y
    const uint8_t* __restrict r1 = r0 + Wp;
    const uint8_t* __restrict r2 = r1 + Wp;
    int32_t a = 0, w = 0;
    for (int64_t x = 1; x <= W; ++x) {
      const int32_t c = r1[x] != 0;
      const int32_t nb = (r0[x - 1] | r0[x] | r0[x + 1] | r1[x - 1] | r1[x + 1] | r2[x - 1] | r2[x] | r2[x + 1]) != 0;
      a += c;
      w += c & nb;
    }
    n_act += a;
    n_nb += w;
    if (cells && y < Hc * cell) {  // a band of cell rows: per-column counts, then per cell
      int32_t* __restrict cl = col.data();
      for (int64_t x = 0; x < W; ++x) cl[x] += r1[x + 1] != 0;
      if ((y + 1) % cell == 0) {
        float* row = cells + (y / cell) * Wc;
        for (int64_t j = 0; j < Wc; ++j) {
          int32_t s = 0;
          for (int64_t x = j * cell; x < (j + 1) * cell; ++x) s += cl[x];
          row[j] += float(s);
        }
        col.assign(size_t(W), 0);
      }
    }
  }
  *active += float(n_act);
  *with_nb += float(n_nb);
}

// The integer counts and float32 sums of the estimators' motion-evidence test
// (dvsland.estimators.abstain), over n events sorted by element b (all on the B x H x W sensor):
// per element the active pixels, those with an active 8-neighbour and, when cells is not null,
// the active pixels of each cell x cell cell (H / cell rows, W / cell columns of cells, the sensor's
// first rows and columns); and the sums of (t, p, t^2, p t) over its events in their order (float32,
// as torch's segment sum adds them: the events must come sorted by b, one run per element),
// t = (t_us_event - t_us) as float32 divided by the largest |t| over all events (at least 1).
// The counts are integers (exact whatever the order): from a dense pass over the pixels where the
// window holds at least one event per 10 pixels, else event by event (where the two cost the same).
// Outputs zeroed by the caller.
extern "C" DVS_CLONES void dvs_motion_counts(const int64_t* b, const int64_t* x, const int64_t* y, const int64_t* t,
                                  const int8_t* p, int64_t n, int64_t B, int64_t H, int64_t W, int64_t cell,
                                  int64_t t_us, float* cells, float* active, float* with_nb, float* sums) {
  const int64_t Wp = W + 2, P = (H + 2) * Wp;
  static thread_local std::vector<uint8_t> occ;  // occupancy with a zero border: 0 none, 1 active, 2 counted
  occ.assign(size_t(B * P), 0);
  uint8_t* o = occ.data();  // a local pointer: byte stores may alias the vector (a TLS look-up per access)
  // the occupancy and the largest |t| in one pass over the events
  float m = 0.0f;
  for (int64_t i = 0; i < n; ++i) {
    o[b[i] * P + (y[i] + 1) * Wp + x[i] + 1] = 1;
    m = std::max(m, std::fabs(float(t[i] - t_us)));
  }
  m = std::max(m, 1.0f);
  const int64_t Hc = cell > 0 ? H / cell : 0, Wc = cell > 0 ? W / cell : 0;
  if (10 * n >= B * H * W) {
    static thread_local std::vector<int32_t> col;
    for (int64_t e = 0; e < B; ++e)
      dense_counts(o + e * P, H, W, cell, Hc, Wc, cells ? cells + e * Hc * Wc : nullptr, active + e, with_nb + e, col);
  } else {
    const int64_t nb[8] = {-Wp - 1, -Wp, -Wp + 1, -1, 1, Wp - 1, Wp, Wp + 1};
    // per run of equal b (one run per element: the events come sorted by b), counts in registers
    int64_t n_act = 0, n_nb = 0;
    for (int64_t i = 0; i < n; ++i) {
      const int64_t k = b[i] * P + (y[i] + 1) * Wp + x[i] + 1;
      if (o[k] == 1) {  // each active pixel once
        o[k] = 2;
        ++n_act;
        bool any = false;
        for (int j = 0; j < 8; ++j) any |= o[k + nb[j]] != 0;
        n_nb += any;
        if (cells && y[i] < Hc * cell && x[i] < Wc * cell)
          cells[b[i] * Hc * Wc + (y[i] / cell) * Wc + x[i] / cell] += 1.0f;
      }
      if (i + 1 == n || b[i + 1] != b[i]) {
        active[b[i]] += float(n_act);
        with_nb[b[i]] += float(n_nb);
        n_act = n_nb = 0;
      }
    }
  }
  // the sums of one element's events in their order (a run of equal b), added to its zeroed entries
  float s0 = 0.0f, s1 = 0.0f, s2 = 0.0f, s3 = 0.0f;
  for (int64_t i = 0; i < n; ++i) {
    const float tf = float(t[i] - t_us) / m, pf = float(p[i]);
    s0 += tf;
    s1 += pf;
    s2 += tf * tf;
    s3 += pf * tf;
    if (i + 1 == n || b[i + 1] != b[i]) {
      float* s = sums + b[i];
      s[0] += s0; s[B] += s1; s[2 * B] += s2; s[3 * B] += s3;
      s0 = s1 = s2 = s3 = 0.0f;
    }
  }
}

// Signed event counts per pooled cell: out[b, y / pool, x / pool] += p (ON +1, OFF -1) over n events on a
// W x H sensor pooled to h x w cells (out (B, h, w) float32, zeroed by the caller; the sums are whole
// numbers, exact in float32 below 2^24 in any order). Returns 0, or -1 where an event's cell lies outside
// the B x h x w grid (nothing is then trusted: the caller runs its torch path).
extern "C" int64_t dvs_cell_counts(const int64_t* b, const int64_t* x, const int64_t* y, const int8_t* p, int64_t n,
                                   int64_t B, int64_t h, int64_t w, int64_t pool, float* out) {
  const int64_t X = w * pool, Y = h * pool;
  // each column's and row's offset in a grid (tables: no division per event)
  static thread_local std::vector<int32_t> col, row;
  col.resize(size_t(X));
  row.resize(size_t(Y));
  for (int64_t v = 0; v < X; ++v) col[v] = int32_t(v / pool);
  for (int64_t v = 0; v < Y; ++v) row[v] = int32_t((v / pool) * w);
  const int32_t* cx = col.data();
  const int32_t* cy = row.data();
  // checked and added in one pass (the caller discards a partial grid where -1 comes back)
  for (int64_t i = 0; i < n; ++i) {
    const int64_t bi = b[i], xi = x[i], yi = y[i];
    if (uint64_t(bi) >= uint64_t(B) || uint64_t(xi) >= uint64_t(X) || uint64_t(yi) >= uint64_t(Y)) return -1;
    out[bi * (h * w) + cy[yi] + cx[xi]] += float(p[i]);
  }
  return 0;
}

// The ideal pixel's step (log interpolation, scalar thresholds and refractory period) in one pass
// over the pixels, the same float64 operations in the same order as EventEmulator._pixel_events /
// _emitted_log / _extra_keys (torch's addcmul is a fused multiply-add: std::fma here). Updates
// lref and t_last in place; dvs_pixel_scan returns the count of events and keeps their unsorted keys
// (up to the cap) for dvs_pixel_write, which copies them out.
static inline double clamp_lo(double x, double lo) { return x < lo ? lo : x; }  // NaN stays NaN, as torch
static inline double clamp_lohi(double x, double lo, double hi) { x = x < lo ? lo : x; return x > hi ? hi : x; }

// A pixel's events as keys: cnt of them at first + i step (µs after t0, rounded, clamped to [1, dt]).
static inline void emit_keys(int64_t code, double cnt, double first, double step, double dt, int64_t t_shift,
                             std::vector<int64_t>& keys) {
  keys.push_back((int64_t(clamp_lohi(std::floor(first + 0.5), 1.0, dt)) << t_shift) + code);
  const int64_t ce = int64_t(cnt);
  for (int64_t i = 1; i < ce; ++i) {
    const double tau = step * double(i) + first;
    keys.push_back((int64_t(clamp_lohi(std::floor(tau + 0.5), 1.0, dt)) << t_shift) + code);
  }
}

// The settings of one scan (scan_pixels). th_on_map / th_off_map: per-pixel thresholds (or null: the
// scalars th_on_s / th_off_s); r_elem: per-element refractory periods (or null: the scalar r_s). As
// the torch path: with maps the candidate bounds are th_on * shrink and th_off * -shrink and the
// general ON/OFF count; per-element r is divided as r / spacing, a scalar r as (1 / spacing) * r
// (torch's scalar / tensor). A pixel's key bits are (b << b_shift) | (y << y_shift) | (x << 1).
struct PixelScan {
  double th_on_s, th_off_s;
  const double *th_on_map, *th_off_map;  // null: the scalars
  double r_s;
  const double* r_elem;  // null: the scalar r_s
  double t0, dt, cap;
  bool spacing_may_bind, maps, same;
  int64_t b_shift, y_shift, t_shift;
};

static const double SCAN_TOL = 1e-9, SCAN_SHRINK = 1.0 - 2 * SCAN_TOL;

// flag[i] = 1 where pixel k + i (i < n) crosses a threshold: the candidate test of the torch path
// (the same float64 comparisons), written branch-free so that it vectorises.
DVS_INLINE void crossing_flags(const PixelScan& s, const double* __restrict l1, const double* __restrict lref,
                               int64_t k, int64_t n, uint8_t* __restrict flag) {
  if (s.maps) {
    const double *on = s.th_on_map + k, *off = s.th_off_map + k;
    for (int64_t i = 0; i < n; ++i) {
      const double d = l1[k + i] - lref[k + i];
      flag[i] = uint8_t(d >= on[i] * SCAN_SHRINK) | uint8_t(d <= off[i] * -SCAN_SHRINK);
    }
  } else if (s.same) {
    const double on = s.th_on_s * SCAN_SHRINK;
    for (int64_t i = 0; i < n; ++i) flag[i] = uint8_t(std::fabs(l1[k + i] - lref[k + i]) >= on);
  } else {
    const double on = s.th_on_s * SCAN_SHRINK, off = -(s.th_off_s * SCAN_SHRINK);
    for (int64_t i = 0; i < n; ++i) {
      const double d = l1[k + i] - lref[k + i];
      flag[i] = uint8_t(d >= on) | uint8_t(d <= off);
    }
  }
}

// What a crossing pixel emits (crossing_step): cnt events at first + i step (µs after t0), with the
// key bits code.
struct Emission {
  double cnt, first, step;
  int64_t code;
};

// The step of pixel k (at column x of the row with key bits row_code), which crosses a threshold: its
// new reference and last event time written, its events returned. No branch on the pixel's values
// (the refractory rule's terms are computed and then selected), so that consecutive pixels' division
// chains overlap in the core: about 3x faster than branching on them.
DVS_INLINE Emission crossing_step(const PixelScan& s, const double* l1, const double* lref_in, double* lref_out,
                                  const double* l0, const double* tlast_in, double* tlast_out, double r, int64_t k,
                                  int64_t x, int64_t row_code) {
  const double lr = lref_in[k], tlk = tlast_in[k];
  const double d = l1[k] - lr;
  const double th_on = s.maps ? s.th_on_map[k] : s.th_on_s, th_off = s.maps ? s.th_off_map[k] : s.th_off_s;
  double n, th;
  if (s.same) {
    n = std::floor(std::fabs(d / th_on) + SCAN_TOL);
    th = (d > 0 ? 1.0 : (d < 0 ? -1.0 : 0.0)) * th_on;
  } else {
    const double n_on = clamp_lo(std::floor(d / th_on + SCAN_TOL), 0.0);
    const double n_off = clamp_lo(std::floor(-d / th_off + SCAN_TOL), 0.0);
    n = n_on + n_off;
    th = d > 0 ? th_on : -th_off;
  }
  const double tl = tlk - s.t0;
  // _emitted_log
  const double dl = l1[k] - l0[k];
  const double scale = (1.0 / dl) * s.dt;  // torch: scalar / tensor = tensor.reciprocal() * scalar
  const double spacing = th * scale;
  const double base = (lr - l0[k]) * scale;
  double cnt = n, first = base + spacing, step = spacing;
  if (s.r_elem || r > 0) {
    const bool near = first < tl + r;
    const bool binds = s.spacing_may_bind ? ((spacing < r) || near) : near;
    const double j0 = clamp_lo(std::ceil(((tl - base) + r) / spacing), 1.0);
    const double m = clamp_lo(std::ceil(s.r_elem ? r / spacing : (1.0 / spacing) * r), 1.0);  // as torch
    const double c = clamp_lo(std::floor((n - j0) / m) + 1.0, 0.0);
    cnt = binds ? (std::isfinite(c) ? c : 0.0) : cnt;
    first = binds ? std::fma(j0, spacing, base) : first;
    step = binds ? m * spacing : step;
  }
  lref_out[k] = std::fma(n, th, lr);
  tlast_out[k] = cnt > 0 ? std::fma(cnt - 1.0, step, first) + s.t0 : tlk;
  return Emission{cnt, first, step, row_code | (x << 1) | (std::signbit(th) ? 1 : 0)};
}

// The pixels are (B, H, W) in row-major order, in chunks of up to SCAN_CHUNK of a row: the candidate
// test over the chunk (vectorised), the chunk's values copied to the outputs where they are not the
// inputs (a donated state is updated in place: a quiet pixel is then not written, and its last
// event time not read), the crossing pixels' steps, then their keys in pixel order (written at once,
// until the cap is passed: then only counted, and the caller refuses the step).
static const int64_t SCAN_CHUNK = 256;

DVS_CLONES static double scan_pixels(const double* l1, const double* lref_in, double* lref_out, const double* l0,
                                     const double* tlast_in, double* tlast_out, int64_t B, int64_t H, int64_t W,
                                     const PixelScan& s, std::vector<int64_t>& keys) {
  uint8_t flag[SCAN_CHUNK];
  int64_t at[SCAN_CHUNK];
  Emission em[SCAN_CHUNK];
  double total = 0.0;
  int64_t k = 0;
  for (int64_t b = 0; b < B; ++b) {
    const double r = s.r_elem ? s.r_elem[b] : s.r_s;
    for (int64_t y = 0; y < H; ++y) {
      const int64_t row_code = (b << s.b_shift) | (y << s.y_shift);
      for (int64_t x0 = 0; x0 < W; x0 += SCAN_CHUNK) {
        const int64_t n = std::min(SCAN_CHUNK, W - x0);
        crossing_flags(s, l1, lref_in, k, n, flag);
        if (lref_out != lref_in) std::memcpy(lref_out + k, lref_in + k, size_t(n) * sizeof(double));
        if (tlast_out != tlast_in) std::memcpy(tlast_out + k, tlast_in + k, size_t(n) * sizeof(double));
        int64_t m = 0;
        for (int64_t i = 0; i < n; ++i) {  // the crossing pixels, compacted without a branch
          at[m] = i;
          m += flag[i];
        }
        for (int64_t j = 0; j < m; ++j)
          em[j] = crossing_step(s, l1, lref_in, lref_out, l0, tlast_in, tlast_out, r, k + at[j], x0 + at[j], row_code);
        for (int64_t j = 0; j < m; ++j) {
          if (!(em[j].cnt > 0)) continue;
          total += em[j].cnt;
          if (total <= s.cap) emit_keys(em[j].code, em[j].cnt, em[j].first, em[j].step, s.dt, s.t_shift, keys);
        }
        k += n;
      }
    }
  }
  return total;
}

static thread_local std::vector<int64_t> g_keys;  // kept across calls (no fresh pages per step)

// th_on_map, th_off_map, r_elem: null for the scalars (see scan_pixels); cap < 0: no cap. Returns the
// events' count; their keys are kept for dvs_pixel_write when the count is within the cap.
extern "C" double dvs_pixel_scan(const double* l1, const double* lref_in, double* lref_out, const double* l0,
                                 const double* tlast_in, double* tlast_out, int64_t B, int64_t H, int64_t W,
                                 int64_t b_shift, int64_t y_shift, double th_on, double th_off,
                                 const double* th_on_map, const double* th_off_map, double r, const double* r_elem,
                                 double t0, double dt, int64_t spacing_may_bind, int64_t t_shift, int64_t cap) {
  g_keys.clear();
  const int64_t P = B * H * W;
  if (g_keys.capacity() < size_t(P)) g_keys.reserve(size_t(P));
  const bool maps = th_on_map != nullptr;
  const PixelScan s{th_on, th_off, th_on_map, th_off_map, r, r_elem, t0, dt, cap < 0 ? HUGE_VAL : double(cap),
                    spacing_may_bind != 0, maps, !maps && th_on == th_off, b_shift, y_shift, t_shift};
  return scan_pixels(l1, lref_in, lref_out, l0, tlast_in, tlast_out, B, H, W, s, g_keys);
}

// The keys of the last dvs_pixel_scan's events (as many as it counted, within its cap) into out.
extern "C" void dvs_pixel_write(int64_t* out) {
  if (!g_keys.empty()) std::memcpy(out, g_keys.data(), g_keys.size() * sizeof(int64_t));
  if (g_keys.capacity() > (size_t(1) << 22)) std::vector<int64_t>().swap(g_keys);  // do not keep huge buffers
}
"""

# no contraction into fused multiply-adds beyond the explicit std::fma calls: the torch path's float64
# results bit for bit (the pixel scan's AVX2/FMA clone comes from its target_clones attribute)
_CFLAGS = ["-O3", "-ffp-contract=off", "-std=c++17"]

_I64, _F64, _VOID, _P = ctypes.c_int64, ctypes.c_double, None, ctypes.c_void_p
#: the C functions' (argument types, result type)
_SIGNATURES = {
    "dvs_radix_sort": ([_P, _I64, _I64], _VOID),
    "dvs_sort_decode": ([_P, _I64, _I64, _I64, _P, _I64] + [_I64] * 6 + [_P] * 5, _VOID),
    "dvs_baf_keep": ([_P] * 4 + [_I64, _P] + [_I64] * 4 + [_P], _VOID),
    "dvs_refractory_keep": ([_P, _P, _I64, _P, _I64, _P], _VOID),
    "dvs_pixel_scan": ([_P] * 6 + [_I64] * 5 + [_F64, _F64, _P, _P, _F64, _P, _F64, _F64, _I64, _I64, _I64], _F64),
    "dvs_pixel_write": ([_P], _VOID),
    "dvs_widen_range": ([_P, _I64, _I64, _P, _P, _P], _VOID),
    "dvs_motion_counts": ([_P] * 5 + [_I64] * 6 + [_P] * 4, _VOID),
    "dvs_cell_counts": ([_P] * 4 + [_I64] * 5 + [_P], _I64),
}


class Kernels:
    """The loaded library's functions on torch tensors (CPU; each checks its inputs' dtype and layout)."""

    def __init__(self, lib: ctypes.CDLL):
        self._lib = bind_functions(lib, _SIGNATURES)

    def radix_sort_(self, keys: torch.Tensor, bits: int) -> None:
        """Sort ``keys`` ((N,) int64, values in [0, 2^bits)) in place."""
        self._lib.dvs_radix_sort(_ptr(keys, torch.int64, "radix_sort_: keys"), keys.numel(), int(bits))

    def sort_decode(self, keys: torch.Tensor, bits: int, lo_bit: int, more: torch.Tensor, b_shift: int, t_shift: int,
                    y_shift: int, x_mask: int, y_mask: int, t0: int):
        """Sort ``keys`` in place (by bits lo_bit..bits-1), merge in ``more`` (sorted) and unpack:
        [b, x, y, t (N,) int64, p (N,) int8]."""
        na, nb = keys.numel(), more.numel()
        out = [torch.empty(na + nb, dtype=torch.int64) for _ in range(4)] + [torch.empty(na + nb, dtype=torch.int8)]
        self._lib.dvs_sort_decode(_ptr(keys, torch.int64, "sort_decode: keys"), na, int(bits), int(lo_bit),
                                  _ptr(more, torch.int64, "sort_decode: more"), nb, int(b_shift), int(t_shift),
                                  int(y_shift), int(x_mask), int(y_mask), int(t0), *(o.data_ptr() for o in out))
        return out

    def widen_range(self, frames: torch.Tensor):
        """(float64 copy (B, ...), lo (B,), hi (B,)) of ``frames`` (B, ...) float32 contiguous: each row's
        min and max as float64 (NaN where the row holds a NaN), in one pass."""
        B = frames.shape[0]
        out = torch.empty(frames.shape, dtype=torch.float64)
        lo, hi = torch.empty(B, dtype=torch.float64), torch.empty(B, dtype=torch.float64)
        self._lib.dvs_widen_range(_ptr(frames, torch.float32, "widen_range: frames"), B, frames.numel() // max(B, 1),
                                  out.data_ptr(), lo.data_ptr(), hi.data_ptr())
        return out, lo, hi

    def baf_keep(self, pix, x, y, t, mem, H: int, W: int, window: int, neighbours: int) -> torch.Tensor:
        """The background-activity filter's keep mask (N,) bool; updates ``mem`` in place."""
        keep = torch.empty(pix.numel(), dtype=torch.bool)
        args = [_ptr(v, torch.int64, f"baf_keep: {k}") for k, v in (("pix", pix), ("x", x), ("y", y), ("t", t))]
        self._lib.dvs_baf_keep(*args, pix.numel(), _ptr(mem, torch.int64, "baf_keep: mem"), int(H), int(W),
                               int(window), int(neighbours), keep.data_ptr())
        return keep

    def refractory_keep(self, pix, t, mem, period: int) -> torch.Tensor:
        """The refractory filter's keep mask (N,) bool; updates ``mem`` in place."""
        keep = torch.empty(pix.numel(), dtype=torch.bool)
        self._lib.dvs_refractory_keep(_ptr(pix, torch.int64, "refractory_keep: pix"),
                                      _ptr(t, torch.int64, "refractory_keep: t"), pix.numel(),
                                      _ptr(mem, torch.int64, "refractory_keep: mem"), int(period), keep.data_ptr())
        return keep

    def motion_counts(self, b, x, y, t, p, B: int, H: int, W: int, cell: int, t_us: int):
        """The motion-evidence test's counts of N events sorted by b (int64 b, x, y, t; int8 p; on the
        B x H x W sensor): (cells (B, (H // cell) (W // cell)) float32 or None when cell < 1, active
        (B,), with_nb (B,) float32, sums (4, B) float32); see the kernel's comment."""
        i64 = torch.int64
        cells = torch.zeros(B, (H // cell) * (W // cell), dtype=torch.float32) if cell >= 1 else None
        active, with_nb = torch.zeros(B, dtype=torch.float32), torch.zeros(B, dtype=torch.float32)
        sums = torch.zeros(4, B, dtype=torch.float32)
        self._lib.dvs_motion_counts(
            _ptr(b, i64, "motion_counts: b"), _ptr(x, i64, "motion_counts: x"), _ptr(y, i64, "motion_counts: y"),
            _ptr(t, i64, "motion_counts: t"), _ptr(p, torch.int8, "motion_counts: p"), b.numel(), int(B), int(H),
            int(W), int(cell) if cells is not None else 0, int(t_us), None if cells is None else cells.data_ptr(),
            active.data_ptr(), with_nb.data_ptr(), sums.data_ptr())
        return cells, active, with_nb, sums

    def cell_counts(self, b, x, y, p, B: int, h: int, w: int, pool: int) -> Optional[torch.Tensor]:
        """(B, h, w) float32 signed counts (ON minus OFF) of N events (int64 b, x, y; int8 p) per ``pool``
        x ``pool`` cell, or None where a cell falls outside the grid (the caller's torch path decides)."""
        out = torch.zeros(int(B), int(h), int(w), dtype=torch.float32)
        status = self._lib.dvs_cell_counts(
            _ptr(b, torch.int64, "cell_counts: b"), _ptr(x, torch.int64, "cell_counts: x"),
            _ptr(y, torch.int64, "cell_counts: y"), _ptr(p, torch.int8, "cell_counts: p"), b.numel(), int(B), int(h),
            int(w), int(pool), out.data_ptr())
        return None if status < 0 else out

    def pixel_events(self, l1, lref, l0, tlast, shape, b_shift: int, y_shift: int, th_on: float, th_off: float,
                     th_on_map, th_off_map, r: float, r_elem, t0: float, dt: float, spacing_may_bind: bool,
                     t_shift: int, cap: int, n_out: torch.Tensor, lref_out=None, tlast_out=None) -> torch.Tensor:
        """The ideal pixel's step over the B x H x W pixels of ``shape`` (float64 (P,) log intensities
        l1, l0, reference lref and last event times tlast, P = B H W, row-major): the unsorted event
        keys (int64; a pixel's key bits are (b << b_shift) | (y << y_shift) | (x << 1) | OFF), or an empty
        tensor when their count (written to ``n_out[0]``) exceeds ``cap`` (cap < 0: no cap). The new
        reference and last event times go to ``lref_out`` / ``tlast_out`` ((P,) float64; None: in place
        into lref / tlast). Empty maps / r_elem ((B,) float64): the scalars."""
        f64 = torch.float64
        B, H, W = (int(v) for v in shape)
        lref_out = lref if lref_out is None else lref_out
        tlast_out = tlast if tlast_out is None else tlast_out
        for name, v in (("l1", l1), ("lref", lref), ("l0", l0), ("tlast", tlast), ("lref_out", lref_out),
                        ("tlast_out", tlast_out)):
            if v.numel() != B * H * W:
                raise RuntimeError(f"pixel_events: {name} must hold B * H * W = {B * H * W} values, got {v.numel()}")
        n = self._lib.dvs_pixel_scan(
            _ptr(l1, f64, "pixel_events: l1"), _ptr(lref, f64, "pixel_events: lref"),
            _ptr(lref_out, f64, "pixel_events: lref_out"), _ptr(l0, f64, "pixel_events: l0"),
            _ptr(tlast, f64, "pixel_events: tlast"), _ptr(tlast_out, f64, "pixel_events: tlast_out"), B, H, W,
            int(b_shift), int(y_shift), float(th_on), float(th_off), _ptr(th_on_map, f64, "pixel_events: maps"),
            _ptr(th_off_map, f64, "pixel_events: maps"), float(r), _ptr(r_elem, f64, "pixel_events: r_elem"),
            float(t0), float(dt), int(bool(spacing_may_bind)), int(t_shift), int(cap))
        n_out[0] = n
        if cap >= 0 and n > cap:
            return torch.empty(0, dtype=torch.int64)
        keys = torch.empty(int(n), dtype=torch.int64)
        self._lib.dvs_pixel_write(keys.data_ptr())
        return keys


#: the library (its mode, cache and build)
LIBRARY = NativeLibrary("dvsland_events_native", _SRC, _CFLAGS, "DVSLAND_NATIVE_SORT", "dvsland.events.native", Kernels)


def use_native_sort(on: Optional[bool] = True) -> None:
    """Pick the mode for this process: True = on, False = off, None = back to ``DVSLAND_NATIVE_SORT``
    (default auto)."""
    LIBRARY.use(on)


@contextlib.contextmanager
def native_sort_mode(on: Optional[bool]):
    """:func:`use_native_sort` (``on``) inside the block, the process's earlier choice after it
    (how the benchmarks time the torch and the compiled path in one process)."""
    saved = LIBRARY.chosen
    use_native_sort(on)
    try:
        yield
    finally:
        LIBRARY.chosen = saved


def mode() -> str:
    """``"on"``, ``"off"`` or ``"auto"``: :func:`use_native_sort`'s choice, else the environment's.

    Raises:
        ValueError naming ``DVSLAND_NATIVE_SORT`` when it holds another word.
    """
    return LIBRARY.mode()


def module_name() -> str:
    """The library's name: a hash of the source, flags, compiler and machine."""
    return LIBRARY.name()


def build_dir() -> Path:
    """The folder of the build (:func:`dvsland.native_build.library_dir`)."""
    return LIBRARY.build_dir()


def cached() -> bool:
    """Whether the build of this exact source is in the cache."""
    return LIBRARY.cached()


def native_sort_enabled() -> bool:
    """Whether the emulator and the denoiser should use the kernels now: mode on; or auto with the
    build cached, loaded, or a C++ compiler to build it with. Never compiles."""
    return LIBRARY.enabled()


def kernels() -> Optional[Kernels]:
    """The kernels when they are to be used now (:func:`native_sort_enabled`; built once when
    needed), else None (the torch path). The same as :func:`load`."""
    return LIBRARY.load()


def build(verbose: bool = False) -> Kernels:
    """Compile (when not cached) and load the kernels. Raises on any build error."""
    return LIBRARY.build(verbose)


def load() -> Optional[Kernels]:
    """The kernels (built once when needed), or None: mode off; auto with neither a cached build nor
    a compiler; or a failed build or load (one warning, then the torch path for the rest of the process)."""
    return LIBRARY.load()


def radix_sort_(keys: torch.Tensor, bits: int) -> bool:
    """Sort ``keys`` ((N,) int64 CPU, contiguous, values in [0, 2^bits)) in place with the compiled
    kernel; returns False (nothing done) when it is not enabled or not available."""
    mod = kernels()
    if mod is None:
        return False
    mod.radix_sort_(keys, int(bits))
    return True


__all__ = ["Kernels", "LIBRARY", "use_native_sort", "native_sort_enabled", "mode", "cached", "build", "build_dir",
           "module_name", "load", "kernels", "radix_sort_"]
