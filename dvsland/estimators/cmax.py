"""``cmax``: divergence by contrast maximisation of radially warped events (beyond the paper).

After McLeod, Meoni, Izzo et al., "Globally optimal event-based divergence estimation for ventral
landing" (ECCV Workshops 2022): the events of a window are warped radially about the focus of
expansion (the camera's principal point) for a candidate D, and the D that makes the warped event
image sharpest is the estimate (:mod:`dvsland.estimators.contrast`).

Per update and batch element, all elements at once:

1. **Window.** The events of the last ``T`` seconds. With ``window_motion`` = kappa > 0 the window
   adapts to the last estimate, T = kappa / |D| clipped to [``window_min_ms``, ``window_max_ms``]:
   the scene then grows by about the same factor exp(kappa) within every window. At high altitude
   (|D| ~ 0.02 1/s) this lengthens the window until features move by pixels (sub-pixel motion
   makes the un-warped image win: events are quantised to pixels); near the ground it shortens
   it, so D hardly changes inside it. ``window_ms`` is the window before the first estimate (and
   always, with kappa = 0).
2. **Thinning.** At most about ``max_events`` per element, kept by a hash of each event's own
   fields (never its position in the batch), so the answer does not depend on event order.
   Events are dithered within their pixel by the same hash.
3. **Search.** An element without a previous estimate runs the global search: a grid of
   ``n_grid`` over [``d_min``, ``d_max``], ``n_refine`` rounds of ``refine_points`` candidates
   around the best. Then every element runs ``newton_iters`` Newton rounds on the score: three
   candidates D0 - h, D0, D0 + h (h = ``step_motion`` / T), the vertex of the parabola through
   their scores is the next D0 (at most 2 h away), h halves. Warm-started from the last
   estimate, two rounds (6 warped images per element) suffice.
4. **Lag and noise.** The warp fits the D of the window middle, T / 2 before the end. With
   ``extrapolate``, the time-to-contact tau = -1 / D of the last ``trend_steps`` window-middle
   estimates is fitted with a line (least squares); its slope carries the estimates to the end
   of the interval, and the last ``smooth_steps`` of them, each carried along that slope, are
   averaged (no lag where tau is linear in t, as in a tau-controlled descent); the average is kept
   within ``smooth_clip`` standard errors (d_std, step 5) of the unaveraged estimate, which bounds
   its lag where tau is curved. Only estimates from full windows enter the trend history.
5. **Confidence.** The events are split in two halves (by hash); the Newton vertex of each half
   from the same warped images gives sigma = |D_1 - D_2| / 2, the standard error of one
   estimate. Where the maximum is not bracketed (a score not concave, or a vertex outside the
   three candidates) sigma is at least 2 h. ``diagnostics()["d_std"]`` = |D| times the RMS of
   sigma / |D| over the estimates averaged in step 4; ``confidence()`` =
   1 / (1 + (d_std / (0.1 |D|))^2).

After a reset an element gives NaN until its window is at least half full, whenever it has
fewer than ``min_events`` events in its window, and when its global search peaked at either end
of [``d_min``, ``d_max``] (no bracketed maximum: events that show no measurable motion).
"""

from __future__ import annotations

import math
from typing import List, Optional

import torch

from dvsland.checks import check_fields
from dvsland.config.schema import CMaxConfig

from .base import DivergenceEstimator, Truth, confidence_from_rel_std
from . import native_cmax
from .contrast import event_hash, pixel_counts, seed_term, split_contrast
from .registry import register_estimator

_HASH_ONE = float(2 ** 31)


def _parabola_offset(s_left: torch.Tensor, s_mid: torch.Tensor, s_right: torch.Tensor,
                     limit: float = 0.5) -> torch.Tensor:
    """Vertex offset (in grid steps, within [-limit, limit]) of the parabola through three scores at
    -1, 0, +1; where the three are not concave, ``limit`` towards the higher side (0 if equal)."""
    den = s_left - 2 * s_mid + s_right
    off = 0.5 * (s_left - s_right) / torch.where(den.abs() > 0, den, torch.ones_like(den))
    uphill = torch.sign(s_right - s_left) * limit
    return torch.where(den < 0, off.clamp(-limit, limit), uphill)


@register_estimator("cmax")
class CMaxEstimator(DivergenceEstimator):
    """Contrast-maximisation divergence estimator (global, no feature tracking). See module doc.

    Args:
        batch_size, sensor_size (W, H), device, dt_s, principal_point_px: see
            :class:`DivergenceEstimator`.
        window_ms: window before the first estimate (and always when window_motion = 0), ms.
        window_motion: kappa = |D| T targeted by the adaptive window (0 = fixed window_ms).
        window_min_ms, window_max_ms: bounds of the adaptive window, ms.
        d_min, d_max: range of D of the global search, 1/s (d_min < d_max); an estimate outside
            it is dropped (NaN) and the element searches globally again.
        n_grid, n_refine, refine_points: global search (see module doc).
        newton_iters: Newton rounds per update (>= 1).
        step_motion: first Newton step h = step_motion / T, 1/s.
        extrapolate: carry the window-middle estimate to the end of the interval (see doc).
        trend_steps: estimates in the slope fit of ``extrapolate`` (>= 3).
        min_events: an element with fewer events in its window gets NaN.
        max_events: events warped per element (hash-thinned) on a 128 x 128 sensor, times
            sqrt(W H) / 128 on a larger one; 0 = all.
        dither: spread each event uniformly within its pixel (by its hash) before warping.
        seed: seed of the event hash.
        radial_bin_px: flatten each element's event density over radius about the FoE in annuli
            this wide, px (0 = off); see :meth:`_radial_weights`.
        research_rel: search globally again when the half-split standard error exceeds this
            fraction of max(|D|, 5 step_motion / T) (the warm start is not trusted then).
        smooth_steps: with ``extrapolate``, average this many of the last estimates along the
            trend line (0 or 1 = off; <= trend_steps); also the span of the RMS in ``d_std``.
        smooth_by_std: weight the averaged estimates by 1 / their relative variance.
        smooth_clip: keep the averaged value within this many standard errors (d_std) of the
            unaveraged one, which bounds the lag where tau is not linear (0 = no bound).
        radial_power: exponent of the radial density weights (0 = off, 1 = flat density).
        research_zero: search globally again when |D| is below this many first Newton steps
            (step_motion / T): an estimate near zero is where a warm start stays locked (0 = off).
        window_growth: the adaptive window grows by at most this factor per update, and only
            from a trusted estimate (not near zero, not lost); an untrusted one sets it back to
            ``window_ms`` (>= 1).
        hot_pixel_factor: an event whose pixel holds more than this many times its element's mean
            count per active pixel in the window is down-weighted to that level (hot pixels and
            other patterns fixed to the sensor, sharpest un-warped; 0 = off).
        trend_tol: the trend of ``extrapolate`` is used only where the RMS residual of its line is
            at most this fraction of the mean time-to-contact (tau not linear in t: no trend).
        blur_sigma_px: kept for compatibility; must be 0 (the score is unblurred).
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, window_ms: float = 1000.0,
                 d_min: float = -1.0, d_max: float = 0.5, n_grid: int = 21, n_refine: int = 2,
                 min_events: int = 50, refine_points: int = 9, blur_sigma_px: float = 0.0,
                 max_events: int = 4000, dither: bool = True, seed: int = 0, window_motion: float = 0.1,
                 window_min_ms: float = 200.0, window_max_ms: float = 3000.0, newton_iters: int = 1,
                 step_motion: float = 0.01, extrapolate: bool = True, trend_steps: int = 100,
                 radial_bin_px: float = 8.0, research_rel: float = 0.5, smooth_steps: int = 20,
                 smooth_by_std: bool = False, radial_power: float = 0.5, smooth_clip: float = 1.0,
                 research_zero: float = 1.0, window_growth: float = 1.5, hot_pixel_factor: float = 8.0,
                 trend_tol: float = 0.15, principal_point_px=None):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        # the ranges of the config schema (estimator.cmax), written once there
        check_fields(CMaxConfig, window_ms=window_ms, d_min=d_min, d_max=d_max, n_grid=n_grid, n_refine=n_refine,
                     min_events=min_events, refine_points=refine_points, blur_sigma_px=blur_sigma_px,
                     max_events=max_events, window_motion=window_motion, window_min_ms=window_min_ms,
                     window_max_ms=window_max_ms, newton_iters=newton_iters, step_motion=step_motion,
                     trend_steps=trend_steps, radial_bin_px=radial_bin_px, research_rel=research_rel,
                     smooth_steps=smooth_steps, radial_power=radial_power, smooth_clip=smooth_clip,
                     research_zero=research_zero, window_growth=window_growth, hot_pixel_factor=hot_pixel_factor,
                     trend_tol=trend_tol)
        checks = [("smooth_steps", int(smooth_steps) <= int(trend_steps), "<= trend_steps"),
                  ("refine_points", int(refine_points) % 2 == 1, "an odd integer >= 3"),
                  ("blur_sigma_px", blur_sigma_px == 0, "0 (the fast score has no blur)"),
                  ("window_min_ms", window_min_ms <= window_max_ms, "<= window_max_ms")]
        for name, ok, rng in checks:
            if not ok:
                raise ValueError(f"{name} must be {rng}, got {locals()[name]}")
        if not (math.isfinite(d_min) and math.isfinite(d_max) and d_min < d_max):
            raise ValueError(f"d_min must be < d_max (both finite), got d_min={d_min}, d_max={d_max}")
        self.window_us = int(round(float(window_ms) * 1000.0))
        self._window_s_init = self.window_us * 1e-6
        self.window_motion = float(window_motion)
        self.window_min_s, self.window_max_s = float(window_min_ms) * 1e-3, float(window_max_ms) * 1e-3
        self.d_min, self.d_max = float(d_min), float(d_max)
        self.n_grid, self.n_refine = int(n_grid), int(n_refine)
        self.min_events, self.refine_points = int(min_events), int(refine_points)
        self.max_events, self.dither, self.seed = int(max_events), bool(dither), int(seed)
        # events come from the scene's edges, whose length in pixels grows with the sensor's linear
        # size: a sensor larger than 128 x 128 keeps max_events x sqrt(W H) / 128 per element
        # (a 640 x 360 sensor with 4000 events had too few per edge pixel to show any structure)
        W, H = self.sensor_size
        self.max_events = int(round(self.max_events * max(1.0, math.sqrt(W * H) / 128.0)))
        self.newton_iters, self.step_motion = int(newton_iters), float(step_motion)
        self.extrapolate, self.trend_steps = bool(extrapolate), int(trend_steps)
        self.research_rel, self.research_zero = float(research_rel), float(research_zero)
        self.window_growth, self.hot_pixel_factor = float(window_growth), float(hot_pixel_factor)
        self.trend_tol = float(trend_tol)
        self.smooth_steps, self.smooth_by_std = int(smooth_steps), bool(smooth_by_std)
        self.smooth_clip = float(smooth_clip)
        if not 0 <= radial_bin_px <= 1000:
            raise ValueError(f"radial_bin_px must be in [0, 1000], got {radial_bin_px}")
        self.radial_bin_px = float(radial_bin_px)
        self.radial_power = float(radial_power)
        W, H = self.sensor_size
        cx, cy = self.principal_point_px
        self._wt = None
        if self.radial_bin_px > 0:  # sensor pixels per annulus about the FoE
            yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                                    indexing="ij")
            rb = (torch.hypot(xx - cx, yy - cy) / self.radial_bin_px).floor().to(torch.int64).flatten()
            self._n_rbins = int(rb.max()) + 1
            self._rbin_of_px = rb.to(self.device)  # (H W,) annulus of each pixel centre
            self._px_per_rbin = torch.bincount(rb, minlength=self._n_rbins).to(torch.float64).to(self.device)
        W, H = self.sensor_size
        cx, cy = self.principal_point_px
        #: farthest pixel centre from the FoE, px
        self.r_max_px = math.hypot(max(cx, W - 1 - cx), max(cy, H - 1 - cy))
        #: canvas margin, px: only events inside the sensor box shrunk about the FoE count (see
        #: :func:`split_contrast`), so one pixel holds every counted bilinear weight, whatever D and
        #: the window (the canvas, hence the cost, does not grow with |D| T)
        self.pad_px = 1
        self.pad_cap_px = int(max(W, H))
        # longest window ever needed, s (the store keeps this much)
        self._keep_s = max(self.window_us * 1e-6, self.window_max_s if self.window_motion > 0 else 0.0)
        # the stored events of recent steps, oldest first, in one ring-like buffer (no per-update
        # concatenation): fields b, xy (2, n), t, key over [_lo, _hi); _steps: (start, latest t)
        self._cap = 0
        self._buf = self._empty_buf(0)
        self._lo = self._hi = 0
        self._steps: List[tuple] = []
        B, dev = self.batch_size, self.device
        self._d = torch.full((B,), float("nan"), dtype=torch.float32, device=dev)
        self._d_mid = torch.full((B,), float("nan"), dtype=torch.float64, device=dev)
        self._sigma = torch.full((B,), float("nan"), dtype=torch.float64, device=dev)
        self._sigma_step = self._sigma.clone()
        self._rel_std = self._sigma.clone()
        self._bracketed = torch.zeros(B, dtype=torch.bool, device=dev)
        self._n_events = torch.zeros(B, dtype=torch.int64, device=dev)
        self._contrast = torch.zeros(B, dtype=torch.float32, device=dev)
        self._window_s = torch.full((B,), self.window_us * 1e-6, dtype=torch.float64, device=dev)
        self._t_start_us = torch.full((B,), -1, dtype=torch.int64, device=dev)
        self._hist_t = torch.zeros(B, self.trend_steps, dtype=torch.float64, device=dev)
        self._hist_d = torch.full((B, self.trend_steps), float("nan"), dtype=torch.float64, device=dev)
        self._hist_s = torch.full((B, self.trend_steps), float("nan"), dtype=torch.float64, device=dev)
        self._k = 0
        self._global = torch.zeros(B, dtype=torch.bool, device=dev)

    # ------------------------------------------------------------------ state
    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        mask = self._mask(mask)
        if self._hi > self._lo:  # rebuild the buffer without the masked elements (rare)
            live = [f[..., self._lo:self._hi] for f in self._buf]
            keep = ~mask[live[0]]
            starts = [st - self._lo for st, _ in self._steps] + [self._hi - self._lo]
            n_keep = torch.cumsum(keep.to(torch.int64), 0)
            new_starts = [int(n_keep[a - 1]) if a > 0 else 0 for a in starts]
            steps = [(new_starts[i], self._steps[i][1]) for i in range(len(self._steps))
                     if new_starts[i + 1] > new_starts[i]]
            kept = [f[..., keep] for f in live]
            self._buf, self._cap = self._empty_buf(0), 0
            self._lo = self._hi = 0
            self._steps = []
            if kept[0].numel():
                self._append(kept)
                self._steps = steps
        self._d[mask] = float("nan")
        self._d_mid[mask] = float("nan")
        self._sigma[mask] = float("nan")
        self._sigma_step[mask] = float("nan")
        self._rel_std[mask] = float("nan")
        self._n_events[mask] = 0
        self._contrast[mask] = 0.0
        self._window_s[mask] = self.window_us * 1e-6
        self._t_start_us[mask] = -1
        self._hist_d[mask] = float("nan")
        self._hist_s[mask] = float("nan")

    def _steps_per_window(self) -> torch.Tensor:
        return (self._window_s / self.dt_s).clamp_min(1.0)

    def _store_step(self, events) -> None:
        """Keep the step's events that lie on the sensor, hash-thinned to about 1.25 max_events /
        (steps per window) per element, with what every later update needs precomputed: element,
        dithered position, time, and a key: a 16-bit hash (window thinning) with the half bit, and
        the event's pixel y W + x above them."""
        dev = self.device
        b, x, y, t = (getattr(events, f).to(dev) for f in ("b", "x", "y", "t"))
        W, H = self.sensor_size
        keep = self._store_keep(b, x, y, t)
        if keep.numel() == 0:
            return
        b, x, y, t = b[keep], x[keep], y[keep], t[keep]
        xy = torch.stack([x, y]).to(torch.float32)
        h2 = event_hash(b, x, y, t, self.seed + 1)
        if self.dither:  # uniform within the pixel: 8 and 7 fresh hash bits
            xy += torch.stack([((h2 >> 16) & 0xFF).to(torch.float32) / 256.0,
                               ((h2 >> 24) & 0x7F).to(torch.float32) / 128.0]) - 0.5
        # window-thinning key in bits 0..14, half in bit 15, the event's pixel y W + x from bit 16
        key = (h2 & 0xFFFF) | ((y.to(torch.int64) * W + x.to(torch.int64)) << 16)
        start = self._append((b, xy, t, key))
        self._steps.append((start, int(t.max())))

    def _store_keep(self, b, x, y, t) -> torch.Tensor:
        """(K,) int64 indices of the step's events kept: on the sensor and in the batch, and (with
        ``max_events``) passing the hash thinning to about 1.25 max_events / (steps per window)
        per element. The compiled kernel (:mod:`native_cmax`) keeps the same events."""
        W, H = self.sensor_size
        B = self.batch_size
        cap = (1.25 * self.max_events / self._steps_per_window()).ceil() if self.max_events > 0 else \
            torch.full((B,), float("inf"), dtype=torch.float64, device=b.device)
        mod = native_cmax.kernel_for(b) if b.numel() else None
        if mod is not None:
            i64 = [v.to(torch.int64).contiguous() for v in (b, x, y, t)]
            return mod.store_select(*i64, cap.to(torch.float64).contiguous(), W, H, seed_term(self.seed))
        ok = (b >= 0) & (b < B) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
        if self.max_events > 0:
            h = event_hash(b, x, y, t, self.seed)
            n_per = torch.bincount(torch.where(ok, b, torch.zeros_like(b)), weights=ok.to(torch.float64),
                                   minlength=B)[:B]
            p = (cap / n_per.clamp_min(1)).clamp(max=1.0)
            ok &= (h & 0xFFFF).to(torch.float64) < p[b.clamp(0, B - 1)] * 65536.0
        return ok.nonzero().squeeze(1)

    def _empty_buf(self, n: int):
        dev = self.device
        i64 = dict(dtype=torch.int64, device=dev)
        return (torch.empty(n, **i64), torch.empty(2, n, dtype=torch.float32, device=dev), torch.empty(n, **i64),
                torch.empty(n, **i64))

    def _append(self, fields) -> int:
        """Write one step's fields at the end of the buffer (compacting / growing it when full);
        returns the start index of the step."""
        n = fields[0].numel()
        if self._hi + n > self._cap:
            live = self._hi - self._lo
            cap = max(self._cap, 2 * (live + n), 4096)
            new = self._empty_buf(cap)
            for dst, src in zip(new, self._buf):
                dst[..., :live] = src[..., self._lo:self._hi]
            shift = self._lo
            self._steps = [(st - shift, tm) for st, tm in self._steps]
            self._buf, self._cap, self._lo, self._hi = new, cap, 0, live
        for dst, src in zip(self._buf, fields):
            dst[..., self._hi:self._hi + n] = src
        start = self._hi
        self._hi += n
        return start

    def _window_events(self, t_us: int):
        """(b, xy (2, E), t, key) of the events in each element's window, thinned to max_events."""
        keep_us = int(math.ceil(float(self._window_s.max()) * 1e6))
        while self._steps and self._steps[0][1] <= t_us - keep_us:
            self._steps.pop(0)
            self._lo = self._steps[0][0] if self._steps else self._hi
        if not self._steps:
            self._lo = self._hi = 0
            z = torch.zeros(0, dtype=torch.int64, device=self.device)
            return z, torch.zeros(2, 0, device=self.device), z, z, torch.zeros(self.batch_size, dtype=torch.int64,
                                                                               device=self.device)
        b, xy_all, t, key = (f[..., self._lo:self._hi] for f in self._buf)
        w_us = (self._window_s * 1e6).round().to(torch.int64)
        inw = (t > t_us - w_us[b]) & (t <= t_us)
        n_per = torch.bincount(b, weights=inw.to(torch.float32), minlength=self.batch_size)[: self.batch_size]
        if self.max_events > 0:
            p = (self.max_events / n_per.clamp_min(1)).clamp(max=1.0)
            inw &= (key & 0x7FFF).to(torch.float32) < p[b] * 32768.0
        sel = inw.nonzero().squeeze(1)
        xy = xy_all.index_select(1, sel)
        return b[sel], xy, t[sel], key[sel], n_per.round().to(torch.int64)

    # ------------------------------------------------------------------ search
    def _score(self, xs, ys, b, half, tau, cand, pad, half_window_s, wt=None):
        cx, cy = self.principal_point_px
        W, H = self.sensor_size
        box = (pad - 0.5, pad + W - 0.5, pad - 0.5, pad + H - 0.5)
        return split_contrast(xs, ys, b, half, tau, cand, (cx + pad, cy + pad), (H + 2 * pad, W + 2 * pad),
                              box, half_window_s, wt)

    def _pad_for(self, d_abs_max: float, window_s: float) -> int:
        """Canvas margin, px, for any D and window: ``pad_px`` (counted events never leave the sensor box)."""
        return self.pad_px

    def _global_search(self, xs, ys, b, half, tau, sel_el: torch.Tensor, win_s: torch.Tensor) -> torch.Tensor:
        """Grid search (+ refinement) for elements ``sel_el`` (B,) bool; returns (B,) float64 D
        (NaN elsewhere). xs, ys are sensor coordinates (no canvas offset).

        Each round scores the events of only the newest part of the window in which candidates one
        grid step apart move an event at the sensor's edge by at most 2 px (the whole window once
        the steps are fine): a peak of the score is then wider than the grid and cannot fall
        between its points (on the full window at |D| ~ 0.05 1/s it did, and the grid's maximum
        was noise)."""
        B, dev = self.batch_size, self.device
        idx = sel_el.nonzero().squeeze(1)
        n = idx.numel()
        remap = torch.full((B,), -1, dtype=torch.int64, device=dev)
        remap[idx] = torch.arange(n, device=dev)
        e = sel_el[b]
        bs = remap[b[e]]
        pad = self.pad_px
        xe, ye = xs[e] + pad, ys[e] + pad
        he, te = half[e], tau[e]
        we = torch.ones_like(te) if self._wt is None else self._wt[e]
        half_w = 0.5 * win_s[idx]
        grid = torch.linspace(self.d_min, self.d_max, self.n_grid, device=dev, dtype=torch.float64)
        cand = grid.unsqueeze(0).expand(n, -1)
        step = (self.d_max - self.d_min) / (self.n_grid - 1)

        def score(cand, step):
            # the newest span of each window, s, re-centred on its own middle
            span = (2.0 / (step * max(self.r_max_px, 1.0)) / win_s[idx]).clamp(max=1.0) * win_s[idx]
            shift = (half_w - 0.5 * span)[bs].to(te.dtype)
            recent = (te >= 2 * shift - half_w[bs].to(te.dtype)).to(we.dtype)
            return self._score(xe, ye, bs, he, te - shift, cand, pad, 0.5 * span, we * recent)[..., 0]

        sc = score(cand, step)
        # a grid maximum at either end of [d_min, d_max] is no bracketed maximum (the score keeps
        # rising out of the range: what events without a measurable motion give): no estimate
        first = sc.argmax(1)
        self._edge = torch.zeros(B, dtype=torch.bool, device=dev)
        self._edge[idx] = (first == 0) | (first == self.n_grid - 1)
        for _ in range(self.n_refine):
            best = cand.gather(1, sc.argmax(1, keepdim=True))
            off = torch.linspace(-1.0, 1.0, self.refine_points, device=dev, dtype=torch.float64)
            cand = best + step * off
            step = step * 2.0 / (self.refine_points - 1)
            sc = score(cand, step)
        out = torch.full((B,), float("nan"), dtype=torch.float64, device=dev)
        out[idx] = cand.gather(1, sc.argmax(1, keepdim=True)).squeeze(1)
        return out

    # ------------------------------------------------------------------ step
    @torch.no_grad()
    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        B, dev = self.batch_size, self.device
        t_us = int(t_us)
        if events is not None and events.b.numel() > 0:
            self._store_step(events)
        b, xy, t, key, n_per = self._window_events(t_us)
        self._n_events = n_per
        t_begin = t_us - int(round(self.dt_s * 1e6))
        self._t_start_us = torch.where(self._t_start_us < 0, torch.full_like(self._t_start_us, t_begin),
                                       self._t_start_us)
        # half of the first window must have passed since the reset (later windows, longer or
        # shorter, simply hold what there is)
        filled = (t_us - self._t_start_us).to(torch.float64) * 2e-6 >= self.window_us * 1e-6 - 1e-9
        ok = (n_per >= self.min_events) & filled
        nan = torch.full((B,), float("nan"), dtype=torch.float32, device=dev)
        if not bool(ok.any()):
            self._d, self._sigma = nan, torch.full_like(self._sigma, float("nan"))
            self._rel_std = torch.full_like(self._sigma, float("nan"))
            return self._d.clone()
        if not bool(ok.all()):
            sel = ok[b].nonzero().squeeze(1)
            b, xy, t, key = b[sel], xy[:, sel], t[sel], key[sel]
        half = (key >> 15) & 1
        win_s = self._window_s.clone()
        t_ref_us = t_us - win_s * 0.5e6  # (B,) float64
        tau = ((t - t_ref_us.round().to(torch.int64)[b]).to(torch.float32) * 1e-6)
        xs, ys = xy[0], xy[1]
        pix = key >> 16
        self._wt = self._radial_weights(pix, b) if self.radial_bin_px > 0 and self.radial_power > 0 else None
        if self.hot_pixel_factor > 0:
            hot = self._hot_pixel_weights(pix, b)
            self._wt = hot if self._wt is None else self._wt * hot
        # start: last estimate (warm), else the global search
        d0 = self._d_mid.clone()
        need = ok & ~torch.isfinite(d0)
        self._global = need
        if bool(need.any()):
            d0 = torch.where(need, self._global_search(xs, ys, b, half, tau, need, win_s), d0)
        hstep = self.step_motion / win_s
        d_abs = float(torch.where(ok, d0.abs() + 2 * hstep, torch.zeros_like(d0)).nan_to_num(0.0).max())
        pad = self._pad_for(d_abs, float(win_s[ok].max()))
        xc, yc = xs + pad, ys + pad
        three = torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64, device=dev)
        d0 = d0.nan_to_num(0.0)
        for it in range(self.newton_iters):
            cand = d0.unsqueeze(1) + hstep.unsqueeze(1) * three
            sc = self._score(xc, yc, b, half, tau, cand, pad, 0.5 * win_s, self._wt)  # (B, 3, 3)
            last = it == self.newton_iters - 1
            off = _parabola_offset(sc[:, 0, 0], sc[:, 1, 0], sc[:, 2, 0], 2.0)
            d_new = d0 + off * hstep
            if last:
                d_halves = [d0 + _parabola_offset(sc[:, 0, k], sc[:, 1, k], sc[:, 2, k], 2.0) * hstep for k in (1, 2)]
                self._sigma = (d_halves[0] - d_halves[1]).abs() * 0.5
                self._contrast = sc[:, 1, 0].to(torch.float32)
                # the maximum is bracketed when the scores of all events and of both halves are
                # concave with their vertex within the three candidates; where it is not, the
                # estimate has not converged and is uncertain by at least the bracket, 2 h
                den = sc[:, 0] - 2 * sc[:, 1] + sc[:, 2]  # (B, 3)
                vtx = 0.5 * (sc[:, 0] - sc[:, 2]) / torch.where(den < 0, den, -torch.ones_like(den))
                self._bracketed = ((den < 0) & (vtx.abs() <= 1.0)).all(1)
                self._sigma_step = torch.where(self._bracketed, self._sigma,
                                               torch.maximum(self._sigma, 2.0 * hstep))
            d0, hstep = d_new, hstep * 0.5
        inside = (d0 >= self.d_min) & (d0 <= self.d_max)
        if bool(need.any()):
            inside &= ~(need & self._edge)
        good = ok & inside
        d_mid = torch.where(good, d0, torch.full_like(d0, float("nan")))
        # keep the last estimate of elements with too few events this step (warm start later);
        # drop it where the estimate left [d_min, d_max] (search globally next time)
        self._d_mid = torch.where(ok, d_mid, self._d_mid)
        # an estimate whose two halves disagree by more than ``research_rel`` of |D| is not trusted
        # as a warm start: that element searches globally again next time
        # (|D| is floored at 5 first Newton steps, so that D near 0 does not count as lost)
        floor = 5.0 * self.step_motion / win_s
        lost = ok & (self._sigma > self.research_rel * torch.maximum(d_mid.abs(), floor))
        # an estimate near zero is where the warm start locks (a static pattern, or motion below a
        # pixel, is sharpest un-warped): search globally again from the next update
        zero = ok & (d_mid.abs() < self.research_zero * self.step_motion / win_s)
        self._d_mid = torch.where(lost | zero, torch.full_like(self._d_mid, float("nan")), self._d_mid)
        # history for the lag correction: (window-middle time, estimate)
        j = self._k % self.trend_steps
        self._k += 1
        # tagged with the middle of the events actually held (the first windows after a reset
        # are not full yet)
        since_s = (t_us - self._t_start_us).to(torch.float64) * 1e-6
        held_s = torch.minimum(win_s, since_s)
        self._hist_t[:, j] = t_us * 1e-6 - 0.5 * held_s
        # only estimates from full windows enter the trend: the first ones after a reset are
        # from shorter windows, with less motion in them (read towards D = 0 at high altitude),
        # and as tau = -1 / D they would tilt the trend line
        full = since_s >= win_s - 1e-6
        self._hist_d[:, j] = torch.where(full, -1.0 / d_mid, torch.full_like(d_mid, float("nan")))  # tau
        # relative standard error of tau (= that of D)
        self._hist_s[:, j] = self._sigma_step / d_mid.abs()
        # relative standard error reported with the estimate: RMS over the estimates it averages
        age = (j - torch.arange(self.trend_steps, device=dev)) % self.trend_steps
        rs = torch.where((age < max(self.smooth_steps, 1)).unsqueeze(0), self._hist_s, torch.nan)
        fin = torch.isfinite(rs)
        rel_rms = ((rs.nan_to_num(0.0) ** 2).sum(1) / fin.sum(1).clamp_min(1)).sqrt()
        self._rel_std = torch.where(fin.any(1) & torch.isfinite(d_mid), rel_rms, torch.full_like(rel_rms, float("nan")))
        d_out = d_mid
        if self.extrapolate:
            # time-to-contact tau = -1 / D, extrapolated linearly over the half window
            tau_mid = -1.0 / d_mid
            slope, trend = self._slope()
            tau_end = tau_mid + slope * (t_us * 1e-6 - self._hist_t[:, j])
            if self.smooth_steps > 1:  # only where the trend is known (no lag from averaging)
                tau_s = self._smoothed_tau(slope, t_us * 1e-6, j)
                if self.smooth_clip > 0:  # at most smooth_clip standard errors from this estimate
                    lim = self.smooth_clip * self._rel_std * tau_end.abs()
                    tau_s = torch.minimum(torch.maximum(tau_s, tau_end - lim), tau_end + lim)
                tau_end = torch.where(trend & torch.isfinite(tau_s), tau_s, tau_end)
            safe = torch.isfinite(tau_end) & (tau_end * tau_mid > 0) & ((tau_end - tau_mid).abs() < 0.5 * tau_mid.abs())
            d_out = torch.where(safe, -1.0 / tau_end, d_mid)
        if self.window_motion > 0:
            self._window_s = self._next_window(d_mid, lost | zero)
        self._d = torch.where(good, d_out, torch.full_like(d_out, float("nan"))).to(torch.float32)
        return self._d.clone()

    def _next_window(self, d_mid: torch.Tensor, untrusted: torch.Tensor) -> torch.Tensor:
        """(B,) float64 next window, s: kappa / |D| within [window_min, window_max], grown by at
        most ``window_growth`` per update; an untrusted estimate (near zero, or its halves
        disagreeing) sets it back to ``window_ms``, so that neither a near-zero estimate stretches
        the window to the slowest motion it could mean nor a wild one shrinks it; no estimate
        keeps it."""
        w = (self.window_motion / d_mid.abs().clamp_min(1e-9)).clamp(self.window_min_s, self.window_max_s)
        w = torch.minimum(w, self._window_s * self.window_growth)
        w = torch.where(untrusted, torch.full_like(w, self._window_s_init), w)
        return torch.where(torch.isfinite(d_mid), w, self._window_s)

    def _hot_pixel_weights(self, pix, b) -> torch.Tensor:
        """(E,) float32 weights of the events of hot pixels: a pixel holding c events, more than
        ``hot_pixel_factor`` times its element's mean count per active pixel m, weighs m / c per
        event (all of its events together count as one ordinary pixel), else 1. m is the mean over
        the pixels not flagged by a first mean (hot pixels inflate it). A hot pixel, or any pattern
        fixed to the sensor, then no longer pulls the estimate to D = 0. ``pix``: (E,) int64 pixel
        y W + x of each event. The compiled kernel (:mod:`native_cmax`) gives the same weights."""
        W, H = self.sensor_size
        B = self.batch_size
        mod = native_cmax.kernel_for(b) if b.numel() else None
        if mod is not None:
            return mod.hot_weights(b.contiguous(), pix.contiguous(), B, H * W, self.hot_pixel_factor)
        c = pixel_counts(b, pix, B, H * W, native=False).to(torch.float64)  # (E,) events at its pixel
        mean = torch.zeros(B, dtype=torch.float64, device=c.device)
        keep = torch.ones_like(c, dtype=torch.bool)
        for _ in range(2):  # mean count per active pixel, then again without the flagged pixels
            n_px = torch.bincount(b, weights=keep.to(torch.float64) / c, minlength=B)[:B]
            n_ev = torch.bincount(b, weights=keep.to(torch.float64), minlength=B)[:B]
            mean = n_ev / n_px.clamp_min(1e-9)
            keep = c <= self.hot_pixel_factor * mean[b]
        return torch.where(keep, torch.ones_like(c), mean[b] / c).to(torch.float32)

    def _radial_weights(self, pix, b) -> torch.Tensor:
        """(E,) weights that flatten each element's event density over radius about the FoE.

        The event rate of a pixel grows with its image speed, D r: events crowd towards the edges
        of the sensor in a pattern fixed to the sensor, not to the scene, and such a pattern is
        sharpest un-warped (D = 0), which pulls the estimate towards 0. Weighting each event by
        the inverse of its element's event density in its annulus (``radial_bin_px`` wide)
        removes that pull. The weight is that inverse to the power ``radial_power``: 1 over-
        corrects on the rendered sites (|D| read about 1 % high), 0.5 leaves no bias there. An event's
        annulus is its pixel centre's (``pix``: (E,) int64 y W + x)."""
        nb = self._n_rbins
        rb = self._rbin_of_px.index_select(0, pix)
        cnt = torch.bincount(b * nb + rb, minlength=self.batch_size * nb)[: self.batch_size * nb]
        dens = cnt.view(self.batch_size, nb).to(torch.float64) / self._px_per_rbin.clamp_min(1)
        mean = dens.sum(1) / (dens > 0).sum(1).clamp_min(1)
        w = (mean.unsqueeze(1) / dens.clamp_min(1e-12)).pow(self.radial_power).clamp(0.1, 10.0)
        return w.view(-1)[b * nb + rb].to(torch.float32)

    def _slope(self):
        """Least-squares slope d tau / dt (B,) of the window-middle time-to-contact in the history
        (0 where fewer than half of the history is filled or the sign of D changed in it), and
        (B,) bool where it is known (not 0 for those reasons)."""
        ok = torch.isfinite(self._hist_d)
        n = ok.sum(1).to(torch.float64)
        w = ok.to(torch.float64)
        tt = torch.where(ok, self._hist_t, torch.zeros_like(self._hist_t))
        dd = torch.where(ok, self._hist_d, torch.zeros_like(self._hist_d))
        tm = (tt * w).sum(1) / n.clamp_min(1)
        dm = (dd * w).sum(1) / n.clamp_min(1)
        ct = (tt - tm.unsqueeze(1)) * w
        var = (ct * ct).sum(1)
        slope = (ct * (dd - dm.unsqueeze(1))).sum(1) / var.clamp_min(1e-12)
        same_sign = (torch.where(ok, torch.sign(self._hist_d), torch.zeros_like(self._hist_d)).sum(1).abs() == n)
        # the line must describe tau: RMS residual within trend_tol of the mean |tau|
        res = torch.where(ok, dd - dm.unsqueeze(1) - slope.unsqueeze(1) * (tt - tm.unsqueeze(1)), torch.zeros_like(dd))
        rms = ((res * res).sum(1) / n.clamp_min(1)).sqrt()
        linear = rms <= self.trend_tol * dm.abs() if self.trend_tol > 0 else torch.ones_like(same_sign)
        use = (n >= max(3, self.trend_steps // 2)) & (var > 0) & same_sign & linear
        return torch.where(use, slope, torch.zeros_like(slope)), use

    def _smoothed_tau(self, slope: torch.Tensor, t_end_s: float, j: int) -> torch.Tensor:
        """(B,) time-to-contact at ``t_end_s``: the mean over the last ``smooth_steps`` window-middle
        estimates of tau_k + slope (t_end - t_k), i.e. the line of the trend slope through their
        centroid (weights 1 / rel. std^2 with ``smooth_by_std``). No lag where tau is linear over
        the trend history; NaN where none of them is finite. ``j`` is the newest history slot."""
        age = (j - torch.arange(self.trend_steps, device=self.device)) % self.trend_steps
        tau = self._hist_d + slope.unsqueeze(1) * (t_end_s - self._hist_t)
        ok = torch.isfinite(tau) & (age < self.smooth_steps).unsqueeze(0)
        w = ok.to(torch.float64)
        if self.smooth_by_std:
            rel = self._hist_s.nan_to_num(1.0).clamp_min(1e-3)
            w = w / (rel * rel)
        return (torch.where(ok, tau, torch.zeros_like(tau)) * w).sum(1) / w.sum(1)

    def confidence(self) -> torch.Tensor:
        """(B,) float32: 1 / (1 + (d_std / (0.1 |D|))^2), d_std the RMS half-split standard error
        (module doc, step 5); 0 where the estimate is NaN."""
        return confidence_from_rel_std(self._rel_std, self._d)

    def diagnostics(self):
        """n_events (B,) events in the window; contrast (B,) score at the estimate; window_s (B,)
        current window, s; d_std (B,) float64 standard error of D, 1/s (module doc, step 5; NaN
        with the estimate); global_search (B,) bool (this step searched globally); bracketed (B,)
        bool (this step's maximum lay within the Newton candidates); confidence (B,) in [0, 1]."""
        return {"n_events": self._n_events.clone(), "contrast": self._contrast.clone(),
                "window_s": self._window_s.clone(), "d_std": self._rel_std * self._d.to(torch.float64).abs(),
                "global_search": self._global.clone(), "bracketed": self._bracketed.clone(),
                "confidence": self.confidence()}
