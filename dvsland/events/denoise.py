"""Front-end event denoising: background-activity, refractory and hot-pixel filters, batch-first.

Each filter is a pure function ``(events, state, ...) -> (keep mask, new state)`` over packed
:class:`~dvsland.events.Events` sorted by (b, t) (the emulator's order, which is also the order
the filters process events in, as tonic's loops do), with per-pixel memory carried from step to
step in a typed state (:class:`DenoiseState`). No Python loop over events or over the batch: the
per-pixel history is found by one stable sort of the events by pixel and binary searches.

Definitions (tonic's ``tonic.functional``, with the memory kept across calls):

- ``baf`` (background-activity filter, tonic ``denoise_numpy``; Delbruck 2008 for 8 neighbours):
  an event at pixel p and time t is kept when one of p's 4 (or 8) neighbours, not p itself, had an
  event at t_n earlier in the stream with ``t - t_n < baf_time_us``. Every event that reaches the
  filter (kept or not) is remembered. A neighbour that never fired supports nothing (tonic starts
  its memory at ``filter_time``, so there every event of the first ``filter_time`` passes).
- ``refractory`` (tonic ``refractory_period_numpy``): an event is kept when ``t - t_prev >
  refractory_us``, t_prev the pixel's previous event, kept or dropped (tonic's memory is written
  for every event). A pixel that never fired passes (tonic starts at ``-refractory_period``).
- ``hot_pixel`` (tonic ``identify_hot_pixel``, streaming): a pixel is hot when its event count
  since :meth:`EventDenoiser.reset` exceeds ``hot_pixel_rate_hz`` times the time since then;
  its events are dropped while it is hot (counts include the current step's events).

Select them by name in the config: ``emulator.denoise: none | baf | refractory | hot_pixel`` or
several joined by ``+`` (applied left to right, e.g. ``hot_pixel+baf``); docs/events.md.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional, Tuple

import numpy as np
import torch

from . import native
from .events import Events

#: "never fired" in the int64 µs time memories
NEVER_US = -(2 ** 62)

#: numpy fast paths on CPU tensors; tests switch it off to run the device-generic torch path
#: (the one CUDA runs) on CPU
CPU_FAST_PATHS = True


def _cpu(t: torch.Tensor) -> bool:
    return CPU_FAST_PATHS and t.device.type == "cpu"


def _native(t: torch.Tensor) -> bool:
    """The compiled loops of :mod:`dvsland.events.native` (CPU, where built and not switched off)."""
    return _cpu(t) and native.kernels() is not None

FILTERS = ("baf", "refractory", "hot_pixel")

_OFFSETS = {4: ((-1, 0), (1, 0), (0, -1), (0, 1)),
            8: ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, -1), (-1, 1), (1, 1))}


class DenoiseState(NamedTuple):
    """Per-pixel memories of the filters, each (B, H, W) on the events' device.

    Attributes:
        baf_t_us: int64 µs, last event seen by ``baf`` per pixel (:data:`NEVER_US` = none).
        refractory_t_us: int64 µs, last event seen by ``refractory`` per pixel.
        hot_count: int64, events seen by ``hot_pixel`` per pixel since the reset.
        t_reset_us: (B,) int64 µs, time of each descent's reset (the hot-pixel rate's time origin).
    """

    baf_t_us: torch.Tensor
    refractory_t_us: torch.Tensor
    hot_count: torch.Tensor
    t_reset_us: torch.Tensor


def parse_filters(spec: str) -> Tuple[str, ...]:
    """Filter names of ``spec`` ('none', one name, or names joined by '+'); ValueError naming
    ``emulator.denoise`` and the allowed names otherwise."""
    if not isinstance(spec, str):
        raise ValueError(f"emulator.denoise must be a string, got {spec!r}")
    s = spec.strip().lower()
    if s in ("", "none"):
        return ()
    names = tuple(n.strip() for n in s.split("+"))
    bad = [n for n in names if n not in FILTERS]
    if bad:
        raise ValueError(f"emulator.denoise: unknown filter(s) {bad} in {spec!r}; allowed: 'none' or "
                         f"names from {FILTERS} joined by '+'")
    return names


def init_state(batch_size: int, height: int, width: int, t_us: int, device=None) -> DenoiseState:
    """Empty memories for (B, H, W) pixels at time ``t_us`` (µs)."""
    shape = (int(batch_size), int(height), int(width))
    never = torch.full(shape, NEVER_US, dtype=torch.int64, device=device)
    t0 = torch.full(shape[:1], int(t_us), dtype=torch.int64, device=device)
    return DenoiseState(never, never.clone(), torch.zeros(shape, dtype=torch.int64, device=device), t0)


def _flat_pixel(ev: Events, shape) -> torch.Tensor:
    B, H, W = shape
    return (ev.b * H + ev.y).mul_(W).add_(ev.x)


def _memory_filter_inputs(ev: Events, memory_t_us: torch.Tensor):
    """What a filter with a per-pixel time memory starts from: ((B, H, W), N, the (B*H*W,) flat
    memory, the events' (N,) flat pixels, int64)."""
    B, H, W = memory_t_us.shape
    return (B, H, W), len(ev), memory_t_us.reshape(-1), _flat_pixel(ev, (B, H, W))


def _by_pixel(pix: torch.Tensor, n: int) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Events in (pixel, stream position) order: the sorted keys ``pixel * n + position``, the
    pixels and the positions in that order, int64 (N,) each. The keys are unique, so a plain sort
    (numpy's on CPU, several times faster than a stable argsort) gives the stable order."""
    key = pix * n + torch.arange(n, device=pix.device)
    if _cpu(key):
        key.numpy().sort()
    else:
        key = torch.sort(key).values
    pix_s = torch.div(key, n, rounding_mode="floor")
    return key, pix_s, key - pix_s * n


def _previous_at(key_sorted: torch.Tensor, t_sorted: torch.Tensor, n: int, last_key: torch.Tensor,
                 last_t: torch.Tensor, memory: torch.Tensor, query_pix: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Time (int64 µs) of the last event at pixel ``query_pix`` earlier in the stream than the query
    key ``q = query_pix * n + position``: from this step's events in (pixel, position) order
    (``key_sorted`` = pixel * n + position) or, when the pixel had none before, from ``memory``.

    Per pixel, ``last_key`` is the key of its last event in this step (-1 = none) and ``last_t``
    that event's time (``memory`` where none): when that event is earlier than the query (most
    queries) two gathers answer; only the others are searched (queries in increasing order, which
    numpy's search narrows by the previous answer)."""
    lk = last_key.index_select(0, query_pix)
    out = last_t.index_select(0, query_pix)
    redo = _nonzero_1d(lk >= q)  # the pixel fired again later in this step: search its earlier events
    if redo.numel():
        qr, pr = q.index_select(0, redo), query_pix.index_select(0, redo)
        if _cpu(qr):
            pos = torch.from_numpy(np.searchsorted(key_sorted.numpy(), qr.numpy())) - 1
        else:
            pos = torch.searchsorted(key_sorted, qr) - 1
        posc = pos.clamp(min=0)
        # key_sorted[pos] < q < (pixel + 1) * n: the same pixel iff it is >= pixel * n
        hit = (pos >= 0) & (key_sorted.index_select(0, posc) >= pr * n)
        out.index_copy_(0, redo, torch.where(hit, t_sorted.index_select(0, posc), memory.index_select(0, pr)))
    return out


def _nonzero_1d(mask: torch.Tensor) -> torch.Tensor:
    if _cpu(mask):
        return torch.from_numpy(np.flatnonzero(mask.numpy()))
    return torch.nonzero(mask).squeeze(1)


def _check_sorted(ev: Events) -> None:
    if not ev.is_sorted():
        raise ValueError("denoise: events must be sorted by (b, t) (Events.sort())")


def baf_keep(ev: Events, memory_t_us: torch.Tensor, time_us: float, neighbours: int = 4
             ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Background-activity filter of events sorted by (b, t).

    Args:
        ev: N events, pixels inside ``memory_t_us``'s (B, H, W).
        memory_t_us: (B, H, W) int64 µs, last event per pixel before these events.
        time_us: support window, µs, > 0.
        neighbours: 4 (tonic) or 8 (jAER / Delbruck 2008).

    Returns:
        keep (N,) bool, and the new (B, H, W) int64 memory (every event remembered).
    """
    (B, H, W), n, mem, pix = _memory_filter_inputs(ev, memory_t_us)
    if n == 0:
        return torch.zeros(0, dtype=torch.bool, device=mem.device), memory_t_us.clone()
    window = math.ceil(time_us)  # exact on integers: d < T  <=>  d < ceil(T)
    if _native(pix):  # the compiled loop over events (where built): the same keep mask and memory
        new = mem.clone()
        keep = native.load().baf_keep(pix, ev.x, ev.y, ev.t, new, H, W, window, neighbours)
        return keep, new.view(B, H, W)
    key_sorted, pix_s, order = _by_pixel(pix, n)  # work in (pixel, position) order: searches come sorted
    t_s, x_s, y_s = ev.t.index_select(0, order), ev.x.index_select(0, order), ev.y.index_select(0, order)
    # per pixel: key and time of its last event in this step (-1 / the memory where none)
    is_last = torch.ones(n, dtype=torch.bool, device=pix.device)
    is_last[:-1] = pix_s[1:] != pix_s[:-1]
    li = _nonzero_1d(is_last)
    lp = pix_s.index_select(0, li)
    last_key = torch.full((B * H * W,), -1, dtype=torch.int64, device=pix.device).index_copy_(0, lp, key_sorted.index_select(0, li))
    last_t = mem.clone().index_copy_(0, lp, t_s.index_select(0, li))
    keep_s = torch.zeros(n, dtype=torch.bool, device=pix.device)
    for dx, dy in _OFFSETS[neighbours]:  # 4 or 8 neighbour directions, each vectorised over events
        ok = None
        for v, d, hi in ((x_s, dx, W), (y_s, dy, H)):
            if d:
                c = v > 0 if d < 0 else v < hi - 1
                ok = c if ok is None else ok & c
        step = dy * W + dx
        npix = (pix_s + step).clamp_(0, B * H * W - 1)  # still sorted; off-sensor ones masked by ok
        t_n = _previous_at(key_sorted, t_s, n, last_key, last_t, mem, npix, key_sorted + step * n)
        keep_s |= ok & (t_s - t_n < window)
    keep = torch.empty_like(keep_s)
    keep[order] = keep_s
    return keep, last_t.view(B, H, W)


def refractory_keep(ev: Events, memory_t_us: torch.Tensor, refractory_us: float
                    ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Refractory filter: keep when ``t - t_prev > refractory_us`` (t_prev: the pixel's previous
    event, kept or not). Arguments and returns as :func:`baf_keep`."""
    (B, H, W), n, mem, pix = _memory_filter_inputs(ev, memory_t_us)
    if n == 0:
        return torch.zeros(0, dtype=torch.bool, device=mem.device), memory_t_us.clone()
    if _native(pix):
        new = mem.clone()
        keep = native.load().refractory_keep(pix, ev.t, new, math.floor(refractory_us))
        return keep, new.view(B, H, W)
    _, p_s, order = _by_pixel(pix, n)
    t_s = ev.t.index_select(0, order)
    first = torch.ones(n, dtype=torch.bool, device=pix.device)
    first[1:] = p_s[1:] != p_s[:-1]
    prev = torch.empty_like(t_s)
    prev[1:] = t_s[:-1]
    prev = torch.where(first, mem.index_select(0, p_s), prev)
    keep = torch.empty(n, dtype=torch.bool, device=pix.device)
    keep[order] = (t_s - prev) > math.floor(refractory_us)  # integer d > R  <=>  d > floor(R)
    new = mem.clone().scatter_reduce_(0, pix, ev.t, reduce="amax")
    return keep, new.view(B, H, W)


def hot_pixel_keep(ev: Events, count: torch.Tensor, elapsed_us, rate_hz: float
                   ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Hot-pixel mask: drop the events of pixels whose count (these events included) exceeds
    ``rate_hz * elapsed_us * 1e-6``. ``count`` (B, H, W) int64 before these events; ``elapsed_us``
    an int (µs, every descent) or a (B,) int64 tensor (each descent's time since its reset);
    returns keep (N,) bool and the new count."""
    B, H, W = count.shape
    pix = _flat_pixel(ev, (B, H, W))
    new = count.reshape(-1) + torch.bincount(pix, minlength=B * H * W)
    # exact: integer count > x  <=>  count > floor(x)
    if isinstance(elapsed_us, torch.Tensor):
        limit = torch.floor(elapsed_us.to(torch.float64).mul(rate_hz).mul_(1e-6)).view(B, 1)
        hot = (new.view(B, H * W) > limit).view(-1)
    else:
        hot = new > math.floor(rate_hz * elapsed_us * 1e-6)
    return ~hot.index_select(0, pix), new.view(B, H, W)


class EventDenoiser:
    """The configured chain of filters with its state; used by the emulator after every step.

    Args:
        filters: 'none', a name of :data:`FILTERS` or names joined by '+'.
        baf_time_us: ``baf`` support window, µs, > 0.
        baf_neighbours: 4 or 8.
        refractory_us: ``refractory`` period, µs, >= 0.
        hot_pixel_rate_hz: ``hot_pixel`` rate above which a pixel is hot, Hz, > 0.
    """

    def __init__(self, filters: str = "none", baf_time_us: float = 10_000.0, baf_neighbours: int = 4,
                 refractory_us: float = 1_000.0, hot_pixel_rate_hz: float = 50.0):
        self.filters = parse_filters(filters)
        for name, v, lo in (("denoise_baf_time_us", baf_time_us, 0.0), ("denoise_hot_pixel_rate_hz", hot_pixel_rate_hz, 0.0)):
            if not (float(v) > lo and np.isfinite(float(v))):
                raise ValueError(f"emulator.{name} must be a finite number > {lo}, got {v}")
        if not (np.isfinite(float(refractory_us)) and float(refractory_us) >= 0):
            raise ValueError(f"emulator.denoise_refractory_us must be a finite number >= 0, got {refractory_us}")
        if int(baf_neighbours) not in _OFFSETS:
            raise ValueError(f"emulator.denoise_baf_neighbours must be 4 or 8, got {baf_neighbours}")
        self.baf_time_us, self.baf_neighbours = float(baf_time_us), int(baf_neighbours)
        self.refractory_us, self.hot_pixel_rate_hz = float(refractory_us), float(hot_pixel_rate_hz)
        self.state: Optional[DenoiseState] = None

    @property
    def active(self) -> bool:
        return bool(self.filters)

    def reset(self, batch_size: int, height: int, width: int, t_us: int, device=None) -> None:
        """Forget every pixel's history; the hot-pixel clock starts at ``t_us``."""
        self.state = init_state(batch_size, height, width, t_us, device)

    def __call__(self, ev: Events, t_us: int) -> Events:
        """The events (sorted by (b, t)) of the step ending at ``t_us`` that pass every filter."""
        if self.state is None:
            raise RuntimeError("EventDenoiser called before reset")
        self.state, ev = denoise(ev, self.state, t_us, self)
        return ev


def denoise(ev: Events, state: DenoiseState, t_us: int, params: EventDenoiser) -> Tuple[DenoiseState, Events]:
    """Apply ``params.filters`` in order; returns (new state, kept events). Pure: ``state`` is not
    modified."""
    if not params.filters or len(ev) == 0:
        return state, ev
    _check_sorted(ev)
    for name in params.filters:
        if name == "baf":
            keep, mem = baf_keep(ev, state.baf_t_us, params.baf_time_us, params.baf_neighbours)
            state = state._replace(baf_t_us=mem)
        elif name == "refractory":
            keep, mem = refractory_keep(ev, state.refractory_t_us, params.refractory_us)
            state = state._replace(refractory_t_us=mem)
        else:
            elapsed = int(t_us) - state.t_reset_us  # (B,) µs since each descent's reset
            keep, cnt = hot_pixel_keep(ev, state.hot_count, elapsed, params.hot_pixel_rate_hz)
            state = state._replace(hot_count=cnt)
        if len(ev) and not bool(keep.all()):
            ev = ev[keep]
    return state, ev


__all__ = ["EventDenoiser", "DenoiseState", "FILTERS", "NEVER_US", "parse_filters", "init_state", "baf_keep",
           "refractory_keep", "hot_pixel_keep", "denoise"]
