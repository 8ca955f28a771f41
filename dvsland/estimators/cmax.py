"""``cmax``: divergence by contrast maximisation of radially warped events (beyond the paper).

After McLeod, Meoni, Izzo et al., "Globally optimal event-based divergence estimation for ventral
landing" (ECCV Workshops 2022): the events of the last ``window_ms`` are warped radially about
the focus of expansion (the image centre for a nadir camera) for a candidate D, and the D that
makes the warped count image sharpest (highest variance) is the estimate. The search is a
batched grid over [d_min, d_max] followed by ``n_refine`` rounds of ``refine_points`` candidates
within one grid step of the best, and a parabolic fit through the best three; every element and
every candidate is scored at once (chunked only to bound memory). The returned D refers to the
middle of the window. After a reset an element gives NaN until its window is at least half
full. See :mod:`dvsland.estimators.contrast` for the warp.
"""

from __future__ import annotations

import math
from typing import List, Optional

import torch

from dvsland.checks import check_fields
from dvsland.config.schema import CMaxConfig

from .base import DivergenceEstimator, Truth
from .contrast import warped_contrast
from .registry import register_estimator


def _parabola_offset(s_left: torch.Tensor, s_mid: torch.Tensor, s_right: torch.Tensor) -> torch.Tensor:
    """Vertex offset (in grid steps, within [-0.5, 0.5]) of the parabola through three scores."""
    den = s_left - 2 * s_mid + s_right
    off = 0.5 * (s_left - s_right) / torch.where(den.abs() > 0, den, torch.ones_like(den))
    return torch.where(den < 0, off.clamp(-0.5, 0.5), torch.zeros_like(off))


@register_estimator("cmax")
class CMaxEstimator(DivergenceEstimator):
    """Contrast-maximisation divergence estimator (global, no feature tracking).

    Args:
        batch_size, sensor_size (W, H), device, dt_s: see :class:`DivergenceEstimator`.
        window_ms: events of the last window_ms are warped (kept across steps when > dt).
        d_min, d_max: searched range of D, 1/s (d_min < d_max).
        n_grid: coarse grid size (>= 3).
        n_refine: refinement rounds.
        min_events: an element with fewer events in the window gets NaN.
        refine_points: candidates per refinement round (odd, >= 3; not in paper).
        blur_sigma_px: Gaussian blur of the warped image before the variance, px (0 = none).
        max_events: per element at most about this many events are warped (each step's events
            are thinned to max_events / (window / dt) by an even stride when stored); 0 = all.
        dither: spread each event uniformly within its pixel (seeded) before warping. Without it
            the un-warped D = 0 lands every event of a pixel on the same spot and wins whenever
            the motion in the window is sub-pixel (high altitude).
        seed: seed of the dither generator (drawn on CPU, then moved).
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, window_ms: float = 1000.0,
                 d_min: float = -1.0, d_max: float = 0.5, n_grid: int = 21, n_refine: int = 2,
                 min_events: int = 50, refine_points: int = 9, blur_sigma_px: float = 0.0,
                 max_events: int = 3000, dither: bool = True, seed: int = 0):
        super().__init__(batch_size, sensor_size, device, dt_s)
        # the ranges of the config schema (estimator.cmax), written once there
        check_fields(CMaxConfig, window_ms=window_ms, d_min=d_min, d_max=d_max, n_grid=n_grid, n_refine=n_refine,
                     min_events=min_events, refine_points=refine_points, blur_sigma_px=blur_sigma_px,
                     max_events=max_events)
        if not d_min < d_max:
            raise ValueError(f"d_min must be < d_max, got d_min={d_min}, d_max={d_max}")
        if int(refine_points) % 2 == 0:
            raise ValueError(f"refine_points must be an odd integer >= 3, got {refine_points}")
        self.window_us = int(round(float(window_ms) * 1000.0))
        self.d_min, self.d_max = float(d_min), float(d_max)
        self.n_grid, self.n_refine = int(n_grid), int(n_refine)
        self.min_events, self.refine_points = int(min_events), int(refine_points)
        self.blur_sigma_px, self.max_events = float(blur_sigma_px), int(max_events)
        self.dither = bool(dither)
        self._gen = torch.Generator(device="cpu").manual_seed(int(seed))
        W, H = self.sensor_size
        # canvas margin: the largest radial displacement over half a window, plus one pixel
        half_s = 0.5 * self.window_us * 1e-6
        # bounded by one sensor size (canvas <= 3x the sensor per side): an extreme |D| * window
        # (d_min = -100) would otherwise ask for an astronomically large canvas; events warped
        # beyond the margin drop out of the image, which only lowers such candidates' contrast
        grow = math.expm1(min(max(abs(self.d_min), abs(self.d_max)) * half_s, 50.0))
        self.pad_px = min(int(math.ceil(grow * 0.5 * max(W, H))) + 1, max(W, H))
        self._store: List[tuple] = []  # (b, x, y, t) of recent steps
        B = self.batch_size
        self._d = torch.full((B,), float("nan"), dtype=torch.float32, device=self.device)
        self._n_events = torch.zeros(B, dtype=torch.int64, device=self.device)
        self._contrast = torch.zeros(B, dtype=torch.float32, device=self.device)
        # time of the first update after a reset (-1 = none yet): no estimate until the window
        # is at least half full (a 0.1 s window holds sub-pixel motion only)
        self._t_start_us = torch.full((B,), -1, dtype=torch.int64, device=self.device)

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        mask = self._mask(mask)
        self._store = [tuple(f[~mask[s[0]]] for f in s) for s in self._store]
        self._d[mask] = float("nan")
        self._n_events[mask] = 0
        self._contrast[mask] = 0.0
        self._t_start_us[mask] = -1

    def _window_events(self, events, t_us: int):
        if events is not None and events.b.numel() > 0:
            fields = tuple(getattr(events, f).to(self.device) for f in ("b", "x", "y", "t"))
            self._store.append(self._cap_step(*fields))
        t0 = t_us - self.window_us
        self._store = [s for s in self._store if s[3].numel() > 0 and bool(s[3].max() > t0)]
        if not self._store:
            z = torch.zeros(0, dtype=torch.int64, device=self.device)
            return z, z, z, z
        b, x, y, t = (torch.cat(f) for f in zip(*self._store))
        keep = (t > t0) & (t <= t_us) & (b >= 0) & (b < self.batch_size)
        return b[keep], x[keep], y[keep], t[keep]

    def _cap_step(self, b, x, y, t):
        """Keep an even stride of at most max_events / (steps per window) events per element of
        one step's events, so the window never holds much more than max_events per element."""
        if self.max_events <= 0:
            return b, x, y, t
        steps = max(1, int(round(self.window_us / (self.dt_s * 1e6))))
        cap = max(1, self.max_events // steps)
        b_ok = b.clamp(0, self.batch_size - 1)
        n_per = torch.bincount(b_ok, minlength=self.batch_size)[: self.batch_size]
        if not bool((n_per > cap).any()):
            return b, x, y, t
        if b.numel() > 1 and not bool((b[1:] >= b[:-1]).all()):  # Events are sorted by (b, t); be safe
            order = torch.argsort(b, stable=True)
            b, x, y, t, b_ok = b[order], x[order], y[order], t[order], b_ok[order]
        start = torch.cumsum(n_per, 0) - n_per
        rank = torch.arange(b.numel(), device=b.device) - start[b_ok]
        stride = (n_per + cap - 1) // cap
        keep = (rank % stride[b_ok]) == 0
        return b[keep], x[keep], y[keep], t[keep]

    def _subsample(self, b, x, y, t, n_per):
        """Keep an even stride of at most max_events events per element (no loops)."""
        if self.max_events <= 0 or b.numel() == 0 or bool((n_per <= self.max_events).all()):
            return b, x, y, t
        order = torch.argsort(b, stable=True)
        b, x, y, t = b[order], x[order], y[order], t[order]
        start = torch.cumsum(n_per, 0) - n_per
        rank = torch.arange(b.numel(), device=b.device) - start[b]
        stride = (n_per + self.max_events - 1) // self.max_events
        keep = (rank % stride[b]) == 0
        return b[keep], x[keep], y[keep], t[keep]

    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        B = self.batch_size
        dev = self.device
        t_us = int(t_us)
        b, x, y, t = self._window_events(events, t_us)
        n_per = torch.bincount(b, minlength=B)[:B]
        self._n_events = n_per
        # the interval of this update began at the previous update (about t_us - dt)
        t_begin = t_us - int(round(self.dt_s * 1e6))
        self._t_start_us = torch.where(self._t_start_us < 0, torch.full_like(self._t_start_us, t_begin),
                                       self._t_start_us)
        filled = (t_us - self._t_start_us) * 2 >= self.window_us
        ok = (n_per >= self.min_events) & filled
        if not bool(ok.any()):
            self._d = torch.full((B,), float("nan"), dtype=torch.float32, device=dev)
            return self._d.clone()
        sel = ok[b]
        b, x, y, t = b[sel], x[sel], y[sel], t[sel]
        b, x, y, t = self._subsample(b, x, y, t, torch.where(ok, n_per, torch.zeros_like(n_per)))
        t_ref = t_us - self.window_us // 2
        tau = (t - t_ref).to(torch.float64).mul(1e-6).to(torch.float32)
        x = x.to(torch.float32)
        y = y.to(torch.float32)
        if self.dither:
            u = torch.rand(2, x.numel(), generator=self._gen).to(dev) - 0.5
            x = x + u[0]
            y = y + u[1]
        W, H = self.sensor_size
        kw = dict(sensor_hw=(H, W), pad_px=self.pad_px, blur_sigma_px=self.blur_sigma_px)

        grid = torch.linspace(self.d_min, self.d_max, self.n_grid, device=dev, dtype=torch.float32)
        cand = grid.unsqueeze(0).expand(B, -1)
        step = torch.full((B,), (self.d_max - self.d_min) / (self.n_grid - 1), device=dev)
        score = warped_contrast(x, y, b, tau, cand, **kw)
        for _ in range(self.n_refine):
            best = cand.gather(1, score.argmax(1, keepdim=True))  # (B, 1)
            off = torch.linspace(-1.0, 1.0, self.refine_points, device=dev)
            cand = best + step.unsqueeze(1) * off
            step = step * 2.0 / (self.refine_points - 1)
            score = warped_contrast(x, y, b, tau, cand, **kw)
        i = score.argmax(1)
        G = cand.shape[1]
        il, ir = (i - 1).clamp(0, G - 1), (i + 1).clamp(0, G - 1)
        s = lambda j: score.gather(1, j.unsqueeze(1)).squeeze(1)  # noqa: E731
        d_best = cand.gather(1, i.unsqueeze(1)).squeeze(1)
        interior = (i > 0) & (i < G - 1)
        spacing = (cand[:, -1] - cand[:, 0]) / (G - 1)
        off = torch.where(interior, _parabola_offset(s(il), s(i), s(ir)), torch.zeros_like(d_best))
        d = d_best + off * spacing
        self._contrast = s(i)
        self._d = torch.where(ok, d, torch.full_like(d, float("nan"))).to(torch.float32)
        return self._d.clone()

    def diagnostics(self):
        """n_events (B,) events in the window; contrast (B,) best variance."""
        return {"n_events": self._n_events.clone(), "contrast": self._contrast.clone()}
