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

(While ``gate_sigma`` is trained through the loop, the hard gate carries the gradient of a smooth
one, :func:`gate_surrogate`; its values are unchanged.)

R_k as in the ``efference`` EKF (fixed, or with ``meas_noise="confidence"`` the estimator's own
error from its ``confidence()``), P the current posterior covariance of theta. Unlike a
recursive filter, an estimate rejected early still counts once the fit moves towards it, and a
run of wrong estimates accepted once is out-voted later by the consistent ones: there is no
lock-out and no covariance that grows without measurements (theta is constant; P only shrinks).

Model errors (thrust not applied as commanded, unknown mass) are outside the model: the filter
assumes the dynamics of the simulator. Cost: O(steps so far) per element and step (the history is
kept, 40 bytes per element and step). On a CPU each round's per-row terms run in one compiled pass
(:mod:`dvsland.control.native_fit`, the same bits as the torch path; not with gradients): on one
torch thread, about 0.8 / 2.8 / 4.0 ms per step for B = 18 after 300 / 1500 / 3000 steps without
forgetting (the torch path: 1.5 / 6.9 / 14 ms; docs/measurements.md). With ``forget_s`` > 0 the fit
reads only the last 12 forget_s of estimates (older ones weigh < exp(-12)), so the cost stops growing
after 12 forget_s / dt steps. On a CPU a finished descent (not ``active``) costs nothing: only the
descents in flight are fitted (:data:`CPU_COMPACT`), with the same bits, because each descent's sums
run over its own rows.

Output per step: the filtered divergence v_hat / z_hat (B,) float64, whether this step's estimate
got weight > 0.5 (B,) int64, and :attr:`altitude_m` / :attr:`velocity_mps`.

Params :class:`EfferenceFitParams`, state :class:`EfferenceFitState`, pure step
:func:`efference_fit_step`. The history is kept per step since :meth:`EfferenceFitFilter.init_state`
(one row per step for every descent, NaN where a descent had no estimate or was not active), so
the step needs no host sync: the rows to fit are known from the history's shape. A restart of some
descents blanks their rows; leading rows blank for every descent are dropped then. A descent frozen
(not active) for some steps has blank rows there, and the ``forget_s`` window counts steps, frozen
ones included; in the loop every descent flies from the first step until it ends, so its rows are
its consecutive estimates.
"""

from __future__ import annotations

import math

from typing import NamedTuple, Optional, Tuple

import torch

from dvsland.config.schema import EfferenceConfig

from . import native_fit
from .efference import PlannedStartFilter, check_filter_plan, check_positive, confidence_rel_sigma
from .filter import FilterOut

Tensor = torch.Tensor


#: ``controller.efference`` options that are not this filter's (the loop's, and the EKF's)
_NOT_MINE = ("prior_state", "accel_sigma_mps2", "accel_sigma_rel", "huber_k", "max_step_rel", "cov_cap_rel")

#: the five columns of a history row
ROW_FIELDS = ("z_dr_m", "v_dr_mps", "t_s", "d_hat", "sigma_c")


class EfferenceFitParams(NamedTuple):
    """Settings of the ``efference_fit`` filter for B descents; frozen in flight.

    Attributes:
        z0_m: (B,) float64 planned initial altitude times ``prior_scale``, m.
        v0_mps: (B,) float64 planned initial velocity times ``prior_scale``, m/s.
        sz0: (B,) float64 prior std. dev. of the altitude offset, m (prior_rel_sigma |z0|).
        sv0: (B,) float64 prior std. dev. of the velocity offset, m/s (prior_rel_sigma_v max(|v0|, 1e-3)).
        dt_s: control interval, s.
        cfg: the ``controller.efference`` section (``prior_rel_sigma_v`` resolved).
        cut_forget: with ``forget_s`` > 0, rows older than this many forget_s are left out of the fit.
    """

    z0_m: Tensor
    v0_mps: Tensor
    sz0: Tensor
    sv0: Tensor
    dt_s: float
    cfg: EfferenceConfig
    cut_forget: float = 12.0


class EfferenceFitState(NamedTuple):
    """State of the ``efference_fit`` filter for B descents.

    Attributes:
        zdr, vdr: (B,) float64 dead-reckoned planned altitude (m) and velocity (m/s).
        t_s: (B,) float64 flight time since the descent's (re)start, s.
        theta: (B, 2) float64 fitted offset (dz m, dv m/s) of the initial state.
        info: (B, 3) float64 posterior information (a, b, c) of [[a, b], [b, c]] of theta.
        n: (B,) int64 estimates pushed since the descent's (re)start (NaN ones included).
        n_rejected: (B,) int64 estimates that got weight 0 since the (re)start.
        rows_packed: (B, L, 5) float64 one row per step since :meth:`~EfferenceFitFilter.init_state`
            (L grows by one each step): :data:`ROW_FIELDS` = (z_dr m, v_dr m/s, t s, D_hat 1/s,
            sigma_c); NaN where the descent had no row.
    """

    zdr: Tensor
    vdr: Tensor
    t_s: Tensor
    theta: Tensor
    info: Tensor
    n: Tensor
    n_rejected: Tensor
    rows_packed: Tensor


def fit_prior(p: EfferenceFitParams) -> EfferenceFitState:
    """Every descent at the planned start: no offset, the prior's information, no history."""
    B, dev, f64 = p.z0_m.shape[0], p.z0_m.device, torch.float64
    zeros_i = torch.zeros(B, dtype=torch.int64, device=dev)
    prior = torch.stack([1.0 / p.sz0 ** 2, torch.zeros_like(p.sz0), 1.0 / p.sv0 ** 2], 1)
    return EfferenceFitState(p.z0_m.clone(), p.v0_mps.clone(), torch.zeros(B, dtype=f64, device=dev),
                             torch.zeros(B, 2, dtype=f64, device=dev), prior, zeros_i, zeros_i.clone(),
                             torch.empty(B, 0, 5, dtype=f64, device=dev))


def fit_altitude(p: EfferenceFitParams, s: EfferenceFitState) -> Tensor:
    """(B,) float64 altitude estimate z_dr + dz + dv t, m (at least ``min_altitude_m``)."""
    return (s.zdr + s.theta[:, 0] + s.theta[:, 1] * s.t_s).clamp_min(p.cfg.min_altitude_m)


def fit_velocity(s: EfferenceFitState) -> Tensor:
    """(B,) float64 velocity estimate v_dr + dv, m/s."""
    return s.vdr + s.theta[:, 1]


def fit_doubt(p: EfferenceFitParams, s: EfferenceFitState) -> Tensor:
    """(B, 3) float64: the fitted offset (dz, dv) in prior standard deviations (dz / sz0, dv / sv0)
    and the share of the descent's estimates rejected so far (``FilterOut.doubt``)."""
    rejected = s.n_rejected.to(torch.float64) / s.n.clamp_min(1).to(torch.float64)
    return torch.stack([s.theta[:, 0] / p.sz0, s.theta[:, 1] / p.sv0, rejected], 1)


def fit_velocity_sigma(s: EfferenceFitState) -> Tensor:
    """(B,) float64 posterior standard deviation of the velocity, m/s: sqrt of the (dv, dv) entry of
    the inverse of the fit's information [[a, b], [b, c]] (v_dr is known exactly), a / (a c - b^2)."""
    a, b, c = s.info.unbind(1)
    return torch.sqrt(a / (a * c - b * b).clamp_min(1e-300))


def _estimates(c: EfferenceConfig, d_hat: Tensor, confidence: Optional[Tensor], dev) -> Tuple[Tensor, Tensor]:
    """(D_hat (B,) float64, NaN where not to be used; sigma_c (B,) float64, 0 unless ``meas_noise="confidence"``)."""
    d = d_hat.to(device=dev, dtype=torch.float64)
    d = torch.where(torch.isfinite(d), d, float("nan"))
    if confidence is None:
        return d, torch.zeros_like(d)
    sig = confidence_rel_sigma(confidence.to(device=dev, dtype=torch.float64))
    low = confidence.to(device=dev, dtype=torch.float64) < c.min_confidence
    d = torch.where(torch.isfinite(sig) & ~low, d, float("nan"))  # confidence 0 (or too low): no estimate
    sig = torch.where(torch.isfinite(sig), sig, 0.0) if c.meas_noise == "confidence" else torch.zeros_like(sig)
    return d, sig


#: width of the gate's surrogate gradient, std. devs. of |u| (:func:`gate_surrogate`)
GATE_SURROGATE_WIDTH = 0.5


def gate_surrogate(u2: Tensor, gate_sigma: Tensor) -> Tensor:
    """Zero in value, with the gradient of a smooth gate (straight-through): s - s.detach() with
    s = sigmoid((gate_sigma - |u|) / GATE_SURROGATE_WIDTH), |u| = sqrt(u2) (any shape, float64).

    The hard gate (an estimate's weight is 0 beyond ``gate_sigma`` std. devs.) has a zero gradient
    almost everywhere. Added to the hard gate's 0/1 factor, this term leaves every weight as it is,
    bit for bit, but gives ``gate_sigma`` the gradient of a sigmoid gate: an estimate within about
    one ``GATE_SURROGATE_WIDTH`` of the gate pulls it out (or in) as its weight would change."""
    soft = torch.sigmoid((gate_sigma - u2.clamp_min(1e-12).sqrt()) / GATE_SURROGATE_WIDTH)  # sqrt' finite
    return soft - soft.detach()


def _terms_torch(c: EfferenceConfig, cols, fade: Optional[Tensor], dz: Tensor, dv: Tensor, pzz: Tensor, pzv: Tensor,
                 pvv: Tensor):
    """The torch path of one round's per-row terms (:func:`_gn_round`): (the five sums (wz jz, wz jv,
    wv jv, wz res, wv res), each (B,), w and R of the newest row (B,) each)."""
    zdr, vdr, t, d0, have_sig, sig0, d0_abs = cols
    z = (zdr + dz[:, None] + dv[:, None] * t).clamp_min(c.min_altitude_m)
    v = vdr + dv[:, None]
    h = v / z
    z2 = z * z
    jz = -v / z2
    jv = (z - v * t) / z2
    h_abs = h.abs()
    r = (c.meas_sigma_rel * h_abs + c.meas_sigma_abs) ** 2
    if sig0 is not None:  # the estimator's own error (meas_noise "confidence"); else it adds 0
        r = r + (sig0 * torch.maximum(d0_abs, h_abs)) ** 2
    s = r + jz * jz * pzz[:, None] + 2 * jz * jv * pzv[:, None] + jv * jv * pvv[:, None]
    res = d0 - h
    u2 = res * res / s
    usable = have_sig & torch.isfinite(u2)
    keep = usable & (u2 <= c.gate_sigma ** 2)

    def cauchy(u2_):  # an estimate's robust weight inside the gate
        return 1.0 / (1.0 + u2_ / c.cauchy_c ** 2) / r

    w = torch.where(keep, cauchy(u2), 0.0)
    if isinstance(c.gate_sigma, Tensor) and c.gate_sigma.requires_grad:  # a gate being trained
        u2s = torch.where(usable, u2, 1.0)  # rows it cannot weigh: a finite stand-in (no NaN gradient)
        w = w + torch.where(usable, cauchy(u2s), 0.0) * gate_surrogate(u2s, c.gate_sigma)
    w_info = w if fade is None else w * fade
    wz, wv = w_info * jz, w_info * jv
    sums = ((wz * jz).sum(1), (wz * jv).sum(1), (wv * jv).sum(1), (wz * res).sum(1), (wv * res).sum(1))
    return sums, w[:, -1], r[:, -1]


def _gn_round(p: EfferenceFitParams, cols, fade: Optional[Tensor], theta: Tensor, info: Tensor, mask: Tensor,
              kern=None):
    """One robust Gauss-Newton round on theta over the history columns ``cols`` (:func:`fit_rounds`;
    each (B, N), a descent's rows along the last dim; ``fade`` None = 1): (theta (B, 2), info (B, 3),
    w and R of the newest row (B,) each); descents not in ``mask`` keep theta, info. Each descent's
    sums run over its own contiguous rows, so they do not depend on the other descents (a compacted
    batch gives the same bits). ``kern``: the compiled per-row terms (:mod:`dvsland.control.native_fit`,
    the same bits), or None (torch)."""
    c = p.cfg
    iz, iv = 1.0 / p.sz0 ** 2, 1.0 / p.sv0 ** 2
    dz, dv = theta[:, 0], theta[:, 1]
    # current posterior covariance of theta: inverse of [[a, b], [b, c]]
    det = (info[:, 0] * info[:, 2] - info[:, 1] ** 2).clamp_min(1e-300)
    pzz, pzv, pvv = info[:, 2] / det, -info[:, 1] / det, info[:, 0] / det
    if kern is None:
        (szz, szv, svv, sz, sv), w, r = _terms_torch(c, cols, fade, dz, dv, pzz, pzv, pvv)
    else:  # cols: the raw rows (5, B, N), contiguous
        prod, w, r = kern.terms(cols, c.meas_noise == "confidence", fade, theta.contiguous(),
                                torch.stack([pzz, pzv, pvv], 1), c.min_altitude_m, c.meas_sigma_rel,
                                c.meas_sigma_abs, c.gate_sigma ** 2, c.cauchy_c ** 2)
        szz, szv, svv, sz, sv = prod.sum(2).unbind(0)  # each row's sum as the torch path's sum(1)
    a = szz + iz
    b = szv
    cc = svv + iv
    gz = sz - dz * iz
    gv = sv - dv * iv
    det = (a * cc - b * b).clamp_min(1e-300)
    step_z = (cc * gz - b * gv) / det
    step_v = (a * gv - b * gz) / det
    # stay inside 4 prior sigmas (a wild step cannot leave the physically possible)
    new_z = (dz + step_z).clamp(-4 * p.sz0, 4 * p.sz0)
    new_v = (dv + step_v).clamp(-4 * p.sv0, 4 * p.sv0)
    m = mask.unsqueeze(1)
    return (torch.where(m, torch.stack([new_z, new_v], 1), theta), torch.where(m, torch.stack([a, b, cc], 1), info),
            w, r)


def _native_kernel(p: EfferenceFitParams, rows: Tensor, theta: Tensor, info: Tensor):
    """The compiled terms for this fit (CPU, nothing carrying a gradient, the settings plain numbers), or None."""
    c = p.cfg
    plain = all(isinstance(v, (int, float)) for v in (c.gate_sigma, c.cauchy_c, c.meas_sigma_rel,
                                                        c.meas_sigma_abs, c.min_altitude_m))
    grads = torch.is_grad_enabled() and any(x.requires_grad for x in (rows, theta, info, p.sz0, p.sv0))
    return native_fit.kernel_for(rows) if plain and not grads else None


def _columns(c: EfferenceConfig, rows: Tensor):
    """The rounds' columns (zdr, vdr, t, D_hat, weighable, sigma_c or None, |D_hat| or None), each (B, N),
    of history ``rows`` (5, B, N): a row without an estimate gets z_dr 1e3, v_dr 0, t 0 and D_hat 0 (and
    weighs 0)."""
    zdr, vdr, t, d, sig_c = rows.unbind(0)
    have = torch.isfinite(d)
    d0 = torch.where(have, d, 0.0)
    zdr, vdr, t = torch.where(have, zdr, 1e3), torch.where(have, vdr, 0.0), torch.where(have, t, 0.0)
    fin_sig = torch.isfinite(sig_c)
    sig0 = torch.where(fin_sig, sig_c, 0.0) if c.meas_noise == "confidence" else None
    return zdr, vdr, t, d0, have & fin_sig, sig0, d0.abs() if sig0 is not None else None


def _fade(c: EfferenceConfig, t: Tensor, t_now: Tensor) -> Tensor:
    """(B, N) float64 weight factor exp(-age / forget_s) of rows at times ``t`` (B, N) s (0 where a row
    has no estimate), ``t_now`` (B,) s."""
    return torch.exp(-(t_now.unsqueeze(1) - t).clamp_min(0.0) / c.forget_s)


def fit_rounds(p: EfferenceFitParams, rows: Tensor, t_now: Tensor, theta: Tensor, info: Tensor, mask: Tensor):
    """``cfg.iterations`` robust Gauss-Newton rounds on theta for the descents of ``mask``.

    Args:
        rows: (5, B, N) float64 the history rows to fit (:data:`ROW_FIELDS`), oldest first along N.
        t_now: (B,) float64 flight time now, s (the age of a row for ``forget_s``).
        theta, info: (B, 2), (B, 3) float64 the fit so far.

    Returns:
        (theta (B, 2), info (B, 3), the robust weights in [0, 1] of the newest row (B,) float64).

    What does not change between rounds is computed once here; a term that is exactly 0 or a factor
    exactly 1 is left out (the confidence's noise under ``meas_noise="fixed"``, the fade without
    ``forget_s``), so the rounds' values are those of the full expression, bit for bit.
    """
    c = p.cfg
    kern = _native_kernel(p, rows, theta, info)
    fade = None
    if kern is None:
        cols = _columns(c, rows)
        if c.forget_s > 0:
            fade = _fade(c, cols[2], t_now)
    else:  # the kernel prepares the raw rows itself, in each round's one pass
        cols = rows.contiguous()
        if c.forget_s > 0:
            fade = _fade(c, torch.where(torch.isfinite(rows[3]), rows[2], 0.0), t_now)
    w = r = None
    for _ in range(c.iterations):  # a fixed number of rounds: no data-dependent branch
        theta, info, w, r = _gn_round(p, cols, fade, theta, info, mask, kern)
    return theta, info, w * r


#: on a CPU, fit only the descents in flight (reading the mask there is no device sync); off, or on
#: other devices, every descent is fitted and the finished ones keep their fit: the same bits
#: (:func:`_gn_round`'s sums are per descent). Tests turn it off to count the GPU path's syncs.
CPU_COMPACT = True


def _fit_active(p: EfferenceFitParams, rows: Tensor, t_now: Tensor, theta: Tensor, info: Tensor, mask: Tensor):
    """:func:`fit_rounds` of the descents of ``mask`` (B,) bool; on a CPU (:data:`CPU_COMPACT`) only
    theirs are computed, so a finished descent costs nothing (same outputs)."""
    B = mask.shape[0]
    if not (CPU_COMPACT and mask.device.type == "cpu"):
        return fit_rounds(p, rows, t_now, theta, info, mask)
    idx = mask.nonzero().squeeze(1)
    k = int(idx.numel())
    if k == B:
        return fit_rounds(p, rows, t_now, theta, info, mask)
    if k == 0:  # nothing in flight: every fit kept, no newest weight
        return theta, info, torch.zeros(B, dtype=rows.dtype, device=rows.device)
    sub = p._replace(z0_m=p.z0_m[idx], v0_mps=p.v0_mps[idx], sz0=p.sz0[idx], sv0=p.sv0[idx])
    th, inf, w = fit_rounds(sub, rows[:, idx], t_now[idx], theta[idx], info[idx], mask[idx])
    return (theta.index_copy(0, idx, th), info.index_copy(0, idx, inf),
            torch.zeros(B, dtype=w.dtype, device=w.device).index_copy(0, idx, w))


def efference_fit_step(p: EfferenceFitParams, state: EfferenceFitState, d_hat: Tensor,
                       active: Optional[Tensor] = None, accel_mps2: Optional[Tensor] = None,
                       confidence: Optional[Tensor] = None) -> Tuple[EfferenceFitState, FilterOut]:
    """Pure step of ``efference_fit``: dead-reckon with the acceleration applied since the last step
    (skipped when ``accel_mps2`` is None: the first step; for the descents where it is NaN: their first
    step after a restart), append this step's row, re-fit.

    Returns:
        (next state, FilterOut(v_hat / z_hat (B,) float64, 1 where this step's estimate got weight
        > 0.5 (B,) int64, z_hat (B,) float64 m, the doubt (B, 3), the posterior velocity standard
        deviation (B,) float64 m/s)).
    """
    c, dt, dev = p.cfg, p.dt_s, p.z0_m.device
    m = torch.ones(p.z0_m.shape[0], dtype=torch.bool, device=dev) if active is None else active.to(dev)
    zdr, vdr, t_s = state.zdr, state.vdr, state.t_s
    if accel_mps2 is not None:
        a = accel_mps2.to(device=dev, dtype=torch.float64)
        go = m & torch.isfinite(a)
        zdr = torch.where(go, zdr + vdr * dt + 0.5 * a * dt * dt, zdr)
        vdr = torch.where(go, vdr + a * dt, vdr)
        t_s = torch.where(go, t_s + dt, t_s)
    d, sig = _estimates(c, d_hat, confidence, dev)
    row = torch.where(m.unsqueeze(1), torch.stack([zdr, vdr, t_s, d, sig], 1), float("nan"))  # (B, 5)
    # the history in the fit's layout (5, B, L + 1), kept batch first as a (B, L + 1, 5) view of it
    hist = torch.cat([state.rows_packed.permute(2, 0, 1), row.t().unsqueeze(2)], 2)
    L = hist.shape[2]
    lo = 0
    if c.forget_s > 0:  # rows older than cut_forget forget_s weigh < exp(-cut_forget): left out
        lo = max(0, L - int(math.ceil(p.cut_forget * c.forget_s / dt)))
    theta, info, w_now = _fit_active(p, hist[:, :, lo:], t_s, state.theta, state.info, m)
    fresh = m & torch.isfinite(d)
    new = EfferenceFitState(zdr, vdr, t_s, theta, info, state.n + m.to(torch.int64),
                            state.n_rejected + (fresh & (w_now == 0)).to(torch.int64), hist.permute(1, 2, 0))
    z_hat = fit_altitude(p, new)
    return new, FilterOut(fit_velocity(new) / z_hat, (fresh & (w_now > 0.5)).to(torch.int64), z_hat,
                          fit_doubt(p, new), fit_velocity_sigma(new))


def fit_reset_where(p: EfferenceFitParams, state: EfferenceFitState, mask: Tensor) -> EfferenceFitState:
    """``state`` with the descents of ``mask`` (B,) bool back at the planned start, their history
    rows blanked (NaN); the other descents bit-identical, but for the leading history rows that are
    blank for every descent: they are dropped (one host sync, not on the step path), so restarts
    one at a time (an environment's autoreset) keep the history as long as the oldest descent in
    flight, not the whole session. (The fit's sums then run over fewer blank rows: the other
    descents' next outputs may move in the last bits.)"""
    fresh = fit_prior(p)
    m1 = mask.unsqueeze(1)
    rows = torch.where(mask.view(-1, 1, 1), float("nan"), state.rows_packed)
    written = torch.isfinite(rows[:, :, 0]).any(0).nonzero()  # z_dr is finite in every row a descent wrote
    first = int(written[0, 0]) if written.numel() else rows.shape[1]
    return EfferenceFitState(torch.where(mask, fresh.zdr, state.zdr), torch.where(mask, fresh.vdr, state.vdr),
                             torch.where(mask, fresh.t_s, state.t_s), torch.where(m1, fresh.theta, state.theta),
                             torch.where(m1, fresh.info, state.info), torch.where(mask, fresh.n, state.n),
                             torch.where(mask, fresh.n_rejected, state.n_rejected), rows[:, first:])


class EfferenceFitFilter(PlannedStartFilter):
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

    Params :class:`EfferenceFitParams`, state :class:`EfferenceFitState` (its fields read as
    attributes: ``theta``, ``n``, ``n_rejected``, ...).
    """

    provides_altitude = True
    #: its :class:`FilterOut` carries ``doubt`` (the ``efference_doubt`` policy observation reads it)
    provides_doubt = True
    provides_velocity_sigma = True

    def __init__(self, z0_m: Tensor, v0_mps: Tensor, dt_s: float, prior_rel_sigma: float = 0.1,
                 prior_rel_sigma_v: Optional[float] = None, meas_sigma_rel: float = 0.05,
                 meas_sigma_abs: float = 0.001, meas_noise: str = "fixed", gate_sigma: float = 5.0,
                 cauchy_c: float = 2.0, iterations: int = 3, min_altitude_m: float = 1.0,
                 prior_scale: float = 1.0, forget_s: float = 0.0, min_confidence: float = 0.0):
        z0, v0 = check_filter_plan(z0_m, v0_mps)
        psv = prior_rel_sigma if prior_rel_sigma_v is None else prior_rel_sigma_v
        check_positive({"dt_s": (dt_s, 0, False), "prior_rel_sigma": (prior_rel_sigma, 0, False),
                        "prior_rel_sigma_v": (psv, 0, False), "meas_sigma_rel": (meas_sigma_rel, 0, True),
                        "meas_sigma_abs": (meas_sigma_abs, 0, False), "gate_sigma": (gate_sigma, 0, False),
                        "cauchy_c": (cauchy_c, 0, False), "iterations": (iterations, 1, True),
                        "min_altitude_m": (min_altitude_m, 0, False), "prior_scale": (prior_scale, 0, False),
                        "forget_s": (forget_s, 0, True)}, min_confidence)
        if meas_noise not in ("fixed", "confidence"):
            raise ValueError(f"meas_noise must be 'fixed' or 'confidence', got {meas_noise!r}")
        cfg = EfferenceConfig(prior_scale=float(prior_scale), prior_rel_sigma=float(prior_rel_sigma),
                              prior_rel_sigma_v=float(psv), meas_sigma_rel=float(meas_sigma_rel),
                              meas_sigma_abs=float(meas_sigma_abs), meas_noise=meas_noise,
                              gate_sigma=float(gate_sigma), cauchy_c=float(cauchy_c), iterations=int(iterations),
                              min_altitude_m=float(min_altitude_m), forget_s=float(forget_s),
                              min_confidence=float(min_confidence))
        z0, v0 = z0 * prior_scale, v0 * prior_scale
        self.params = EfferenceFitParams(z0, v0, float(prior_rel_sigma) * z0.abs(),
                                         float(psv) * v0.abs().clamp_min(1e-3), float(dt_s), cfg)
        self._template = self.init_state()
        self.state = self.init_state()

    @classmethod
    def from_params(cls, p, **options) -> "EfferenceFitFilter":
        """From the loop's :class:`~dvsland.control.DescentParams` and the ``controller.efference`` options."""
        options = {k: v for k, v in options.items() if k not in _NOT_MINE}
        return cls(p.z0_m, p.v0_mps, p.dt_s, **options)

    # ------------------------------------------------------------------ the contract
    def init_state(self) -> EfferenceFitState:
        return fit_prior(self.params)

    def step_state(self, state: EfferenceFitState, d_hat: Tensor, active: Optional[Tensor] = None,
                   accel_mps2: Optional[Tensor] = None, thrust_accel_mps2: Optional[Tensor] = None,
                   confidence: Optional[Tensor] = None) -> Tuple[EfferenceFitState, FilterOut]:
        """Pure step (:func:`efference_fit_step`); ``thrust_accel_mps2`` is not used (no process
        noise: the dynamics are exact)."""
        self._check_inputs(state, d_hat, confidence)
        return efference_fit_step(self.params, state, d_hat, active, accel_mps2, confidence)

    def reset_where(self, state: EfferenceFitState, mask: Tensor) -> EfferenceFitState:
        """:func:`fit_reset_where` (the history is packed: written by hand)."""
        return fit_reset_where(self.params, state, self._mask(mask, state))

    # ------------------------------------------------------------------ the object API
    @property
    def altitude_m(self) -> Tensor:
        """(B,) float64 altitude estimate, m."""
        return fit_altitude(self.params, self.state)

    @property
    def velocity_mps(self) -> Tensor:
        """(B,) float64 velocity estimate, m/s."""
        return fit_velocity(self.state)

    @property
    def divergence(self) -> Tensor:
        """(B,) float64 filtered divergence v_hat / z_hat, 1/s."""
        return self.velocity_mps / self.altitude_m
