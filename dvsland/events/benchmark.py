"""Speed of the emulator side by side with v2e, and of the non-ideal pixel model against the ideal one.

:func:`bench_vs_v2e` runs v2e's ``EventEmulator.generate_events`` (imported from a folder outside
the package, see :func:`load_v2e`; v2e is not on PyPI) and dvsland's :class:`EventEmulator` on
the same frames at the same settings (ON/OFF threshold, refractory period, no mismatch, no noise,
no low-pass), one frame at a time per stream as v2e works, and dvsland also batched. Every call
is timed with the process CPU clock (one torch thread: on a shared machine a waiting process is
not charged) and the wall clock; the medians are reported per frame, beside a ``torch.log`` pass
over the same float32 frames. :func:`bench_noise` times the ideal emulator against each non-ideal
part and all of them at once on the same frames.

v2e takes 8-bit-like intensities: it gets ``255 * I / max(I)`` of the same frames (its lin-log
mapping is linear below 20, so it emits somewhat fewer events in the darkest pixels; both counts
are reported). With ``identical=True`` both get ``I * s`` with ``s`` putting every pixel above 20
(v2e's log region), dvsland's ``log_eps`` is 1e-9 and both refractory periods are 0 (v2e applies
its own only when it exceeds dt / (most events of a pixel in the frame), never at these
settings): both models then emit ``floor(|L - L_ref| / theta)`` events per pixel and frame, so the
same (x, y, polarity) counts up to float32 rounding in v2e; only the timestamps differ by design
(v2e: the k-th event of every pixel at ``t0 + k dt / n_max``; dvsland: each at its interpolated
crossing time). :func:`bench_vs_v2e` counts the per-frame, per-pixel ON/OFF count differences.

dvsland is timed on each available path: ``torch`` (always) and ``compiled`` (the kernels of
:mod:`dvsland.events.native`, where built).
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Dict, Optional

import numpy as np
import torch

from .emulator import EventEmulator

DT_US = 100_000

#: Fresh batched emulators timed over the same frames (the batched median is over that many times more steps).
BATCHED_REPEATS = 5

#: the noise settings of :func:`bench_noise` (v2e's "noisy" preset where it has one)
NOISY = dict(photoreceptor_cutoff_hz=30.0, shot_noise_rate_hz=5.0, leak_rate_hz=0.1,
             hot_pixel_fraction=1e-4, mismatch_sigma=0.05)


def load_v2e(v2e_dir) -> type:
    """v2e's ``EventEmulator`` class from ``v2e_dir`` (holding ``v2ecore/`` and ``stubs/``).

    Raises:
        FileNotFoundError naming the folder when it has no ``v2ecore/emulator.py``.
    """
    d = Path(v2e_dir)
    if not (d / "v2ecore" / "emulator.py").is_file():
        raise FileNotFoundError(f"v2e's emulator not found: {d / 'v2ecore' / 'emulator.py'} (copy it there; "
                                f"see docs/events.md, 'Speed against v2e')")
    for p in (d / "stubs", d):
        if p.is_dir() and str(p) not in sys.path:
            sys.path.insert(0, str(p))
    import logging

    logging.getLogger("v2ecore").setLevel(logging.ERROR)  # v2e warns on every event-free frame
    from v2ecore.emulator import EventEmulator as V2EEmulator

    return V2EEmulator


def smooth_frames(B: int, H: int, W: int, n: int, omega: float = 0.1, seed: int = 0) -> torch.Tensor:
    """A smooth drifting pattern, (n, B, H, W) float32 irradiance; the log change per frame grows
    with ``omega`` (0.1 gives about 0.5 events per pixel per frame at threshold 0.1)."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    ph = torch.rand(B, 1, 1, generator=g, dtype=torch.float64) * 6.283
    kx = 0.05 + 0.1 * torch.rand(B, 1, 1, generator=g, dtype=torch.float64)
    ky = 0.05 + 0.1 * torch.rand(B, 1, 1, generator=g, dtype=torch.float64)
    out = []
    for k in range(n):
        s = torch.sin(kx * xx + ph + omega * k) * torch.cos(ky * yy - 0.7 * omega * k)
        out.append((0.5 * torch.exp(1.5 * s) + 0.01).to(torch.float32))
    return torch.stack(out)


def _clock_pair():
    return time.process_time(), time.perf_counter()


def _median_ms(xs):
    return statistics.median(xs) * 1e3 if xs else float("nan")


def _count_image(x, y, neg, H: int, W: int) -> np.ndarray:
    """(2 H W,) int64 ON/OFF event counts per pixel (index 2 (y W + x) + OFF)."""
    idx = (np.asarray(y, dtype=np.int64) * W + np.asarray(x, dtype=np.int64)) * 2 + np.asarray(neg, dtype=np.int64)
    return np.bincount(idx, minlength=2 * H * W)


def _time_dvsland(frames: torch.Tensor, make: Callable[[], EventEmulator], per_stream: bool, warmup: int,
                  repeats: int = 1, counts: Optional[list] = None):
    """Per-frame CPU and wall ms of dvsland steps (per stream: B = 1 emulators one after the other;
    batched: ``repeats`` fresh emulators over the same frames, so the median is over
    ``repeats * (n - 1 - warmup)`` steps rather than a handful on a loaded machine). ``counts``
    (per stream only): gets the ON/OFF count image of every frame (stream-major), untimed."""
    n, B, H, W = frames.shape
    cpu, wall, n_ev = [], [], 0
    groups = [slice(b, b + 1) for b in range(B)] if per_stream else [slice(0, B)] * max(1, int(repeats))
    for g in groups:
        emu = make()
        emu.reset(frames[0, g], 0)
        for k in range(1, n):
            c0, w0 = _clock_pair()
            ev = emu.step(frames[k, g], k * DT_US)
            c1, w1 = _clock_pair()
            if counts is not None:
                counts.append(_count_image(ev.x.numpy(), ev.y.numpy(), ev.p.numpy() < 0, H, W))
            if k > warmup:
                nb = g.stop - g.start
                cpu.append((c1 - c0) / nb)
                wall.append((w1 - w0) / nb)
                n_ev += len(ev)
    n_frames = len(cpu) * (1 if per_stream else B)
    return {"cpu_ms_per_frame": _median_ms(cpu), "wall_ms_per_frame": _median_ms(wall),
            "events_per_frame": n_ev / max(n_frames, 1)}


def _time_v2e(dn: np.ndarray, V2E, threshold: float, refractory_us: float, warmup: int,
              counts: Optional[list] = None):
    """Per-frame CPU and wall ms of v2e's generate_events on ``dn`` ((n, B, H, W) float64 DN),
    one stream after the other; ``counts`` as in :func:`_time_dvsland`."""
    n, B, H, W = dn.shape
    cpu, wall, n_ev = [], [], 0
    for b in range(B):
        emu = V2E(pos_thres=threshold, neg_thres=threshold, sigma_thres=0.0, cutoff_hz=0.0, leak_rate_hz=0.0,
                  refractory_period_s=refractory_us * 1e-6, shot_noise_rate_hz=0.0, device="cpu")
        emu.generate_events(dn[0, b], 0.0)  # first frame: initialises the state, no events
        for k in range(1, n):
            c0, w0 = _clock_pair()
            ev = emu.generate_events(dn[k, b], k * DT_US * 1e-6)
            c1, w1 = _clock_pair()
            if counts is not None:
                e = np.zeros((0, 4)) if ev is None else ev
                counts.append(_count_image(e[:, 1], e[:, 2], e[:, 3] < 0, H, W))
            if k > warmup:
                cpu.append(c1 - c0)
                wall.append(w1 - w0)
                n_ev += 0 if ev is None else len(ev)
    return {"cpu_ms_per_frame": _median_ms(cpu), "wall_ms_per_frame": _median_ms(wall),
            "events_per_frame": n_ev / max(len(cpu), 1)}


def _time_log(frames: torch.Tensor, repeats: int = 30) -> Dict[str, float]:
    """One torch.log pass over a (B, H, W) float32 batch: CPU ms per frame (median)."""
    f = frames[1].contiguous()
    B = f.shape[0]
    cpu, wall = [], []
    for _ in range(repeats):
        c0, w0 = _clock_pair()
        torch.log(f)
        c1, w1 = _clock_pair()
        cpu.append((c1 - c0) / B)
        wall.append((w1 - w0) / B)
    return {"cpu_ms_per_frame": _median_ms(cpu), "wall_ms_per_frame": _median_ms(wall)}


def _paths() -> list:
    """The dvsland paths to time: torch always, compiled where the kernels are cached or can be built."""
    from . import native

    paths = ["torch"]
    if native.kernels() is not None:
        paths.append("compiled")
    return paths


def bench_vs_v2e(frames: torch.Tensor, v2e_dir=None, threshold: float = 0.1, refractory_us: float = 15.0,
                 warmup: int = 1, threads: Optional[int] = 1, identical: bool = False) -> dict:
    """dvsland vs v2e on the same frames ((n, B, H, W) float32 irradiance, n >= warmup + 2).

    ``identical``: the setting in which both emit the same per-pixel counts (module docstring):
    frames scaled into v2e's log region for both, dvsland ``log_eps`` 1e-9, refractory 0.

    Returns a dict: ``v2e`` (or None with ``v2e_error`` when it cannot be imported); per dvsland
    path (``paths``: {"torch": ..., "compiled": ...}) ``per_stream`` (B = 1, frame by frame, as
    v2e) and ``batched`` (all B streams in one step, cost divided by B); ``dvsland_per_stream`` and
    ``dvsland_batched`` (the fastest path's); ``torch_log``; each with cpu_ms_per_frame,
    wall_ms_per_frame (medians) and events_per_frame; the speed-ups (v2e / dvsland, CPU time),
    dvsland's cost in ``torch.log`` passes, and with v2e ``agreement``: events of both over all
    frames and the sum over frames and pixels of |count difference| (ON and OFF apart).
    """
    from . import native

    if threads:
        torch.set_num_threads(int(threads))
    n, B, H, W = frames.shape
    if n < warmup + 2:
        raise ValueError(f"frames must hold at least warmup + 2 = {warmup + 2} frames, got {n}")
    frames = frames.to(torch.float32).cpu()
    log_eps = 1e-4
    if identical:
        refractory_us, log_eps = 0.0, 1e-9
        scale = 21.0 / max(float(frames.min()), 1e-12)  # every pixel above v2e's lin-log knee (20)
        frames = (frames.double() * scale).float()
        dn = frames.double().numpy()
    else:
        dn = (frames / frames.max() * 255.0).double().numpy()
    out = {"B": B, "H": H, "W": W, "frames_per_stream": n, "threshold": threshold, "refractory_us": refractory_us,
           "log_eps": log_eps, "identical": identical, "torch_threads": torch.get_num_threads(), "paths": {}}

    def make():
        return EventEmulator(threshold=threshold, refractory_us=refractory_us, log_eps=log_eps)

    counts_dvs: list = []
    for path in _paths():
        with native.native_sort_mode(path == "compiled"):
            out["paths"][path] = {
                "per_stream": _time_dvsland(frames, make, True, warmup, counts=counts_dvs if path == "torch" else None),
                "batched": _time_dvsland(frames, make, False, warmup, repeats=BATCHED_REPEATS)}
    best = min(out["paths"], key=lambda p: out["paths"][p]["batched"]["cpu_ms_per_frame"])
    out["fastest_path"] = best
    out["dvsland_per_stream"] = out["paths"][best]["per_stream"]
    out["dvsland_batched"] = out["paths"][best]["batched"]
    out["torch_log"] = _time_log(frames)
    out["v2e"] = None
    if v2e_dir is not None:
        try:
            V2E = load_v2e(v2e_dir)
        except Exception as e:  # report why, keep the dvsland figures
            out["v2e_error"] = f"{type(e).__name__}: {e}"
        else:
            counts_v2e: list = []
            out["v2e"] = _time_v2e(dn, V2E, threshold, refractory_us, warmup, counts=counts_v2e)
            a, b = np.stack(counts_v2e), np.stack(counts_dvs)
            out["agreement"] = {"frames": int(a.shape[0]), "events_v2e": int(a.sum()), "events_dvsland": int(b.sum()),
                                "abs_count_difference": int(np.abs(a - b).sum()),
                                "pixels_differing": int((a != b).sum())}
    log_ms = out["torch_log"]["cpu_ms_per_frame"]
    rows = [r for p in out["paths"].values() for r in p.values()]
    for r in rows:
        r["x_torch_log"] = r["cpu_ms_per_frame"] / log_ms if log_ms > 0 else math.nan
        if out["v2e"] is not None:
            r["speedup_vs_v2e"] = out["v2e"]["cpu_ms_per_frame"] / r["cpu_ms_per_frame"]
    return out


def calibrated_omega(B: int, H: int, W: int, target: float, threshold: float = 0.1, steps: int = 6) -> float:
    """The ``omega`` of :func:`smooth_frames` giving about ``target`` events per pixel per frame
    (steady state, refractory 15 µs, threshold ``threshold``), by four proportional corrections."""
    if not target > 0:
        raise ValueError(f"target must be > 0 events per pixel per frame, got {target}")
    omega = 0.1
    for _ in range(4):
        f = smooth_frames(B, H, W, steps, omega=omega)
        emu = EventEmulator(threshold=threshold, max_events_per_step=None)
        emu.reset(f[0], 0)
        emu.step(f[1], DT_US)
        ev = sum(len(emu.step(f[k], k * DT_US)) for k in range(2, steps))
        omega *= target / max(ev / ((steps - 2) * B * H * W), 1e-6)
    return omega


def bench_noise(frames: torch.Tensor, warmup: int = 1, threads: Optional[int] = 1, parts: Optional[dict] = None,
                seed: int = 0) -> dict:
    """Batched step cost of each non-ideal part (and all together) relative to the ideal emulator.

    Returns {name: {cpu_ms_per_frame, wall_ms_per_frame, events_per_frame, x_ideal}} with names
    "ideal", one per part of ``parts`` (default :data:`NOISY`), "all", and "all, shot noise 0.5 Hz"
    (the cost of shot noise grows with its events: at 5 Hz they outnumber the scene's events).
    """
    if threads:
        torch.set_num_threads(int(threads))
    frames = frames.to(torch.float32).cpu()
    parts = dict(NOISY if parts is None else parts)
    configs = {"ideal": {}, **{k: {k: v} for k, v in parts.items()}, "all": parts,
               "all, shot noise 0.5 Hz": {**parts, "shot_noise_rate_hz": 0.5}}
    out = {}
    for name, kw in configs.items():
        out[name] = _time_dvsland(frames, lambda kw=kw: EventEmulator(seed=seed, **kw), False, warmup,
                                  repeats=BATCHED_REPEATS)
    base = out["ideal"]["cpu_ms_per_frame"]
    for r in out.values():
        r["x_ideal"] = r["cpu_ms_per_frame"] / base if base > 0 else math.nan
    return out


#: the chains :func:`bench_denoise` times by default
DENOISE_CHAINS = ("baf", "refractory", "hot_pixel", "hot_pixel+baf")


def bench_denoise(frames: torch.Tensor, emulator_kwargs: Optional[dict] = None, chains=DENOISE_CHAINS,
                  warmup: int = 1, threads: Optional[int] = 1, seed: int = 0, **denoise_kwargs) -> dict:
    """Cost of the front-end denoising chains on the events of a noisy pixel.

    The events of every step are emulated once (``emulator_kwargs``, default :data:`NOISY`); each
    chain is then run over the same steps (fresh state, in order). Returns {chain: {cpu_ms_per_step,
    wall_ms_per_step (medians), events_in_per_step, events_out_per_step, kept}} plus
    "emulator" (the emulation's own cpu_ms_per_step for scale).
    """
    from .denoise import EventDenoiser

    if threads:
        torch.set_num_threads(int(threads))
    frames = frames.to(torch.float32).cpu()
    n, B, H, W = frames.shape
    emu = EventEmulator(seed=seed, **dict(NOISY if emulator_kwargs is None else emulator_kwargs))
    emu.reset(frames[0], 0)
    steps, cpu = [], []
    for k in range(1, n):
        c0, _ = _clock_pair()
        steps.append(emu.step(frames[k], k * DT_US))
        cpu.append(time.process_time() - c0)
    out = {"emulator": {"cpu_ms_per_step": _median_ms(cpu[warmup:]), "B": B, "H": H, "W": W}}
    for chain in chains:
        d = EventDenoiser(chain, **denoise_kwargs)
        d.reset(B, H, W, 0)
        cpu, wall, n_in, n_out = [], [], 0, 0
        for k, ev in enumerate(steps, start=1):
            c0, w0 = _clock_pair()
            kept = d(ev, k * DT_US)
            c1, w1 = _clock_pair()
            if k > warmup:
                cpu.append(c1 - c0)
                wall.append(w1 - w0)
                n_in, n_out = n_in + len(ev), n_out + len(kept)
        m = max(len(cpu), 1)
        out[chain] = {"cpu_ms_per_step": _median_ms(cpu), "wall_ms_per_step": _median_ms(wall),
                      "events_in_per_step": n_in / m, "events_out_per_step": n_out / m,
                      "kept": n_out / max(n_in, 1)}
    return out


def format_denoise(res: dict) -> str:
    """Plain-text table of :func:`bench_denoise`."""
    e = res["emulator"]
    lines = [f"Denoising cost per step (B = {e['B']}, {e['W']}x{e['H']}; the noisy emulation itself: "
             f"{e['cpu_ms_per_step']:.2f} CPU ms per step)",
             f"{'chain':<16} {'CPU ms':>8} {'wall ms':>8} {'events in':>10} {'out':>9} {'kept':>6}"]
    for name, x in res.items():
        if name == "emulator":
            continue
        lines.append(f"{name:<16} {x['cpu_ms_per_step']:>8.3f} {x['wall_ms_per_step']:>8.3f} "
                     f"{x['events_in_per_step']:>10.0f} {x['events_out_per_step']:>9.0f} {x['kept']:>6.1%}")
    return "\n".join(lines)


def format_results(res_v2e: Optional[dict], res_noise: Optional[dict]) -> str:
    """Plain-text tables of :func:`bench_vs_v2e` and :func:`bench_noise` results."""
    lines = []
    if res_v2e:
        r = res_v2e
        lines.append(f"Emulator vs v2e: B = {r['B']} streams of {r['frames_per_stream']} frames, {r['W']}x{r['H']}, "
                     f"threshold {r['threshold']}, refractory {r['refractory_us']} us, log_eps {r.get('log_eps', 1e-4)}, "
                     f"{'identical-events setting, ' if r.get('identical') else ''}"
                     f"{r['torch_threads']} torch thread(s); medians per frame")
        lines.append(f"{'':<32} {'CPU ms':>9} {'wall ms':>9} {'events':>9} {'x log':>7} {'v2e/x':>7}")
        rows = [("v2e (per frame)", r.get("v2e"))]
        paths = r.get("paths") or {"": {"per_stream": r["dvsland_per_stream"], "batched": r["dvsland_batched"]}}
        for name, p in paths.items():
            tag = f" {name}" if name else ""
            rows += [(f"dvsland{tag} B=1", p["per_stream"]), (f"dvsland{tag} B={r['B']} (/B)", p["batched"])]
        rows.append(("torch.log", r["torch_log"]))
        for label, x in rows:
            if x is None:
                lines.append(f"{label:<32} not run: {r.get('v2e_error', 'no v2e folder given')}")
                continue
            lines.append(f"{label:<32} {x['cpu_ms_per_frame']:>9.3f} {x['wall_ms_per_frame']:>9.3f} "
                         f"{x.get('events_per_frame', float('nan')):>9.0f} {x.get('x_torch_log', float('nan')):>7.1f} "
                         f"{x.get('speedup_vs_v2e', float('nan')):>7.1f}")
        a = r.get("agreement")
        if a:
            lines.append(f"events over {a['frames']} stream-frames: v2e {a['events_v2e']}, dvsland {a['events_dvsland']}; "
                         f"sum of |per-pixel ON/OFF count difference| {a['abs_count_difference']} "
                         f"({a['pixels_differing']} pixel-polarity-frames differ)")
    if res_noise:
        lines.append("")
        lines.append("Pixel model cost (batched, per frame) relative to the ideal emulator")
        lines.append(f"{'part':<26} {'CPU ms':>9} {'events':>9} {'x ideal':>8}")
        for name, x in res_noise.items():
            lines.append(f"{name:<26} {x['cpu_ms_per_frame']:>9.3f} {x['events_per_frame']:>9.0f} {x['x_ideal']:>8.2f}")
    return "\n".join(lines)


__all__ = ["bench_vs_v2e", "calibrated_omega", "bench_noise", "bench_denoise", "format_denoise", "DENOISE_CHAINS", "load_v2e", "smooth_frames", "format_results", "NOISY"]
