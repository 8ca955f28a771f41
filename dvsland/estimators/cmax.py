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

6. **Noise floor.** Structureless events (sensor noise, a scene moving less than a pixel) score
   S0 = 4/9 x sum(w^2) / sum(w) whatever the warp (a dithered event's bilinear corner weights
   square-sum to (2/3)^2 on average; w the event weights). The structure of the estimate is
   S / S0 - 1 (``diagnostics()["structure"]``; 1.2-20 on the rendered sites through the ideal pixel,
   below 0.15 on three quarters of the estimates that were 50 % off or worse through the realistic
   one). It grows with the events per pixel, so on a sensor larger than 128 x 128, whose windows
   hold more events spread thinner (``max_events`` x :func:`sensor_scale`), it is multiplied by
   :func:`sensor_scale` (a binned 1280 x 720 sensor: 0.17 -> 0.64 on a correct estimate). At or
   below ``structure_none`` the estimate is NaN, the window goes back to ``window_ms`` and the
   next update searches globally (a wild estimate cannot shrink its own window into a trap
   of few, noise-dominated events); from ``structure_full`` on the confidence is unchanged, linear
   between.

After a reset an element gives NaN until its window is at least half full, whenever it has
fewer than ``min_events`` events in its window, and when its global search peaked at either end
of [``d_min``, ``d_max``] (no bracketed maximum: events that show no measurable motion).

As a stage (:mod:`dvsland.pytree`): the params are the config section
:class:`dvsland.config.schema.CMaxConfig`, the constants derived once from it, the sensor and the
batch a :class:`CMaxSetup`, the state between updates a :class:`CMaxState` (the stored events of all
descents packed, and per descent the warm start, the window, the trend history, the ring position
and the hash seeds), and the step the pure :func:`cmax_step`. :class:`CMaxEstimator` offers
``init_state`` / ``step_state`` / ``reset_where`` over them; its object API (``update``, ``reset``,
``confidence``, ``diagnostics``) is the base class's, holding one state.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from typing import Any, NamedTuple, Optional, Tuple

import torch

from dvsland.checks import check_fields, check_keys
from dvsland.config.schema import CMaxConfig
from dvsland.pytree import check_state_like, packed_append

from .base import DivergenceEstimator, EstimateOut, Truth, confidence_from_rel_std
from . import native_cmax
from .contrast import event_hash, fold_seed, pixel_counts, seed_term, split_contrast
from .registry import register_estimator

_I64, _F32, _F64 = torch.int64, torch.float32, torch.float64


class CMaxSetup(NamedTuple):
    """What ``cmax`` derives once from its params, the sensor and the batch (constant in flight).

    Attributes:
        batch_size: B.
        sensor_size: (W, H), px.
        centre: (cx, cy) the focus of expansion (principal point), px.
        dt_s: control interval, s.
        window_us: the first window (``window_ms``), int µs.
        max_events: events warped per element: ``max_events`` x max(1, sqrt(W H) / 128) (0 = all).
        r_max_px: farthest pixel centre from the FoE, px.
        pad_px: canvas margin, px (only events inside the sensor box shrunk about the FoE count,
            :func:`split_contrast`, so one pixel holds every counted bilinear weight).
        n_rbins: annuli of the radial weights (0 when off).
        rbin_of_px: (H W,) int64 annulus of each pixel centre (None when off).
        px_per_rbin: (n_rbins,) float64 pixels per annulus (None when off).
        device: torch device of the state.
    """

    batch_size: int
    sensor_size: Tuple[int, int]
    centre: Tuple[float, float]
    dt_s: float
    window_us: int
    max_events: int
    r_max_px: float
    pad_px: int
    n_rbins: int
    rbin_of_px: Optional[torch.Tensor]
    px_per_rbin: Optional[torch.Tensor]
    device: torch.device


class CMaxState(NamedTuple):
    """State of ``cmax`` for B descents between two updates.

    The stored events of recent steps, oldest first, of all descents together (packed; only what
    later windows may need), and one row per stored step:

    Attributes:
        ev_b_packed: (N,) int64 descent of each stored event.
        ev_x_packed, ev_y_packed: (N,) float32 event position, dithered within its pixel, px.
        ev_t_packed: (N,) int64 event time, µs.
        ev_key_packed: (N,) int64: bits 0-14 the window-thinning hash, bit 15 the half, from bit 16
            the event's pixel y W + x.
        step_start_packed: (S,) int64 index of each stored step's first event in the ev_ leaves.
        step_tmax_packed: (S,) int64 latest event time of each stored step, µs.
        d_mid: (B,) float64 last window-middle estimate, 1/s (the warm start; NaN = search globally).
        window_s: (B,) float64 window of the next update, s.
        t_start_us: (B,) int64 start of the descent's first interval since its (re)start, µs (-1 =
            not yet seen an update).
        hist_t: (B, trend_steps) float64 window-middle times of the trend history, s (a ring).
        hist_d: (B, trend_steps) float64 time-to-contact tau = -1 / D of those estimates, s (NaN =
            none, or not from a full window).
        hist_s: (B, trend_steps) float64 relative standard error of those estimates.
        k: (B,) int64 updates since :meth:`CMaxEstimator.init_state` (the ring's write position,
            k % trend_steps; kept by ``reset_where``, so the same for every descent).
        seed_thin: (B,) int64 folded (31-bit) seed of the store-thinning hash.
        seed_dither: (B,) int64 folded seed of the dither / window-thinning / half hash.
    """

    ev_b_packed: torch.Tensor
    ev_x_packed: torch.Tensor
    ev_y_packed: torch.Tensor
    ev_t_packed: torch.Tensor
    ev_key_packed: torch.Tensor
    step_start_packed: torch.Tensor
    step_tmax_packed: torch.Tensor
    d_mid: torch.Tensor
    window_s: torch.Tensor
    t_start_us: torch.Tensor
    hist_t: torch.Tensor
    hist_d: torch.Tensor
    hist_s: torch.Tensor
    k: torch.Tensor
    seed_thin: torch.Tensor
    seed_dither: torch.Tensor


_EVENT_FIELDS = ("ev_b_packed", "ev_x_packed", "ev_y_packed", "ev_t_packed", "ev_key_packed")
#: per-descent fields that ``reset_where`` restarts (``hist_t`` and ``k`` are kept: a ring position)
_RESTARTED = ("d_mid", "window_s", "t_start_us", "hist_d", "hist_s", "seed_thin", "seed_dither")


def _parabola_offset(s_left: torch.Tensor, s_mid: torch.Tensor, s_right: torch.Tensor,
                     limit: float = 0.5) -> torch.Tensor:
    """Vertex offset (in grid steps, within [-limit, limit]) of the parabola through three scores at
    -1, 0, +1; where the three are not concave, ``limit`` towards the higher side (0 if equal)."""
    den = s_left - 2 * s_mid + s_right
    off = 0.5 * (s_left - s_right) / torch.where(den.abs() > 0, den, torch.ones_like(den))
    uphill = torch.sign(s_right - s_left) * limit
    return torch.where(den < 0, off.clamp(-limit, limit), uphill)


# ------------------------------------------------------------------ setup and state
def sensor_scale(sensor_size: Tuple[int, int]) -> float:
    """max(1, sqrt(W H) / 128) of a (W, H) sensor: how much longer (in pixels) a scene's edges are than
    on the 128 x 128 sensor the defaults were set on. ``max_events`` grows by it, and so the events
    per pixel of a full window fall by it; the structure (module doc, step 6), which grows with the
    events per pixel, is multiplied by it (1 on 128 x 128 and smaller: the same bits there)."""
    W, H = int(sensor_size[0]), int(sensor_size[1])
    return max(1.0, math.sqrt(W * H) / 128.0)


def make_setup(p: CMaxConfig, batch_size: int, sensor_size: Tuple[int, int], centre: Tuple[float, float],
               dt_s: float, device: Any) -> CMaxSetup:
    """The :class:`CMaxSetup` of params ``p`` for B descents on a (W, H) sensor with FoE ``centre``."""
    W, H = int(sensor_size[0]), int(sensor_size[1])
    cx, cy = centre
    dev = torch.device(device)
    # events come from the scene's edges, whose length in pixels grows with the sensor's linear
    # size: a sensor larger than 128 x 128 keeps max_events x sqrt(W H) / 128 per element
    # (a 640 x 360 sensor with 4000 events had too few per edge pixel to show any structure)
    max_events = int(round(int(p.max_events) * sensor_scale((W, H))))
    n_rbins, rbin, per_bin = 0, None, None
    if p.radial_bin_px > 0:  # sensor pixels per annulus about the FoE
        yy, xx = torch.meshgrid(torch.arange(H, dtype=_F64), torch.arange(W, dtype=_F64), indexing="ij")
        rb = (torch.hypot(xx - cx, yy - cy) / p.radial_bin_px).floor().to(_I64).flatten()
        n_rbins = int(rb.max()) + 1
        rbin, per_bin = rb.to(dev), torch.bincount(rb, minlength=n_rbins).to(_F64).to(dev)
    r_max = math.hypot(max(cx, W - 1 - cx), max(cy, H - 1 - cy))
    return CMaxSetup(int(batch_size), (W, H), (float(cx), float(cy)), float(dt_s),
                     int(round(float(p.window_ms) * 1000.0)), max_events, r_max, 1, n_rbins, rbin, per_bin, dev)


def cmax_init_state(p: CMaxConfig, setup: CMaxSetup, seed: int = 0) -> CMaxState:
    """The state of B descents that have seen nothing; every descent's hash seeds from ``seed``
    (any int: the thinning hash takes ``seed``, the dither hash ``seed + 1``, each folded)."""
    B, dev, T = setup.batch_size, setup.device, int(p.trend_steps)
    i64, f64 = dict(dtype=_I64, device=dev), dict(dtype=_F64, device=dev)
    nan = float("nan")
    return CMaxState(
        torch.empty(0, **i64), torch.empty(0, dtype=_F32, device=dev), torch.empty(0, dtype=_F32, device=dev),
        torch.empty(0, **i64), torch.empty(0, **i64), torch.empty(0, **i64), torch.empty(0, **i64),
        d_mid=torch.full((B,), nan, **f64), window_s=torch.full((B,), setup.window_us * 1e-6, **f64),
        t_start_us=torch.full((B,), -1, **i64), hist_t=torch.zeros(B, T, **f64), hist_d=torch.full((B, T), nan, **f64),
        hist_s=torch.full((B, T), nan, **f64), k=torch.zeros(B, **i64),
        seed_thin=torch.full((B,), fold_seed(seed), **i64),
        seed_dither=torch.full((B,), fold_seed(int(seed) + 1), **i64))


def cmax_reset_where(state: CMaxState, mask: torch.Tensor, fresh: CMaxState) -> CMaxState:
    """``state`` with the descents where ``mask`` (B,) bool is True restarted (their stored events
    dropped, their fields from ``fresh``, a state of :func:`cmax_init_state`); the others unchanged.
    A stored step left without events is dropped."""
    b = state.ev_b_packed
    keep = ~mask[b]
    out = {}
    if b.numel() and not bool(keep.all()):
        cum = torch.cat([torch.zeros(1, dtype=_I64, device=b.device), torch.cumsum(keep.to(_I64), 0)])
        starts = state.step_start_packed
        ends = torch.cat([starts[1:], torch.full((1,), b.numel(), dtype=_I64, device=b.device)])
        new_start, new_end = cum[starts], cum[ends]
        live = new_end > new_start
        sel = keep.nonzero().squeeze(1)
        out = {f: getattr(state, f).index_select(0, sel) for f in _EVENT_FIELDS}
        out.update(step_start_packed=new_start[live], step_tmax_packed=state.step_tmax_packed[live])
    for f in _RESTARTED:
        old, new = getattr(state, f), getattr(fresh, f)
        m = mask.view((-1,) + (1,) * (old.dim() - 1))
        out[f] = torch.where(m, new, old)
    return state._replace(**out)


# ------------------------------------------------------------------ the event store
def store_keep(p: CMaxConfig, setup: CMaxSetup, state: CMaxState, b, x, y, t) -> torch.Tensor:
    """(K,) int64 indices of the step's events kept: on the sensor and in the batch, and (with
    ``max_events``) passing the hash thinning to about 1.25 max_events / (steps per window) per
    element. The compiled kernel (:mod:`native_cmax`) keeps the same events."""
    W, H = setup.sensor_size
    B, max_events = setup.batch_size, setup.max_events
    steps_per_window = (state.window_s / setup.dt_s).clamp_min(1.0)
    cap = (1.25 * max_events / steps_per_window).ceil() if max_events > 0 else \
        torch.full((B,), float("inf"), dtype=_F64, device=b.device)
    mod = native_cmax.kernel_for(b) if b.numel() else None
    if mod is not None:
        i64 = [v.to(_I64).contiguous() for v in (b, x, y, t)]
        return mod.store_select(*i64, cap.to(_F64).contiguous(), W, H, seed_term(state.seed_thin).contiguous())
    ok = (b >= 0) & (b < B) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
    if max_events > 0:
        h = event_hash(b, x, y, t, state.seed_thin[b.clamp(0, B - 1)])
        n_per = torch.bincount(torch.where(ok, b, torch.zeros_like(b)), weights=ok.to(_F64), minlength=B)[:B]
        frac = (cap / n_per.clamp_min(1)).clamp(max=1.0)
        ok &= (h & 0xFFFF).to(_F64) < frac[b.clamp(0, B - 1)] * 65536.0
    return ok.nonzero().squeeze(1)


def _store(p: CMaxConfig, setup: CMaxSetup, state: CMaxState, events) -> CMaxState:
    """``state`` with the step's kept events (:func:`store_keep`) appended as one stored step, with
    what every later update needs: descent, dithered position, time, and the key (a 16-bit hash
    of the dither seed: window thinning and half bit; the event's pixel y W + x above them)."""
    dev = setup.device
    b, x, y, t = (getattr(events, f).to(dev) for f in ("b", "x", "y", "t"))
    keep = store_keep(p, setup, state, b, x, y, t)
    if keep.numel() == 0:
        return state
    b, x, y, t = (v.index_select(0, keep) for v in (b, x, y, t))
    b, t = b.to(_I64), t.to(_I64)
    h2 = event_hash(b, x, y, t, state.seed_dither.index_select(0, b))
    xf, yf = x.to(_F32), y.to(_F32)
    if p.dither:  # uniform within the pixel: 8 and 7 fresh hash bits
        xf = xf + (((h2 >> 16) & 0xFF).to(_F32) / 256.0 - 0.5)
        yf = yf + (((h2 >> 24) & 0x7F).to(_F32) / 128.0 - 0.5)
    key = (h2 & 0xFFFF) | ((y.to(_I64) * setup.sensor_size[0] + x.to(_I64)) << 16)
    n_old = state.ev_b_packed.numel()
    new = dict(zip(_EVENT_FIELDS, (b, xf, yf, t, key)))
    out = {f: packed_append(getattr(state, f), v) for f, v in new.items()}  # no copy of the store
    start = torch.full((1,), n_old, dtype=_I64, device=dev)
    out.update(step_start_packed=torch.cat([state.step_start_packed, start]),
               step_tmax_packed=torch.cat([state.step_tmax_packed, t.max().view(1)]))
    return state._replace(**out)


def _prune(state: CMaxState, t_us: int) -> CMaxState:
    """``state`` without its oldest stored steps: those whose latest event is at least the longest
    current window before ``t_us`` (up to the first step that is not)."""
    n_steps = state.step_tmax_packed.numel()
    if n_steps == 0:
        return state
    keep_us = torch.ceil(state.window_s.max() * 1e6).to(_I64)
    old = state.step_tmax_packed <= t_us - keep_us
    n_pop_t = old.to(_I64).cumprod(0).sum()
    starts = torch.cat([state.step_start_packed, state.step_start_packed.new_tensor([state.ev_b_packed.numel()])])
    n_pop, lo = torch.stack([n_pop_t, starts[n_pop_t]]).tolist()  # one host sync: steps and events to drop
    if n_pop == 0:
        return state
    out = {f: getattr(state, f)[lo:] for f in _EVENT_FIELDS}
    return state._replace(step_start_packed=state.step_start_packed[n_pop:] - lo,
                          step_tmax_packed=state.step_tmax_packed[n_pop:], **out)


def _window_since(state: CMaxState, t_us: int) -> torch.Tensor:
    """(B,) int64 each element's window start (excluded), µs."""
    return t_us - (state.window_s * 1e6).round().to(_I64)


def _window_mask(setup: CMaxSetup, state: CMaxState, t_us: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """(inw (N,) bool: which stored events lie in their element's window, hash-thinned to
    max_events; n_per (B,) int64 events in each window before the thinning). The torch path."""
    B = setup.batch_size
    b, t, key = state.ev_b_packed, state.ev_t_packed, state.ev_key_packed
    if b.numel() == 0:
        return torch.zeros(0, dtype=torch.bool, device=b.device), torch.zeros(B, dtype=_I64, device=b.device)
    inw = (t > _window_since(state, t_us).index_select(0, b)) & (t <= t_us)
    n_per = torch.bincount(b, weights=inw.to(_F32), minlength=B)[:B]
    if setup.max_events > 0:
        frac = (setup.max_events / n_per.clamp_min(1)).clamp(max=1.0)
        inw &= (key & 0x7FFF).to(_F32) < (frac * 32768.0).index_select(0, b)
    return inw, n_per.round().to(_I64)


def _gather(state: CMaxState, mask: torch.Tensor, ok: Optional[torch.Tensor], t_ref_us: torch.Tensor, pad: int):
    """The stored events where ``mask`` (N,) bool holds, and ``ok`` (B,) bool of their element (None:
    every element), in store order, as the score takes them: (b (E,) int64; xc, yc (E,) float32 the
    canvas coordinates, x and y plus the margin ``pad`` px; tau (E,) float32 s after the element's
    reference time ``t_ref_us`` (B,) int64; half (E,) int64 the half-split bit; pix (E,) int64 the
    pixel y W + x). The torch path."""
    fields = [getattr(state, f) for f in _EVENT_FIELDS]
    if ok is not None:
        mask = mask & ok.index_select(0, fields[0])
    sel = mask.nonzero().squeeze(1)
    b, x, y, t, key = (v.index_select(0, sel) for v in fields)
    tau = (t - t_ref_us.index_select(0, b)).to(_F32) * 1e-6
    return b, x + pad, y + pad, tau, (key >> 15) & 1, key >> 16


def _window_events(p: CMaxConfig, setup: CMaxSetup, state: CMaxState, t_us: int, filled: torch.Tensor):
    """Each element's window over the stored events: (n_per (B,) int64 its events before the thinning;
    ok (B,) bool the elements that estimate, with at least ``min_events`` and a ``filled`` first window;
    their kept events as the score takes them (:func:`_gather`), or None where no element estimates).
    The compiled kernel: two passes over the store. One host read either way."""
    t_ref_us = (t_us - state.window_s * 0.5e6).round().to(_I64)  # (B,) each window's middle
    b = state.ev_b_packed
    mod = native_cmax.kernel_for(b) if b.numel() else None
    if mod is not None:
        fields = [getattr(state, f).contiguous() for f in _EVENT_FIELDS]
        n_f, ev = mod.window_gather(*fields, _window_since(state, t_us).contiguous(), t_us, setup.max_events,
                                    filled.contiguous(), p.min_events, t_ref_us.contiguous(), setup.pad_px)
        n_per = n_f.round().to(_I64)
        ok = (n_per >= p.min_events) & filled
        return n_per, ok, (ev if bool(ok.any()) else None)
    inw, n_per = _window_mask(setup, state, t_us)
    ok = (n_per >= p.min_events) & filled
    any_ok, all_ok = torch.stack([ok.any(), ok.all()]).tolist()  # one host sync for both
    if not any_ok:
        return n_per, ok, None
    return n_per, ok, _gather(state, inw, None if all_ok else ok, t_ref_us, setup.pad_px)


# ------------------------------------------------------------------ event weights
def hot_pixel_weights(p: CMaxConfig, setup: CMaxSetup, pix: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(E,) float32 weights of the events of hot pixels: a pixel holding c events, more than
    ``hot_pixel_factor`` times its element's mean count per active pixel m, weighs m / c per
    event (all of its events together count as one ordinary pixel), else 1. m is the mean over
    the pixels not flagged by a first mean (hot pixels inflate it). A hot pixel, or any pattern
    fixed to the sensor, then no longer pulls the estimate to D = 0. ``pix``: (E,) int64 pixel
    y W + x of each event; ``b``: (E,) int64 its element. The compiled kernel gives the same weights."""
    W, H = setup.sensor_size
    B = setup.batch_size
    mod = native_cmax.kernel_for(b) if b.numel() else None
    if mod is not None:
        return mod.hot_weights(b.contiguous(), pix.contiguous(), B, H * W, float(p.hot_pixel_factor))
    c = pixel_counts(b, pix, B, H * W, native=False).to(_F64)  # (E,) events at its pixel
    mean = torch.zeros(B, dtype=_F64, device=c.device)
    keep = torch.ones_like(c, dtype=torch.bool)
    for _ in range(2):  # mean count per active pixel, then again without the flagged pixels
        n_px = torch.bincount(b, weights=keep.to(_F64) / c, minlength=B)[:B]
        n_ev = torch.bincount(b, weights=keep.to(_F64), minlength=B)[:B]
        mean = n_ev / n_px.clamp_min(1e-9)
        keep = c <= p.hot_pixel_factor * mean[b]
    return torch.where(keep, torch.ones_like(c), mean[b] / c).to(_F32)


def radial_weights(p: CMaxConfig, setup: CMaxSetup, pix: torch.Tensor, b: torch.Tensor,
                   times: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(E,) float32 weights that flatten each element's event density over radius about the FoE.

    The event rate of a pixel grows with its image speed, D r: events crowd towards the edges
    of the sensor in a pattern fixed to the sensor, not to the scene, and such a pattern is
    sharpest un-warped (D = 0), which pulls the estimate towards 0. Weighting each event by
    the inverse of its element's event density in its annulus (``radial_bin_px`` wide)
    removes that pull. The weight is that inverse to the power ``radial_power``: 1 over-
    corrects on the rendered sites (|D| read about 1 % high), 0.5 leaves no bias there. An event's
    annulus is its pixel centre's (``pix``: (E,) int64 y W + x). With ``times`` (E,) float32, the
    weights times it (float32). The compiled kernel gives the same weights."""
    nb, B = setup.n_rbins, setup.batch_size
    mod = native_cmax.kernel_for(b) if b.numel() else None
    if mod is not None:
        b, pix = b.contiguous(), pix.contiguous()
        cnt = mod.radial_counts(b, pix, setup.rbin_of_px, B, nb)
    else:
        key = b * nb + setup.rbin_of_px.index_select(0, pix)
        cnt = torch.bincount(key, minlength=B * nb)[: B * nb]
    dens = cnt.view(B, nb).to(_F64) / setup.px_per_rbin.clamp_min(1)
    mean = dens.sum(1) / (dens > 0).sum(1).clamp_min(1)
    w = (mean.unsqueeze(1) / dens.clamp_min(1e-12)).pow(p.radial_power).clamp(0.1, 10.0)
    if mod is not None:
        return mod.radial_apply(b, pix, setup.rbin_of_px, w.view(-1), nb, times)
    w = w.view(-1).index_select(0, key).to(_F32)
    return w if times is None else w * times


def _event_weights(p: CMaxConfig, setup: CMaxSetup, pix: torch.Tensor, b: torch.Tensor) -> Optional[torch.Tensor]:
    """(E,) float32 radial x hot-pixel weights of the window's events, or None (all 1)."""
    hot = hot_pixel_weights(p, setup, pix, b) if p.hot_pixel_factor > 0 else None
    if p.radial_bin_px > 0 and p.radial_power > 0:
        return radial_weights(p, setup, pix, b, times=hot)
    return hot


# ------------------------------------------------------------------ search
def _score(setup: CMaxSetup, xs, ys, b, half, tau, cand, half_window_s, wt=None) -> torch.Tensor:
    """(n, G, 3) float64 :func:`split_contrast` of the events on the canvas (xs, ys with the
    margin ``pad_px`` added) for candidates ``cand`` (n, G)."""
    cx, cy = setup.centre
    W, H = setup.sensor_size
    pad = setup.pad_px
    box = (pad - 0.5, pad + W - 0.5, pad - 0.5, pad + H - 0.5)
    return split_contrast(xs, ys, b, half, tau, cand, (cx + pad, cy + pad), (H + 2 * pad, W + 2 * pad),
                          box, half_window_s, wt)


def _global_search(p: CMaxConfig, setup: CMaxSetup, xs, ys, b, half, tau, sel_el, win_s, wt):
    """Grid search (+ refinement) for elements ``sel_el`` (B,) bool: ((B,) float64 D, NaN
    elsewhere; (B,) bool where the grid's maximum lay at either end of [d_min, d_max]). xs, ys
    are canvas coordinates (:func:`_gather`).

    Each round scores the events of only the newest part of the window in which candidates one
    grid step apart move an event at the sensor's edge by at most 2 px (the whole window once
    the steps are fine): a peak of the score is then wider than the grid and cannot fall
    between its points (on the full window at |D| ~ 0.05 1/s it did, and the grid's maximum
    was noise)."""
    B, dev = setup.batch_size, setup.device
    idx = sel_el.nonzero().squeeze(1)
    n = idx.numel()
    remap = torch.full((B,), -1, dtype=_I64, device=dev).index_put((idx,), torch.arange(n, device=dev))
    e = sel_el.index_select(0, b).nonzero().squeeze(1)  # the events of those elements
    bs = remap.index_select(0, b.index_select(0, e))
    xe, ye, he, te = (v.index_select(0, e) for v in (xs, ys, half, tau))
    we = torch.ones_like(te) if wt is None else wt.index_select(0, e)
    win, half_w = win_s[idx], 0.5 * win_s[idx]
    grid = torch.linspace(p.d_min, p.d_max, p.n_grid, device=dev, dtype=_F64)
    cand = grid.unsqueeze(0).expand(n, -1)
    step = (p.d_max - p.d_min) / (p.n_grid - 1)

    def score(cand, step):
        # the newest span of each window, s, re-centred on its own middle
        span = (2.0 / (step * max(setup.r_max_px, 1.0)) / win).clamp(max=1.0) * win
        shift = (half_w - 0.5 * span).index_select(0, bs).to(te.dtype)
        recent = (te >= 2 * shift - half_w.index_select(0, bs).to(te.dtype)).to(we.dtype)
        return _score(setup, xe, ye, bs, he, te - shift, cand, 0.5 * span, we * recent)[..., 0]

    sc = score(cand, step)
    # a grid maximum at either end of [d_min, d_max] is no bracketed maximum (the score keeps
    # rising out of the range: what events without a measurable motion give): no estimate
    first = sc.argmax(1)
    edge = torch.zeros(B, dtype=torch.bool, device=dev).index_put((idx,), (first == 0) | (first == p.n_grid - 1))
    off = torch.linspace(-1.0, 1.0, p.refine_points, device=dev, dtype=_F64)
    for _ in range(p.n_refine):
        best = cand.gather(1, sc.argmax(1, keepdim=True))
        cand = best + step * off
        step = step * 2.0 / (p.refine_points - 1)
        sc = score(cand, step)
    best = cand.gather(1, sc.argmax(1, keepdim=True)).squeeze(1)
    return torch.full((B,), float("nan"), dtype=_F64, device=dev).index_put((idx,), best), edge


def _newton(p: CMaxConfig, setup: CMaxSetup, xs, ys, b, half, tau, d0, win_s, wt):
    """``newton_iters`` rounds from d0 (B,) float64: three candidates d0 - h, d0, d0 + h (h =
    step_motion / T, halved each round), the parabola's vertex the next d0. Returns (d (B,),
    sigma (B,) half-split standard error, sigma_step (B,) the same, at least 2 h where the maximum
    is not bracketed, contrast (B,) float32 score at d0, bracketed (B,) bool) of the last round."""
    hstep = p.step_motion / win_s
    three = torch.tensor([-1.0, 0.0, 1.0], dtype=_F64, device=setup.device)
    for _ in range(p.newton_iters):
        cand = d0.unsqueeze(1) + hstep.unsqueeze(1) * three
        sc = _score(setup, xs, ys, b, half, tau, cand, 0.5 * win_s, wt)  # (B, 3 candidates, 3: all, halves)
        off = _parabola_offset(sc[:, 0], sc[:, 1], sc[:, 2], 2.0)  # (B, 3): all events, each half
        d_last, h_last = d0, hstep
        d0, hstep = d0 + off[:, 0] * hstep, hstep * 0.5
    d_halves = d_last.unsqueeze(1) + off[:, 1:] * h_last.unsqueeze(1)  # (B, 2)
    sigma = (d_halves[:, 0] - d_halves[:, 1]).abs() * 0.5
    # the maximum is bracketed when the scores of all events and of both halves are concave with
    # their vertex within the three candidates; where it is not, the estimate has not converged
    # and is uncertain by at least the bracket, 2 h
    den = sc[:, 0] - 2 * sc[:, 1] + sc[:, 2]  # (B, 3)
    vtx = 0.5 * (sc[:, 0] - sc[:, 2]) / torch.where(den < 0, den, -torch.ones_like(den))
    bracketed = ((den < 0) & (vtx.abs() <= 1.0)).all(1)
    sigma_step = torch.where(bracketed, sigma, torch.maximum(sigma, 2.0 * h_last))
    return d0, sigma, sigma_step, sc[:, 1, 0].to(_F32), bracketed


# ------------------------------------------------------------------ lag correction
def _slope(p: CMaxConfig, hist_t: torch.Tensor, hist_d: torch.Tensor):
    """Least-squares slope d tau / dt (B,) of the window-middle time-to-contact in the history
    (0 where fewer than half of the history is filled or the sign of D changed in it), and
    (B,) bool where it is known (not 0 for those reasons)."""
    ok = torch.isfinite(hist_d)
    n = ok.sum(1).to(_F64)
    w = ok.to(_F64)
    tt = torch.where(ok, hist_t, torch.zeros_like(hist_t))
    dd = torch.where(ok, hist_d, torch.zeros_like(hist_d))
    tm = (tt * w).sum(1) / n.clamp_min(1)
    dm = (dd * w).sum(1) / n.clamp_min(1)
    ct = (tt - tm.unsqueeze(1)) * w
    var = (ct * ct).sum(1)
    slope = (ct * (dd - dm.unsqueeze(1))).sum(1) / var.clamp_min(1e-12)
    same_sign = (torch.where(ok, torch.sign(hist_d), torch.zeros_like(hist_d)).sum(1).abs() == n)
    # the line must describe tau: RMS residual within trend_tol of the mean |tau|
    res = torch.where(ok, dd - dm.unsqueeze(1) - slope.unsqueeze(1) * (tt - tm.unsqueeze(1)), torch.zeros_like(dd))
    rms = ((res * res).sum(1) / n.clamp_min(1)).sqrt()
    linear = rms <= p.trend_tol * dm.abs() if p.trend_tol > 0 else torch.ones_like(same_sign)
    use = (n >= max(3, p.trend_steps // 2)) & (var > 0) & same_sign & linear
    return torch.where(use, slope, torch.zeros_like(slope)), use


def _smoothed_tau(p: CMaxConfig, hist_t, hist_d, hist_s, age, slope: torch.Tensor, t_end_s: float) -> torch.Tensor:
    """(B,) time-to-contact at ``t_end_s``: the mean over the last ``smooth_steps`` window-middle
    estimates (``age`` (B, T) int64, 0 = the newest) of tau_k + slope (t_end - t_k), i.e. the line
    of the trend slope through their centroid (weights 1 / rel. std^2 with ``smooth_by_std``).
    No lag where tau is linear over the trend history; NaN where none of them is finite."""
    tau = hist_d + slope.unsqueeze(1) * (t_end_s - hist_t)
    ok = torch.isfinite(tau) & (age < p.smooth_steps)
    w = ok.to(_F64)
    if p.smooth_by_std:
        rel = hist_s.nan_to_num(1.0).clamp_min(1e-3)
        w = w / (rel * rel)
    return (torch.where(ok, tau, torch.zeros_like(tau)) * w).sum(1) / w.sum(1)


def _extrapolate(p: CMaxConfig, hist_t, hist_d, hist_s, age, d_mid, t_mid, rel_std, t_end_s: float):
    """(B,) float64 D carried from the window middle ``t_mid`` to ``t_end_s`` along the trend of
    tau (module doc, step 4); ``d_mid`` where that is not safe."""
    tau_mid = -1.0 / d_mid
    slope, trend = _slope(p, hist_t, hist_d)
    tau_end = tau_mid + slope * (t_end_s - t_mid)
    if p.smooth_steps > 1:  # only where the trend is known (no lag from averaging)
        tau_s = _smoothed_tau(p, hist_t, hist_d, hist_s, age, slope, t_end_s)
        if p.smooth_clip > 0:  # at most smooth_clip standard errors from this estimate
            lim = p.smooth_clip * rel_std * tau_end.abs()
            tau_s = torch.minimum(torch.maximum(tau_s, tau_end - lim), tau_end + lim)
        tau_end = torch.where(trend & torch.isfinite(tau_s), tau_s, tau_end)
    safe = torch.isfinite(tau_end) & (tau_end * tau_mid > 0) & ((tau_end - tau_mid).abs() < 0.5 * tau_mid.abs())
    return torch.where(safe, -1.0 / tau_end, d_mid)


def _next_window(p: CMaxConfig, setup: CMaxSetup, window_s, d_mid: torch.Tensor, untrusted: torch.Tensor):
    """(B,) float64 next window, s: kappa / |D| within [window_min, window_max], grown by at
    most ``window_growth`` per update; an untrusted estimate (near zero, its halves
    disagreeing, or at the noise floor) sets it back to ``window_ms``, so that neither a
    near-zero estimate stretches the window to the slowest motion it could mean nor a wild one
    shrinks it; no estimate keeps it."""
    w = (p.window_motion / d_mid.abs().clamp_min(1e-9)).clamp(p.window_min_ms * 1e-3, p.window_max_ms * 1e-3)
    w = torch.minimum(w, window_s * p.window_growth)
    w = torch.where(untrusted, torch.full_like(w, setup.window_us * 1e-6), w)
    return torch.where(torch.isfinite(d_mid) | untrusted, w, window_s)


#: the score of structureless, dithered unit-weight events (module doc, step 6)
NOISE_FLOOR_SCORE = 4.0 / 9.0


def _noise_floor(b: torch.Tensor, wt: Optional[torch.Tensor], B: int, device) -> torch.Tensor:
    """(B,) float64 score of structureless events with the window's weights ``wt`` (E,) (None =
    1): 4/9 sum(w^2) / sum(w) per element (4/9 where it holds no event)."""
    if wt is None:
        return torch.full((B,), NOISE_FLOOR_SCORE, dtype=_F64, device=device)
    kern = native_cmax.kernel_for(b) if wt.dtype == torch.float32 and wt.device == b.device else None
    if kern is not None:  # both sums in one compiled pass, in event order: the same bits
        s1, s2 = kern.weight_sums(b.contiguous(), wt.contiguous(), B)
    else:
        w = wt.to(_F64)
        s1 = torch.zeros(B, dtype=_F64, device=device).index_add_(0, b, w)
        s2 = torch.zeros(B, dtype=_F64, device=device).index_add_(0, b, w * w)
    return torch.where(s1 > 0, NOISE_FLOOR_SCORE * s2 / s1.clamp_min(1e-30), torch.full_like(s1, NOISE_FLOOR_SCORE))


def structure_factor(p: CMaxConfig, structure: torch.Tensor) -> torch.Tensor:
    """(B,) float64 confidence factor of the noise-floor test (module doc, step 6) from the
    structure S / S0 - 1 (B,): 0 at or below ``structure_none``, 1 from ``structure_full`` on,
    linear between; 1 everywhere when the test is off (``structure_full`` = 0 or no dither)."""
    s = structure.to(_F64)
    if p.structure_full <= 0 or not p.dither:
        return torch.ones_like(s)
    lo, hi = float(p.structure_none), float(p.structure_full)
    ramp = ((s - lo) / max(hi - lo, 1e-12)).clamp(0.0, 1.0) if hi > lo else (s > lo).to(_F64)
    return torch.where(torch.isnan(s), torch.ones_like(s), ramp)


def _history(p: CMaxConfig, state: CMaxState, t_us: int, d_mid, sigma_step, win_s, t_start):
    """The trend history with this update's (window-middle time, tau, relative standard error)
    written at slot k % trend_steps: (hist_t, hist_d, hist_s, age (B, T) int64 (0 = this
    update), t_mid (B,) s, rel_std (B,) the RMS relative standard error of the last
    ``smooth_steps`` estimates (NaN without an estimate))."""
    T = p.trend_steps
    j = (state.k % T).unsqueeze(1)  # (B, 1)
    slots = torch.arange(T, device=j.device)
    here = slots.unsqueeze(0) == j
    # tagged with the middle of the events actually held (the first windows after a reset are not full yet)
    since_s = (t_us - t_start).to(_F64) * 1e-6
    t_mid = t_us * 1e-6 - 0.5 * torch.minimum(win_s, since_s)
    # only estimates from full windows enter the trend: the first ones after a reset are from
    # shorter windows, with less motion in them (read towards D = 0 at high altitude), and as
    # tau = -1 / D they would tilt the trend line
    full = since_s >= win_s - 1e-6
    tau = torch.where(full, -1.0 / d_mid, torch.full_like(d_mid, float("nan")))
    hist_t = torch.where(here, t_mid.unsqueeze(1), state.hist_t)
    hist_d = torch.where(here, tau.unsqueeze(1), state.hist_d)
    hist_s = torch.where(here, (sigma_step / d_mid.abs()).unsqueeze(1), state.hist_s)  # rel. std of tau (= of D)
    age = (j - slots) % T
    rs = torch.where(age < max(p.smooth_steps, 1), hist_s, torch.nan)
    fin = torch.isfinite(rs)
    rel_rms = ((rs.nan_to_num(0.0) ** 2).sum(1) / fin.sum(1).clamp_min(1)).sqrt()
    rel_std = torch.where(fin.any(1) & torch.isfinite(d_mid), rel_rms, torch.full_like(rel_rms, float("nan")))
    return hist_t, hist_d, hist_s, age, t_mid, rel_std


# ------------------------------------------------------------------ the step
def _estimate_out(d: torch.Tensor, rel_std: torch.Tensor, n_events, contrast, window_s, global_search,
                  bracketed, structure: torch.Tensor, factor: Optional[torch.Tensor] = None) -> EstimateOut:
    """The step's :class:`EstimateOut` (d (B,) float32 D_hat; the confidence times the noise
    floor's ``factor`` (B,), None = 1; diagnostics documented at :meth:`CMaxEstimator.step_state`)."""
    conf = confidence_from_rel_std(rel_std, d)
    if factor is not None:
        conf = conf * factor.to(conf.dtype)
    diag = {"n_events": n_events, "contrast": contrast, "structure": structure.to(_F32), "window_s": window_s.clone(),
            "d_std": rel_std * d.to(_F64).abs(), "global_search": global_search, "bracketed": bracketed,
            "confidence": conf}
    return EstimateOut(d, conf, diag)


def blank_out(state: CMaxState, n_events: Optional[torch.Tensor] = None) -> EstimateOut:
    """The :class:`EstimateOut` of B descents without an estimate (NaN, confidence 0, contrast 0,
    no search), with ``n_events`` (B,) int64 (default 0) and the state's window."""
    B, dev = state.d_mid.shape[0], state.d_mid.device
    nan = torch.full((B,), float("nan"), dtype=_F32, device=dev)
    no = torch.zeros(B, dtype=torch.bool, device=dev)
    n = torch.zeros(B, dtype=_I64, device=dev) if n_events is None else n_events
    return _estimate_out(nan, torch.full((B,), float("nan"), dtype=_F64, device=dev), n,
                         torch.zeros(B, dtype=_F32, device=dev), state.window_s, no, no.clone(), nan.clone())


def _search(p: CMaxConfig, setup: CMaxSetup, state: CMaxState, ev, ok):
    """Warm start (or global search) and Newton rounds on the window's events ``ev`` (:func:`_gather`'s
    b, xc, yc, tau, half, pix) of the elements ``ok``: (d0 (B,) float64, need (B,) bool searched
    globally, edge (B,) bool global maximum at a range end, sigma, sigma_step, contrast, bracketed;
    see :func:`_newton`; then the noise floor (B,) float64 of the window's events, :func:`_noise_floor`)."""
    b, xs, ys, tau, half, pix = ev
    win_s = state.window_s
    wt = _event_weights(p, setup, pix, b)
    # start: last estimate (warm), else the global search
    d0 = state.d_mid
    need = ok & ~torch.isfinite(d0)
    edge = torch.zeros_like(need)
    if bool(need.any()):
        d_glob, edge = _global_search(p, setup, xs, ys, b, half, tau, need, win_s, wt)
        d0 = torch.where(need, d_glob, d0)
    out = _newton(p, setup, xs, ys, b, half, tau, d0.nan_to_num(0.0), win_s, wt)
    return (out[0], need, edge) + out[1:] + (_noise_floor(b, wt, d0.shape[0], d0.device),)


@torch.no_grad()
def cmax_step(p: CMaxConfig, state: CMaxState, events, t_us: int, setup: CMaxSetup) -> Tuple[CMaxState, EstimateOut]:
    """Pure step of ``cmax`` (module doc): (next state, :class:`EstimateOut`) after the events of
    the last interval (:class:`dvsland.events.Events` or None), ending at ``t_us`` (int µs).
    ``state`` is left unchanged."""
    t_us = int(t_us)
    if events is not None and events.b.numel() > 0:
        state = _store(p, setup, state, events)
    state = _prune(state, t_us)
    t_begin = t_us - int(round(setup.dt_s * 1e6))
    t_start = torch.where(state.t_start_us < 0, torch.full_like(state.t_start_us, t_begin), state.t_start_us)
    state = state._replace(t_start_us=t_start)
    # half of the first window must have passed since the reset (later windows, longer or
    # shorter, simply hold what there is)
    filled = (t_us - t_start).to(_F64) * 2e-6 >= setup.window_us * 1e-6 - 1e-9
    n_per, ok, ev = _window_events(p, setup, state, t_us, filled)  # the estimating elements' events
    if ev is None:
        return state, blank_out(state, n_per)
    d0, need, edge, sigma, sigma_step, contrast, bracketed, floor = _search(p, setup, state, ev, ok)
    win_s = state.window_s
    structure = torch.where(ok, contrast.to(_F64) / floor - 1.0, torch.full_like(floor, float("nan")))
    scale = sensor_scale(setup.sensor_size)
    if scale != 1.0:  # the events per pixel of a 128 x 128 sensor's window (sensor_scale)
        structure = structure * scale
    factor = structure_factor(p, structure)
    floored = ok & (factor <= 0)  # at the noise floor: no estimate, and not trusted (step 6)
    good = ok & (d0 >= p.d_min) & (d0 <= p.d_max) & ~(need & edge) & ~floored
    nan = torch.full_like(d0, float("nan"))
    d_mid = torch.where(good, d0, nan)
    # keep the last estimate of elements with too few events this step (warm start later); drop it
    # where the estimate left [d_min, d_max] (search globally next time). An estimate whose two
    # halves disagree by more than research_rel of |D| (floored at 5 first Newton steps, so that D
    # near 0 does not count as lost) is not trusted as a warm start, nor one near zero (where the
    # warm start locks: a static pattern, or motion below a pixel, is sharpest un-warped)
    lost = ok & (sigma > p.research_rel * torch.maximum(d_mid.abs(), 5.0 * p.step_motion / win_s))
    zero = ok & (d_mid.abs() < p.research_zero * p.step_motion / win_s)
    d_next = torch.where(lost | zero | floored, nan, torch.where(ok, d_mid, state.d_mid))
    hist_t, hist_d, hist_s, age, t_mid, rel_std = _history(p, state, t_us, d_mid, sigma_step, win_s, t_start)
    d_out = d_mid
    if p.extrapolate:  # time-to-contact tau = -1 / D, extrapolated linearly over the half window
        d_out = _extrapolate(p, hist_t, hist_d, hist_s, age, d_mid, t_mid, rel_std, t_us * 1e-6)
    window_s = _next_window(p, setup, win_s, d_mid, lost | zero | floored) if p.window_motion > 0 else win_s
    d = torch.where(good, d_out, nan).to(_F32)
    state = state._replace(d_mid=d_next, window_s=window_s, hist_t=hist_t, hist_d=hist_d, hist_s=hist_s, k=state.k + 1)
    return state, _estimate_out(d, rel_std, n_per, contrast, window_s, need, bracketed, structure, factor)


def _coerce(f: dataclasses.Field, value):
    """A keyword value as its schema field's type (float / int / bool), as the settings always were."""
    kind = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
    return {"float": float, "int": int, "bool": bool}.get(kind, lambda v: v)(value)


def cmax_params(**kw) -> CMaxConfig:
    """The :class:`CMaxConfig` of keyword settings (defaults for those not given), checked: the
    schema's ranges, and the rules between fields. Raises ValueError naming the field."""
    fields = {f.name: f for f in dataclasses.fields(CMaxConfig)}
    check_keys("estimator 'cmax'", kw, list(fields))
    check_fields(CMaxConfig, **kw)
    p = CMaxConfig(**{k: _coerce(fields[k], v) for k, v in kw.items()})
    for name, ok, rng in (("smooth_steps", p.smooth_steps <= p.trend_steps, "<= trend_steps"),
                          ("refine_points", p.refine_points % 2 == 1, "an odd integer >= 3"),
                          ("blur_sigma_px", p.blur_sigma_px == 0, "0 (the fast score has no blur)"),
                          ("window_min_ms", p.window_min_ms <= p.window_max_ms, "<= window_max_ms")):
        if not ok:
            raise ValueError(f"{name} must be {rng}, got {getattr(p, name)}")
    if not (math.isfinite(p.d_min) and math.isfinite(p.d_max) and p.d_min < p.d_max):
        raise ValueError(f"d_min must be < d_max (both finite), got d_min={p.d_min}, d_max={p.d_max}")
    if not 0 <= p.radial_bin_px <= 1000:
        raise ValueError(f"radial_bin_px must be in [0, 1000], got {p.radial_bin_px}")
    return p


@register_estimator("cmax")
class CMaxEstimator(DivergenceEstimator):
    """Contrast-maximisation divergence estimator (global, no feature tracking). See module doc.

    Its params are :class:`dvsland.config.schema.CMaxConfig` (``self.params``; every field is a
    keyword argument here, documented in the schema), its derived constants :class:`CMaxSetup`
    (``self.setup``), its state :class:`CMaxState`; the step is :func:`cmax_step`.

    Args:
        batch_size, sensor_size (W, H), device, dt_s, principal_point_px: see
            :class:`DivergenceEstimator`.
        seed: seed of the event hash (thinning, dither, half split), any int.
        **params: fields of :class:`CMaxConfig` (the rest at their defaults); e.g. ``window_ms``,
            ``d_min``, ``d_max``, ``max_events``, ``newton_iters``, ``extrapolate``.
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, seed: int = 0,
                 principal_point_px=None, **params):
        self._setup_from(cmax_params(**params), batch_size, sensor_size, device, dt_s, seed, principal_point_px)

    @classmethod
    def from_config(cls, params: CMaxConfig, batch_size: int, sensor_size, device: Any = "cpu", dt_s: float = 0.1,
                    seed: int = 0, principal_point_px=None) -> "CMaxEstimator":
        """The estimator of a config section (checked as the keyword constructor checks it)."""
        est = cls.__new__(cls)
        est._setup_from(cmax_params(**dataclasses.asdict(params)), batch_size, sensor_size, device, dt_s, seed,
                        principal_point_px)
        return est

    def _setup_from(self, params: CMaxConfig, batch_size, sensor_size, device, dt_s, seed, principal_point_px):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        self.params, self.seed = params, int(seed)
        self.setup = make_setup(params, self.batch_size, self.sensor_size, self.principal_point_px, self.dt_s,
                                self.device)
        self._template = self.init_state()  # what check_state_like compares a state with
        self.state = self.init_state()
        self._last = blank_out(self.state)

    @property
    def pad_px(self) -> int:
        """Canvas margin of the score, px (:class:`CMaxSetup`)."""
        return self.setup.pad_px

    # ------------------------------------------------------------------ the stage contract
    def init_state(self) -> CMaxState:
        """The :class:`CMaxState` of B descents that have seen nothing."""
        return cmax_init_state(self.params, self.setup, self.seed)

    def reset_where(self, state: CMaxState, mask: torch.Tensor) -> CMaxState:
        """``state`` with the descents where ``mask`` (B,) bool is True restarted."""
        return cmax_reset_where(state, self._mask(mask), self.init_state())

    def step_state(self, state: CMaxState, events, t_us: int, truth: Optional[Truth] = None):
        """Pure step (:func:`cmax_step`): (next state, :class:`EstimateOut`).

        The diagnostics: n_events (B,) int64 events in the window; contrast (B,) float32 score at
        the estimate; structure (B,) float32 the score over the noise floor's, minus 1 (module doc,
        step 6; NaN without a search); window_s (B,) float64 next window, s; d_std (B,) float64 standard error of D,
        1/s (module doc, step 5; NaN with the estimate); global_search (B,) bool (this step searched
        globally); bracketed (B,) bool (this step's maximum lay within the Newton candidates);
        confidence (B,) float32 in [0, 1], 1 / (1 + (d_std / (0.1 |D|))^2) times the noise floor's
        factor, 0 where D is NaN.
        """
        check_state_like("cmax", state, self._template)
        return cmax_step(self.params, state, events, t_us, self.setup)

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        """The base's reset; the diagnostics of a restarted descent then say it has no estimate
        (no events, contrast 0, the first window, d_std NaN), as its next update would."""
        super().reset(mask)
        fresh = blank_out(self.state)
        if mask is None or self._last is None:
            self._last = fresh
            return
        m = self._mask(mask)
        diag = {k: torch.where(m, fresh.diagnostics[k], v) if k in ("n_events", "contrast", "structure", "d_std") else v
                for k, v in self._last.diagnostics.items()}
        diag.update(window_s=self.state.window_s.clone(), confidence=self._last.confidence)
        self._last = self._last._replace(diagnostics=diag)


# the registry and the factory read the keyword parameters from the signature: the schema's fields
CMaxEstimator.__signature__ = inspect.Signature(
    [inspect.Parameter(n, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=d) for n, d in
     (("batch_size", inspect.Parameter.empty), ("sensor_size", inspect.Parameter.empty), ("device", "cpu"),
      ("dt_s", 0.1), ("seed", 0), ("principal_point_px", None))]
    + [inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default)
       for f in dataclasses.fields(CMaxConfig)])
