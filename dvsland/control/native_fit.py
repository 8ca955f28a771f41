"""Compiled per-row terms of the ``efference_fit`` filter's Gauss-Newton round (CPU), identical to
the torch path.

Each round of :func:`dvsland.control.efference_fit.fit_rounds` evaluates, for every history row of
every descent, the predicted divergence, its Jacobian, the measurement variance, the robust weight
and the five products whose sums make the normal equations. The torch path does that in about 35
elementwise passes over the (B, N) history, each a temporary; with the history growing by one row
per step this was the ``control`` stage's cost late in a descent. This kernel reads the raw history
rows and computes the same per-row values in one pass (the rows' preparation included), operation
for operation as the torch path does (float64, no contraction: ``-ffp-contract=off``), and writes
the five products; torch then sums them as before
(one ``sum`` over the rows of a (5, B, N) tensor, the same per-row reduction as five separate sums),
so the fit's outputs are the same to the bit. Tests pin the two paths to equality.

Plain C++ behind a C interface, compiled on first use where a C++ compiler is found (about a second;
:class:`dvsland.native_build.NativeLibrary`). ``DVSLAND_NATIVE_FIT`` (or :func:`use_native_fit`) picks
the mode: ``auto`` (default), ``1`` / ``on``, ``0`` / ``off``.
"""

from __future__ import annotations

import ctypes
from typing import Optional, Tuple

import torch

from dvsland.native_build import CLONES, NativeLibrary, bind_functions, tensor_address

_SRC = r"""
#include <cmath>
#include <cstdint>

""" + CLONES + r"""
// torch.maximum and clamp_min: NaN in, NaN out
DVS_INLINE double nan_max(double a, double b) { return (a != a || b != b) ? NAN : (a > b ? a : b); }

struct Consts {
  double dz, dv, pzz, pzv, pvv, min_alt, msr, msa, g2, cc2;
};

// One history row's terms: z = max((zdr + dz) + dv t, min_alt), v = vdr + dv, h = v / z, jz = -v / z^2,
// jv = (z - v t) / z^2, r = (msr |h| + msa)^2 [+ (sig0 max(|d0|, |h|))^2], s = r + jz jz pzz + 2 jz jv pzv
// + jv jv pvv, res = d0 - h, u2 = res^2 / s, w = 1 / (1 + u2 / cc2) / r where have & finite(u2) & u2 <= g2,
// else 0; wi = w [* fade]; the five products (wi jz jz, wi jz jv, wi jv jv, wi jz res, wi jv res) with
// wz = wi jz, wv = wi jv as the torch path multiplies them. Returns w; writes r.
template <bool SIG>
DVS_INLINE double row(const Consts& c, double zdr, double vdr, double tk, double d0, bool have, double sig0,
                      double d0_abs, double fade, double* prod, double& r) {
  double z = (zdr + c.dz) + c.dv * tk;
  z = nan_max(z, c.min_alt);
  const double v = vdr + c.dv;
  const double h = v / z;
  const double z2 = z * z;
  const double jz = -v / z2;
  const double jv = (z - v * tk) / z2;
  const double h_abs = std::fabs(h);
  const double m = c.msr * h_abs + c.msa;
  r = m * m;
  if (SIG) {
    const double e = sig0 * nan_max(d0_abs, h_abs);
    r = r + e * e;
  }
  const double s = ((r + (jz * jz) * c.pzz) + ((2.0 * jz) * jv) * c.pzv) + (jv * jv) * c.pvv;
  const double res = d0 - h;
  const double u2 = res * res / s;
  const bool keep = have & (std::fabs(u2) < INFINITY) & (u2 <= c.g2);  // finite: neither NaN nor inf
  const double w = keep ? 1.0 / (1.0 + u2 / c.cc2) / r : 0.0;
  const double wi = w * fade;  // fade 1 without forgetting: the same bits as w
  const double wz = wi * jz, wv = wi * jv;
  prod[0] = wz * jz;
  prod[1] = wz * jv;
  prod[2] = wv * jv;
  prod[3] = wz * res;
  prod[4] = wv * res;
  return w;
}

// One raw history row k of (5, B N) ``hist`` (z_dr, v_dr, t, D_hat, sigma_c) as fit_rounds prepares it:
// have = finite(D_hat); without it z_dr 1e3, v_dr 0, t 0, D_hat 0; sigma_c 0 where not finite; the row
// weighs only where both are finite. Its terms as row() (fade: 1 or the given factor). Returns w.
template <bool SIG, bool FADE>
DVS_INLINE double raw_row(const Consts& c, const double* __restrict hist, int64_t BN, int64_t k,
                          const double* __restrict fade, double* prod, double& r) {
  const double d = hist[3 * BN + k], sc = hist[4 * BN + k];
  const bool have = std::fabs(d) < INFINITY, fin_sig = std::fabs(sc) < INFINITY;
  const double d0 = have ? d : 0.0;
  return row<SIG>(c, have ? hist[k] : 1e3, have ? hist[BN + k] : 0.0, have ? hist[2 * BN + k] : 0.0, d0,
                  have & fin_sig, fin_sig ? sc : 0.0, std::fabs(d0), FADE ? fade[k] : 1.0, prod, r);
}

// Row k's five products into out (5, B N), product by product.
DVS_INLINE void put(double* __restrict out, int64_t BN, int64_t k, const double* prod) {
  for (int q = 0; q < 5; ++q) out[q * BN + k] = prod[q];
}

// The rows [k0, k1) of one descent.
template <bool SIG, bool FADE>
DVS_INLINE void rows(const Consts& c, int64_t k0, int64_t k1, int64_t BN, const double* __restrict hist,
                     const double* __restrict fade, double* __restrict out) {
  for (int64_t k = k0; k < k1; ++k) {
    double prod[5], r;
    raw_row<SIG, FADE>(c, hist, BN, k, fade, prod, r);
    put(out, BN, k, prod);
  }
}

// hist (5, B, N) raw history rows; theta (B, 2) = (dz, dv); pcov (B, 3) = (pzz, pzv, pvv); fade (B, N) or
// null; w_last, r_last (B,) = w, r of each descent's last row.
template <bool SIG, bool FADE>
DVS_INLINE void terms(int64_t B, int64_t N, const double* hist, const double* fade, const double* theta,
                      const double* pcov, double min_alt, double msr, double msa, double g2, double cc2, double* out,
                      double* w_last, double* r_last) {
  const int64_t BN = B * N;
  for (int64_t b = 0; b < B; ++b) {
    const Consts c{theta[2 * b], theta[2 * b + 1], pcov[3 * b], pcov[3 * b + 1], pcov[3 * b + 2], min_alt, msr, msa,
                   g2, cc2};
    const int64_t k0 = b * N, k1 = k0 + N;
    double prod[5], r = 0.0, w = 0.0;
    if (N > 0) {  // every row but the last in the vectorised loop; the last gives w and r too
      rows<SIG, FADE>(c, k0, k1 - 1, BN, hist, fade, out);
      w = raw_row<SIG, FADE>(c, hist, BN, k1 - 1, fade, prod, r);
      put(out, BN, k1 - 1, prod);
    }
    w_last[b] = w;
    r_last[b] = r;
  }
}

DVS_CLONES static void terms_any(int64_t B, int64_t N, const double* hist, int64_t sig, const double* fade,
                                 const double* theta, const double* pcov, double min_alt, double msr, double msa,
                                 double g2, double cc2, double* out, double* w_last, double* r_last) {
  if (sig && fade)
    terms<true, true>(B, N, hist, fade, theta, pcov, min_alt, msr, msa, g2, cc2, out, w_last, r_last);
  else if (sig)
    terms<true, false>(B, N, hist, fade, theta, pcov, min_alt, msr, msa, g2, cc2, out, w_last, r_last);
  else if (fade)
    terms<false, true>(B, N, hist, fade, theta, pcov, min_alt, msr, msa, g2, cc2, out, w_last, r_last);
  else
    terms<false, false>(B, N, hist, fade, theta, pcov, min_alt, msr, msa, g2, cc2, out, w_last, r_last);
}

extern "C" {
void fit_terms(int64_t B, int64_t N, const double* hist, int64_t sig, const double* fade, const double* theta,
               const double* pcov, double min_alt, double msr, double msa, double g2, double cc2, double* out,
               double* w_last, double* r_last) {
  terms_any(B, N, hist, sig, fade, theta, pcov, min_alt, msr, msa, g2, cc2, out, w_last, r_last);
}
}
"""

_CFLAGS = ["-O3", "-ffp-contract=off", "-fno-trapping-math", "-std=c++17"]
_I64, _F64, _P = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
#: the C function's (argument types, result type)
_SIGNATURES = {"fit_terms": ([_I64, _I64, _P, _I64, _P, _P, _P] + [_F64] * 5 + [_P] * 3, None)}


class Kernels:
    """The loaded library's round terms on torch tensors (CPU)."""

    def __init__(self, lib: ctypes.CDLL):
        self._f = bind_functions(lib, _SIGNATURES).fit_terms

    def terms(self, hist: torch.Tensor, sig: bool, fade: Optional[torch.Tensor], theta: torch.Tensor,
              pcov: torch.Tensor, min_alt: float, msr: float, msa: float, g2: float,
              cc2: float) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(products (5, B, N), w of the last row (B,), r of the last row (B,)), float64, of one round.

        Args:
            hist: (5, B, N) float64 the history rows to fit (:data:`~dvsland.control.efference_fit.ROW_FIELDS`,
                NaN where a descent had no estimate), contiguous.
            sig: add the estimator's own error (``meas_noise="confidence"``).
            fade: (B, N) float64 or None (1). theta: (B, 2); pcov: (B, 3) = (pzz, pzv, pvv), float64.
            min_alt, msr, msa: the altitude floor (m) and the measurement noise's relative and absolute parts.
            g2, cc2: the gate and the Cauchy scale, squared.
        """
        if hist.dim() != 3 or hist.shape[0] != 5:
            raise RuntimeError(f"native fit: hist must have shape (5, B, N), got {tuple(hist.shape)}")
        _, B, N = hist.shape

        def address(t: Optional[torch.Tensor], what: str, numel: int) -> Optional[int]:
            return None if t is None else tensor_address(t, torch.float64, f"native fit: {what}", numel)

        ptr = address(hist, "hist", 5 * B * N)
        fd, th, pc = address(fade, "fade", B * N), address(theta, "theta", 2 * B), address(pcov, "pcov", 3 * B)
        out = torch.empty(5, B, N, dtype=torch.float64)
        w_last, r_last = torch.empty(B, dtype=torch.float64), torch.empty(B, dtype=torch.float64)
        self._f(B, N, ptr, int(bool(sig)), fd, th, pc, float(min_alt), float(msr), float(msa), float(g2), float(cc2),
                out.data_ptr(), w_last.data_ptr(), r_last.data_ptr())
        return out, w_last, r_last


#: the library (its mode, cache and build: ``LIBRARY.build()``, ``LIBRARY.cached()``, ``LIBRARY.build_dir()``)
LIBRARY = NativeLibrary("dvsland_fit_native", _SRC, _CFLAGS, "DVSLAND_NATIVE_FIT", "dvsland.control.native_fit",
                        Kernels)


def use_native_fit(on: Optional[bool] = True) -> None:
    """Pick the mode for this process: True = on, False = off, None = back to ``DVSLAND_NATIVE_FIT``."""
    LIBRARY.use(on)


def kernel_for(t: torch.Tensor) -> Optional[Kernels]:
    """The kernel for work on ``t``'s device where enabled (built once when needed), else None."""
    return LIBRARY.kernel_for(t)


__all__ = ["Kernels", "LIBRARY", "use_native_fit", "kernel_for"]
