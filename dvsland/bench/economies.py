"""What each "model only what the scene needs" economy buys, as time and error side by side.

Times are process CPU time with one torch thread (renderer threads = 1): on a shared machine they
track the uncontended cost far better than wall time.

1. ``lod``: the footprint-only level-of-detail render (128 px from a pyramid of 384-texel windows)
   against a 2x supersampled render of the same footprint from levels twice as fine (256 px, four
   times the texels, box-filtered to 128 px): ms per call at B = 18, texels held, and the
   difference of the two frames (RMS of log-irradiance, correlation). Holding the whole 10 km
   footprint at the finest texel is counted (texels, memory) and its preparation time
   extrapolated from the measured CPU cost per texel of shading a 256 x 256 window, not run.
2. ``ring``: the ``dpr`` window as a ring of per-step pixel indices and a running count image
   (add the new step, subtract the oldest) against keeping the raw events of the window and
   rebuilding the count image every step: ms per step, bytes held, and whether the two windows
   are identical (they must be: the ring is lossless).
3. ``changed``: the emulator already does per-event work only for pixels whose log-intensity
   crossed a threshold; measured here: the fraction of such pixels and of pixels that changed at
   all, the time of the dense per-pixel pass (log + difference + candidate search over every
   pixel) against the whole step, and emulating a batch in which half the descents have finished
   (frozen frames: no events) against emulating only the running half.
"""

from __future__ import annotations

import copy
import statistics
import time
from collections import deque
from typing import Dict, List

import numpy as np
import torch
import torch.nn.functional as F

from dvsland.config import Config
from dvsland.evaluate.trajectory import closed_form_descents


def _ms(fn, repeat: int) -> float:
    fn()
    out = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        out.append((time.process_time() - t0) * 1e3)
    return statistics.median(out)


def _descent_altitudes(cfg: Config, sites: List[str], frac: float, n: int) -> torch.Tensor:
    """(n + 1, B) float32 altitudes of ``n + 1`` consecutive frames starting at fraction ``frac``."""
    desc = closed_form_descents(cfg, sites)
    last = desc.valid.sum(1) - 1
    k0 = np.floor(frac * np.maximum(last - n - 1, 0)).astype(np.int64)
    rows = [desc.altitude_m[np.arange(len(sites)), k0 + j] for j in range(n + 1)]
    return torch.as_tensor(np.stack(rows), dtype=torch.float32)


def lod_economy(cfg: Config, sites: List[str], batch_size: int = 18, repeat: int = 5) -> Dict:
    """See module doc, item 1."""
    from dvsland.render import get_renderer

    c2 = copy.deepcopy(cfg)
    c2.camera.width_px, c2.camera.height_px = 2 * cfg.camera.width_px, 2 * cfg.camera.height_px
    fast = get_renderer("fast", sites, cfg.camera, cfg.render)
    t0 = time.perf_counter()
    fine = get_renderer("fast", sites, c2.camera, c2.render)
    fine_build_s = time.perf_counter() - t0
    n = len(sites)
    idx = torch.arange(batch_size) % n
    alts = torch.exp(torch.linspace(np.log(60.0), np.log(8000.0), batch_size))
    ms_lod = _ms(lambda: fast.render(alts, idx), repeat)
    ms_fine = _ms(lambda: F.avg_pool2d(fine.render(alts, idx).unsqueeze(1), 2).squeeze(1), repeat)
    a = torch.log(fast.render(alts, idx))
    b = torch.log(F.avg_pool2d(fine.render(alts, idx).unsqueeze(1), 2).squeeze(1))
    diff = (a - b).flatten(1)
    rms = diff.pow(2).mean(1).sqrt()
    ac, bc = a.flatten(1) - a.flatten(1).mean(1, keepdim=True), b.flatten(1) - b.flatten(1).mean(1, keepdim=True)
    corr = (ac * bc).sum(1) / (ac.norm(dim=1) * bc.norm(dim=1)).clamp(min=1e-12)
    lv = fast.levels
    texels_lod = lv.n_levels * lv.tile_size ** 2
    texels_fine = fine.levels.n_levels * fine.levels.tile_size ** 2
    prep = [v for v in fast.prep_cpu_s.values() if v > 0] + [v for v in fine.prep_cpu_s.values() if v > 0]
    # the whole footprint seen at the start (the highest configured altitude) at level 0's texel
    z_top = max(s.z0_m for s in cfg.simulation.sites)
    tan_half = np.tan(np.radians(cfg.camera.fov_deg) / 2)
    side = 2 * z_top * tan_half / lv.base_texel_m
    texels_whole = float(side * side)
    # preparation cost per texel (CPU seconds): shade one 256 x 256 window at level 0's texel, as
    # the level preparation does (terrain fields + shading with shadows)
    from dvsland.terrain import load_site, shaded_sun_grid

    terrain = load_site(sites[0], cfg.render.sun_elevation_deg)
    shaded_sun_grid(terrain, (0.0, 0.0), 64, lv.base_texel_m, lv.ambient, lv.shadow_pad)  # warm
    c0 = time.process_time()
    shaded_sun_grid(terrain, (0.0, 0.0), 256, lv.base_texel_m, lv.ambient, lv.shadow_pad)
    per_texel = (time.process_time() - c0) / (256 * 256)
    return dict(
        sites=sites, batch_size=batch_size,
        lod=dict(ms_per_call=ms_lod, texels_per_site=texels_lod, mib_per_site=texels_lod * 8 / 2 ** 20),
        supersampled_2x=dict(ms_per_call=ms_fine, texels_per_site=texels_fine,
                             mib_per_site=texels_fine * 8 / 2 ** 20, build_s=fine_build_s),
        lod_vs_2x=dict(rms_log_diff_median=float(rms.median()), rms_log_diff_max=float(rms.max()),
                       corr_median=float(corr.median()), corr_min=float(corr.min())),
        whole_footprint_finest=dict(altitude_m=z_top, texel_m=lv.base_texel_m, texels=texels_whole,
                                    mib_float32=texels_whole * 4 / 2 ** 20,
                                    prep_cpu_s_extrapolated=(texels_whole * per_texel) if per_texel else None,
                                    prep_cpu_s_per_texel_measured=per_texel, prep_cpu_s_measured=prep),
    )


def _event_stream(cfg: Config, sites: List[str], batch_size: int, n_steps: int, frac: float):
    """Events of ``n_steps`` steps of B = ``batch_size`` descents (fast renderer + emulator)."""
    from dvsland.events import EventEmulator
    from dvsland.render import get_renderer

    rend = get_renderer("fast", sites, cfg.camera, cfg.render)
    emu = EventEmulator.from_config(cfg.emulator, seed=cfg.simulation.seed)
    n = len(sites)
    idx = torch.arange(batch_size) % n
    alt = _descent_altitudes(cfg, sites, frac, n_steps)[:, idx.numpy()]
    frames = [rend.render(alt[j], idx) for j in range(n_steps + 1)]
    emu.reset(frames[0], 1_000_000)
    evs = [emu.step(frames[j], 1_000_000 + j * 100_000) for j in range(1, n_steps + 1)]
    return frames, evs, emu


def ring_economy(cfg: Config, sites: List[str], batch_size: int = 18, n_steps: int = 12, frac: float = 0.7) -> Dict:
    """See module doc, item 2."""
    from dvsland.estimators import make_estimator

    _, evs, _ = _event_stream(cfg, sites, batch_size, n_steps, frac)
    W, H = cfg.camera.width_px, cfg.camera.height_px
    est = make_estimator(cfg, batch_size, "cpu", name="dpr")
    K = est.n_ring
    q = est._pad
    Hp, Wp = H + 2 * q, W + 2 * q
    # (a) the ring: per-step flat indices, running sum (dpr's own bookkeeping, timed apart)
    ring: deque = deque()
    win = torch.zeros(batch_size, Hp, Wp)
    ring_ms, raw_ms, equal, ring_bytes, raw_bytes, n_window = [], [], True, [], [], []
    raw: deque = deque()
    from dvsland.events import Events

    for j, ev in enumerate(evs):
        t_us = 1_000_000 + (j + 1) * 100_000
        t0 = time.process_time()
        lin = torch.add(ev.x, ev.y, alpha=Wp).add_(ev.b, alpha=Hp * Wp).add_(q * Wp + q)
        flat = win.view(-1)
        flat.scatter_add_(0, lin, torch.ones(lin.numel()))
        ring.append(lin)
        if len(ring) > K:
            old = ring.popleft()
            flat.scatter_add_(0, old, torch.full((old.numel(),), -1.0))
        ring_ms.append((time.process_time() - t0) * 1e3)
        ring_bytes.append(sum(r.numel() * r.element_size() for r in ring) + win.numel() * win.element_size())
        # (b) raw events of the window, count image rebuilt every step
        t0 = time.process_time()
        raw.append(ev)
        if len(raw) > K:
            raw.popleft()
        allev = Events.cat(list(raw))
        img = allev.to_count_image(batch_size, H, W).sum(1)  # ON + OFF, as dpr counts
        raw_ms.append((time.process_time() - t0) * 1e3)
        raw_bytes.append(sum(_event_bytes(e) for e in raw) + img.numel() * img.element_size())
        n_window.append(len(allev))
        est.update(ev, t_us)
        equal = equal and torch.equal(img, win[:, q:q + H, q:q + W]) and torch.equal(img, est.window_image())
    skip = min(K, len(evs) - 1)  # report the steady state (full window)
    return dict(batch_size=batch_size, window_steps=K, steps=len(evs),
                events_in_window_mean=float(np.mean(n_window[skip:])),
                ring=dict(ms_per_step=statistics.median(ring_ms[skip:]), bytes_held=int(np.mean(ring_bytes[skip:]))),
                raw_events=dict(ms_per_step=statistics.median(raw_ms[skip:]),
                                bytes_held=int(np.mean(raw_bytes[skip:]))),
                windows_identical=bool(equal))


def _event_bytes(ev) -> int:
    return sum(t.numel() * t.element_size() for t in (ev.b, ev.x, ev.y, ev.t, ev.p))


def changed_pixels_economy(cfg: Config, sites: List[str], batch_size: int = 18, n_steps: int = 8,
                           fractions=(0.2, 0.6, 0.9)) -> Dict:
    """See module doc, item 3."""
    from dvsland.events import EventEmulator

    th = float(cfg.emulator.threshold)
    eps = float(cfg.emulator.log_eps)
    cand, changed, step_ms, dense_ms = [], [], [], []
    for frac in fractions:
        frames, evs, _ = _event_stream(cfg, sites, batch_size, n_steps, frac)
        emu = EventEmulator.from_config(cfg.emulator, seed=cfg.simulation.seed)
        emu.reset(frames[0], 1_000_000)
        for j in range(1, n_steps + 1):
            lref = emu.reference.clone() if hasattr(emu, "reference") else None
            l1 = torch.log(frames[j] + eps)
            l0 = torch.log(frames[j - 1] + eps)
            changed.append(float(((l1 - l0).abs() > 1e-6).float().mean()))
            if lref is not None:
                cand.append(float(((l1 - lref).abs() >= th * (1 - 2e-9)).float().mean()))
            t0 = time.process_time()
            emu.step(frames[j], 1_000_000 + j * 100_000)
            step_ms.append((time.process_time() - t0) * 1e3)

            def dense():
                d = torch.log(frames[j] + eps) - lref
                np.flatnonzero(np.abs(d.numpy().reshape(-1)) >= th)

            if lref is not None:
                dense_ms.append(_ms(dense, 2))
    # half the batch finished (frozen frames) vs only the running half
    frames, _, _ = _event_stream(cfg, sites, batch_size, 3, 0.6)
    half = batch_size // 2
    frozen = [f.clone() for f in frames]
    for f in frozen[1:]:
        f[half:] = frozen[0][half:]
    emu_all = EventEmulator.from_config(cfg.emulator, seed=cfg.simulation.seed)
    emu_half = EventEmulator.from_config(cfg.emulator, seed=cfg.simulation.seed)
    ms_all, ms_half, n_frozen_events = [], [], 0
    # process CPU time (one torch thread): on a loaded machine it tracks the uncontended cost far
    # better than wall time for a difference of a few ms
    for rep in range(7):  # interleaved, alternating which goes first; the first pass is a warm-up
        emu_all.reset(frozen[0], 1_000_000)
        emu_half.reset(frozen[0][:half], 1_000_000)
        for j in range(1, len(frozen)):
            t_us = 1_000_000 + j * 100_000
            for which in ((0, 1) if (rep + j) % 2 else (1, 0)):
                t0 = time.process_time()
                if which == 0:
                    ev = emu_all.step(frozen[j], t_us)
                    n_frozen_events += int((ev.b >= half).sum())
                else:
                    emu_half.step(frozen[j][:half], t_us)
                if rep:
                    (ms_all if which == 0 else ms_half).append((time.process_time() - t0) * 1e3)
    return dict(batch_size=batch_size, steps=len(step_ms), fractions=list(fractions),
                candidate_pixel_fraction_mean=float(np.mean(cand)) if cand else None,
                changed_pixel_fraction_mean=float(np.mean(changed)),
                step_ms_median=statistics.median(step_ms),
                dense_pass_ms_median=statistics.median(dense_ms) if dense_ms else None,
                half_finished=dict(cpu_ms_all_elements=statistics.median(ms_all),
                                   cpu_ms_running_only=statistics.median(ms_half),
                                   events_from_frozen_elements=n_frozen_events))
