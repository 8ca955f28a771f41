"""Time per control step of each stage of the loop, and peak memory, for a batch of B descents.

The batch follows the closed-form oracle descents of the configured sites (element ``b`` flies
site ``b mod n_sites`` with controller setting ``(b // n_sites) mod n_settings``), starting at
fractions of the way down (``fractions``): the event rate grows as the descent goes on, so one
point would not be typical. At each start the emulator and estimator are reset; the first
``warmup`` steps are not timed (the ring fills, the estimator initialises). Timed per step:

- ``render``: the renderer's frames (B, H, W);
- ``emulate``: :meth:`dvsland.events.EventEmulator.step`;
- ``estimate``: the estimator's ``update``;
- ``control_dynamics``: moving-average filter + Eq. 2 controller + exact dynamics step.

Estimators that need no events (``needs_events = False``) skip render and emulate (as the
closed loop does). CUDA is synchronised around each stage. Peak memory (CUDA only): ``torch.cuda.max_memory_allocated``
minus the allocation before. On the CPU a long-lived process keeps freed memory in its heap, so
:func:`peak_memory_subprocess` measures a fresh process instead.
"""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path
from typing import Dict, Optional, Sequence

import numpy as np
import torch

from dvsland.config import Config
from dvsland.control import MovingAverageFilter, TauPController, initial_ttc
from dvsland.dynamics import LanderDynamics
from dvsland.estimators import Truth, make_estimator
from dvsland.evaluate.run import parse_estimator_spec, variant_config
from dvsland.evaluate.trajectory import closed_form_descents

STAGE_NAMES = ("render", "emulate", "estimate", "control_dynamics")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def build_estimator(cfg: Config, spec, batch_size: int, device):
    """Estimator from a spec ``"name"`` or ``"name[key=value;...]"`` (see
    :func:`dvsland.evaluate.run.parse_estimator_spec`), parameters from ``cfg`` plus the overrides."""
    label, name, over = parse_estimator_spec(spec)
    return make_estimator(variant_config(cfg, name, over, label), batch_size, device, name=name)


def _rss_kib(field: str) -> Optional[int]:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


class PeakMemory:
    """Peak memory growth over a block, MiB (None where it cannot be measured)."""

    def __init__(self, device: torch.device):
        self.device = device
        self.mib: Optional[float] = None

    def __enter__(self):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._base = torch.cuda.memory_allocated(self.device)
        else:
            self._base = _rss_kib("VmRSS")
            try:
                Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
                self._ok = self._base is not None
            except OSError:
                self._ok = False
        return self

    def __exit__(self, *exc):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.mib = (torch.cuda.max_memory_allocated(self.device) - self._base) / 2 ** 20
        elif self._ok:
            peak = _rss_kib("VmHWM")
            if peak is not None:
                self.mib = max(0.0, (peak - self._base) / 1024.0)
        return False


def time_stages(cfg: Config, batch_size: int, device="cpu", estimator="dpr", n_steps: int = 8, warmup: int = 3,
                fractions: Sequence[float] = (0.3, 0.8), sites: Optional[Sequence[str]] = None,
                renderer=None, frame_source=None) -> Dict:
    """Median ms per control step of each stage (see module doc) for B = ``batch_size``.

    Args:
        cfg: config (sites, camera, render, emulator, estimator, controller, dynamics).
        batch_size: B >= 1.
        device: torch device.
        estimator: spec ``"name"`` or ``"name[key=value;...]"``.
        n_steps: timed steps per start fraction; ``warmup``: untimed steps before them.
        fractions: where along each descent (0 = start, 1 = the success altitude) the segments start.
        sites: site names (default all configured).
        renderer: a renderer object to reuse (default: built from ``cfg.render.renderer``).
        frame_source: ``f(altitude_m, site_idx) -> frames`` instead of a renderer.

    Returns:
        dict: batch_size, estimator, ms {stage: median wall ms per step}, ms_total, ms_p90_total,
        cpu_ms {stage: median process CPU ms per step}, cpu_ms_total (with one torch thread, the
        cost on an idle core; meaningless on CUDA),
        events_per_step (mean over timed steps, all elements), peak_memory_mib, steps_timed,
        needs_events.
    """
    from dvsland.events import EventEmulator

    B = int(batch_size)
    if B < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if n_steps < 1 or warmup < 0:
        raise ValueError(f"n_steps must be >= 1 and warmup >= 0, got {n_steps}, {warmup}")
    if not fractions or any(not 0.0 <= f < 1.0 for f in fractions):
        raise ValueError(f"fractions must be in [0, 1), got {list(fractions)}")
    dev = torch.device(device)
    desc = closed_form_descents(cfg, sites)
    n_sites = len(desc.sites)
    settings = list(cfg.controller.settings)
    b = np.arange(B)
    site_of = b % n_sites
    setting_of = (b // n_sites) % len(settings)
    last_valid = desc.valid.sum(1) - 1  # index of the last frame above the success altitude, per site
    est = build_estimator(cfg, estimator, B, dev)
    needs_events = bool(getattr(est, "needs_events", True))
    with PeakMemory(dev) as mem:
        if needs_events and frame_source is None:
            if renderer is None:
                from dvsland.render import get_renderer

                renderer = get_renderer(cfg.render.renderer, desc.sites, cfg.camera, cfg.render, device=dev)
            frame_source = renderer.render
        emu = EventEmulator.from_config(cfg.emulator, device=dev, seed=cfg.simulation.seed) if needs_events else None
        site_idx = torch.as_tensor(site_of, device=dev)
        kp = torch.as_tensor([settings[i].kp for i in setting_of], dtype=torch.float64, device=dev)
        n_bin = torch.as_tensor([settings[i].n_bin for i in setting_of], dtype=torch.int64, device=dev)
        specs = {s.name: s for s in cfg.simulation.sites}
        z0 = torch.as_tensor([specs[desc.sites[i]].z0_m for i in site_of], dtype=torch.float64, device=dev)
        v0 = torch.as_tensor([specs[desc.sites[i]].v0_mps for i in site_of], dtype=torch.float64, device=dev)
        c = cfg.controller
        filt = MovingAverageFilter(n_bin, device=dev)
        ctl = TauPController(kp, initial_ttc(z0, v0), c.c2, cfg.dynamics.g_mps2, c.thrust_min_n, c.thrust_max_n,
                             c.missing_policy)
        dyn = LanderDynamics.from_config(cfg.dynamics)
        m = torch.full((B,), float(cfg.dynamics.mass_kg), dtype=torch.float64, device=dev)
        active = torch.ones(B, dtype=torch.bool, device=dev)
        ms = {k: [] for k in STAGE_NAMES}
        cpu = {k: [] for k in STAGE_NAMES}  # process CPU time: the uncontended cost on a shared machine
        n_events = []
        dt = float(cfg.dt_s)
        seg_us = (warmup + n_steps + 2) * int(round(dt * 1e6))
        for i_seg, frac in enumerate(fractions):
            k0 = np.floor(frac * np.maximum(last_valid - n_steps - warmup - 1, 0)).astype(np.int64)
            est.reset(None)
            filt.reset(None)
            ctl.reset(None)
            for j in range(warmup + n_steps + 1):
                kk = k0[site_of] + j
                z = torch.as_tensor(desc.altitude_m[site_of, kk], device=dev)
                v = torch.as_tensor(desc.velocity_mps[site_of, kk], device=dev)
                t_us = 1_000_000 + i_seg * seg_us + int(round(j * dt * 1e6))  # time keeps increasing
                timed = j > warmup
                ev = None
                if needs_events:
                    _sync(dev)
                    t0, c0 = time.perf_counter(), time.process_time()
                    frames = frame_source(z.to(torch.float32), site_idx)
                    _sync(dev)
                    t1, c1 = time.perf_counter(), time.process_time()
                    if j == 0:
                        emu.reset(frames, t_us)
                    else:
                        ev = emu.step(frames, t_us)
                    _sync(dev)
                    t2, c2 = time.perf_counter(), time.process_time()
                    if timed:
                        ms["render"].append((t1 - t0) * 1e3)
                        ms["emulate"].append((t2 - t1) * 1e3)
                        cpu["render"].append((c1 - c0) * 1e3)
                        cpu["emulate"].append((c2 - c1) * 1e3)
                        n_events.append(len(ev))
                if j == 0:
                    continue  # the first frame has no events yet
                _sync(dev)
                t0, c0 = time.perf_counter(), time.process_time()
                d_hat = est.update(ev, t_us, Truth(z, v)).to(device=dev, dtype=torch.float64)
                _sync(dev)
                t1, c1 = time.perf_counter(), time.process_time()
                d_f, _ = filt.update(d_hat, mask=active)
                out = ctl(j * dt, d_f, m, active)
                dyn.step(z, v, m, out.thrust_n, dt)
                _sync(dev)
                t2, c2 = time.perf_counter(), time.process_time()
                if timed:
                    ms["estimate"].append((t1 - t0) * 1e3)
                    ms["control_dynamics"].append((t2 - t1) * 1e3)
                    cpu["estimate"].append((c1 - c0) * 1e3)
                    cpu["control_dynamics"].append((c2 - c1) * 1e3)
    med = {k: (statistics.median(v) if v else 0.0) for k, v in ms.items()}
    cpu_med = {k: (statistics.median(v) if v else 0.0) for k, v in cpu.items()}
    totals = [sum(ms[k][i] if ms[k] else 0.0 for k in STAGE_NAMES) for i in range(len(ms["estimate"]))]
    return dict(batch_size=B, estimator=str(estimator), device=str(dev), needs_events=needs_events, ms=med,
                ms_total=float(sum(med.values())), cpu_ms=cpu_med, cpu_ms_total=float(sum(cpu_med.values())),
                ms_p90_total=float(np.percentile(totals, 90)) if totals else math.nan,
                events_per_step=float(np.mean(n_events)) if n_events else 0.0,
                peak_memory_mib=mem.mib if dev.type == "cuda" else None,
                steps_timed=len(ms["estimate"]), torch_threads=torch.get_num_threads())


_MEMORY_SCRIPT = r"""
import json, sys, torch
torch.set_num_threads(1)
from pathlib import Path
def kib(f):
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f + ":"):
            return int(line.split()[1])
from dvsland.config import load_config
from dvsland.bench.stages import time_stages
cfg = load_config(sys.argv[2] or None)
cfg.render.threads = 1
base = kib("VmRSS")
r = time_stages(cfg, int(sys.argv[1]), "cpu", sys.argv[3], n_steps=1, warmup=1, fractions=(0.5,))
print(json.dumps(dict(base_rss_mib=base / 1024, peak_rss_mib=kib("VmHWM") / 1024)))
"""


def peak_memory_subprocess(batch_size: int, estimator: str = "dpr", config: str = "", timeout_s: float = 600) -> dict:
    """CPU peak memory of a fresh process flying B descents for two steps (Linux only).

    Returns {base_rss_mib (after imports), peak_rss_mib, growth_mib} or {} where unavailable. A fresh
    process is needed: freed memory stays in the allocator's heap, so the growth of a long-lived
    process's peak says little."""
    import json
    import subprocess
    import sys

    if not Path("/proc/self/status").exists():
        return {}
    try:
        out = subprocess.run([sys.executable, "-c", _MEMORY_SCRIPT, str(int(batch_size)), config, estimator],
                             capture_output=True, text=True, timeout=timeout_s)
        line = [x for x in out.stdout.splitlines() if x.startswith("{")][-1]
    except (subprocess.SubprocessError, IndexError, OSError):
        return {}
    r = json.loads(line)
    r["growth_mib"] = r["peak_rss_mib"] - r["base_rss_mib"]
    return r
