"""Robust efference-copy filter (filter ``efference_fit``): a robust batch fit of the two numbers
the craft does not know, its initial altitude and velocity errors, to every D_hat so far.

The thrust the craft applied is known (the efference copy), and between control steps the
dynamics are exact. So the whole trajectory is the dead-reckoned one from the planned start
(z0, v0) plus a constant offset theta = (dz, dv) of the initial state:

    z_k = z_dr_k + dz + dv t_k,    v_k = v_dr_k + dv,    D_k = v_k / z_k

(z_dr, v_dr advance exactly with a = u/m - g). Every estimate D_hat_k is one measurement of
theta. Each control step the filter re-fits theta to all of them (maximum a posteriori, prior
theta ~ N(0, diag((prior_rel_sigma z0)^2, (prior_rel_sigma_v v0)^2))) by a few Gauss-Newton /
iteratively re-weighted least-squares rounds, warm-started from the last step, with a robust
(Cauchy) weight per measurement:

    u_k = (D_hat_k - D_k(theta)) / sqrt(R_k + J_k P J_k^T),   w_k = 1 / (1 + (u_k / cauchy_c)^2),
    w_k = 0 where |u_k| > gate_sigma or D_hat_k is NaN (or confidence 0),
    times exp(-age_k / forget_s) with ``forget_s`` > 0 (old estimates fade)

R_k as in the ``efference`` EKF (fixed, or with ``meas_noise="confidence"`` the estimator's own
error from its ``confidence()``), P the current posterior covariance of theta. Unlike a
recursive filter, an estimate rejected early still counts once the fit moves towards it, and a
run of wrong estimates accepted once is out-voted later by the consistent ones: there is no
lock-out and no covariance that grows without measurements (theta is constant; P only shrinks).

Model errors (thrust not applied as commanded, unknown mass) are outside the model: the filter
assumes the dynamics of the simulator. Cost: O(steps so far) per element and step (the history is
kept, 40 bytes per element and step): on one torch thread of a loaded 2-core CPU (load 7), median
0.9 / 3.7 / 17 ms per step for B = 18 after 300 / 900 / 1800 steps without forgetting
(docs/controllers.md). With ``forget_s`` > 0 the fit reads only the last 12 forget_s of estimates
(older ones weigh < exp(-12)), so the cost stops growing after 12 forget_s / dt steps.

Output per step: the filtered divergence v_hat / z_hat (B,) float64, whether this step's estimate
got weight > 0.5 (B,) int64, and :attr:`altitude_m` / :attr:`velocity_mps`.
"""

from __future__ import annotations

import math

from typing import Optional, Tuple

import torch

from .efference import confidence_rel_sigma

Tensor = torch.Tensor


#: ``controller.efference`` options that are not this filter's (the loop's, and the EKF's)
_NOT_MINE = ("prior_state", "accel_sigma_mps2", "accel_sigma_rel", "huber_k", "max_step_rel", "cov_cap_rel")


class EfferenceFitFilter:
    """Batched robust MAP fit of the initial-state offset (dz, dv) to all D_hat so far.

    Args:
        z0_m: (B,) float64 planned initial altitude, m (> 0).
        v0_mps: (B,) float64 planned initial velocity, m/s.
        dt_s: control interval, s (> 0).
        prior_rel_sigma: relative std. dev. of the initial altitude error (> 0).
        prior_rel_sigma_v: relative std. dev. of the initial velocity error (> 0); None = prior_rel_sigma.
        meas_sigma_rel, meas_sigma_abs: fixed part of one estimate's std. dev. (relative >= 0;
            absolute > 0, 1/s).
        meas_noise: ``"fixed"`` or ``"confidence"`` (add 0.1 sqrt(1/c - 1) max(|D_hat|, |D|)).
        gate_sigma: estimates further than this many std. dev. get weight 0 (> 0).
        cauchy_c: scale of the Cauchy weight, std. dev. (> 0).
        iterations: Gauss-Newton rounds per step (>= 1).
        min_altitude_m: the altitude estimate is kept above this, m (> 0).
        prior_scale: the planned start is (prior_scale z0, prior_scale v0) (> 0; tests).
        forget_s: an estimate's weight decays as exp(-age / forget_s) (>= 0 s; 0 = never): old
            estimates fade, the posterior widens again and newer ones can correct the fit.
        min_confidence: estimates with a confidence below this are not used (in [0, 1]).
    """

    provides_altitude = True
    _cut_forget = 12.0  # history older than this many forget_s is left out of the fit

    def __init__(self, z0_m: Tensor, v0_mps: Tensor, dt_s: float, prior_rel_sigma: float = 0.1,
                 prior_rel_sigma_v: Optional[float] = None, meas_sigma_rel: float = 0.05,
                 meas_sigma_abs: float = 0.001, meas_noise: str = "fixed", gate_sigma: float = 5.0,
                 cauchy_c: float = 2.0, iterations: int = 3, min_altitude_m: float = 1.0,
                 prior_scale: float = 1.0, forget_s: float = 0.0, min_confidence: float = 0.0):
        z0 = torch.as_tensor(z0_m, dtype=torch.float64).reshape(-1)
        v0 = torch.as_tensor(v0_mps, dtype=torch.float64, device=z0.device).reshape(-1)
        if z0.shape != v0.shape:
            raise ValueError(f"z0_m and v0_mps must have one shape (B,), got {tuple(z0.shape)}, {tuple(v0.shape)}")
        if bool((z0 <= 0).any()):
            raise ValueError("z0_m must be > 0 for every element")
        psv = prior_rel_sigma if prior_rel_sigma_v is None else prior_rel_sigma_v
        checks = {"dt_s": (dt_s, 0, False), "prior_rel_sigma": (prior_rel_sigma, 0, False),
                  "prior_rel_sigma_v": (psv, 0, False), "meas_sigma_rel": (meas_sigma_rel, 0, True),
                  "meas_sigma_abs": (meas_sigma_abs, 0, False), "gate_sigma": (gate_sigma, 0, False),
                  "cauchy_c": (cauchy_c, 0, False), "iterations": (iterations, 1, True),
                  "min_altitude_m": (min_altitude_m, 0, False), "prior_scale": (prior_scale, 0, False),
                  "forget_s": (forget_s, 0, True)}
        if not 0.0 <= min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {min_confidence}")
        self.min_confidence = float(min_confidence)
        for name, (val, lo, inclusive) in checks.items():
            if not (val >= lo if inclusive else val > lo):
                raise ValueError(f"{name} must be {'>=' if inclusive else '>'} {lo}, got {val}")
        if meas_noise not in ("fixed", "confidence"):
            raise ValueError(f"meas_noise must be 'fixed' or 'confidence', got {meas_noise!r}")
        self.z0_m, self.v0_mps, self.dt_s = z0 * prior_scale, v0 * prior_scale, float(dt_s)
        self.sz0 = float(prior_rel_sigma) * self.z0_m.abs()
        self.sv0 = float(psv) * self.v0_mps.abs().clamp_min(1e-3)
        self.meas_sigma_rel, self.meas_sigma_abs = float(meas_sigma_rel), float(meas_sigma_abs)
        self.meas_noise, self.gate_sigma, self.cauchy_c = meas_noise, float(gate_sigma), float(cauchy_c)
        self.iterations, self.min_altitude_m = int(iterations), float(min_altitude_m)
        self.forget_s = float(forget_s)
        self.batch_size = B = int(z0.numel())
        dev = z0.device
        self.n_rejected = torch.zeros(B, dtype=torch.int64, device=dev)
        self._cap = 0
        self._hist = None
        self.reset(None)

    @classmethod
    def from_params(cls, p, **options) -> "EfferenceFitFilter":
        """From the loop's :class:`~dvsland.control.DescentParams` and the ``controller.efference`` options."""
        options = {k: v for k, v in options.items() if k not in _NOT_MINE}
        return cls(p.z0_m, p.v0_mps, p.dt_s, **options)

    # ------------------------------------------------------------------ state
    def reset(self, mask: Optional[Tensor] = None) -> None:
        """Back to the planned start, with no estimates, where ``mask`` (B,) bool is True (all when None)."""
        B, dev, f64 = self.batch_size, self.z0_m.device, torch.float64
        if mask is None:
            mask = torch.ones(B, dtype=torch.bool, device=dev)
        if self._hist is None:
            self._cap = 256
            self._hist = torch.full((5, self._cap, B), float("nan"), dtype=f64, device=dev)
            self.zdr, self.vdr = self.z0_m.clone(), self.v0_mps.clone()
            self.theta = torch.zeros(2, B, dtype=f64, device=dev)
            self.t_s = torch.zeros(B, dtype=f64, device=dev)
            self.n = torch.zeros(B, dtype=torch.int64, device=dev)
            self.info = torch.zeros(3, B, dtype=f64, device=dev)  # posterior information (a, b, c) of [[a, b], [b, c]]
        self.zdr = torch.where(mask, self.z0_m, self.zdr)
        self.vdr = torch.where(mask, self.v0_mps, self.vdr)
        self.theta = torch.where(mask, 0.0, self.theta)
        self.t_s = torch.where(mask, 0.0, self.t_s)
        self.n = torch.where(mask, 0, self.n)
        self._hist[:, :, mask] = float("nan")
        prior = torch.stack([1.0 / self.sz0 ** 2, torch.zeros_like(self.sz0), 1.0 / self.sv0 ** 2])
        self.info = torch.where(mask, prior, self.info)
        self.n_rejected = torch.where(mask, 0, self.n_rejected)

    @property
    def altitude_m(self) -> Tensor:
        """(B,) float64 altitude estimate, m."""
        return (self.zdr + self.theta[0] + self.theta[1] * self.t_s).clamp_min(self.min_altitude_m)

    @property
    def velocity_mps(self) -> Tensor:
        """(B,) float64 velocity estimate, m/s."""
        return self.vdr + self.theta[1]

    @property
    def divergence(self) -> Tensor:
        """(B,) float64 filtered divergence v_hat / z_hat, 1/s."""
        return self.velocity_mps / self.altitude_m

    # ------------------------------------------------------------------ steps
    def _push(self, d: Tensor, rel_sig: Tensor, mask: Tensor) -> None:
        """Append (z_dr, v_dr, t, D_hat, sigma_c) at each active element's row ``n``."""
        if int(self.n.max()) >= self._cap:
            extra = torch.full((5, self._cap, self.batch_size), float("nan"), dtype=self._hist.dtype,
                               device=self._hist.device)
            self._hist = torch.cat([self._hist, extra], 1)
            self._cap *= 2
        row = self.n.clamp_max(self._cap - 1)
        new = torch.stack([self.zdr, self.vdr, self.t_s, d, rel_sig])  # (5, B)
        cur = self._hist.gather(1, row.view(1, 1, -1).expand(5, 1, -1)).squeeze(1)
        val = torch.where(mask, new, cur)
        self._hist.scatter_(1, row.view(1, 1, -1).expand(5, 1, -1), val.unsqueeze(1))
        self.n = self.n + mask.to(torch.int64)

    def _fit(self, mask: Tensor) -> Tensor:
        """Robust Gauss-Newton rounds on theta for the elements of ``mask``; returns the weights (N, B)."""
        n_max = int(self.n.max())
        lo = 0
        if self.forget_s > 0 and bool(mask.any()):
            # rows older than 12 forget_s weigh < exp(-12) = 6e-6: left out, so the cost stops growing
            # with the flight (cut only below every fitted element's own history: rows are per element)
            window = int(math.ceil(self._cut_forget * self.forget_s / self.dt_s))
            lo = max(0, int(self.n[mask].min()) - window)
        zdr, vdr, t, d, sig_c = (h[lo:n_max] for h in self._hist)
        have = torch.isfinite(d)
        d0 = torch.where(have, d, 0.0)
        zdr, vdr, t = torch.where(have, zdr, 1e3), torch.where(have, vdr, 0.0), torch.where(have, t, 0.0)
        fade = (torch.exp(-(self.t_s.unsqueeze(0) - t).clamp_min(0.0) / self.forget_s)
                if self.forget_s > 0 else torch.ones_like(d))
        iz, iv = 1.0 / self.sz0 ** 2, 1.0 / self.sv0 ** 2
        theta = self.theta.clone()
        info = self.info
        w = torch.zeros_like(d)
        for _ in range(self.iterations):
            dz, dv = theta[0], theta[1]
            z = (zdr + dz + dv * t).clamp_min(self.min_altitude_m)
            v = vdr + dv
            h = v / z
            jz = -v / (z * z)
            jv = (z - v * t) / (z * z)
            r_fix = (self.meas_sigma_rel * h.abs() + self.meas_sigma_abs) ** 2
            r_c = (torch.where(torch.isfinite(sig_c), sig_c, 0.0) * torch.maximum(d0.abs(), h.abs())) ** 2
            r = r_fix + r_c
            # current posterior covariance of theta: inverse of [[a, b], [b, c]]
            det = (info[0] * info[2] - info[1] ** 2).clamp_min(1e-300)
            pzz, pzv, pvv = info[2] / det, -info[1] / det, info[0] / det
            s = r + jz * jz * pzz + 2 * jz * jv * pzv + jv * jv * pvv
            res = d0 - h
            u2 = res * res / s
            keep = have & (u2 <= self.gate_sigma ** 2) & torch.isfinite(sig_c) & torch.isfinite(u2)
            w = torch.where(keep, 1.0 / (1.0 + u2 / self.cauchy_c ** 2) / r, 0.0)
            w_info = w * fade
            a = (w_info * jz * jz).sum(0) + iz
            b = (w_info * jz * jv).sum(0)
            c = (w_info * jv * jv).sum(0) + iv
            gz = (w_info * jz * res).sum(0) - dz * iz
            gv = (w_info * jv * res).sum(0) - dv * iv
            det = (a * c - b * b).clamp_min(1e-300)
            step_z = (c * gz - b * gv) / det
            step_v = (a * gv - b * gz) / det
            # stay inside 4 prior sigmas (a wild step cannot leave the physically possible)
            new_z = (dz + step_z).clamp(-4 * self.sz0, 4 * self.sz0)
            new_v = (dv + step_v).clamp(-4 * self.sv0, 4 * self.sv0)
            theta = torch.where(mask, torch.stack([new_z, new_v]), theta)
            info = torch.where(mask, torch.stack([a, b, c]), info)
        self.theta, self.info = theta, info
        self._fit_lo = lo
        return w * r  # the robust weights in [0, 1] of rows lo .. n_max - 1

    def update(self, d_hat: Tensor, mask: Optional[Tensor] = None, accel_mps2: Optional[Tensor] = None,
               thrust_accel_mps2: Optional[Tensor] = None,
               confidence: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """One control step: dead-reckon with the acceleration applied since the last update
        (skipped when ``accel_mps2`` is None: the first step), store ``d_hat``, re-fit.

        Args:
            d_hat: (B,) float estimates, 1/s; NaN = missing.
            mask: optional (B,) bool: only these elements advance (others stay frozen).
            accel_mps2: (B,) float64 known acceleration u/m - g over the last step, m/s^2, or None.
            thrust_accel_mps2: ignored (no process noise: the dynamics are exact).
            confidence: optional (B,) float in [0, 1], the estimator's ``confidence()``
                (0 = no update; with ``meas_noise="confidence"`` it also sets the noise).

        Returns:
            (d_filtered (B,) float64, used (B,) int64: 1 where this step's estimate got weight > 0.5).
        """
        B = self.batch_size
        if d_hat.shape != (B,):
            raise ValueError(f"d_hat must have shape ({B},), got {tuple(d_hat.shape)}")
        if confidence is not None and confidence.shape != (B,):
            raise ValueError(f"confidence must have shape ({B},), got {tuple(confidence.shape)}")
        dev = self.z0_m.device
        m = torch.ones(B, dtype=torch.bool, device=dev) if mask is None else mask.to(dev)
        if accel_mps2 is not None:
            a = accel_mps2.to(device=dev, dtype=torch.float64)
            dt = self.dt_s
            self.zdr = torch.where(m, self.zdr + self.vdr * dt + 0.5 * a * dt * dt, self.zdr)
            self.vdr = torch.where(m, self.vdr + a * dt, self.vdr)
            self.t_s = torch.where(m, self.t_s + dt, self.t_s)
        d = d_hat.to(device=dev, dtype=torch.float64)
        d = torch.where(torch.isfinite(d), d, float("nan"))
        if confidence is not None:
            sig = confidence_rel_sigma(confidence.to(device=dev, dtype=torch.float64))
            low = confidence.to(device=dev, dtype=torch.float64) < self.min_confidence
            d = torch.where(torch.isfinite(sig) & ~low, d, float("nan"))  # confidence 0 (or too low): no estimate
            sig = torch.where(torch.isfinite(sig), sig, 0.0) if self.meas_noise == "confidence" else torch.zeros_like(sig)
        else:
            sig = torch.zeros_like(d)
        self._push(d, sig, m)
        if int(self.n.max()) == 0:
            return self.divergence, torch.zeros(B, dtype=torch.int64, device=dev)
        w = self._fit(m)
        row = (self.n - 1 - self._fit_lo).clamp(0, w.shape[0] - 1)
        w_now = w.gather(0, row.view(1, -1)).squeeze(0)
        used = m & torch.isfinite(d) & (w_now > 0.5)
        self.n_rejected += (m & torch.isfinite(d) & (w_now == 0)).to(torch.int64)
        return self.divergence, used.to(torch.int64)
