"""``dpr``: the paper's estimator (Sikorski et al. 2021, section 4; docs/estimators.md).

Per step:

1. The interval's events become a count image (ON + OFF summed: shadows and lit rims both mark a
   feature, and the clustering only needs where events are). The windowed count image over
   T = memory_ms is the sum of the last ``K = round(memory_ms / dt)`` steps' images, kept as a
   running sum: the state holds the window's events as pixel indices in arrival order
   (``ring_packed``) with each descent's count per step (``ring_counts``), and each step adds the
   new step's events and subtracts the ones K steps old, a prefix of the ring (two
   ``scatter_add_`` calls, no dense image per step).
2. Mean-shift (flat kernel R = ``radius_px``) seeded with last step's centroids, iterated to
   convergence on the windowed image, batched over (B, N_max).
3. A centroid is dropped when fewer than ``n_min`` events lie within R of it, when it is closer
   than ``r_min_px`` to the sensor edge (pixel centres at 0 .. W-1), or when it has merged with a
   better-ranked centroid (closer than ``merge_px``, not in paper).
4. Eq. 8 over all pairs tracked at both steps gives D (NaN when no pair). For the first
   ``K`` steps after a reset the ring is still filling and the window's mean event time moves
   by dt / 2 per step, so Eq. 8 uses dt / 2 there (not in paper).
5. Elements left with fewer than ``c_min`` centroids re-initialise with Density Peaks Ranking
   (blur, max-pool local maxima, top ``n_max`` by density) on the windowed image, followed by
   mean-shift to convergence on the same image (so the next step compares like with like). DPR
   runs only for those elements.

The stage contract (:mod:`dvsland.pytree`): params are :class:`~dvsland.config.schema.DPRConfig`
(``DPREstimator.params``) with the sensor constants :class:`DPRConsts`; the state is
:class:`DPRState`; the step is the pure :func:`dpr_step`.
"""

from __future__ import annotations

import math
from typing import Dict, NamedTuple, Optional, Tuple

import torch

from dvsland.checks import check_fields
from dvsland.config.schema import DPRConfig
from dvsland.pytree import check_state_like, packed_append, tree_where

from .base import DivergenceEstimator, EstimateOut, Truth, confidence_from_rel_std
from .abstain import EVIDENCE_KEY
from .density_peaks import density_peaks
from .divergence import baseline_divergence, eq8_with_spread
from .meanshift import meanshift_flat
from .registry import register_estimator


class DPRState(NamedTuple):
    """State of the ``dpr`` estimator for B descents (N = n_max, K = the ring's steps,
    kb = baseline_steps + 1, q = the window's zero border, Hp = H + 2q, Wp = W + 2q).

    Attributes:
        ring_packed: (E,) int64, the E events of every descent's window as flat indices
            (b Hp + y + q) Wp + x + q into ``window``, in the order they came in (the events of
            the oldest step first). Variable length (all descents packed together).
        ring_counts: (B, K) int64 events of each descent in each step of the window, oldest step
            first (the oldest column's events are the ring's prefix that leaves next).
        window: (B, Hp, Wp) float32 windowed count image (events per pixel over the last K steps,
            ON + OFF) with a zero border of q px (mean-shift patches never leave it).
        centroids: (B, N, 2) float32 tracked centroids (x, y), px; NaN where not tracked.
        valid: (B, N) bool, which centroids are tracked.
        counts: (B, N) float32 events within R of each centroid (0 where not tracked).
        reinit: (B,) bool, DPR re-initialised the descent at the last step.
        n_pairs: (B,) int64 pairs of the last estimate.
        age: (B,) int64 steps since the descent's (re)start.
        last_t_us: (B,) int64 time of the last step, µs (-1 = none yet).
        hist: (B, kb, N, 2) float32 the centroids after each of the last kb steps, oldest first
            (NaN where not tracked).
        hist_t: (B, kb) float64 the window mean event time of those steps, s.
        slot_age: (B, N) int64 consecutive steps each centroid slot has been tracked.
    """

    ring_packed: torch.Tensor
    ring_counts: torch.Tensor
    window: torch.Tensor
    centroids: torch.Tensor
    valid: torch.Tensor
    counts: torch.Tensor
    reinit: torch.Tensor
    n_pairs: torch.Tensor
    age: torch.Tensor
    last_t_us: torch.Tensor
    hist: torch.Tensor
    hist_t: torch.Tensor
    slot_age: torch.Tensor


class DPRConsts(NamedTuple):
    """Constants of a ``dpr`` estimator besides its :class:`DPRConfig` (made once, never written).

    Attributes:
        batch_size: B. sensor_size: (W, H) px. dt_s: nominal step, s (the first step's dt).
        n_ring: K, steps in the memory window. pad: q, the window's zero border, px.
        lo_xy, hi_xy: (2,) float32 edge bounds of the r_min rule, px. upper: (N, N) bool strict
            upper triangle (merge rule). n_min, merge, nan, zero: float32 scalars. two_one: (2,)
            float32 (2, 1), Eq. 8's factor while the ring fills. unit: (2,) float32 (+1, -1).
    """

    batch_size: int
    sensor_size: Tuple[int, int]
    dt_s: float
    n_ring: int
    pad: int
    lo_xy: torch.Tensor
    hi_xy: torch.Tensor
    upper: torch.Tensor
    n_min: torch.Tensor
    merge: torch.Tensor
    nan: torch.Tensor
    zero: torch.Tensor
    two_one: torch.Tensor
    unit: torch.Tensor


def dpr_consts(p: DPRConfig, batch_size: int, sensor_size: Tuple[int, int], dt_s: float, device) -> DPRConsts:
    """The :class:`DPRConsts` of ``p`` for B descents on a (W, H) sensor at a ``dt_s`` step."""
    W, H = sensor_size
    dev = torch.device(device)
    f32 = dict(dtype=torch.float32, device=dev)
    r = float(p.r_min_px)
    return DPRConsts(int(batch_size), (int(W), int(H)), float(dt_s),
                     max(1, int(round(float(p.memory_ms) / (1000.0 * float(dt_s))))),
                     int(math.ceil(float(p.radius_px))) + 1,
                     torch.tensor([r, r], **f32), torch.tensor([W - 1 - r, H - 1 - r], **f32),
                     torch.ones(p.n_max, p.n_max, dtype=torch.bool, device=dev).triu(1),
                     torch.tensor(float(p.n_min), **f32), torch.tensor(float(p.merge_px), **f32),
                     torch.full((), float("nan"), **f32), torch.zeros((), **f32),
                     torch.tensor([2.0, 1.0], **f32), torch.tensor([1.0, -1.0], **f32))


def dpr_init_state(p: DPRConfig, c: DPRConsts) -> DPRState:
    """The :class:`DPRState` of B descents that have seen nothing."""
    B, N, kb = c.batch_size, int(p.n_max), int(p.baseline_steps) + 1
    W, H = c.sensor_size
    q, dev = c.pad, c.lo_xy.device
    i64 = dict(dtype=torch.int64, device=dev)
    return DPRState(ring_packed=torch.zeros(0, **i64), ring_counts=torch.zeros(B, c.n_ring, **i64),
                    window=torch.zeros(B, H + 2 * q, W + 2 * q, dtype=torch.float32, device=dev),
                    centroids=torch.full((B, N, 2), float("nan"), dtype=torch.float32, device=dev),
                    valid=torch.zeros(B, N, dtype=torch.bool, device=dev),
                    counts=torch.zeros(B, N, dtype=torch.float32, device=dev),
                    reinit=torch.zeros(B, dtype=torch.bool, device=dev), n_pairs=torch.zeros(B, **i64),
                    age=torch.zeros(B, **i64), last_t_us=torch.full((B,), -1, **i64),
                    hist=torch.full((B, kb, N, 2), float("nan"), dtype=torch.float32, device=dev),
                    hist_t=torch.zeros(B, kb, dtype=torch.float64, device=dev), slot_age=torch.zeros(B, N, **i64))


def dpr_reset_where(p: DPRConfig, c: DPRConsts, state: DPRState, mask: torch.Tensor) -> DPRState:
    """``state`` with the descents where ``mask`` (B,) bool is True restarted (their events leave
    the ring); the others bit-identical. The clock ``last_t_us`` is kept: it is the caller's."""
    plane = state.window.shape[1] * state.window.shape[2]
    ring = state.ring_packed
    ring = ring[~mask[ring // plane]]
    fresh = dpr_init_state(p, c)._replace(ring_packed=ring, last_t_us=state.last_t_us)
    return tree_where(mask, fresh, state._replace(ring_packed=ring))


def _window_step(c: DPRConsts, state: DPRState, events,
                 donate: bool = False) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(ring_packed, ring_counts, window) after the step's events came in and the ones K steps
    old (the ring's prefix) left (``donate``: in the state's window, else in a copy). One host read:
    the prefix's length.

    ``events`` must lie on the sensor and in the batch (the estimator's input gate checks that)."""
    W, H = c.sensor_size
    q, dev = c.pad, state.window.device
    Hp, Wp = H + 2 * q, W + 2 * q
    ring, rc = state.ring_packed, state.ring_counts
    n_old = int(rc[:, 0].sum()) if ring.numel() else 0
    old, kept = ring[:n_old], ring[n_old:]
    window = state.window if donate else state.window.clone()
    flat = window.view(-1)
    # scatter_add_ (about 2x faster than index_add_ on CPU for these scattered indices); counts
    # are integers, which float32 adds exactly in any order
    if old.numel():
        flat.scatter_add_(0, old, c.unit[1].expand(old.numel()))
    if events is None or events.b.numel() == 0:
        return kept, torch.cat([rc[:, 1:], torch.zeros_like(rc[:, :1])], 1), window
    b = events.b.to(dev)
    # lin = (b * Hp + y + q) * Wp + x + q, in three integer ops
    new = torch.add(events.x.to(dev), events.y.to(dev), alpha=Wp).add_(b, alpha=Hp * Wp).add_(q * Wp + q)
    flat.scatter_add_(0, new, c.unit[0].expand(new.numel()))
    n_new = torch.bincount(b, minlength=c.batch_size).unsqueeze(1)
    return packed_append(kept, new), torch.cat([rc[:, 1:], n_new], 1), window


def capped_window(window: torch.Tensor, factor: float) -> torch.Tensor:
    """``window`` (B, Hp, Wp) float32 with every pixel capped at ``factor`` times its element's
    mean count per active pixel (a new tensor; the ``hot_pixel_factor`` rule)."""
    n_act = (window > 0).sum((1, 2)).clamp_min(1).to(window.dtype)
    cap = factor * window.sum((1, 2)) / n_act
    return torch.minimum(window, cap.view(-1, 1, 1))


def dpr_keep(p: DPRConfig, c: DPRConsts, cen: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """The n_min, r_min and merge rules on mean-shift's output ``cen`` (B', N, 2) and ``counts``
    (B', N): the kept mask (B', N) bool. (counts >= n_min >= 1 implies a valid seed that was not
    lost: mean-shift gives 0 counts otherwise, and NaN centroids fail the edge rule.)"""
    inside = ((cen >= c.lo_xy) & (cen <= c.hi_xy)).all(-1)  # NaN compares False
    keep = (counts >= c.n_min) & inside
    if p.merge_px > 0 and keep.shape[1] > 1:
        # pairs with a dropped centroid get a NaN distance (never close)
        cc = torch.where(keep.unsqueeze(-1), cen, c.nan)
        dist = torch.linalg.vector_norm(cc.unsqueeze(2) - cc.unsqueeze(1), dim=-1)  # (B', N, N)
        close = (dist < c.merge) & c.upper
        keep = keep & ~close.any(1)  # j merged into a better-ranked i < j
    return keep


def dpr_initialise(p: DPRConfig, c: DPRConsts, padded: torch.Tensor):
    """DPR + mean-shift to convergence on windowed images given with their zero border
    (B', Hp, Wp) float32: (centroids (B', N, 2) float32 px, counts (B', N) float32, keep (B', N)
    bool), kept centroids first in rank order."""
    q = c.pad
    W, H = c.sensor_size
    peaks, _, ok = density_peaks(padded[:, q:q + H, q:q + W], p.n_max, p.blur_sigma_px, p.nms_px)
    cen, counts, _ = meanshift_flat(padded, peaks, ok, p.radius_px, p.meanshift_iters, p.meanshift_tol_px,
                                    image_pad_px=q)
    keep = dpr_keep(p, c, cen, counts)
    order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)
    cen = torch.gather(cen, 1, order.unsqueeze(-1).expand(-1, -1, 2))
    return cen, torch.gather(counts, 1, order), torch.gather(keep, 1, order)


def _divergence(p: DPRConfig, c: DPRConsts, state: DPRState, cen, keep, dt, t_mean, age):
    """Eq. 8 (or the multi-step baseline) between ``state``'s centroids and the tracked ``cen``:
    (d (B,) float32 1/s, n_pairs (B,) int64, rel_std (B,) float64, slot ages (B, N) int64)."""
    kb = p.baseline_steps + 1
    age_now = torch.where(keep, state.slot_age + 1, torch.zeros_like(state.slot_age)).clamp(max=p.baseline_steps)
    if p.baseline_steps == 1:
        # the paper's Eq. 8; rel from the same pairs over one step (hist's last entry is state.centroids,
        # the window mean time then hist_t's last), for the confidence. While the ring fills after a
        # reset the window's mean event time advances by dt / 2 per step instead of dt: Eq. 8 then uses
        # dt / 2 (not in paper; removes a x2 bias at start)
        d, n_pairs, rel = eq8_with_spread(state.centroids, cen, keep, dt, t_mean - state.hist_t[:, -1],
                                          weighting=p.pair_weighting)
        return d * torch.where(age <= c.n_ring, c.two_one[0], c.two_one[1]), n_pairs, rel, age_now
    lag = torch.minimum(age_now.unsqueeze(2), age_now.unsqueeze(1))  # (B, N, N)
    ring = (kb - lag) % kb  # hist index of the step `lag` steps ago (lag 0: unused, the oldest)
    hp = state.hist.permute(0, 2, 1, 3)  # (B, N, kb, 2)
    past_i = hp.gather(2, ring.unsqueeze(-1).expand(-1, -1, -1, 2))
    past_j = hp.gather(2, ring.transpose(1, 2).unsqueeze(-1).expand(-1, -1, -1, 2)).transpose(1, 2)
    elapsed = t_mean.view(-1, 1, 1) - state.hist_t.gather(1, ring.flatten(1)).view_as(ring)
    return (*baseline_divergence(cen, torch.stack([past_i, past_j], 3), lag, elapsed), age_now)


def _reinitialise(p: DPRConfig, c: DPRConsts, image, centroids, valid, counts, ring_counts):
    """Re-initialise (DPR) the descents left with fewer than c_min centroids, only those; writes
    into ``centroids``, ``valid``, ``counts`` (this step's new tensors). ``ring_counts`` (B, K): the
    window's events per stored step. Returns need (B,) bool."""
    need = valid.sum(1) < p.c_min
    # an element with an empty window (e.g. a finished descent) has no density peak, so DPR would
    # give it no centroid; its state already says so (a kept centroid needs n_min >= 1 events within
    # R): it is skipped. Its window holds no event exactly when its image is all zeros.
    run = need & (ring_counts.sum(1) > 0)
    if bool(run.any()):
        idx = run.nonzero().squeeze(1)
        ci, ni, ki = dpr_initialise(p, c, image.index_select(0, idx))
        centroids[idx] = torch.where(ki.unsqueeze(-1), ci, c.nan)
        valid[idx] = ki
        counts[idx] = torch.where(ki, ni, c.zero)
    return need


def dpr_step(p: DPRConfig, c: DPRConsts, state: DPRState, events, t_us: int,
             donate: bool = False) -> Tuple[DPRState, EstimateOut]:
    """Pure step of ``dpr`` (module doc): (next state, :class:`EstimateOut`); ``state`` unchanged
    unless ``donate`` (its count window is then moved in place: ``state`` must not be used again).

    Args:
        p, c: the params and constants. state: :class:`DPRState` of B descents.
        events: :class:`dvsland.events.Events` of the interval (b in [0, B), x, y on the sensor),
            or None / empty.
        t_us: end of the interval, int µs; dt = the time since the last step (``dt_s`` at first).
    """
    t_us = int(t_us)
    last = state.last_t_us
    dt = torch.where((last >= 0) & (last < t_us), (t_us - last).to(torch.float64) * 1e-6,
                     torch.full(last.shape, c.dt_s, dtype=torch.float64, device=last.device))  # (B,) s
    ring, ring_counts, window = _window_step(c, state, events, donate)
    image = capped_window(window, p.hot_pixel_factor) if p.hot_pixel_factor > 0 else window
    cen, counts, _ = meanshift_flat(image, state.centroids, state.valid, p.radius_px, p.meanshift_iters,
                                    p.meanshift_tol_px, image_pad_px=c.pad)
    keep = dpr_keep(p, c, cen, counts)
    age = state.age + 1
    # window mean event time (the ring holds min(age, K) steps), s
    t_mean = t_us * 1e-6 - age.clamp(max=c.n_ring).to(torch.float64) * (0.5 * dt)
    d, n_pairs, rel, slot_age = _divergence(p, c, state, cen, keep, dt, t_mean, age)
    centroids = torch.where(keep.unsqueeze(-1), cen, c.nan)
    counts = torch.where(keep, counts, c.zero)
    valid = keep.clone()
    need = _reinitialise(p, c, image, centroids, valid, counts, ring_counts)
    new = DPRState(ring, ring_counts, window, centroids, valid, counts, need, n_pairs, age,
                   torch.full_like(last, t_us), torch.cat([state.hist[:, 1:], centroids.unsqueeze(1)], 1),
                   torch.cat([state.hist_t[:, 1:], t_mean.unsqueeze(1)], 1),
                   torch.where(need.unsqueeze(1), torch.zeros_like(slot_age), slot_age))
    conf = confidence_from_rel_std(rel, d)
    return new, EstimateOut(d, conf, dpr_diagnostics(new, conf))


def dpr_diagnostics(state: DPRState, confidence: torch.Tensor) -> Dict[str, torch.Tensor]:
    """centroids (B, N_max, 2) float32 (x, y) px, NaN = unused; n_tracked (B,) int64; reinit (B,)
    bool (DPR ran this step); counts (B, N_max) events within R; n_pairs (B,) pairs used by Eq. 8;
    window_events (B,) float32 events in the memory window; confidence (B,) float32."""
    return {"centroids": state.centroids, "n_tracked": state.valid.sum(1), "reinit": state.reinit,
            "counts": state.counts, "n_pairs": state.n_pairs,
            "window_events": state.ring_counts.sum(1).to(torch.float32), "confidence": confidence}


@register_estimator("dpr")
class DPREstimator(DivergenceEstimator):
    """Density Peaks Ranking + mean-shift tracking + Eq. 8 (the paper's pipeline), batched.

    Args:
        batch_size, sensor_size (W, H), device, dt_s: see :class:`DivergenceEstimator`.
        n_max: N_max, centroids kept by DPR.
        n_min: events within R needed to keep a centroid.
        radius_px: R, flat mean-shift kernel radius, px.
        c_min: below this many tracked centroids an element re-initialises with DPR.
        r_min_px: centroids closer than this to the edge are dropped, px.
        memory_ms: temporal memory T, ms (rounded to whole steps, at least one).
        blur_sigma_px: DPR Gaussian blur sigma, px.
        meanshift_iters: maximum mean-shift iterations per step.
        meanshift_tol_px: mean-shift convergence tolerance, px.
        merge_px: two centroids closer than this merge (the lower-ranked one is dropped), px.
        nms_px: odd max-pool window of the DPR local maxima, px.
        pair_weighting: Eq. 8 average: "none" (the paper's plain mean over pairs) or "length"
            (pairs weighted by their length; not in paper).
        baseline_steps: 1 = the paper's Eq. 8 between consecutive steps. k > 1 (not in paper):
            each pair is compared with its own length up to k steps ago (as long as both
            centroids were tracked since), D_ij = -log(l / l') / elapsed, averaged with
            inverse-variance weights (l' elapsed)^2 (:func:`~.divergence.baseline_divergence`);
            ``pair_weighting`` is then ignored. The estimate refers to about k dt / 2 before now.
        hot_pixel_factor: cap every pixel of the windowed image at this many times its element's
            mean count per active pixel before tracking and DPR (hot pixels, fixed to the sensor,
            are density peaks that never move and read as D = 0; not in paper); 0 = off (the
            paper's algorithm, the default).
        principal_point_px: the focus of expansion. Eq. 8 uses only distances between
            centroids, which a zoom about any point scales alike, so ``dpr`` needs no FoE; it is
            accepted for the common interface.

    Params: ``params`` (:class:`DPRConfig`) and ``consts`` (:class:`DPRConsts`); state:
    :class:`DPRState`. ``confidence()``: 1 / (1 + (sigma_rel / 0.1)^2) from the relative standard
    error of the pairs' mean (0 with fewer than two pairs or no estimate).
    """

    accepts_donate = True  # step_state(..., donate=True): the count window moved in place

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, n_max: int = 15,
                 n_min: int = 15, radius_px: float = 4.0, c_min: int = 3, r_min_px: float = 3.0,
                 memory_ms: float = 500.0, blur_sigma_px: float = 2.0, meanshift_iters: int = 20,
                 meanshift_tol_px: float = 0.01, merge_px: float = 1.0, nms_px: int = 3,
                 pair_weighting: str = "none", baseline_steps: int = 1, hot_pixel_factor: float = 0.0,
                 principal_point_px=None):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        # the ranges of the config schema (estimator.dpr), written once there
        check_fields(DPRConfig, n_max=n_max, n_min=n_min, radius_px=radius_px, c_min=c_min, r_min_px=r_min_px,
                     memory_ms=memory_ms, blur_sigma_px=blur_sigma_px, meanshift_iters=meanshift_iters,
                     meanshift_tol_px=meanshift_tol_px, merge_px=merge_px, nms_px=nms_px,
                     pair_weighting=pair_weighting, baseline_steps=baseline_steps, hot_pixel_factor=hot_pixel_factor)
        if int(nms_px) < 1 or int(nms_px) % 2 == 0:
            raise ValueError(f"nms_px must be an odd integer >= 1, got {nms_px}")
        if pair_weighting not in ("none", "length"):
            raise ValueError(f"pair_weighting must be 'none' or 'length', got {pair_weighting!r}")
        self.params = DPRConfig(n_max=int(n_max), n_min=int(n_min), radius_px=float(radius_px), c_min=int(c_min),
                                r_min_px=float(r_min_px), memory_ms=float(memory_ms),
                                blur_sigma_px=float(blur_sigma_px), meanshift_iters=int(meanshift_iters),
                                meanshift_tol_px=float(meanshift_tol_px), merge_px=float(merge_px),
                                nms_px=int(nms_px), pair_weighting=pair_weighting,
                                baseline_steps=int(baseline_steps), hot_pixel_factor=float(hot_pixel_factor))
        self.consts = dpr_consts(self.params, self.batch_size, self.sensor_size, self.dt_s, self.device)
        #: number of per-step count images in the window (T / dt, at least 1)
        self.n_ring = self.consts.n_ring
        #: zero border of the windowed image, px
        self._pad = self.consts.pad
        self._template = dpr_init_state(self.params, self.consts)
        self.state = self.init_state()

    # ------------------------------------------------------------------ the stage contract
    def init_state(self) -> DPRState:
        """B descents that have seen nothing (:class:`DPRState`)."""
        return dpr_init_state(self.params, self.consts)

    def reset_where(self, state: DPRState, mask: torch.Tensor) -> DPRState:
        """``state`` with the descents where ``mask`` (B,) bool is True restarted."""
        return dpr_reset_where(self.params, self.consts, state, self._mask(mask))

    def step_state(self, state: DPRState, events, t_us: int, truth: Optional[Truth] = None, donate: bool = False):
        """Pure step (:func:`dpr_step`): (next :class:`DPRState`, :class:`EstimateOut`); ``donate``:
        ``state``'s window is moved in place."""
        check_state_like("dpr", state, self._template)
        return dpr_step(self.params, self.consts, state, events, t_us, donate)

    # ------------------------------------------------------------------ object API extras
    def window_image(self) -> torch.Tensor:
        """The windowed count image over the last T, (B, H, W) float32 (a copy)."""
        q = self._pad
        W, H = self.sensor_size
        return self.state.window[:, q:q + H, q:q + W].clone()

    def diagnostics(self) -> Dict[str, torch.Tensor]:
        """:func:`dpr_diagnostics` of the held state (copies), also right after a reset, and the
        last update's ``motion_evidence`` (:mod:`.abstain`)."""
        out = {k: v.clone() for k, v in dpr_diagnostics(self.state, self.confidence()).items()}
        last = getattr(self, "_last", None)
        if last is not None and EVIDENCE_KEY in last.diagnostics:
            out[EVIDENCE_KEY] = last.diagnostics[EVIDENCE_KEY].clone()
        return out

