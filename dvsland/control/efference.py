"""Efference-copy fusion filter (filter ``efference``): D_hat fused with the thrust the craft knows
it applied, carrying D through gaps and estimating altitude.

The craft knows its own acceleration a = u/m - g (commanded thrust u, mass m). A divergence
estimate D_hat measures v/z only up to scale, but together with a known, non-zero acceleration
both z and v become observable (de Croon, "Monocular distance estimation with optical flow
maneuvers and efference copies", 2016). The filter is a batched extended Kalman filter on
x = (z, v):

    predict:  z += v dt + a dt^2 / 2,  v += a dt     (a = u/m - g from the last step's command)
              P = F P F^T + Q,  Q = sigma_a^2 [[dt^4/4, dt^3/2], [dt^3/2, dt^2]],
              sigma_a = accel_sigma_mps2 + accel_sigma_rel |u/m|  (thrust uncertainty)
    update:   y = D_hat = v / z,  H = [-v/z^2, 1/z],  R = (meas_sigma_rel |v/z| + meas_sigma_abs)^2
              skipped where D_hat is NaN (the prediction carries D through the gap) or where the
              innovation exceeds ``gate_sigma`` standard deviations of the predicted
              S = H P H^T + R (outliers).

Robust options (all off by default; ``configs/montecarlo_efference.yaml`` turns them on):

- ``meas_noise="confidence"``: each estimate brings its own noise. The estimator's
  ``confidence()`` c in [0, 1] (every estimator has one) gives its relative standard error
  sigma_c = 0.1 sqrt(1/c - 1) (the inverse of c = 1 / (1 + (sigma_c / 0.1)^2)), and
  R = (sigma_c max(|D_hat|, |v/z|))^2 + (meas_sigma_rel |v/z| + meas_sigma_abs)^2: the fixed part is a floor
  for an estimator that is over-confident. Confidence 0 (or not finite) = no update.
- ``huber_k`` > 0: an accepted innovation beyond ``huber_k`` sqrt(S) is clipped to it (a Huber
  update: a far estimate pulls no harder than one at ``huber_k`` sigma).
- ``max_step_rel`` > 0: one update moves z_hat and v_hat by at most this fraction of their value
  (the linearisation of v/z holds only for small steps; keeps z_hat and v_hat sane).
- ``cov_cap_rel`` > 0: the standard deviations of z and v are capped at this fraction of z_hat and
  |v_hat| (correlation kept): without measurements the gate cannot open wider than that.

The prior is the descent's nominal initial state (z0, v0) scaled by ``prior_scale`` (1 = the
nominal start; 1.3 = a 30 % wrong guess, for tests of convergence), with relative standard
deviation ``prior_rel_sigma`` on z (and on v unless ``prior_rel_sigma_v`` is given). In a
dispersed batch the loop gives the site's undispersed start (``prior_state="nominal"``): the
craft does not know its dispersion.

Output per step: the filtered divergence v/z (B,), the number of estimates used this step (0 or
1), and :attr:`altitude_m` / :attr:`velocity_mps` (B,) for controllers that use them.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

Tensor = torch.Tensor


#: ``controller.efference`` options that are not this filter's (the loop's, and ``efference_fit``'s):
#: one config section serves both filters
_NOT_MINE = ("prior_state", "cauchy_c", "iterations", "forget_s")


def confidence_rel_sigma(confidence: Tensor) -> Tensor:
    """Relative standard error sigma_rel = 0.1 sqrt(1/c - 1) of an estimate with confidence c,
    the inverse of the estimators' c = 1 / (1 + (sigma_rel / 0.1)^2).

    Args:
        confidence: (B,) float in [0, 1].

    Returns:
        (B,) same dtype: 0 at c = 1, inf at c = 0 or where c is not finite (no information).
    """
    c = confidence.clamp(0.0, 1.0)
    ok = torch.isfinite(confidence) & (c > 0)
    return torch.where(ok, 0.1 * (1.0 / torch.where(ok, c, 1.0) - 1.0).clamp_min(0.0).sqrt(), float("inf"))


def cap_covariance(pzz: Tensor, pzv: Tensor, pvv: Tensor, sz_max: Tensor, sv_max: Tensor):
    """Cap the standard deviations of a batch of 2x2 covariances [[pzz, pzv], [pzv, pvv]] at
    ``sz_max``, ``sv_max`` (B,) by scaling rows and columns (the correlation is kept, the matrix
    stays positive semi-definite). Returns (pzz, pzv, pvv)."""
    fz = (sz_max / pzz.clamp_min(1e-300).sqrt()).clamp(max=1.0)
    fv = (sv_max / pvv.clamp_min(1e-300).sqrt()).clamp(max=1.0)
    return pzz * fz * fz, pzv * fz * fv, pvv * fv * fv


class EfferenceFilter:
    """Batched EKF on (altitude, velocity) fed by D_hat and the known acceleration.

    Args:
        z0_m: (B,) float64 nominal initial altitude, m (> 0).
        v0_mps: (B,) float64 nominal initial velocity, m/s.
        dt_s: control interval, s (> 0).
        prior_scale: the initial guess is (prior_scale z0, prior_scale v0), > 0.
        prior_rel_sigma: relative std. dev. of the prior on z and v, > 0.
        accel_sigma_mps2: absolute std. dev. of the known acceleration, m/s^2 (>= 0).
        accel_sigma_rel: relative std. dev. of the thrust acceleration u/m (>= 0).
        meas_sigma_rel: relative std. dev. of one D_hat (>= 0).
        meas_sigma_abs: absolute std. dev. of one D_hat, 1/s (> 0).
        gate_sigma: innovations beyond this many std. dev. are rejected (> 0).
        min_altitude_m: the altitude estimate is kept above this, m (> 0).
        prior_rel_sigma_v: relative std. dev. of the prior on v (> 0), None = ``prior_rel_sigma``.
        meas_noise: ``"fixed"`` (R from meas_sigma_rel / meas_sigma_abs) or ``"confidence"`` (plus
            the estimator's own error from ``confidence``, passed to :meth:`update`).
        huber_k: clip accepted innovations to this many std. dev. (>= 0, 0 = off).
        max_step_rel: largest relative change of z_hat, v_hat per update (>= 0, 0 = off).
        cov_cap_rel: cap of the std. dev. of z and v relative to z_hat, |v_hat| (>= 0, 0 = off).
        min_confidence: estimates whose ``confidence`` is below this are not used (in [0, 1]).
    """

    provides_altitude = True

    def __init__(self, z0_m: Tensor, v0_mps: Tensor, dt_s: float, prior_scale: float = 1.0,
                 prior_rel_sigma: float = 0.3, accel_sigma_mps2: float = 0.05, accel_sigma_rel: float = 0.02,
                 meas_sigma_rel: float = 0.3, meas_sigma_abs: float = 0.005, gate_sigma: float = 5.0,
                 min_altitude_m: float = 1.0, prior_rel_sigma_v: Optional[float] = None,
                 meas_noise: str = "fixed", huber_k: float = 0.0, max_step_rel: float = 0.0,
                 cov_cap_rel: float = 0.0, min_confidence: float = 0.0):
        z0 = torch.as_tensor(z0_m, dtype=torch.float64).reshape(-1)
        v0 = torch.as_tensor(v0_mps, dtype=torch.float64, device=z0.device).reshape(-1)
        if z0.shape != v0.shape:
            raise ValueError(f"z0_m and v0_mps must have one shape (B,), got {tuple(z0.shape)}, {tuple(v0.shape)}")
        if bool((z0 <= 0).any()):
            raise ValueError("z0_m must be > 0 for every element")
        checks = {"dt_s": (dt_s, 0, False), "prior_scale": (prior_scale, 0, False),
                  "prior_rel_sigma": (prior_rel_sigma, 0, False), "accel_sigma_mps2": (accel_sigma_mps2, 0, True),
                  "accel_sigma_rel": (accel_sigma_rel, 0, True), "meas_sigma_rel": (meas_sigma_rel, 0, True),
                  "meas_sigma_abs": (meas_sigma_abs, 0, False), "gate_sigma": (gate_sigma, 0, False),
                  "min_altitude_m": (min_altitude_m, 0, False), "huber_k": (huber_k, 0, True),
                  "max_step_rel": (max_step_rel, 0, True), "cov_cap_rel": (cov_cap_rel, 0, True)}
        if not 0.0 <= min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {min_confidence}")
        self.min_confidence = float(min_confidence)
        if prior_rel_sigma_v is not None:
            checks["prior_rel_sigma_v"] = (prior_rel_sigma_v, 0, False)
        for name, (val, lo, inclusive) in checks.items():
            if not (val >= lo if inclusive else val > lo):
                raise ValueError(f"{name} must be {'>=' if inclusive else '>'} {lo}, got {val}")
        self.z0_m, self.v0_mps, self.dt_s = z0, v0, float(dt_s)
        self.prior_scale, self.prior_rel_sigma = float(prior_scale), float(prior_rel_sigma)
        self.accel_sigma_mps2, self.accel_sigma_rel = float(accel_sigma_mps2), float(accel_sigma_rel)
        self.meas_sigma_rel, self.meas_sigma_abs = float(meas_sigma_rel), float(meas_sigma_abs)
        self.gate_sigma, self.min_altitude_m = float(gate_sigma), float(min_altitude_m)
        if meas_noise not in ("fixed", "confidence"):
            raise ValueError(f"meas_noise must be 'fixed' or 'confidence', got {meas_noise!r}")
        self.prior_rel_sigma_v = self.prior_rel_sigma if prior_rel_sigma_v is None else float(prior_rel_sigma_v)
        self.meas_noise, self.huber_k = meas_noise, float(huber_k)
        self.max_step_rel, self.cov_cap_rel = float(max_step_rel), float(cov_cap_rel)
        self.batch_size = int(z0.numel())
        self.n_rejected = torch.zeros(self.batch_size, dtype=torch.int64, device=z0.device)
        self.reset(None)

    @classmethod
    def from_params(cls, p, **options) -> "EfferenceFilter":
        """From the loop's :class:`~dvsland.control.DescentParams` and the ``controller.efference`` options
        (``prior_state`` is the loop's: it decides which (z0, v0) ``p`` holds)."""
        options = {k: v for k, v in options.items() if k not in _NOT_MINE}
        return cls(p.z0_m, p.v0_mps, p.dt_s, **options)

    # ------------------------------------------------------------------ state
    def reset(self, mask: Optional[Tensor] = None) -> None:
        """Back to the prior where ``mask`` (B,) bool is True (all when None)."""
        z = self.z0_m * self.prior_scale
        v = self.v0_mps * self.prior_scale
        pzz = (self.prior_rel_sigma * z) ** 2
        pvv = (self.prior_rel_sigma_v * v) ** 2
        pzv = torch.zeros_like(z)
        if mask is None:
            self.z, self.v, self.pzz, self.pzv, self.pvv = z.clone(), v.clone(), pzz, pzv, pvv
            self.n_rejected.zero_()
            return
        self.z = torch.where(mask, z, self.z)
        self.v = torch.where(mask, v, self.v)
        self.pzz = torch.where(mask, pzz, self.pzz)
        self.pzv = torch.where(mask, pzv, self.pzv)
        self.pvv = torch.where(mask, pvv, self.pvv)
        self.n_rejected = torch.where(mask, 0, self.n_rejected)

    @property
    def altitude_m(self) -> Tensor:
        """(B,) float64 altitude estimate, m."""
        return self.z

    @property
    def velocity_mps(self) -> Tensor:
        """(B,) float64 velocity estimate, m/s."""
        return self.v

    @property
    def divergence(self) -> Tensor:
        """(B,) float64 filtered divergence v / z, 1/s."""
        return self.v / self.z

    # ------------------------------------------------------------------ steps
    def predict(self, accel_mps2: Tensor, thrust_accel_mps2: Optional[Tensor] = None,
                mask: Optional[Tensor] = None) -> None:
        """Advance by dt with the known acceleration ``accel_mps2`` (B,) (u/m - g), m/s^2;
        ``thrust_accel_mps2`` (B,) = u/m scales the process noise (default: |accel + 0|)."""
        dt = self.dt_s
        a = accel_mps2.to(torch.float64)
        ua = a.abs() if thrust_accel_mps2 is None else thrust_accel_mps2.to(torch.float64).abs()
        sa2 = (self.accel_sigma_mps2 + self.accel_sigma_rel * ua) ** 2
        z = self.z + self.v * dt + 0.5 * a * dt * dt
        v = self.v + a * dt
        # P = F P F^T + Q, F = [[1, dt], [0, 1]]
        pzz = self.pzz + 2 * dt * self.pzv + dt * dt * self.pvv + sa2 * dt ** 4 / 4
        pzv = self.pzv + dt * self.pvv + sa2 * dt ** 3 / 2
        pvv = self.pvv + sa2 * dt * dt
        z = z.clamp_min(self.min_altitude_m)
        if self.cov_cap_rel > 0:
            pzz, pzv, pvv = cap_covariance(pzz, pzv, pvv, self.cov_cap_rel * z, self.cov_cap_rel * v.abs())
        if mask is not None:
            z, v = torch.where(mask, z, self.z), torch.where(mask, v, self.v)
            pzz, pzv, pvv = (torch.where(mask, pzz, self.pzz), torch.where(mask, pzv, self.pzv),
                             torch.where(mask, pvv, self.pvv))
        self.z, self.v, self.pzz, self.pzv, self.pvv = z, v, pzz, pzv, pvv

    def correct(self, d_hat: Tensor, mask: Optional[Tensor] = None, confidence: Optional[Tensor] = None) -> Tensor:
        """Fuse one D_hat (B,) (1/s, NaN = none); returns (B,) bool: which elements used it.

        ``confidence`` (B,) in [0, 1] (the estimator's ``confidence()``) is used with
        ``meas_noise="confidence"``: 0 or not finite = no update, else it adds its relative error
        sigma_c = 0.1 sqrt(1/c - 1) to R. Ignored with ``meas_noise="fixed"``."""
        d = d_hat.to(torch.float64)
        z, v = self.z, self.v
        h = v / z
        hz, hv = -v / (z * z), 1.0 / z
        r = (self.meas_sigma_rel * h.abs() + self.meas_sigma_abs) ** 2
        finite = torch.isfinite(d)
        if confidence is not None and self.min_confidence > 0:
            finite = finite & (confidence.to(device=d.device, dtype=torch.float64) >= self.min_confidence)
        if self.meas_noise == "confidence" and confidence is not None:
            sig_c = confidence_rel_sigma(confidence.to(device=d.device, dtype=torch.float64))
            finite = finite & torch.isfinite(sig_c)
            scale = torch.maximum(torch.where(finite, d, 0.0).abs(), h.abs())  # a near-0 D_hat is no surer
            r = r + (torch.where(torch.isfinite(sig_c), sig_c, 0.0) * scale) ** 2
        s = hz * hz * self.pzz + 2 * hz * hv * self.pzv + hv * hv * self.pvv + r
        innov = d - h
        ok = finite & (innov * innov <= self.gate_sigma ** 2 * s)
        if mask is not None:
            ok = ok & mask
        rejected = finite & ~ok
        if mask is not None:
            rejected = rejected & mask
        self.n_rejected += rejected.to(torch.int64)
        # K = P H^T / s
        kz = (self.pzz * hz + self.pzv * hv) / s
        kv = (self.pzv * hz + self.pvv * hv) / s
        innov = torch.where(ok, innov, 0.0)
        if self.huber_k > 0:  # Huber: a far estimate pulls like one at huber_k sigma
            lim = self.huber_k * s.sqrt()
            innov = torch.maximum(torch.minimum(innov, lim), -lim)
        dz, dv = kz * innov, kv * innov
        if self.max_step_rel > 0:  # one update moves z, v by at most max_step_rel of their value
            lz, lv = self.max_step_rel * z, self.max_step_rel * v.abs().clamp_min(1e-3)
            dz = torch.maximum(torch.minimum(dz, lz), -lz)
            dv = torch.maximum(torch.minimum(dv, lv), -lv)
        z_new = (z + dz).clamp_min(self.min_altitude_m)
        v_new = v + dv
        # P = (I - K H) P, symmetric form
        pzz = self.pzz - kz * kz * s
        pzv = self.pzv - kz * kv * s
        pvv = self.pvv - kv * kv * s
        self.z = torch.where(ok, z_new, z)
        self.v = torch.where(ok, v_new, v)
        self.pzz = torch.where(ok, pzz.clamp_min(1e-12), self.pzz)
        self.pzv = torch.where(ok, pzv, self.pzv)
        self.pvv = torch.where(ok, pvv.clamp_min(1e-12), self.pvv)
        return ok

    def update(self, d_hat: Tensor, mask: Optional[Tensor] = None, accel_mps2: Optional[Tensor] = None,
               thrust_accel_mps2: Optional[Tensor] = None,
               confidence: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """One control step: predict with the acceleration applied since the last update (skipped
        when ``accel_mps2`` is None: the first step), then fuse ``d_hat``.

        Args:
            d_hat: (B,) float estimates, 1/s; NaN = missing.
            mask: optional (B,) bool: only these elements advance (others stay frozen).
            accel_mps2: (B,) float64 known acceleration u/m - g over the last step, m/s^2, or None.
            thrust_accel_mps2: (B,) float64 u/m over the last step (scales the process noise).
            confidence: optional (B,) float in [0, 1], the estimator's ``confidence()`` (used with
                ``meas_noise="confidence"``).

        Returns:
            (d_filtered (B,) float64 = v/z, n_used (B,) int64 = 1 where D_hat was fused).
        """
        if d_hat.shape != (self.batch_size,):
            raise ValueError(f"d_hat must have shape ({self.batch_size},), got {tuple(d_hat.shape)}")
        if accel_mps2 is not None:
            self.predict(accel_mps2, thrust_accel_mps2, mask)
        if confidence is not None and confidence.shape != (self.batch_size,):
            raise ValueError(f"confidence must have shape ({self.batch_size},), got {tuple(confidence.shape)}")
        used = self.correct(d_hat, mask, confidence)
        return self.divergence, used.to(torch.int64)
