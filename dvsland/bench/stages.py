"""Time per control step of each stage of the loop, and peak memory, for a batch of B descents.

The batch flies on :func:`dvsland.sim.loop_step` with the stages of
:func:`dvsland.stages.build_stages` (the configured renderer, emulator, filter, controller by
``controller.name`` and dynamics; the estimator from the spec). Element ``b`` flies site
``b mod n_sites`` with controller setting ``(b // n_sites) mod n_settings``. Each segment starts a
closed-loop flight at a fraction of the way down the site's closed-form oracle descent
(``fractions``: the event rate grows as the descent goes on, so one point would not be typical),
planned from there (the controller's initial state is that point); :func:`dvsland.sim.init_state`
resets every stage, and the first ``warmup`` steps are not timed (the ring fills, the estimator
initialises). Timed per step, by the loop's own stage timer (``loop_step(..., timer=...)``):

- ``render``: the renderer's frames (B, H, W);
- ``emulate``: :meth:`dvsland.events.EventEmulator.step`;
- ``estimate``: the estimator's ``update`` (with the loop's sanitising and confidence);
- ``control_dynamics``: the loop's ``control`` (filter + controller) and ``dynamics`` (step,
  termination, bookkeeping) stages.

Estimators that need no events (``needs_events = False``) skip render and emulate (as the
closed loop does). CUDA is synchronised around each stage. Peak memory (CUDA only): ``torch.cuda.max_memory_allocated``
minus the allocation before. On the CPU a long-lived process keeps freed memory in its heap, so
:func:`peak_memory_subprocess` measures a fresh process instead.
"""

from __future__ import annotations

import copy
import math
import statistics
import time
from pathlib import Path
from typing import Dict, Optional, Sequence

import numpy as np
import torch

from dvsland.config import Config
from dvsland.estimators import make_estimator
from dvsland.evaluate.run import parse_estimator_spec, variant_config
from dvsland.evaluate.trajectory import closed_form_descents

STAGE_NAMES = ("render", "emulate", "estimate", "control_dynamics")
#: the loop's stages (``loop_step``'s timer names) behind each column of :data:`STAGE_NAMES`
LOOP_STAGES = {"render": ("render",), "emulate": ("emulate",), "estimate": ("estimate",),
               "control_dynamics": ("control", "dynamics")}


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


class StepTimer:
    """``loop_step`` timer: wall and process-CPU ms of each stage of the current step (CUDA
    synchronised around each stage); :meth:`take` returns them and starts the next step."""

    def __init__(self, device: torch.device):
        self.device = device
        self.wall: Dict[str, float] = {}
        self.cpu: Dict[str, float] = {}

    def __call__(self, stage: str):
        return _StageClock(self, stage)

    def take(self):
        wall, cpu = self.wall, self.cpu
        self.wall, self.cpu = {}, {}
        return wall, cpu


class _StageClock:
    def __init__(self, timer: StepTimer, stage: str):
        self.timer, self.stage = timer, stage

    def __enter__(self):
        _sync(self.timer.device)
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        _sync(self.timer.device)
        t, c = self.timer, self.stage
        t.wall[c] = t.wall.get(c, 0.0) + (time.perf_counter() - self.t0) * 1e3
        t.cpu[c] = t.cpu.get(c, 0.0) + (time.process_time() - self.c0) * 1e3
        return False


def bench_layout(cfg: Config, batch_size: int, sites: Optional[Sequence[str]] = None, z0_m=None, v0_mps=None):
    """The bench's batch layout: element ``b`` flies site ``b mod n_sites`` with controller setting
    ``(b // n_sites) mod n_settings`` (plain sites, no dispersion), starting at ``z0_m``, ``v0_mps``
    ((B,) arrays; default the sites' initial conditions)."""
    from dvsland.layout import build_layout
    from dvsland.layout.batch import expand_seeds

    plain = copy.deepcopy(cfg)
    if sites is not None:  # in the order given (build_layout keeps the config's order)
        specs = {s.name: s for s in plain.simulation.sites}
        plain.simulation.sites = [specs[n] for n in sites]
    plain.simulation.n_seeds = 1
    if hasattr(plain.simulation, "seed_offset"):
        plain.simulation.seed_offset = 0
    if getattr(plain, "dispersion", None) is not None:
        plain.dispersion.enabled = False
    base = build_layout(plain, sites)  # site-major: (i_site * n_settings + i_setting)
    n_sites, n_set = len(base.site_names), len(plain.controller.settings)
    b = np.arange(int(batch_size))
    idx = (b % n_sites) * n_set + (b // n_sites) % n_set
    lay = copy.deepcopy(base)
    for name in ("site", "label"):
        setattr(lay, name, [getattr(base, name)[i] for i in idx])
    for name in ("site_idx", "setting_idx", "seed_idx", "kp", "n_bin", "z0_m", "v0_mps"):
        setattr(lay, name, np.asarray(getattr(base, name))[idx])
    lay.run_label = [f"{base.run_label[i]}/b{j}" for j, i in enumerate(idx)]
    lay.seed = expand_seeds(plain.simulation.seed, len(idx))
    lay.scene = list(lay.site)
    lay.scene_idx = np.asarray(lay.site_idx, np.int64).copy()
    if z0_m is not None:
        lay.z0_m = np.asarray(z0_m, np.float64)
    if v0_mps is not None:
        lay.v0_mps = np.asarray(v0_mps, np.float64)
    return plain, lay


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
        needs_events, controller, ended (descents that ended during a segment: they stop rendering).
    """
    from dvsland.sim import init_state, loop_step
    from dvsland.stages import build_stages

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
    site_of = np.arange(B) % n_sites
    last_valid = desc.valid.sum(1) - 1  # index of the last frame above the success altitude, per site
    est = build_estimator(cfg, estimator, B, dev)
    needs_events = bool(getattr(est, "needs_events", True))
    timer = StepTimer(dev)
    ms = {k: [] for k in STAGE_NAMES}
    cpu = {k: [] for k in STAGE_NAMES}  # process CPU time: the uncontended cost on a shared machine
    n_events, ended, ctl_name = [], 0, None
    with PeakMemory(dev) as mem:
        if needs_events:
            if frame_source is not None:
                renderer = frame_source
            elif renderer is None:  # built once, shared by the segments' stages
                from dvsland.render import get_renderer

                renderer = get_renderer(cfg.render.renderer, desc.sites, cfg.camera, cfg.render, device=dev)
        for frac in fractions:
            k0 = np.floor(frac * np.maximum(last_valid - n_steps - warmup - 1, 0)).astype(np.int64)
            fcfg, layout = bench_layout(cfg, B, desc.sites, desc.altitude_m[site_of, k0[site_of]],
                                        desc.velocity_mps[site_of, k0[site_of]])
            stages = build_stages(fcfg, layout, dev, estimator=est, renderer=renderer if needs_events else None)
            ctl_name = getattr(stages.controller, "controller_name", type(stages.controller).__name__)
            state = init_state(stages)  # every stage reset; the plan starts here
            for j in range(warmup + n_steps + 1):
                state, out = loop_step(stages, state, timer=timer, donate=True)  # as the loop runners step
                wall, proc = timer.take()
                if j <= warmup:
                    continue  # step 0 has no events yet; then the warm-up
                for col, parts in LOOP_STAGES.items():
                    if any(p in wall for p in parts):
                        ms[col].append(sum(wall.get(p, 0.0) for p in parts))
                        cpu[col].append(sum(proc.get(p, 0.0) for p in parts))
                if out.events is not None:
                    n_events.append(len(out.events))
            ended += int((~state.active).sum())
    med = {k: (statistics.median(v) if v else 0.0) for k, v in ms.items()}
    cpu_med = {k: (statistics.median(v) if v else 0.0) for k, v in cpu.items()}
    totals = [sum(ms[k][i] if ms[k] else 0.0 for k in STAGE_NAMES) for i in range(len(ms["estimate"]))]
    return dict(batch_size=B, estimator=str(estimator), device=str(dev), needs_events=needs_events, ms=med,
                ms_total=float(sum(med.values())), cpu_ms=cpu_med, cpu_ms_total=float(sum(cpu_med.values())),
                ms_p90_total=float(np.percentile(totals, 90)) if totals else math.nan,
                events_per_step=float(np.mean(n_events)) if n_events else 0.0,
                peak_memory_mib=mem.mib if dev.type == "cuda" else None,
                steps_timed=len(ms["estimate"]), torch_threads=torch.get_num_threads(), controller=ctl_name,
                ended=ended)


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
