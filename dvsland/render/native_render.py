"""Compiled sampling passes of the fast renderer (CPU), identical to its torch path.

A frame of :class:`dvsland.render.fast.FastRenderer` is, per pixel, two bilinear, border-clamped
samples of the irradiance atlas (levels lo and lo + 1 at grid offset + ray slope x range), their blend
and the view-angle gain; before it, the relief's ray ranges take ``parallax_iters`` samples of the
height atlas each. The torch path writes a sampling grid, calls ``grid_sampler`` and then blends in
three more passes; these kernels do each in one pass over the pixels, reading the per-site slopes and
gains by the frames' site indices (no gathered copies), so the grid and the two sampled levels never
reach memory.

The passes read the atlases in tiles (:class:`TiledAtlas`; :func:`tiled_empty` and :func:`tiled_write`
build one, :func:`tile_atlas` converts a row-major one): squares of 32 x 32 texels, each one 4 KB page.
A frame's samples walk its tile of the atlas along a rotated, scaled grid; in the row-major atlas (a
row of 13 levels is 20 KB at 128 x 128 pixels) the texels of a few neighbouring pixels lay in as many
memory pages, so each frame of a dispersed batch (every descent its own scene) spent most of its
time waiting for memory. In tiles, neighbours share a page and mostly a cache line. In the B = 63
campaign batch on an Intel Xeon the levels pass took 4.5-4.6 ms a step instead of 8.6-8.8 and the
relief 1.4-1.5 ms instead of 2.5-2.6 (huge pages on, as the command line sets them; without them
7.2-7.8 ms instead of 13.7-17.7). The same texels, the same bits.

The arithmetic is torch's, operation for operation, on CPUs where torch runs its AVX2 or AVX-512
kernels (every x86-64 CPU of the last decade): the grid as ``fma(slope, range, offset)`` (``addcmul``),
the unnormalisation ``fma(g + 1, size / 2, -0.5)``, the clamp to the border, the four corner weights
and their sum as a chain of ``fma`` (torch's vectorised ``grid_sampler`` is compiled with
contraction), and the blend as ``lerp``'s ``fma(coeff, v1 - v0, base)``. Tests pin every frame to
the torch path bit for bit there (and to float rounding elsewhere).

Plain C++ behind a C interface (no torch headers), called through ``ctypes`` on the tensors' memory,
compiled in a second or two on first use where a C++ compiler is found, with AVX-512, AVX2 + FMA and
baseline clones picked at load time on x86-64 Linux (:class:`dvsland.native_build.NativeLibrary`); GCC 12
or later builds it with :data:`~dvsland.native_build.GATHER_FLAGS`, so that the vectorised samples load
their texels with gather instructions (the same arithmetic; half the time on an Intel Xeon).
``DVSLAND_NATIVE_RENDER`` (or :func:`use_native_render`) picks the mode: ``auto`` (default), ``1`` /
``on``, ``0`` / ``off`` (as ``DVSLAND_NATIVE_CMAX``).
"""

from __future__ import annotations

import ctypes
from typing import NamedTuple, Optional

import torch

from dvsland.native_build import CLONES, GATHER_FLAGS, PARALLEL_RANGES, NativeLibrary, bind_functions, tensor_address

#: texels on a side of the square tiles of a :class:`TiledAtlas` (one 4 KB page of float32 each)
TILE_TEXELS = 32

_SRC = f"#define TILE_BITS {TILE_TEXELS.bit_length() - 1}\n" + r"""
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

""" + PARALLEL_RANGES + r"""
""" + CLONES + r"""
// The texture's geometry for torch.grid_sampler (bilinear, border padding, align_corners=False), its
// texels stored in square tiles of 2^TILE_BITS texels a side (module doc): texel (y, x) in tile
// (y >> TILE_BITS, x >> TILE_BITS), row-major over nt tiles a row, and row-major within its tile.
struct Tex {
  const float* __restrict a;  // (Ha / tile rounded up, nt, tile, tile) float32
  int32_t Ha, Wa, nt;
  float sx, sy, mx, my;       // size / 2 and size - 1, per axis
};

DVS_INLINE int32_t texel(const Tex& t, int32_t y, int32_t x) {
  constexpr int32_t m = (1 << TILE_BITS) - 1;
  return (((y >> TILE_BITS) * t.nt + (x >> TILE_BITS)) << (2 * TILE_BITS)) + ((y & m) << TILE_BITS) + (x & m);
}

// torch.grid_sampler's sample at normalised (gx, gy): unnormalise, clamp to the border, four corners.
// A corner past the last row or column has weight 0 exactly (the coordinate is clamped to the last
// texel); it reads the last texel in place of torch's masked 0, which adds the same +0.
DVS_INLINE float sample(const Tex& t, float gx, float gy) {
  float ix = __builtin_fmaf(gx + 1.0f, t.sx, -0.5f);
  float iy = __builtin_fmaf(gy + 1.0f, t.sy, -0.5f);
  ix = ix < 0.0f ? 0.0f : ix;
  ix = ix > t.mx ? t.mx : ix;
  iy = iy < 0.0f ? 0.0f : iy;
  iy = iy > t.my ? t.my : iy;
  const float xw = __builtin_floorf(ix), yn = __builtin_floorf(iy);
  const float w = ix - xw, e = 1.0f - w, n = iy - yn, s = 1.0f - n;
  const int32_t x0 = (int32_t)xw, y0 = (int32_t)yn;
  const int32_t x1 = x0 + 1 < t.Wa ? x0 + 1 : x0, y1 = y0 + 1 < t.Ha ? y0 + 1 : y0;
  const float* __restrict a = t.a;
  return __builtin_fmaf(a[texel(t, y1, x1)], n * w,
                        __builtin_fmaf(a[texel(t, y1, x0)], n * e,
                                       __builtin_fmaf(a[texel(t, y0, x1)], s * w, a[texel(t, y0, x0)] * (s * e))));
}

// One frame: out[p] = lerp(v0, v1, frac) * gain[p], v_k = level k's sample at its grid (see module doc).
template <bool PER_PIXEL_RANGE>
DVS_INLINE void frame(const Tex& t, float ox0, float oy0, float ox1, float oy1, const float* __restrict slx,
                      const float* __restrict sly, const float* __restrict rng, float frac,
                      const float* __restrict gain, float* __restrict out, int64_t P) {
  const bool small = __builtin_fabsf(frac) < 0.5f;  // torch's lerp: weight below 0.5 from v0, else from v1
  const float coeff = small ? frac : frac - 1.0f;
  const float r0 = rng[0];
  for (int64_t p = 0; p < P; ++p) {
    const float r = PER_PIXEL_RANGE ? rng[p] : r0;
    const float gx0 = __builtin_fmaf(slx[p], r, ox0), gy0 = __builtin_fmaf(sly[p], r, oy0);
    const float v0 = sample(t, gx0, gy0);
    const float v1 = sample(t, __builtin_fmaf(gx0, 0.5f, ox1), __builtin_fmaf(gy0, 0.5f, oy1));
    out[p] = __builtin_fmaf(coeff, v1 - v0, small ? v0 : v1) * gain[p];
  }
}

DVS_CLONES static void levels_range(const Tex t, const float* off, int64_t B, const float* slopes, int64_t S,
                                    const int64_t* site, const float* rng, int64_t rng_per_pixel, const float* frac,
                                    const float* gain, int64_t gain_per_site, float* out, int64_t P, int64_t f0,
                                    int64_t f1) {
  for (int64_t f = f0; f < f1; ++f) {
    const int64_t s = site[f];
    const float* slx = slopes + s * P;
    const float* sly = slopes + (S + s) * P;
    const float* g = gain + (gain_per_site ? s * P : 0);
    if (rng_per_pixel)
      frame<true>(t, off[f], off[B + f], off[2 * B + f], off[3 * B + f], slx, sly, rng + f * P, frac[f], g,
                  out + f * P, P);
    else
      frame<false>(t, off[f], off[B + f], off[2 * B + f], off[3 * B + f], slx, sly, rng + f, frac[f], g,
                   out + f * P, P);
  }
}

// Bilinear 2x upsampling of one (h, w) field into (2h, 2w), align_corners=False with edge clamping, as
// fast._upsample2x: columns first, then rows, each output value lerp(x, neighbour, 0.25) = x + 0.25 (n - x)
// (torch's lerp with a weight below 0.5; 0.25 (n - x) is exact, so with or without an fma the same bits).
DVS_INLINE float quarter_to(float x, float n) { return x + 0.25f * (n - x); }

// (inlined into each clone of relief_range; the interior columns without a branch, so they vectorise)
DVS_INLINE void upsample2x_field(const float* __restrict x, int64_t h, int64_t w, float* __restrict col,
                                 float* __restrict out) {
  for (int64_t i = 0; i < h; ++i) {  // columns: col (h, 2w)
    const float* __restrict xi = x + i * w;
    float* __restrict ci = col + i * 2 * w;
    ci[0] = quarter_to(xi[0], xi[0]);
    ci[1] = quarter_to(xi[0], xi[w > 1 ? 1 : 0]);
    for (int64_t j = 1; j + 1 < w; ++j) {
      ci[2 * j] = quarter_to(xi[j], xi[j - 1]);
      ci[2 * j + 1] = quarter_to(xi[j], xi[j + 1]);
    }
    if (w > 1) {
      ci[2 * w - 2] = quarter_to(xi[w - 1], xi[w - 2]);
      ci[2 * w - 1] = quarter_to(xi[w - 1], xi[w - 1]);
    }
  }
  const int64_t W2 = 2 * w;
  for (int64_t i = 0; i < h; ++i) {  // rows: out (2h, 2w)
    const float* c = col + i * W2;
    const float* up = col + (i > 0 ? i - 1 : 0) * W2;
    const float* dn = col + (i + 1 < h ? i + 1 : h - 1) * W2;
    float* o0 = out + (2 * i) * W2;
    float* o1 = o0 + W2;
    for (int64_t k = 0; k < W2; ++k) {
      o0[k] = quarter_to(c[k], up[k]);
      o1[k] = quarter_to(c[k], dn[k]);
    }
  }
}

// Relief ranges of frames [f0, f1): r = z, then iters times r = max(z - h(off + slope r inv), 0.05 z);
// out = r * inv_lo (see FastRenderer._relief_range, the torch path), upsampled 2x when up2 (out (B, 4 Q),
// the (hh, ww) field of Q points upsampled into (2 hh, 2 ww)).
DVS_CLONES static void relief_range(const Tex t, const float* off, int64_t B, const float* slopes, int64_t S,
                                    const int64_t* site, const float* z, const float* inv, const float* inv_lo,
                                    int64_t iters, float* out, int64_t Q, int64_t up2, int64_t hh, int64_t f0,
                                    int64_t f1) {
  std::vector<float> half(up2 ? 3 * Q : 0);  // the frame's field, then its column pass
  for (int64_t f = f0; f < f1; ++f) {
    const int64_t s = site[f];
    const float* __restrict slx = slopes + s * Q;
    const float* __restrict sly = slopes + (S + s) * Q;
    float* __restrict r = up2 ? half.data() : out + f * Q;
    const float zf = z[f], inv_f = inv[f], ox = off[f], oy = off[B + f], floor_m = zf * 0.05f;
    for (int64_t q = 0; q < Q; ++q) r[q] = zf;
    for (int64_t it = 0; it < iters; ++it) {
      for (int64_t q = 0; q < Q; ++q) {
        const float ri = r[q] * inv_f;
        const float d = zf - sample(t, __builtin_fmaf(slx[q], ri, ox), __builtin_fmaf(sly[q], ri, oy));
        r[q] = d < floor_m ? floor_m : d;
      }
    }
    const float k = inv_lo[f];
    for (int64_t q = 0; q < Q; ++q) r[q] = r[q] * k;
    if (up2) upsample2x_field(r, hh, Q / hh, half.data() + Q, out + f * 4 * Q);
  }
}

static Tex texture(const float* a, int64_t Ha, int64_t Wa) {
  const int32_t nt = (int32_t)((Wa + (1 << TILE_BITS) - 1) >> TILE_BITS);
  return Tex{a, (int32_t)Ha, (int32_t)Wa, nt, (float)Wa / 2, (float)Ha / 2, (float)(Wa - 1), (float)(Ha - 1)};
}

// the texels of an (Ha, Wa) texture in whole tiles
static int64_t tiled_texels(int64_t Ha, int64_t Wa) {
  const int64_t n = int64_t(1) << TILE_BITS;
  return ((Ha + n - 1) / n) * ((Wa + n - 1) / n) * n * n;
}

extern "C" {

// out (B, P) = the blended, gain-weighted frames. atlas (Ha, Wa) in tiles (Tex); off (4, B) (x lo, y lo,
// x lo+1 - x lo / 2, y lo+1 - y lo / 2); slopes (2, S, P); site (B,) in [0, S); rng (B, P) or (B,); frac (B,);
// gain (S, P) or (P,).
// Returns 0, or -1 on a bad size or site index.
int64_t render_levels(const float* atlas, int64_t Ha, int64_t Wa, const float* off, int64_t B, const float* slopes,
                      int64_t S, const int64_t* site, const float* rng, int64_t rng_per_pixel, const float* frac,
                      const float* gain, int64_t gain_per_site, float* out, int64_t P, int64_t n_threads) {
  if (Ha < 1 || Wa < 1 || tiled_texels(Ha, Wa) >= (int64_t(1) << 31) || B < 0 || S < 1 || P < 1) return -1;
  for (int64_t f = 0; f < B; ++f) if (site[f] < 0 || site[f] >= S) return -1;
  const Tex t = texture(atlas, Ha, Wa);
  parallel_ranges(B, n_threads, [&](int64_t f0, int64_t f1) {
    levels_range(t, off, B, slopes, S, site, rng, rng_per_pixel, frac, gain, gain_per_site, out, P, f0, f1);
  });
  return 0;
}

// out (B, Q) = the relief's ray ranges times inv_lo; with up2, out (B, 4 Q) = those of each (hh, Q / hh)
// field upsampled 2x. atlas (Ha, Wa) heights in tiles (Tex); off (2, B); slopes (2, S, Q); site (B,);
// z, inv, inv_lo (B,).
// Returns 0, or -1 on a bad size or site index.
int64_t render_relief(const float* atlas, int64_t Ha, int64_t Wa, const float* off, int64_t B, const float* slopes,
                      int64_t S, const int64_t* site, const float* z, const float* inv, const float* inv_lo,
                      int64_t iters, float* out, int64_t Q, int64_t up2, int64_t hh, int64_t n_threads) {
  if (Ha < 1 || Wa < 1 || tiled_texels(Ha, Wa) >= (int64_t(1) << 31) || B < 0 || S < 1 || Q < 1 || iters < 0) return -1;
  if (up2 && (hh < 1 || Q % hh != 0)) return -1;
  for (int64_t f = 0; f < B; ++f) if (site[f] < 0 || site[f] >= S) return -1;
  const Tex t = texture(atlas, Ha, Wa);
  parallel_ranges(B, n_threads, [&](int64_t f0, int64_t f1) {
    relief_range(t, off, B, slopes, S, site, z, inv, inv_lo, iters, out, Q, up2, hh, f0, f1);
  });
  return 0;
}

}
"""

# -ffp-contract=off: every fma is written out (torch's own contractions), nothing else is fused
_CFLAGS = ["-O3", "-ffp-contract=off", "-fno-trapping-math", "-std=c++17", "-pthread"]
_ENV = "DVSLAND_NATIVE_RENDER"
_I64, _P = ctypes.c_int64, ctypes.c_void_p
#: the C functions' (argument types, result type)
_SIGNATURES = {
    "render_levels": ([_P, _I64, _I64, _P, _I64, _P, _I64, _P, _P, _I64, _P, _P, _I64, _P, _I64, _I64], _I64),
    "render_relief": ([_P, _I64, _I64, _P, _I64, _P, _I64, _P, _P, _P, _P, _I64, _P, _I64, _I64, _I64, _I64], _I64),
}


def _f32(t: torch.Tensor, what: str, numel: int) -> int:
    """The address of ``t`` after checking (:func:`~dvsland.native_build.tensor_address`) that it is a
    contiguous CPU float32 tensor, and that it holds ``numel`` elements."""
    return tensor_address(t, torch.float32, f"native render: {what}", numel)


def _sites(site_idx: torch.Tensor, b: int) -> torch.Tensor:
    if site_idx.device.type != "cpu" or site_idx.numel() != b:
        raise RuntimeError(f"native render: site_idx must be a CPU tensor of {b} indices, got "
                           f"{tuple(site_idx.shape)} on {site_idx.device}")
    return site_idx.to(torch.int64).contiguous()


class TiledAtlas(NamedTuple):
    """An atlas as the compiled passes read it: ``texels`` (ceil(height / T) * ceil(width / T) * T * T,)
    float32 with T = :data:`TILE_TEXELS`, tile after tile (row-major over the tiles), each tile's T x T
    texels row-major; the padding past ``height`` x ``width`` is 0 and never read."""

    texels: torch.Tensor
    height: int
    width: int


def _tile_counts(height: int, width: int):
    """(rows, columns) of whole tiles that hold ``height`` x ``width`` texels."""
    return -(-int(height) // TILE_TEXELS), -(-int(width) // TILE_TEXELS)


def _tiled_numel(height: int, width: int) -> int:
    """The texels of a ``height`` x ``width`` atlas in whole tiles (its padding included)."""
    ht, wt = _tile_counts(height, width)
    return ht * wt * TILE_TEXELS ** 2


def _segments(start: int, stop: int):
    """[start, stop) of one axis of the atlas in pieces that each lie in one tile or span whole tiles:
    (tile index or slice, slice within the tile, slice of [start, stop) from 0, the piece's shape)."""
    T, out, a = TILE_TEXELS, [], start
    if a % T and a < stop:  # the head, inside one tile
        b = min(stop, (a // T + 1) * T)
        out.append((a // T, slice(a % T, a % T + b - a), slice(a - start, b - start), (b - a,)))
        a = b
    n = (stop - a) // T
    if n:  # whole tiles
        out.append((slice(a // T, a // T + n), slice(0, T), slice(a - start, a - start + n * T), (n, T)))
        a += n * T
    if a < stop:  # the tail, inside one tile
        out.append((a // T, slice(0, stop - a), slice(a - start, stop - start), (stop - a,)))
    return out


def _blocks(atlas: TiledAtlas, y0: int, x0: int, h: int, w: int):
    """Triples (view of ``atlas.texels``, (rows, cols) slices of an (h, w) block, the view's shape) that
    together cover the block placed at (y0, x0) of the atlas, each view shaped as its piece of the
    block reshapes."""
    T = TILE_TEXELS
    ht, wt = _tile_counts(atlas.height, atlas.width)
    v = atlas.texels.as_strided((ht, T, wt, T), (wt * T * T, T, T * T, 1))  # (tile y, y in tile, tile x, x in tile)
    return [(v[ty, iy, tx, ix], (sy, sx), hy + hx)
            for ty, iy, sy, hy in _segments(y0, y0 + h) for tx, ix, sx, hx in _segments(x0, x0 + w)]


def tiled_empty(height: int, width: int) -> TiledAtlas:
    """A zeroed :class:`TiledAtlas` of ``height`` x ``width`` texels (CPU float32), to be written with
    :func:`tiled_write` (the padding past its edges stays 0)."""
    return TiledAtlas(torch.zeros(_tiled_numel(height, width), dtype=torch.float32), int(height), int(width))


def tiled_write(atlas: TiledAtlas, y0: int, x0: int, block: torch.Tensor) -> None:
    """Write the (h, w) float32 ``block`` into ``atlas`` at texel (y0, x0) (inside the atlas)."""
    h, w = block.shape
    if not (0 <= y0 and y0 + h <= atlas.height and 0 <= x0 and x0 + w <= atlas.width):
        raise ValueError(f"tiled_write: a ({h}, {w}) block at ({y0}, {x0}) is outside the atlas "
                         f"({atlas.height}, {atlas.width})")
    for dst, (rows, cols), shape in _blocks(atlas, y0, x0, h, w):
        dst.copy_(block[rows, cols].reshape(shape))


def tile_atlas(atlas: torch.Tensor) -> TiledAtlas:
    """``atlas`` (H, W) float32 (CPU) in the tiled layout of the passes (:class:`TiledAtlas`)."""
    if atlas.dim() != 2 or atlas.dtype != torch.float32 or atlas.device.type != "cpu":
        raise ValueError(f"tile_atlas: atlas must be a (H, W) float32 CPU tensor, got {tuple(atlas.shape)} "
                         f"{atlas.dtype} on {atlas.device}")
    out = tiled_empty(*atlas.shape)
    tiled_write(out, 0, 0, atlas)
    return out


def untile_atlas(tiled: TiledAtlas) -> torch.Tensor:
    """The (H, W) float32 atlas of ``tiled`` (:func:`tile_atlas`'s inverse)."""
    out = torch.empty(tiled.height, tiled.width, dtype=torch.float32)
    for src, (rows, cols), shape in _blocks(tiled, 0, 0, tiled.height, tiled.width):
        out[rows, cols].view(shape).copy_(src)
    return out


def _tiles(atlas: TiledAtlas, what: str) -> int:
    """The address of a :class:`TiledAtlas`'s texels after checking them (``what`` names the argument)."""
    if not isinstance(atlas, TiledAtlas):
        raise RuntimeError(f"native render: {what} must be a TiledAtlas (tile_atlas(atlas)), "
                           f"got {type(atlas).__name__}")
    return _f32(atlas.texels, what, _tiled_numel(atlas.height, atlas.width))


class Kernels:
    """The loaded library's passes on torch tensors (CPU; each checks its inputs)."""

    def __init__(self, lib: ctypes.CDLL):
        self._lib = bind_functions(lib, _SIGNATURES)

    def levels(self, atlas: TiledAtlas, off: torch.Tensor, slopes: torch.Tensor, site_idx: torch.Tensor,
               rng_n: torch.Tensor, frac: torch.Tensor, gain: torch.Tensor, out: torch.Tensor,
               threads: int = 1) -> torch.Tensor:
        """Write into ``out`` (B, H, W) the frames blended from levels lo and lo + 1 of ``atlas`` (tiled):
        grid off (4, B) + slopes (2, S, H, W)[:, site_idx] x rng_n ((B, H, W) or (B,)), blend frac
        (B,), times gain ((S, H, W) per site or (H, W) shared); all float32, site_idx int64 (B,)."""
        b, h, w = out.shape
        p = h * w
        s = slopes.shape[1]
        site = _sites(site_idx, b)
        per_pixel = rng_n.numel() == b * p and p > 1
        per_site = gain.dim() == 3
        status = self._lib.render_levels(
            _tiles(atlas, "atlas"), atlas.height, atlas.width, _f32(off, "off", 4 * b), b,
            _f32(slopes, "slopes", 2 * s * p), s, site.data_ptr(), _f32(rng_n, "rng_n", b * p if per_pixel else b),
            int(per_pixel), _f32(frac, "frac", b), _f32(gain, "gain", (s if per_site else 1) * p), int(per_site),
            _f32(out, "out", b * p), p, int(threads))
        if status < 0:
            raise RuntimeError(f"native render: bad sizes or a site index outside [0, {s - 1}]")
        return out

    def relief(self, atlas: TiledAtlas, off: torch.Tensor, slopes: torch.Tensor, site_idx: torch.Tensor,
               z: torch.Tensor, inv: torch.Tensor, inv_lo: torch.Tensor, iters: int, threads: int = 1,
               upsample2x: bool = False) -> torch.Tensor:
        """(B, h, w) relief ray ranges (m) times ``inv_lo``: per point r = z, then ``iters`` times
        r = max(z - height(off + slopes[:, site] r inv), 0.05 z), heights sampled from ``atlas`` (tiled).
        off (2, B); slopes (2, S, h, w); z, inv, inv_lo (B,); all float32, site_idx int64 (B,). With
        ``upsample2x``: (B, 2 h, 2 w), each field upsampled as :func:`dvsland.render.fast._upsample2x`
        (the same bits), in the same pass."""
        b = z.numel()
        s, hh, ww = slopes.shape[1:]
        q = hh * ww
        site = _sites(site_idx, b)
        out = torch.empty(b, 2 * hh, 2 * ww) if upsample2x else torch.empty(b, hh, ww)
        status = self._lib.render_relief(
            _tiles(atlas, "atlas"), atlas.height, atlas.width, _f32(off, "off", 2 * b), b,
            _f32(slopes, "slopes", 2 * s * q), s, site.data_ptr(), _f32(z, "z", b), _f32(inv, "inv", b),
            _f32(inv_lo, "inv_lo", b), int(iters), out.data_ptr(), q, int(upsample2x), hh, int(threads))
        if status < 0:
            raise RuntimeError(f"native render: bad sizes or a site index outside [0, {s - 1}]")
        return out


#: the library (its mode, cache and build: ``LIBRARY.build()``, ``LIBRARY.cached()``, ``LIBRARY.build_dir()``)
LIBRARY = NativeLibrary("dvsland_render_native", _SRC, _CFLAGS, _ENV, "dvsland.render.native_render", Kernels,
                        gcc_flags=GATHER_FLAGS)


def use_native_render(on: Optional[bool] = True) -> None:
    """Pick the mode for this process: True = on, False = off, None = back to ``DVSLAND_NATIVE_RENDER``."""
    LIBRARY.use(on)


def kernel_for(t: torch.Tensor) -> Optional[Kernels]:
    """The kernels for work on ``t``'s device where enabled (built once when needed), else None."""
    return LIBRARY.kernel_for(t)


def fits(atlas) -> bool:
    """Whether the passes take this atlas (a tensor (..., H, W), a :class:`TiledAtlas` or its (H, W)):
    texel indices are int32, so fewer than 2^31 texels in whole tiles (about 1,100 dispersed scenes of
    128 x 128 frames); a larger one is sampled by torch's ``grid_sample``."""
    if isinstance(atlas, TiledAtlas):
        h, w = atlas.height, atlas.width
    else:
        h, w = atlas.shape[-2:] if isinstance(atlas, torch.Tensor) else atlas
    return 2 <= w and _tiled_numel(h, w) < 2 ** 31


__all__ = ["Kernels", "LIBRARY", "use_native_render", "kernel_for", "fits", "TILE_TEXELS", "TiledAtlas",
           "tiled_empty", "tiled_write", "tile_atlas", "untile_atlas"]
