"""``dpr``: the paper's estimator (Sikorski et al. 2021, section 4; docs/estimators.md).

Per step:

1. The interval's events become a count image (ON + OFF summed: shadows and lit rims both mark a
   feature, and the clustering only needs where events are). A ring of the last
   ``K = round(memory_ms / dt)`` steps gives the windowed count image over T = memory_ms; the ring
   holds each step's events as pixel indices and the window is a running sum (add the new step,
   subtract the oldest: two ``scatter_add_`` calls, no dense image per step).
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
"""

from __future__ import annotations

import math
from typing import Optional

import torch

from dvsland.checks import check_fields
from dvsland.config.schema import DPRConfig

from .base import DivergenceEstimator, Truth, confidence_from_rel_std
from .density_peaks import density_peaks
from .divergence import baseline_divergence, pairwise_divergence
from .meanshift import meanshift_flat
from .registry import register_estimator


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

    ``confidence()``: 1 / (1 + (sigma_rel / 0.1)^2) from the relative standard error of the
    pairs' mean (0 with fewer than two pairs or no estimate).
    """

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
        self.hot_pixel_factor = float(hot_pixel_factor)
        self.baseline_steps = int(baseline_steps)
        if int(nms_px) < 1 or int(nms_px) % 2 == 0:
            raise ValueError(f"nms_px must be an odd integer >= 1, got {nms_px}")
        self.n_max, self.n_min, self.c_min = int(n_max), int(n_min), int(c_min)
        self.radius_px, self.r_min_px = float(radius_px), float(r_min_px)
        self.memory_ms, self.blur_sigma_px = float(memory_ms), float(blur_sigma_px)
        self.meanshift_iters, self.meanshift_tol_px = int(meanshift_iters), float(meanshift_tol_px)
        self.merge_px, self.nms_px = float(merge_px), int(nms_px)
        if pair_weighting not in ("none", "length"):
            raise ValueError(f"pair_weighting must be 'none' or 'length', got {pair_weighting!r}")
        self.pair_weighting = pair_weighting
        #: number of per-step count images in the ring (T / dt, at least 1)
        self.n_ring = max(1, int(round(self.memory_ms / (1000.0 * self.dt_s))))
        B, N = self.batch_size, self.n_max
        W, H = self.sensor_size
        dev = self.device
        # ring of the last K steps' events as flat indices into the padded window (sparse: the
        # window is updated by adding the new step's events and removing the oldest step's)
        self._ring = [torch.zeros(0, dtype=torch.int64, device=dev) for _ in range(self.n_ring)]
        self._slot = 0
        # running ring sum, stored with a zero border so mean-shift patches never leave it
        self._pad = int(math.ceil(self.radius_px)) + 1
        q = self._pad
        self._window_padded = torch.zeros(B, H + 2 * q, W + 2 * q, dtype=torch.float32, device=dev)
        self._window = self._window_padded[:, q:q + H, q:q + W]  # a view
        self._centroids = torch.full((B, N, 2), float("nan"), dtype=torch.float32, device=dev)
        self._valid = torch.zeros(B, N, dtype=torch.bool, device=dev)
        self._counts = torch.zeros(B, N, dtype=torch.float32, device=dev)
        self._reinit = torch.zeros(B, dtype=torch.bool, device=dev)
        self._n_pairs = torch.zeros(B, dtype=torch.int64, device=dev)
        self._d = torch.full((B,), float("nan"), dtype=torch.float32, device=dev)
        self._last_t_us: Optional[int] = None
        self._age = torch.zeros(B, dtype=torch.int64, device=dev)  # steps since reset
        # per-step constants, made once: +-1 sources of scatter_add_ (grown on demand), scalars,
        # the edge bounds of the r_min rule and the strict upper triangle of the merge rule
        self._ones = torch.tensor([[1.0], [-1.0]], device=dev).repeat(1, 4096)
        self._nan = torch.full((), float("nan"), dtype=torch.float32, device=dev)
        self._zero = torch.zeros((), dtype=torch.float32, device=dev)
        r = self.r_min_px
        self._lo_xy = torch.tensor([r, r], dtype=torch.float32, device=dev)
        self._hi_xy = torch.tensor([W - 1 - r, H - 1 - r], dtype=torch.float32, device=dev)
        self._upper = torch.ones(N, N, dtype=torch.bool, device=dev).triu(1)
        self._n_min_t = torch.tensor(float(self.n_min), dtype=torch.float32, device=dev)
        self._merge_t = torch.tensor(self.merge_px, dtype=torch.float32, device=dev)
        self._two_one = torch.tensor([2.0, 1.0], dtype=torch.float32, device=dev)
        self._rel_std = torch.full((B,), float("inf"), dtype=torch.float64, device=dev)
        # multi-step baseline: ring of the last k + 1 steps' centroids and window mean times, and
        # for each slot the number of consecutive steps its centroid has been tracked
        kb = self.baseline_steps + 1
        self._hist = torch.full((B, kb, N, 2), float("nan"), dtype=torch.float32, device=dev)
        self._hist_t = torch.zeros(B, kb, dtype=torch.float64, device=dev)
        self._hist_ptr = 0
        self._slot_age = torch.zeros(B, N, dtype=torch.int64, device=dev)

    # ------------------------------------------------------------------ state
    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        mask = self._mask(mask)
        plane = self._window_padded.shape[1] * self._window_padded.shape[2]
        self._ring = [r[~mask[r // plane]] for r in self._ring]
        self._window_padded[mask] = 0.0
        self._centroids[mask] = float("nan")
        self._valid[mask] = False
        self._counts[mask] = 0.0
        self._reinit[mask] = False
        self._n_pairs[mask] = 0
        self._d[mask] = float("nan")
        self._age[mask] = 0
        self._rel_std[mask] = float("inf")
        self._slot_age[mask] = 0

    def window_image(self) -> torch.Tensor:
        """The windowed count image over the last T, (B, H, W) float32 (a copy).

        Kept as a running sum of the ring (counts are integers: float32 adds them exactly)."""
        return self._window.clone()

    def _event_index(self, events) -> torch.Tensor:
        """Flat indices of the events into the padded window, (E,) int64 (off-sensor dropped)."""
        if events is None or events.b.numel() == 0:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        W, H = self.sensor_size
        q = self._pad
        Hp, Wp = H + 2 * q, W + 2 * q
        b = events.b.to(self.device)
        x = events.x.to(self.device)
        y = events.y.to(self.device)
        # lin = (b * Hp + y + q) * Wp + x + q, in three integer ops
        lin = torch.add(x, y, alpha=Wp).add_(b, alpha=Hp * Wp).add_(q * Wp + q)
        # range check from the extremes (one sync); the mask is built only when needed
        lo_hi = torch.stack([*torch.aminmax(b), *torch.aminmax(x), *torch.aminmax(y)]).tolist()
        if (lo_hi[0] < 0 or lo_hi[1] >= self.batch_size or lo_hi[2] < 0 or lo_hi[3] >= W or lo_hi[4] < 0
                or lo_hi[5] >= H):
            ok = (b >= 0) & (b < self.batch_size) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
            lin = lin[ok]
        return lin

    def _capped(self) -> torch.Tensor:
        """The padded windowed image (B, H + 2q, W + 2q) float32 with every pixel capped at
        ``hot_pixel_factor`` times its element's mean count per active pixel (a new tensor)."""
        img = self._window_padded
        n_act = (img > 0).sum((1, 2)).clamp_min(1).to(img.dtype)
        cap = self.hot_pixel_factor * img.sum((1, 2)) / n_act
        return torch.minimum(img, cap.view(-1, 1, 1))

    def _unit(self, n: int) -> torch.Tensor:
        """(2, n) float32 view: row 0 = +1, row 1 = -1, the window's scatter sources (kept
        between steps, grown on demand)."""
        if self._ones.shape[1] < n:
            self._ones = torch.tensor([[1.0], [-1.0]], device=self.device).repeat(1, 2 * n)
        return self._ones[:, :n]

    # ------------------------------------------------------------------ rules
    def _keep(self, c: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
        """Apply n_min, r_min and merge rules to mean-shift's output; returns the kept mask
        (B', N) bool. (counts >= n_min >= 1 implies a valid seed that was not lost: mean-shift
        gives 0 counts otherwise, and NaN centroids fail the edge rule.)"""
        inside = ((c >= self._lo_xy) & (c <= self._hi_xy)).all(-1)  # NaN compares False
        keep = (counts >= self._n_min_t) & inside
        if self.merge_px > 0 and keep.shape[1] > 1:
            # pairs with a dropped centroid get a NaN distance (never close)
            cc = torch.where(keep.unsqueeze(-1), c, self._nan)
            dist = torch.linalg.vector_norm(cc.unsqueeze(2) - cc.unsqueeze(1), dim=-1)  # (B', N, N)
            close = (dist < self._merge_t) & self._upper
            keep = keep & ~close.any(1)  # j merged into a better-ranked i < j
        return keep

    def _initialise(self, padded: torch.Tensor):
        """DPR + mean-shift to convergence on the windowed image, given with its zero border
        (B', H + 2q, W + 2q); returns (c, counts, keep)."""
        q = self._pad
        W, H = self.sensor_size
        peaks, _, ok = density_peaks(padded[:, q:q + H, q:q + W], self.n_max, self.blur_sigma_px, self.nms_px)
        c, counts, _ = meanshift_flat(padded, peaks, ok, self.radius_px, self.meanshift_iters,
                                      self.meanshift_tol_px, image_pad_px=q)
        keep = self._keep(c, counts)
        # compact: kept centroids first, in rank order
        order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)
        c = torch.gather(c, 1, order.unsqueeze(-1).expand(-1, -1, 2))
        counts = torch.gather(counts, 1, order)
        keep = torch.gather(keep, 1, order)
        return c, counts, keep

    # ------------------------------------------------------------------ step
    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        W, H = self.sensor_size
        t_us = int(t_us)
        dt = self.dt_s
        if self._last_t_us is not None and t_us > self._last_t_us:
            dt = (t_us - self._last_t_us) * 1e-6
        self._last_t_us = t_us
        new = self._event_index(events)
        flat = self._window_padded.view(-1)
        old = self._ring[self._slot]
        # scatter_add_ (about 2x faster than index_add_ on CPU for these scattered indices)
        if old.numel():
            flat.scatter_add_(0, old, self._unit(old.numel())[1])
        if new.numel():
            flat.scatter_add_(0, new, self._unit(new.numel())[0])
        self._ring[self._slot] = new
        self._slot = (self._slot + 1) % self.n_ring

        # 1. track: mean-shift from last step's centroids
        prev = self._centroids
        image = self._capped() if self.hot_pixel_factor > 0 else self._window_padded
        c, counts, _ = meanshift_flat(image, prev, self._valid, self.radius_px, self.meanshift_iters,
                                      self.meanshift_tol_px, image_pad_px=self._pad)
        keep = self._keep(c, counts)
        # 2. Eq. 8 over the pairs tracked at both steps (computed before any re-initialisation).
        # While the ring fills after a reset the window's mean event time advances by dt / 2 per
        # step instead of dt: Eq. 8 then uses dt / 2 (not in paper; removes a x2 bias at start).
        self._age += 1
        # window mean event time (the ring holds min(age, K) steps), s
        t_mean = t_us * 1e-6 - self._age.clamp(max=self.n_ring).to(torch.float64) * (0.5 * dt)
        kb = self.baseline_steps + 1
        age_now = torch.where(keep, self._slot_age + 1, torch.zeros_like(self._slot_age)).clamp(max=self.baseline_steps)
        lag = torch.minimum(age_now.unsqueeze(2), age_now.unsqueeze(1))  # (B, N, N)
        ring = (self._hist_ptr - lag) % kb
        hp = self._hist.permute(0, 2, 1, 3)  # (B, N, kb, 2)
        past_i = hp.gather(2, ring.unsqueeze(-1).expand(-1, -1, -1, 2))
        past_j = hp.gather(2, ring.transpose(1, 2).unsqueeze(-1).expand(-1, -1, -1, 2)).transpose(1, 2)
        elapsed = t_mean.view(-1, 1, 1) - self._hist_t.gather(1, ring.flatten(1)).view_as(ring)
        d_b, n_b, rel = baseline_divergence(c, torch.stack([past_i, past_j], 3), lag, elapsed)
        if self.baseline_steps > 1:
            d, n_pairs = d_b, n_b
        else:  # the paper's Eq. 8 (rel from the same pairs over one step, for the confidence)
            d, n_pairs = pairwise_divergence(prev, c, keep, dt, weighting=self.pair_weighting)
            d = d * torch.where(self._age <= self.n_ring, self._two_one[0], self._two_one[1])
        self._rel_std = rel
        self._hist[:, self._hist_ptr] = torch.where(keep.unsqueeze(-1), c, self._nan)
        self._hist_t[:, self._hist_ptr] = t_mean
        self._slot_age = age_now
        self._centroids = torch.where(keep.unsqueeze(-1), c, self._nan)
        self._valid = keep
        self._counts = torch.where(keep, counts, self._zero)
        # 3. re-initialise (DPR) the elements below C_min, only those
        need = keep.sum(1) < self.c_min
        self._reinit = need
        if bool(need.any()):
            idx = need.nonzero().squeeze(1)
            padded = image[idx]
            # an element with an empty window (e.g. a finished descent) has no density peak, so
            # DPR would give it no centroid; its state already says so (a kept centroid needs
            # n_min >= 1 events within R): skip it
            busy = padded.sum((1, 2)) > 0
            if not bool(busy.all()):
                sel = busy.nonzero().squeeze(1)
                idx, padded = idx[sel], padded[sel]
            if idx.numel():
                ci, ni, ki = self._initialise(padded)
                self._centroids[idx] = torch.where(ki.unsqueeze(-1), ci, self._nan)
                self._valid[idx] = ki
                self._counts[idx] = torch.where(ki, ni, self._zero)
                self._hist[idx, self._hist_ptr] = self._centroids[idx]
        self._slot_age = torch.where(need.unsqueeze(1), torch.zeros_like(self._slot_age), self._slot_age)
        self._hist_ptr = (self._hist_ptr + 1) % (self.baseline_steps + 1)
        self._n_pairs = n_pairs
        self._d = d
        return d.clone()

    def diagnostics(self):
        """centroids (B, N_max, 2) float32 (x, y) px, NaN = unused; n_tracked (B,) int64;
        reinit (B,) bool (DPR ran this step); counts (B, N_max) events within R; n_pairs (B,)
        pairs used by Eq. 8; window_events (B,) events in the memory window; confidence (B,)."""
        return {
            "centroids": self._centroids.clone(),
            "n_tracked": self._valid.sum(1),
            "reinit": self._reinit.clone(),
            "counts": self._counts.clone(),
            "n_pairs": self._n_pairs.clone(),
            "window_events": self._window.sum((1, 2)),
            "confidence": self.confidence(),
        }

    def confidence(self) -> torch.Tensor:
        """(B,) float32 in [0, 1] from the relative standard error of the pairs (see class doc)."""
        return confidence_from_rel_std(self._rel_std, self._d)
