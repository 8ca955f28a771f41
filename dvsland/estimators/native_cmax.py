"""Compiled kernels of ``cmax`` (CPU), each identical to its torch path.

The splat-and-sum of the score: :func:`dvsland.estimators.contrast.split_contrast` splats every
warped event (bilinear, four corners) into one image per element, candidate and half of the
events, and needs per image the total weight and the sums of squares and cross products. The torch
path builds all images at once (one large canvas, B x G x 2 images); this kernel takes the events
element by element and half by half (a counting sort), computes their corner weights in one
vectorised pass, splats them into one small canvas per (element, candidate) that stays in the
cache, and clears only the corners touched. Corner weights are integers (multiples of 2^-12 of an
event, see ``WEIGHT_UNIT`` in contrast.py) and the sums are int64, so the kernel's sums are the
torch path's exactly, in any order and on any number of threads; its float32 arithmetic (warp,
box test, corner weights) is the torch path's operation for operation (the exponential comes in
from torch).

Beside it, the per-event passes of an update: the store's thinning (``store_select``), each
window's counts and the gather of its estimating elements' events as the score takes them
(``window_gather``), and the event weights (``hot_weights``, ``radial_counts`` / ``radial_apply``).
Tests pin every kernel to its torch path.

Plain C++ behind a C interface (no torch headers), called through ``ctypes`` on the tensors'
memory, compiled with the system's C++ compiler in a second or two into a cache folder
(:func:`dvsland.native_build.library_dir`), under a name that carries a hash of the source, the
flags, the compiler and the machine. ``DVSLAND_NATIVE_CMAX`` (or :func:`use_native_cmax`) picks the mode:

- ``auto`` (default, also when unset or empty): use the kernel; when it is not in the cache, build
  it on first use if a C++ compiler is found, else run the torch path, silently.
- ``1`` / ``on`` / ``true`` / ``yes``: the same, but a missing compiler is warned about.
- ``0`` / ``off`` / ``false`` / ``no``: never use it.

``python -m dvsland.estimators.build_native`` (or ``dvsland build-native``) builds it ahead. On any
build or load error the torch path runs, with one warning.
"""

from __future__ import annotations

import ctypes
import platform
from pathlib import Path
from typing import Optional

import torch

from dvsland.native_build import PARALLEL_RANGES, NativeLibrary, bind_functions, tensor_address as _ptr

_SRC = r"""
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <thread>
#include <vector>

""" + PARALLEL_RANGES + r"""
// A stable counting sort of the events [0, E) by their element Bi[e] in [0, B): start (B + 1) the first
// position of each element in order (E), which lists the events element by element, in event order
// within one. The events come in runs of one element (each stored step is sorted by element): the counts
// and positions move by whole runs, not by one shared counter per event (a chain of loads and stores
// through the same counter that a plain histogram waits on).
static void sort_by_element(const int64_t* Bi, int64_t E, int64_t B, std::vector<int64_t>& start,
                            std::vector<int64_t>& order) {
  start.assign(B + 1, 0);
  order.resize(E);
  for (int64_t e = 0; e < E;) {
    const int64_t k = Bi[e];
    int64_t j = e + 1;
    while (j < E && Bi[j] == k) ++j;
    start[k + 1] += j - e;
    e = j;
  }
  for (int64_t i = 0; i < B; ++i) start[i + 1] += start[i];
  std::vector<int64_t> pos(start.begin(), start.end() - 1);
  for (int64_t e = 0; e < E;) {
    const int64_t k = Bi[e];
    int64_t j = e + 1;
    while (j < E && Bi[j] == k) ++j;
    int64_t* o = order.data() + pos[k];
    for (int64_t i = e; i < j; ++i) o[i - e] = i;
    pos[k] += j - e;
    e = j;
  }
}

// A stable counting sort of the events [0, E) by key(e) in [0, n_keys): start (n_keys + 1) the first
// position of each key in order (E), which lists the events key by key, in event order within a key.
template <class F>
static void counting_sort(int64_t E, int64_t n_keys, F key, std::vector<int64_t>& start, std::vector<int64_t>& order) {
  start.assign(n_keys + 1, 0);
  order.resize(E);
  for (int64_t e = 0; e < E; ++e) start[key(e) + 1]++;
  for (int64_t i = 0; i < n_keys; ++i) start[i + 1] += start[i];
  std::vector<int64_t> pos(start.begin(), start.end() - 1);
  for (int64_t e = 0; e < E; ++e) order[pos[key(e)]++] = e;
}

// Per element b and candidate g: n[b,g,h] = sum of the integer corner weights of half h, and
// s[b,g,:] = (sum_p I0^2, sum_p I1^2, sum_p I0 I1) over the canvas pixels p; see the module doc
// of dvsland/estimators/native_cmax.py and split_contrast in contrast.py (the torch path).
//
// The events of an element are taken ordered by half. For each candidate, a branch-free pass over them
// (corner_weights, which the compiler vectorises, with a clone per instruction set on x86-64 Linux) gives
// each event's canvas slot and four integer corner weights (all 0 outside the counted box: it adds nothing);
// a scalar pass adds them to the canvas, which holds both halves of a pixel side by side, and keeps the sums
// as it goes: adding q to pixel value v of half h (the other half holding u there) adds q (2 v + q) to
// sum I_h^2 and q u to sum I0 I1. The sums are integers, so any order of the events gives them exactly.
#if defined(__x86_64__) && defined(__linux__) && (!defined(__clang__) || __clang_major__ >= 14)
#define DVS_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define DVS_CLONES
#endif

DVS_CLONES
void cmax_corner_weights(const float* __restrict ex, const float* __restrict ey, const float* __restrict ew,
                         const float* __restrict es, int64_t n_e, float fcx, float fcy, float xl, float xh, float yl,
                         float yh, float xmax, float ymax, float uf, int32_t row, int32_t* __restrict at,
                         int32_t* __restrict q) {
  for (int64_t k = 0; k < n_e; ++k) {
    const float sc = es[k];
    const float xw = (ex[k] - fcx) * sc;
    const float yw = (ey[k] - fcy) * sc;
    const bool in = (xw >= xl) & (xw <= xh) & (yw >= yl) & (yw <= yh);
    const float wk = ew[k];
    const float w = in ? wk : 0.0f;
    const float xs = xw + fcx, ys = yw + fcy;
    const float x0 = std::min(std::max(std::floor(xs), 0.0f), xmax);
    const float y0 = std::min(std::max(std::floor(ys), 0.0f), ymax);
    const float fx = std::min(std::max(xs - x0, 0.0f), 1.0f);
    const float fy = std::min(std::max(ys - y0, 0.0f), 1.0f);
    const float wy1 = w * fy;
    const float wy0 = w - wy1;
    const float a = wy0 * fx, c = wy1 * fx;
    const float w00 = wy0 - a, w10 = wy1 - c;
    q[4 * k] = (int32_t)std::nearbyint(w00 * uf);
    q[4 * k + 1] = (int32_t)std::nearbyint(a * uf);
    q[4 * k + 2] = (int32_t)std::nearbyint(w10 * uf);
    q[4 * k + 3] = (int32_t)std::nearbyint(c * uf);
    const int32_t slot = (int32_t)y0 * row + 2 * (int32_t)x0;
    at[k] = in ? slot : 0;
  }
}

// events [k0, k1) of half h into the side-by-side canvas cv (row width Wc pixels); adds to n, s_h, s01
template <class T>
static inline void add_half(const int32_t* at, const int32_t* q, int64_t k0, int64_t k1, int h, T* cv, int64_t Wc,
                            int64_t& n, int64_t& s, int64_t& s01) {
  const int64_t d1 = 2, dW = 2 * Wc, dW1 = 2 * Wc + 2;
  const int o = 1 - 2 * h;  // the other half's slot, relative
  int64_t nn = 0, ss = 0, sx = 0;
  for (int64_t k = k0; k < k1; ++k) {
    const int64_t q0 = q[4 * k], q1 = q[4 * k + 1], q2 = q[4 * k + 2], q3 = q[4 * k + 3];
    T* p = cv + at[k] + h;
    const int64_t v0 = p[0], v1 = p[d1], v2 = p[dW], v3 = p[dW1];
    const int64_t u0 = p[o], u1 = p[d1 + o], u2 = p[dW + o], u3 = p[dW1 + o];
    nn += q0 + q1 + q2 + q3;
    ss += q0 * (2 * v0 + q0) + q1 * (2 * v1 + q1) + q2 * (2 * v2 + q2) + q3 * (2 * v3 + q3);
    sx += q0 * u0 + q1 * u1 + q2 * u2 + q3 * u3;
    p[0] = (T)(v0 + q0); p[d1] = (T)(v1 + q1); p[dW] = (T)(v2 + q2); p[dW1] = (T)(v3 + q3);
  }
  n += nn; s += ss; s01 += sx;
}

// both halves of the four corners of each event's slot back to 0
template <class T> static inline void clear_corners(T* cv, const int32_t* at, int64_t n_e, int64_t Wc) {
  for (int64_t k = 0; k < n_e; ++k) {
    T* p = cv + at[k];
    p[0] = 0; p[1] = 0; p[2] = 0; p[3] = 0;
    p[2 * Wc] = 0; p[2 * Wc + 1] = 0; p[2 * Wc + 2] = 0; p[2 * Wc + 3] = 0;
  }
}

// xc, yc, wt (E,) float32; b, half (E,) int64; scale (G, E) float32; ginv (G, B) float32; outputs
// n (B, G, 2) and s (B, G, 3) int64, zeroed by the caller. Returns 0; -1 when some b is out of [0, B) or
// some half not 0 / 1, -2 when some |weight| x unit is 2^30 or more or not finite (the corner weights are
// int32); nothing written then.
extern "C" int64_t cmax_splat_sums(const float* X, const float* Y, const int64_t* Bi, const int64_t* Hf,
                                   const float* S, const float* GI, const float* W, int64_t E, int64_t G, int64_t B,
                                   double cx, double cy, double x_lo, double x_hi, double y_lo, double y_hi,
                                   int64_t Hc, int64_t Wc, double unit, int64_t n_threads, int64_t* N, int64_t* Sq) {
  const int64_t P = Hc * Wc;
  for (int64_t e = 0; e < E; ++e)
    if (!(Bi[e] >= 0 && Bi[e] < B && (Hf[e] == 0 || Hf[e] == 1))) return -1;
  for (int64_t e = 0; e < E; ++e)
    if (!(std::fabs((double)W[e]) * unit < 1073741824.0)) return -2;
  static thread_local std::vector<int64_t> start, order;  // by (element, half); kept: no fresh pages per call
  counting_sort(E, 2 * B, [&](int64_t e) { return 2 * Bi[e] + Hf[e]; }, start, order);
  const float fcx = (float)cx, fcy = (float)cy, uf = (float)unit;
  const float lox = (float)(x_lo - cx), hix = (float)(x_hi - cx), loy = (float)(y_lo - cy), hiy = (float)(y_hi - cy);
  const float xmax = (float)(Wc - 2), ymax = (float)(Hc - 2);
  parallel_ranges(B, n_threads, [&](int64_t lo, int64_t hi) {
    // each thread's canvases and buffers are kept across calls (no fresh pages per call); every use
    // clears the canvas pixels it touched, so a kept canvas is all zeros
    static thread_local std::vector<int32_t> canvas32;
    static thread_local std::vector<int64_t> canvas64;
    static thread_local std::vector<float> ex, ey, ew, es;
    static thread_local std::vector<int32_t> at, q;
    if (canvas32.size() != size_t(2 * P)) canvas32.assign(2 * P, 0);
    if (!canvas64.empty() && canvas64.size() != size_t(2 * P)) canvas64.clear();
    for (int64_t bi = lo; bi < hi; ++bi) {
      const int64_t e0 = start[2 * bi], n0_e = start[2 * bi + 1] - e0, n_e = start[2 * bi + 2] - e0;
      if (n_e == 0) continue;
      // the element's events, contiguous (read G times); an int32 canvas when no pixel can
      // reach 2^31 (every pixel holds at most the element's whole weight), else int64
      ex.resize(n_e); ey.resize(n_e); ew.resize(n_e); es.resize(n_e); at.resize(n_e); q.resize(4 * n_e);
      double total = 0.0;
      for (int64_t k = 0; k < n_e; ++k) {
        const int64_t e = order[e0 + k];
        ex[k] = X[e]; ey[k] = Y[e]; ew[k] = W[e];
        total += std::fabs((double)W[e]) * unit + 4.0;
      }
      const bool wide = !(total < 2147483647.0);
      if (wide && canvas64.empty()) canvas64.assign(2 * P, 0);
      for (int64_t g = 0; g < G; ++g) {
        const float* Sg = S + g * E;
        for (int64_t k = 0; k < n_e; ++k) es[k] = Sg[order[e0 + k]];
        const float gi = GI[g * B + bi];
        cmax_corner_weights(ex.data(), ey.data(), ew.data(), es.data(), n_e, fcx, fcy, lox * gi, hix * gi, loy * gi,
                            hiy * gi, xmax, ymax, uf, (int32_t)(2 * Wc), at.data(), q.data());
        int64_t n0 = 0, n1 = 0, s0 = 0, s1 = 0, s01 = 0;
        if (wide) {
          add_half(at.data(), q.data(), 0, n0_e, 0, canvas64.data(), Wc, n0, s0, s01);
          add_half(at.data(), q.data(), n0_e, n_e, 1, canvas64.data(), Wc, n1, s1, s01);
          clear_corners(canvas64.data(), at.data(), n_e, Wc);
        } else {
          add_half(at.data(), q.data(), 0, n0_e, 0, canvas32.data(), Wc, n0, s0, s01);
          add_half(at.data(), q.data(), n0_e, n_e, 1, canvas32.data(), Wc, n1, s1, s01);
          clear_corners(canvas32.data(), at.data(), n_e, Wc);
        }
        const int64_t j = bi * G + g;
        N[j * 2] = n0; N[j * 2 + 1] = n1;
        Sq[j * 3] = s0; Sq[j * 3 + 1] = s1; Sq[j * 3 + 2] = s01;
      }
    }
  });
  return 0;
}

// For each event, how many events of its element lie on its pixel: bincount(b * n_px + px)[b * n_px + px]
// computed element by element in a small canvas (b (E,) int64 in [0, B), px (E,) int64 in [0, n_px)).
// out (E,) int64. Returns 0, or -1 when some b or px is out of range (nothing written).
// For the events idx[0 .. n) of one element (pixels Px[idx[k]] in [0, n_px)): put(k, c), c the events of the
// n on event k's pixel, counted on ``canvas`` (n_px zeros, left zeroed).
// (The pixels are gathered once into ``pk``, a buffer of the caller's, and read three times from there.)
template <class F>
static void element_pixel_counts(const int64_t* Px, const int64_t* idx, int64_t n, int32_t* canvas,
                                 std::vector<int64_t>& pk, F put) {
  pk.resize(n);
  for (int64_t k = 0; k < n; ++k) pk[k] = Px[idx[k]];
  for (int64_t k = 0; k < n; ++k) canvas[pk[k]]++;
  for (int64_t k = 0; k < n; ++k) put(k, canvas[pk[k]]);
  for (int64_t k = 0; k < n; ++k) canvas[pk[k]] = 0;
}

static int64_t pixel_counts(const int64_t* Bi, const int64_t* Px, int64_t E, int64_t B, int64_t n_px, int64_t* O) {
  for (int64_t e = 0; e < E; ++e)
    if (!(Bi[e] >= 0 && Bi[e] < B && Px[e] >= 0 && Px[e] < n_px)) return -1;
  static thread_local std::vector<int64_t> start, order;  // by element; kept: no fresh pages per call
  sort_by_element(Bi, E, B, start, order);
  static thread_local std::vector<int32_t> canvas;  // kept across calls, all zeros between uses
  static thread_local std::vector<int64_t> pk;
  if (canvas.size() != size_t(n_px)) canvas.assign(n_px, 0);
  for (int64_t bi = 0; bi < B; ++bi) {
    const int64_t* idx = order.data() + start[bi];
    element_pixel_counts(Px, idx, start[bi + 1] - start[bi], canvas.data(), pk,
                         [&](int64_t k, int32_t c) { O[idx[k]] = c; });
  }
  return 0;
}

// The noise floor's per-element sums of the event weights w and w^2 (cmax._noise_floor, the torch path:
// two index_add_ into zeroed float64 sums, in event order): s1[b] += w, s2[b] += w * w, w = double(wt[e]).
// Returns 0, or -1 when some b is out of range (nothing written).
extern "C" int64_t cmax_weight_sums(const int64_t* Bi, const float* wt, int64_t E, int64_t B, double* s1, double* s2) {
  for (int64_t e = 0; e < E; ++e)
    if (!(Bi[e] >= 0 && Bi[e] < B)) return -1;
  for (int64_t e = 0; e < E; ++e) {
    const double w = double(wt[e]);
    s1[Bi[e]] += w;
    s2[Bi[e]] += w * w;
  }
  return 0;
}

extern "C" int64_t cmax_pixel_counts(const int64_t* Bi, const int64_t* Px, int64_t E, int64_t B, int64_t n_px,
                                     int64_t* O) {
  return pixel_counts(Bi, Px, E, B, n_px, O);
}

// cmax's hot-pixel weights (cmax.hot_pixel_weights, the torch path): c = events of the element on
// the event's pixel; two rounds of mean = sum(keep) / sum(keep / c) per element (float64, summed in event order
// as bincount does), keep = c <= factor * mean; weight = 1 where kept, else mean / c (as float32).
// out (E,) float32. Returns 0, or -1 when some b or px is out of range (nothing written).
extern "C" int64_t cmax_hot_weights(const int64_t* Bi, const int64_t* Px, int64_t E, int64_t B, int64_t n_px,
                                    double factor, float* O) {
  for (int64_t e = 0; e < E; ++e)
    if (!(Bi[e] >= 0 && Bi[e] < B && Px[e] >= 0 && Px[e] < n_px)) return -1;
  static thread_local std::vector<int64_t> start, order;  // by element; kept: no fresh pages per call
  sort_by_element(Bi, E, B, start, order);
  // element by element, its events in event order (the order of torch's bincount sums): the count of
  // its pixel, then two rounds of the mean count per active pixel
  static thread_local std::vector<int32_t> canvas;  // kept across calls, all zeros between uses
  static thread_local std::vector<int64_t> pk;
  static thread_local std::vector<double> cnt, inv;
  static thread_local std::vector<unsigned char> keep;
  if (canvas.size() != size_t(n_px)) canvas.assign(n_px, 0);
  for (int64_t bi = 0; bi < B; ++bi) {
    const int64_t k0 = start[bi], n = start[bi + 1] - k0;
    if (n == 0) continue;
    cnt.resize(n); inv.resize(n); keep.assign(n, 1);
    element_pixel_counts(Px, order.data() + k0, n, canvas.data(), pk,
                         [&](int64_t k, int32_t c) { cnt[k] = (double)c; });
    for (int64_t k = 0; k < n; ++k) inv[k] = 1.0 / cnt[k];
    double mean = 0.0;
    for (int round = 0; round < 2; ++round) {
      double n_px_s = 0.0, n_ev_s = 0.0;
      for (int64_t k = 0; k < n; ++k) {
        n_px_s += keep[k] ? inv[k] : 0.0;  // 1 / c or 0 / c, exactly
        n_ev_s += keep[k] ? 1.0 : 0.0;
      }
      mean = n_ev_s / std::max(n_px_s, 1e-9);
      bool dropped = false;
      for (int64_t k = 0; k < n; ++k) {
        keep[k] = cnt[k] <= factor * mean;
        dropped |= !keep[k];
      }
      // nothing flagged: the second round would sum the same terms to the same mean and keep all
      if (!dropped) break;
    }
    for (int64_t k = 0; k < n; ++k) O[order[k0 + k]] = keep[k] ? 1.0f : (float)(mean / cnt[k]);
  }
  return 0;
}

// cmax's radial weights (cmax.radial_weights, the torch path): CNT (B, nb) int64 the events of each element
// in each annulus, RB (n_px,) int64 each pixel's annulus in [0, nb). Returns 0, or -1 when some b, px or
// annulus is out of range (nothing written).
extern "C" int64_t cmax_radial_counts(const int64_t* Bi, const int64_t* Px, const int64_t* RB, int64_t E, int64_t B,
                                      int64_t n_px, int64_t nb, int64_t* CNT) {
  for (int64_t e = 0; e < E; ++e)
    if (!(Bi[e] >= 0 && Bi[e] < B && Px[e] >= 0 && Px[e] < n_px && RB[Px[e]] >= 0 && RB[Px[e]] < nb)) return -1;
  for (int64_t i = 0; i < B * nb; ++i) CNT[i] = 0;
  for (int64_t e = 0; e < E; ++e) CNT[Bi[e] * nb + RB[Px[e]]]++;
  return 0;
}

// O[e] = (float) WR[b nb + RB[px]], times O[e] (float32) when ``times``: each event's radial weight from the
// (B, nb) float64 table WR (the caller checked the indices with cmax_radial_counts).
extern "C" void cmax_radial_apply(const int64_t* Bi, const int64_t* Px, const int64_t* RB, int64_t E, int64_t nb,
                                  const double* WR, int64_t times, float* O) {
  if (times) {
    for (int64_t e = 0; e < E; ++e) O[e] = (float)WR[Bi[e] * nb + RB[Px[e]]] * O[e];
  } else {
    for (int64_t e = 0; e < E; ++e) O[e] = (float)WR[Bi[e] * nb + RB[Px[e]]];
  }
}

// cmax's window and the gather of its events (cmax._window_mask then cmax._gather, the torch path), in two
// passes over the stored events. A stored event lies in its element's window when its time is in (since[b],
// t_us]; NP (B,) float32 the events in each window, summed in event order in float32 (as torch's bincount
// does). With max_events > 0 the window is then hash-thinned: kept where (key & 0x7FFF) < min(max_events /
// max(NP, 1), 1) x 32768, computed in float32 as torch does (the division as reciprocal times max_events,
// torch's int / tensor). An element estimates (OK) when round(NP) >= min_events and filled[b]. Its kept
// events are written in store order as the score takes them: b, the canvas coordinates x + pad and y + pad
// (float32), tau = float32(t - TREF[b]) * float32(1e-6) s, half = (key >> 15) & 1 and pix = key >> 16
// (outputs of room for N). Returns how many, or -1 when some b is out of [0, B) (nothing written).
extern "C" int64_t cmax_window_gather(const int64_t* Bi, const float* X, const float* Y, const int64_t* T,
                                      const int64_t* K, int64_t N, int64_t B, const int64_t* since, int64_t t_us,
                                      int64_t max_events, const uint8_t* filled, int64_t min_events,
                                      const int64_t* TREF, double pad, float* NP, int64_t* ob, float* ox, float* oy,
                                      float* otau, int64_t* ohalf, int64_t* opix) {
  for (int64_t e = 0; e < N; ++e)
    if (!(Bi[e] >= 0 && Bi[e] < B)) return -1;
  for (int64_t i = 0; i < B; ++i) NP[i] = 0.0f;
  for (int64_t e = 0; e < N; ++e) NP[Bi[e]] += (T[e] > since[Bi[e]] && T[e] <= t_us) ? 1.0f : 0.0f;
  std::vector<float> thr(B, 32768.0f);  // every in-window key passes without thinning ((key & 0x7FFF) < 2^15)
  std::vector<uint8_t> ok(B);
  for (int64_t i = 0; i < B; ++i) {
    if (max_events > 0) thr[i] = std::min((1.0f / std::max(NP[i], 1.0f)) * (float)max_events, 1.0f) * 32768.0f;
    ok[i] = filled[i] && (int64_t)std::nearbyint(NP[i]) >= min_events;
  }
  const float pf = (float)pad, us = (float)1e-6;
  int64_t n = 0;
  for (int64_t e = 0; e < N; ++e) {
    const int64_t b = Bi[e];
    if (!(ok[b] && T[e] > since[b] && T[e] <= t_us && (float)(K[e] & 0x7FFF) < thr[b])) continue;
    ob[n] = b; ox[n] = X[e] + pf; oy[n] = Y[e] + pf;
    otau[n] = (float)(T[e] - TREF[b]) * us;
    ohalf[n] = (K[e] >> 15) & 1;
    opix[n] = K[e] >> 16;
    ++n;
  }
  return n;
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
// out (E,) int64: the kept indices, in order; returns how many.
extern "C" int64_t cmax_store_select(const int64_t* Bi, const int64_t* X, const int64_t* Y, const int64_t* T,
                                     int64_t E, const double* C, int64_t B, int64_t W, int64_t H, const int64_t* ST,
                                     int64_t* out) {
  std::vector<double> n(B, 0.0), p(B);
  for (int64_t e = 0; e < E; ++e)
    if (Bi[e] >= 0 && Bi[e] < B && X[e] >= 0 && X[e] < W && Y[e] >= 0 && Y[e] < H) n[Bi[e]] += 1.0;
  for (int64_t i = 0; i < B; ++i) p[i] = std::min(C[i] / std::max(n[i], 1.0), 1.0);
  int64_t k = 0;
  for (int64_t e = 0; e < E; ++e) {
    if (!(Bi[e] >= 0 && Bi[e] < B && X[e] >= 0 && X[e] < W && Y[e] >= 0 && Y[e] < H)) continue;
    const int64_t h = event_hash1(Bi[e], X[e], Y[e], T[e], ST[Bi[e]]);
    if ((double)(h & 0xFFFF) < p[Bi[e]] * 65536.0) out[k++] = e;
  }
  return k;
}
"""

# SSE4.1 on x86-64 (every x86-64 CPU since about 2008): floor and round-to-nearest-even become one
# instruction instead of a libm call each (the kernel is about 2x faster); the same IEEE results.
# -fno-trapping-math lets the compiler turn the corner weights' selects into vector blends (it
# vectorises that pass; another 1.7-2x): no value changes, only floating-point exception flags
_CFLAGS = (["-O3", "-ffp-contract=off", "-fno-trapping-math", "-std=c++17", "-pthread"]
           + (["-msse4.1"] if platform.machine().lower() in ("x86_64", "amd64") else []))
_ENV = "DVSLAND_NATIVE_CMAX"

_I64, _F64, _P = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
#: the C functions' (argument types, result type)
_SIGNATURES = {
    "cmax_splat_sums": ([_P] * 7 + [_I64] * 3 + [_F64] * 6 + [_I64, _I64, _F64, _I64, _P, _P], _I64),
    "cmax_pixel_counts": ([_P, _P, _I64, _I64, _I64, _P], _I64),
    "cmax_hot_weights": ([_P, _P, _I64, _I64, _I64, _F64, _P], _I64),
    "cmax_store_select": ([_P] * 4 + [_I64, _P, _I64, _I64, _I64, _P, _P], _I64),
    "cmax_radial_counts": ([_P, _P, _P, _I64, _I64, _I64, _I64, _P], _I64),
    "cmax_radial_apply": ([_P, _P, _P, _I64, _I64, _P, _I64, _P], None),
    "cmax_window_gather": ([_P] * 5 + [_I64, _I64, _P, _I64, _I64, _P, _I64, _P, _F64] + [_P] * 7, _I64),
    "cmax_weight_sums": ([_P, _P, _I64, _I64, _P, _P], _I64),
}


def _ok(status: int, what: str) -> None:
    if status < 0:
        raise RuntimeError(what)


class Kernels:
    """The loaded library's functions on torch tensors (CPU; each checks its inputs)."""

    def __init__(self, lib: ctypes.CDLL):
        self._lib = bind_functions(lib, _SIGNATURES)

    def splat_sums(self, xc, yc, b, half, scale, ginv, wt, cx: float, cy: float, x_lo: float, x_hi: float,
                   y_lo: float, y_hi: float, Hc: int, Wc: int, unit: float):
        """[n (B, G, 2) int64, s (B, G, 3) int64]: per element and candidate the integer weight of each
        half and the sums (I0^2, I1^2, I0 I1) of the splatted images (module doc). xc, yc, wt (E,)
        float32; b, half (E,) int64; scale (G, E), ginv (G, B) float32."""
        f32, i64 = torch.float32, torch.int64
        E = xc.numel()
        if scale.dim() != 2 or ginv.dim() != 2:
            raise RuntimeError("splat_sums: scale (G,E), ginv (G,B) float32")
        G, B = ginv.shape
        if not (scale.shape == (G, E) and yc.numel() == E and b.numel() == E and half.numel() == E
                and wt.numel() == E and Hc >= 2 and Wc >= 2):
            raise RuntimeError("splat_sums: shapes")
        n = torch.zeros(B, G, 2, dtype=i64)
        s = torch.zeros(B, G, 3, dtype=i64)
        _ok(self._lib.cmax_splat_sums(
            _ptr(xc, f32, "splat_sums: xc"), _ptr(yc, f32, "splat_sums: yc"), _ptr(b, i64, "splat_sums: b"),
            _ptr(half, i64, "splat_sums: half"), _ptr(scale, f32, "splat_sums: scale"),
            _ptr(ginv, f32, "splat_sums: ginv"), _ptr(wt, f32, "splat_sums: wt"), E, G, B, float(cx), float(cy),
            float(x_lo), float(x_hi), float(y_lo), float(y_hi), int(Hc), int(Wc), float(unit),
            torch.get_num_threads(), n.data_ptr(), s.data_ptr()),
            "splat_sums: b out of [0, B), half not 0/1, or an event weight not finite or of 2^18 events or more")
        return [n, s]

    def pixel_counts(self, b, px, B: int, n_px: int) -> torch.Tensor:
        """For each event (E,) int64: the events of its element on its pixel."""
        if b.numel() != px.numel():
            raise RuntimeError("pixel_counts: b, px contiguous int64 (E,)")
        out = torch.empty(b.numel(), dtype=torch.int64)
        _ok(self._lib.cmax_pixel_counts(_ptr(b, torch.int64, "pixel_counts: b"),
                                        _ptr(px, torch.int64, "pixel_counts: px"), b.numel(), int(B), int(n_px),
                                        out.data_ptr()),
            "pixel_counts: b or px out of range")
        return out

    def weight_sums(self, b, wt, B: int):
        """(sum w, sum w^2) (B,) float64 per element of the weights ``wt`` (E,) float32 of events in
        elements ``b`` (E,) int64, added in event order (module source)."""
        if b.numel() != wt.numel():
            raise RuntimeError("weight_sums: b (E,) int64 and wt (E,) float32")
        s1, s2 = torch.zeros(int(B), dtype=torch.float64), torch.zeros(int(B), dtype=torch.float64)
        _ok(self._lib.cmax_weight_sums(_ptr(b, torch.int64, "weight_sums: b"),
                                       _ptr(wt, torch.float32, "weight_sums: wt"), b.numel(), int(B), s1.data_ptr(),
                                       s2.data_ptr()), "weight_sums: b out of range")
        return s1, s2

    def hot_weights(self, b, px, B: int, n_px: int, factor: float) -> torch.Tensor:
        """cmax's hot-pixel weights (E,) float32 (module source)."""
        if b.numel() != px.numel():
            raise RuntimeError("pixel_counts: b, px contiguous int64 (E,)")
        out = torch.empty(b.numel(), dtype=torch.float32)
        _ok(self._lib.cmax_hot_weights(_ptr(b, torch.int64, "hot_weights: b"), _ptr(px, torch.int64, "hot_weights: px"),
                                       b.numel(), int(B), int(n_px), float(factor), out.data_ptr()),
            "pixel_counts: b or px out of range")
        return out

    def store_select(self, b, x, y, t, cap, W: int, H: int, seed_terms) -> torch.Tensor:
        """The indices (K,) int64 of the events cmax's store keeps (module source)."""
        i64 = torch.int64
        E, B = b.numel(), cap.numel()
        if seed_terms.numel() != B:
            raise RuntimeError("store_select: seed_terms contiguous int64 (B,)")
        out = torch.empty(E, dtype=i64)
        k = self._lib.cmax_store_select(_ptr(b, i64, "store_select: b"), _ptr(x, i64, "store_select: x"),
                                        _ptr(y, i64, "store_select: y"), _ptr(t, i64, "store_select: t"), E,
                                        _ptr(cap, torch.float64, "store_select: cap"), B, int(W), int(H),
                                        _ptr(seed_terms, i64, "store_select: seed_terms"), out.data_ptr())
        return out[:k].clone() if k < E else out

    def radial_counts(self, b, px, rbin_of_px, B: int, nb: int) -> torch.Tensor:
        """(B * nb,) int64: the events of each element in each annulus (cmax.radial_weights). b, px (E,)
        int64; rbin_of_px (n_px,) int64 in [0, nb)."""
        i64 = torch.int64
        if b.numel() != px.numel():
            raise RuntimeError("radial_counts: b, px contiguous int64 (E,)")
        out = torch.empty(int(B) * int(nb), dtype=i64)
        _ok(self._lib.cmax_radial_counts(_ptr(b, i64, "radial_counts: b"), _ptr(px, i64, "radial_counts: px"),
                                         _ptr(rbin_of_px, i64, "radial_counts: rbin_of_px"), b.numel(), int(B),
                                         rbin_of_px.numel(), int(nb), out.data_ptr()),
            "radial_counts: b, px or annulus out of range")
        return out

    def radial_apply(self, b, px, rbin_of_px, table, nb: int, times=None) -> torch.Tensor:
        """(E,) float32: each event's weight from the (B * nb,) float64 ``table``, times ``times``
        (E,) float32 when given (then written in place). Indices as checked by :meth:`radial_counts`."""
        i64 = torch.int64
        E = b.numel()
        out = torch.empty(E, dtype=torch.float32) if times is None else times
        if out.numel() != E or px.numel() != E:
            raise RuntimeError("radial_apply: b, px, times (E,)")
        self._lib.cmax_radial_apply(_ptr(b, i64, "radial_apply: b"), _ptr(px, i64, "radial_apply: px"),
                                    _ptr(rbin_of_px, i64, "radial_apply: rbin_of_px"), E, int(nb),
                                    _ptr(table, torch.float64, "radial_apply: table"), int(times is not None),
                                    _ptr(out, torch.float32, "radial_apply: times"))
        return out

    def window_gather(self, b, x, y, t, key, since, t_us: int, max_events: int, filled, min_events: int,
                      t_ref_us, pad: float):
        """cmax's window over its stored events and the gather of the estimating elements' (module source):
        (n_per (B,) float32 the events in each window before thinning, (b, xc, yc, tau, half, pix) of the kept
        events of the elements with round(n_per) >= ``min_events`` and ``filled``, in store order). b, t, key
        (N,) int64; x, y (N,) float32; since, t_ref_us (B,) int64; filled (B,) bool."""
        i64, f32 = torch.int64, torch.float32
        N, B = b.numel(), since.numel()
        if not all(v.numel() == N for v in (x, y, t, key)):
            raise RuntimeError("window_gather: b, x, y, t, key (N,)")
        if filled.dtype != torch.bool or filled.numel() != B or t_ref_us.numel() != B:
            raise RuntimeError("window_gather: filled bool (B,), t_ref_us int64 (B,)")
        n_per = torch.empty(B, dtype=f32)
        outs = [torch.empty(N, dtype=d) for d in (i64, f32, f32, f32, i64, i64)]
        n = self._lib.cmax_window_gather(
            _ptr(b, i64, "window_gather: b"), _ptr(x, f32, "window_gather: x"), _ptr(y, f32, "window_gather: y"),
            _ptr(t, i64, "window_gather: t"), _ptr(key, i64, "window_gather: key"), N, B,
            _ptr(since, i64, "window_gather: since"), int(t_us), int(max_events),
            _ptr(filled, torch.bool, "window_gather: filled"), int(min_events),
            _ptr(t_ref_us, i64, "window_gather: t_ref_us"), float(pad), n_per.data_ptr(), *(o.data_ptr() for o in outs))
        _ok(n, "window_gather: b out of range")
        return n_per, tuple(o[:n] for o in outs)


#: the library (its mode, cache and build)
LIBRARY = _LIB = NativeLibrary("dvsland_cmax_native", _SRC, _CFLAGS, _ENV, "dvsland.estimators.native_cmax", Kernels)


def use_native_cmax(on: Optional[bool] = True) -> None:
    """Pick the mode for this process: True = on, False = off, None = back to ``DVSLAND_NATIVE_CMAX``
    (default auto)."""
    _LIB.use(on)


def mode() -> str:
    """``"on"``, ``"off"`` or ``"auto"``: :func:`use_native_cmax`'s choice, else the environment's.

    Raises:
        ValueError naming ``DVSLAND_NATIVE_CMAX`` when it holds another word.
    """
    return _LIB.mode()


def module_name() -> str:
    """The library's name: a hash of the source, flags, compiler and machine."""
    return _LIB.name()


def build_dir() -> Path:
    """The folder of the build (:func:`dvsland.native_build.library_dir`)."""
    return _LIB.build_dir()


def cached() -> bool:
    """Whether the build of this exact source is in the cache."""
    return _LIB.cached()


def enabled() -> bool:
    """Whether ``cmax`` should use the kernel now: mode on; or auto with the build cached, loaded, or
    a C++ compiler to build it with. Never compiles."""
    return _LIB.enabled()


def kernel_for(t: torch.Tensor, native: Optional[bool] = None) -> Optional[Kernels]:
    """The kernels for work on ``t``'s device, or None for the torch path: CPU tensors only;
    ``native`` None = where :func:`enabled` (built once when needed), True = :func:`load` them
    whatever the mode says, False = never."""
    if native is False or t.device.type != "cpu":
        return None
    return load(force=bool(native))


def build(verbose: bool = False) -> Kernels:
    """Compile (when not cached) and load the kernel. Raises on any build error."""
    return _LIB.build(verbose)


def load(force: bool = False) -> Optional[Kernels]:
    """The kernels, or None: mode off (unless ``force``); auto with neither a cached build nor a
    compiler; or a failed build or load (one warning, then the torch path for the rest of the process)."""
    return _LIB.load(force)


__all__ = ["Kernels", "LIBRARY", "use_native_cmax", "enabled", "kernel_for", "mode", "cached", "build", "build_dir",
           "module_name", "load"]
