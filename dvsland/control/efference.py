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

Params :class:`EfferenceParams` (the planned start and the ``controller.efference`` section), state
:class:`EfferenceState`, pure step :func:`efference_step` (:func:`efference_predict`, then
:func:`efference_correct`).
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

import torch

from dvsland.config.schema import EfferenceConfig
from dvsland.estimators.base import confidence_rel_sigma

from .filter import DivergenceFilter, FilterOut

Tensor = torch.Tensor


#: ``controller.efference`` options that are not this filter's (the loop's, and ``efference_fit``'s):
#: one config section serves both filters
_NOT_MINE = ("prior_state", "cauchy_c", "iterations", "forget_s")


def cap_covariance(pzz: Tensor, pzv: Tensor, pvv: Tensor, sz_max: Tensor, sv_max: Tensor):
    """Cap the standard deviations of a batch of 2x2 covariances [[pzz, pzv], [pzv, pvv]] at
    ``sz_max``, ``sv_max`` (B,) by scaling rows and columns (the correlation is kept, the matrix
    stays positive semi-definite). Returns (pzz, pzv, pvv)."""
    fz = (sz_max / pzz.clamp_min(1e-300).sqrt()).clamp(max=1.0)
    fv = (sv_max / pvv.clamp_min(1e-300).sqrt()).clamp(max=1.0)
    return pzz * fz * fz, pzv * fz * fv, pvv * fv * fv


class EfferenceParams(NamedTuple):
    """Settings of the ``efference`` EKF for B descents; frozen in flight.

    Attributes:
        z0_m: (B,) float64 nominal initial altitude, m (> 0).
        v0_mps: (B,) float64 nominal initial velocity, m/s.
        dt_s: control interval, s.
        cfg: the ``controller.efference`` section (``prior_rel_sigma_v`` resolved: never None).
    """

    z0_m: Tensor
    v0_mps: Tensor
    dt_s: float
    cfg: EfferenceConfig


class EfferenceState(NamedTuple):
    """State of the ``efference`` EKF for B descents, all (B,).

    Attributes:
        z, v: float64 estimated altitude (m) and velocity (m/s).
        pzz, pzv, pvv: float64 covariance [[pzz, pzv], [pzv, pvv]] of (z, v), m^2, m^2/s, m^2/s^2.
        n_rejected: int64 estimates rejected by the gate since the descent's (re)start.
    """

    z: Tensor
    v: Tensor
    pzz: Tensor
    pzv: Tensor
    pvv: Tensor
    n_rejected: Tensor


def efference_prior(p: EfferenceParams) -> EfferenceState:
    """The prior of every descent: (prior_scale z0, prior_scale v0), relative std. dev.
    ``prior_rel_sigma`` on z and ``prior_rel_sigma_v`` on v, uncorrelated, nothing rejected."""
    c = p.cfg
    z = p.z0_m * c.prior_scale
    v = p.v0_mps * c.prior_scale
    return EfferenceState(z, v, (c.prior_rel_sigma * z) ** 2, torch.zeros_like(z), (c.prior_rel_sigma_v * v) ** 2,
                          torch.zeros(z.shape, dtype=torch.int64, device=z.device))


def efference_predict(p: EfferenceParams, s: EfferenceState, accel_mps2: Tensor,
                      thrust_accel_mps2: Optional[Tensor] = None, active: Optional[Tensor] = None) -> EfferenceState:
    """Advance by dt with the known acceleration ``accel_mps2`` (B,) (u/m - g), m/s^2;
    ``thrust_accel_mps2`` (B,) = u/m scales the process noise (default: |accel + 0|). Descents not
    ``active`` (B,) bool, and those whose acceleration is NaN (no efference copy: the first step
    after a restart), keep their state."""
    c, dt = p.cfg, p.dt_s
    a = accel_mps2.to(torch.float64)
    known = torch.isfinite(a)
    active = known if active is None else active & known
    ua = a.abs() if thrust_accel_mps2 is None else thrust_accel_mps2.to(torch.float64).abs()
    sa2 = (c.accel_sigma_mps2 + c.accel_sigma_rel * ua) ** 2
    z = s.z + s.v * dt + 0.5 * a * dt * dt
    v = s.v + a * dt
    # P = F P F^T + Q, F = [[1, dt], [0, 1]]
    pzz = s.pzz + 2 * dt * s.pzv + dt * dt * s.pvv + sa2 * dt ** 4 / 4
    pzv = s.pzv + dt * s.pvv + sa2 * dt ** 3 / 2
    pvv = s.pvv + sa2 * dt * dt
    z = z.clamp_min(c.min_altitude_m)
    if c.cov_cap_rel > 0:
        pzz, pzv, pvv = cap_covariance(pzz, pzv, pvv, c.cov_cap_rel * z, c.cov_cap_rel * v.abs())
    z, v = torch.where(active, z, s.z), torch.where(active, v, s.v)
    pzz, pzv, pvv = torch.where(active, pzz, s.pzz), torch.where(active, pzv, s.pzv), torch.where(active, pvv, s.pvv)
    return EfferenceState(z, v, pzz, pzv, pvv, s.n_rejected)


def _measurement(c: EfferenceConfig, d: Tensor, h: Tensor, confidence: Optional[Tensor]):
    """(R (B,) float64, usable (B,) bool) of the estimates ``d`` against the prediction ``h``."""
    r = (c.meas_sigma_rel * h.abs() + c.meas_sigma_abs) ** 2
    finite = torch.isfinite(d)
    if confidence is not None and c.min_confidence > 0:
        finite = finite & (confidence.to(device=d.device, dtype=torch.float64) >= c.min_confidence)
    if c.meas_noise == "confidence" and confidence is not None:
        sig_c = confidence_rel_sigma(confidence.to(device=d.device, dtype=torch.float64))
        finite = finite & torch.isfinite(sig_c)
        scale = torch.maximum(torch.where(finite, d, 0.0).abs(), h.abs())  # a near-0 D_hat is no surer
        r = r + (torch.where(torch.isfinite(sig_c), sig_c, 0.0) * scale) ** 2
    return r, finite


def _limited_step(c: EfferenceConfig, z: Tensor, v: Tensor, kz: Tensor, kv: Tensor, innov: Tensor, s: Tensor):
    """(dz, dv) of one update after the Huber clip of the innovation and the step limit."""
    if c.huber_k > 0:  # Huber: a far estimate pulls like one at huber_k sigma
        lim = c.huber_k * s.sqrt()
        innov = torch.maximum(torch.minimum(innov, lim), -lim)
    dz, dv = kz * innov, kv * innov
    if c.max_step_rel > 0:  # one update moves z, v by at most max_step_rel of their value
        lz, lv = c.max_step_rel * z, c.max_step_rel * v.abs().clamp_min(1e-3)
        dz = torch.maximum(torch.minimum(dz, lz), -lz)
        dv = torch.maximum(torch.minimum(dv, lv), -lv)
    return dz, dv


def efference_correct(p: EfferenceParams, st: EfferenceState, d_hat: Tensor, active: Optional[Tensor] = None,
                      confidence: Optional[Tensor] = None) -> Tuple[EfferenceState, Tensor]:
    """Fuse one D_hat (B,) (1/s, NaN = none); returns (next state, (B,) bool: which descents used it).

    ``confidence`` (B,) in [0, 1] (the estimator's ``confidence()``) is used with
    ``meas_noise="confidence"``: 0 or not finite = no update, else it adds its relative error
    sigma_c = 0.1 sqrt(1/c - 1) to R. Ignored with ``meas_noise="fixed"``."""
    c = p.cfg
    d = d_hat.to(torch.float64)
    z, v = st.z, st.v
    h = v / z
    hz, hv = -v / (z * z), 1.0 / z
    r, finite = _measurement(c, d, h, confidence)
    s = hz * hz * st.pzz + 2 * hz * hv * st.pzv + hv * hv * st.pvv + r
    innov = d - h
    ok = finite & (innov * innov <= c.gate_sigma ** 2 * s)
    rejected = finite & ~ok
    if active is not None:
        ok, rejected = ok & active, rejected & active
    # K = P H^T / s
    kz = (st.pzz * hz + st.pzv * hv) / s
    kv = (st.pzv * hz + st.pvv * hv) / s
    dz, dv = _limited_step(c, z, v, kz, kv, torch.where(ok, innov, 0.0), s)
    z_new = (z + dz).clamp_min(c.min_altitude_m)
    v_new = v + dv
    # P = (I - K H) P, symmetric form
    pzz = st.pzz - kz * kz * s
    pzv = st.pzv - kz * kv * s
    pvv = st.pvv - kv * kv * s
    return EfferenceState(torch.where(ok, z_new, z), torch.where(ok, v_new, v),
                          torch.where(ok, pzz.clamp_min(1e-12), st.pzz), torch.where(ok, pzv, st.pzv),
                          torch.where(ok, pvv.clamp_min(1e-12), st.pvv),
                          st.n_rejected + rejected.to(torch.int64)), ok


def efference_step(p: EfferenceParams, state: EfferenceState, d_hat: Tensor, active: Optional[Tensor] = None,
                   accel_mps2: Optional[Tensor] = None, thrust_accel_mps2: Optional[Tensor] = None,
                   confidence: Optional[Tensor] = None) -> Tuple[EfferenceState, FilterOut]:
    """Pure step of the ``efference`` EKF: predict with the acceleration applied since the last step
    (skipped when ``accel_mps2`` is None: the first step; for the descents where it is NaN: their
    first step after a restart), then fuse ``d_hat``.

    Returns:
        (next state, FilterOut(v/z (B,) float64, 1 where D_hat was fused (B,) int64, z (B,) float64 m,
        no doubt, sqrt(pvv) (B,) float64 m/s)).
    """
    if accel_mps2 is not None:
        state = efference_predict(p, state, accel_mps2, thrust_accel_mps2, active)
    state, used = efference_correct(p, state, d_hat, active, confidence)
    return state, FilterOut(state.v / state.z, used.to(torch.int64), state.z, None, torch.sqrt(state.pvv))


def check_filter_plan(z0_m, v0_mps) -> Tuple[Tensor, Tensor]:
    """(z0, v0) as (B,) float64 tensors on z0's device; ValueError unless they match and z0 > 0."""
    z0 = torch.as_tensor(z0_m, dtype=torch.float64).reshape(-1)
    v0 = torch.as_tensor(v0_mps, dtype=torch.float64, device=z0.device).reshape(-1)
    if z0.shape != v0.shape:
        raise ValueError(f"z0_m and v0_mps must have one shape (B,), got {tuple(z0.shape)}, {tuple(v0.shape)}")
    if bool((z0 <= 0).any()):
        raise ValueError("z0_m must be > 0 for every element")
    return z0, v0


def check_positive(checks: dict, min_confidence: float) -> None:
    """ValueError naming the first option out of range: ``checks`` maps name -> (value, lower bound,
    bound allowed); ``min_confidence`` must lie in [0, 1]."""
    if not 0.0 <= min_confidence <= 1.0:
        raise ValueError(f"min_confidence must be in [0, 1], got {min_confidence}")
    for name, (val, lo, inclusive) in checks.items():
        if not (val >= lo if inclusive else val > lo):
            raise ValueError(f"{name} must be {'>=' if inclusive else '>'} {lo}, got {val}")


class PlannedStartFilter(DivergenceFilter):
    """A filter whose params hold each descent's planned start (``params.z0_m`` (B,)): its batch
    size and device are those of the plan."""

    @property
    def batch_size(self) -> int:
        return int(self.params.z0_m.numel())

    @property
    def device(self) -> torch.device:
        return self.params.z0_m.device


class EfferenceFilter(PlannedStartFilter):
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

    Params :class:`EfferenceParams`, state :class:`EfferenceState` (its fields read as attributes:
    ``z``, ``v``, ``pzz``, ``pzv``, ``pvv``, ``n_rejected``).
    """

    provides_altitude = True
    provides_velocity_sigma = True

    def __init__(self, z0_m: Tensor, v0_mps: Tensor, dt_s: float, prior_scale: float = 1.0,
                 prior_rel_sigma: float = 0.3, accel_sigma_mps2: float = 0.05, accel_sigma_rel: float = 0.02,
                 meas_sigma_rel: float = 0.3, meas_sigma_abs: float = 0.005, gate_sigma: float = 5.0,
                 min_altitude_m: float = 1.0, prior_rel_sigma_v: Optional[float] = None,
                 meas_noise: str = "fixed", huber_k: float = 0.0, max_step_rel: float = 0.0,
                 cov_cap_rel: float = 0.0, min_confidence: float = 0.0):
        z0, v0 = check_filter_plan(z0_m, v0_mps)
        checks = {"dt_s": (dt_s, 0, False), "prior_scale": (prior_scale, 0, False),
                  "prior_rel_sigma": (prior_rel_sigma, 0, False), "accel_sigma_mps2": (accel_sigma_mps2, 0, True),
                  "accel_sigma_rel": (accel_sigma_rel, 0, True), "meas_sigma_rel": (meas_sigma_rel, 0, True),
                  "meas_sigma_abs": (meas_sigma_abs, 0, False), "gate_sigma": (gate_sigma, 0, False),
                  "min_altitude_m": (min_altitude_m, 0, False), "huber_k": (huber_k, 0, True),
                  "max_step_rel": (max_step_rel, 0, True), "cov_cap_rel": (cov_cap_rel, 0, True)}
        if prior_rel_sigma_v is not None:
            checks["prior_rel_sigma_v"] = (prior_rel_sigma_v, 0, False)
        check_positive(checks, min_confidence)
        if meas_noise not in ("fixed", "confidence"):
            raise ValueError(f"meas_noise must be 'fixed' or 'confidence', got {meas_noise!r}")
        psv = prior_rel_sigma if prior_rel_sigma_v is None else prior_rel_sigma_v
        cfg = EfferenceConfig(prior_scale=float(prior_scale), prior_rel_sigma=float(prior_rel_sigma),
                              accel_sigma_mps2=float(accel_sigma_mps2), accel_sigma_rel=float(accel_sigma_rel),
                              meas_sigma_rel=float(meas_sigma_rel), meas_sigma_abs=float(meas_sigma_abs),
                              gate_sigma=float(gate_sigma), min_altitude_m=float(min_altitude_m),
                              prior_rel_sigma_v=float(psv), meas_noise=meas_noise, huber_k=float(huber_k),
                              max_step_rel=float(max_step_rel), cov_cap_rel=float(cov_cap_rel),
                              min_confidence=float(min_confidence))
        self.params = EfferenceParams(z0, v0, float(dt_s), cfg)
        self._template = self.init_state()
        self.state = self.init_state()

    @classmethod
    def from_params(cls, p, **options) -> "EfferenceFilter":
        """From the loop's :class:`~dvsland.control.DescentParams` and the ``controller.efference`` options
        (``prior_state`` is the loop's: it decides which (z0, v0) ``p`` holds)."""
        options = {k: v for k, v in options.items() if k not in _NOT_MINE}
        return cls(p.z0_m, p.v0_mps, p.dt_s, **options)

    # ------------------------------------------------------------------ the contract
    def init_state(self) -> EfferenceState:
        return efference_prior(self.params)

    def step_state(self, state: EfferenceState, d_hat: Tensor, active: Optional[Tensor] = None,
                   accel_mps2: Optional[Tensor] = None, thrust_accel_mps2: Optional[Tensor] = None,
                   confidence: Optional[Tensor] = None) -> Tuple[EfferenceState, FilterOut]:
        """Pure step (:func:`efference_step`)."""
        self._check_inputs(state, d_hat, confidence)
        return efference_step(self.params, state, d_hat, active, accel_mps2, thrust_accel_mps2, confidence)

    # ------------------------------------------------------------------ the object API
    @property
    def altitude_m(self) -> Tensor:
        """(B,) float64 altitude estimate, m."""
        return self.state.z

    @property
    def velocity_mps(self) -> Tensor:
        """(B,) float64 velocity estimate, m/s."""
        return self.state.v

    @property
    def divergence(self) -> Tensor:
        """(B,) float64 filtered divergence v / z, 1/s."""
        return self.state.v / self.state.z

    def predict(self, accel_mps2: Tensor, thrust_accel_mps2: Optional[Tensor] = None,
                mask: Optional[Tensor] = None) -> None:
        """The held state advanced by :func:`efference_predict`."""
        self.state = efference_predict(self.params, self.state, accel_mps2, thrust_accel_mps2, mask)

    def correct(self, d_hat: Tensor, mask: Optional[Tensor] = None, confidence: Optional[Tensor] = None) -> Tensor:
        """The held state corrected by :func:`efference_correct`; returns (B,) bool: which descents used it."""
        self.state, ok = efference_correct(self.params, self.state, d_hat, mask, confidence)
        return ok
