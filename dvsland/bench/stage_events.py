#!/usr/bin/env python
"""Benchmark of :class:`dvsland.events.EventEmulator`.

Measures, per device (CPU; CUDA when available):

- time per ``step`` for B = 18 and B = 256 at 128x128 on smooth synthetic frames calibrated to
  about 1 and about 0.5 events per pixel per step (``--rates``), and on real descent frames of
  the fast renderer (sites A-I along the oracle trajectory, 10 Hz) when it is available;
- events/s, and the cost as a multiple of one ``torch.log`` pass over the same float32 frames
  (the target: <= 30x at about 0.5 events/pixel/step). Step and log are timed
  interleaved, frame by frame, and the ratio uses the medians, so load from other processes
  affects both alike;
- peak memory of one step with a burst of 10 events per pixel at B = 256, in a fresh subprocess
  after the frames and the emulator state exist: on CPU the peak RSS during the step minus the
  RSS before it (the peak counter VmHWM is reset through /proc/self/clear_refs first; fallback:
  ``ru_maxrss`` growth); on CUDA ``torch.cuda.max_memory_allocated`` minus the allocation before
  the step. The output Events alone take 33 bytes per event.

Usage::

    python scripts/bench_events.py                   # table
    python scripts/bench_events.py --json out.json   # also JSON
    python scripts/bench_events.py --batch 18 --no-real --no-memory --steps 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import torch

from dvsland.events import EventEmulator

DT_US = 100_000  # 10 Hz


def _sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


# ----------------------------------------------------------------------------- frames
def synthetic_frames(B, H, W, n, omega, device, seed=0):
    """Smooth drifting pattern, (n, B, H, W) float32 irradiance on ``device``; log change per step
    ~ omega (:func:`dvsland.events.benchmark.smooth_frames`, the same frames as the v2e comparison)."""
    from dvsland.events.benchmark import smooth_frames

    return smooth_frames(B, H, W, n, omega=omega, seed=seed).to(device)


def calibrated_frames(B, H, W, n, target, device):
    """Synthetic frames whose emulated event rate is about ``target`` events/pixel/step."""
    omega = 0.1
    for _ in range(4):
        f = synthetic_frames(B, H, W, 6, omega, "cpu")
        emu = EventEmulator(max_events_per_step=None)  # measure the raw emulator: no cap
        emu.reset(f[0], 0)
        emu.step(f[1], DT_US)
        ev = sum(len(emu.step(f[k], k * DT_US)) for k in range(2, 6))  # steady state
        rate = ev / (4 * B * H * W)
        omega *= target / max(rate, 1e-6)
    return synthetic_frames(B, H, W, n, omega, device)


def descent_frames(B, n, device, camera=None):
    """Fast-renderer frames along the oracle descent (sites A-I cycled over the batch, each
    element started at a different phase), (n, B, H, W); see
    :func:`dvsland.bench.frames.descent_frames`. None if the renderer is unavailable."""
    try:
        from .frames import descent_frames as frames_along_descent
    except Exception:  # pragma: no cover - renderer not installed
        return None
    return frames_along_descent(B, n, camera).to(device)


# ----------------------------------------------------------------------------- timing
def time_steps(frames, device, warmup=2, clock=time.perf_counter):
    """Interleaved timing of emulator steps and torch.log passes over the same frames."""
    n, B, H, W = frames.shape
    emu = EventEmulator(device=device, max_events_per_step=None)
    emu.reset(frames[0], 0)
    t_step, t_log, n_ev = [], [], []
    for k in range(1, n):
        f = frames[k]
        _sync(device)
        t0 = clock()
        torch.log(f)
        _sync(device)
        t1 = clock()
        ev = emu.step(f, k * DT_US)
        _sync(device)
        t2 = clock()
        if k > warmup:
            t_log.append(t1 - t0)
            t_step.append(t2 - t1)
            n_ev.append(len(ev))
    step_ms = statistics.median(t_step) * 1e3
    log_ms = statistics.median(t_log) * 1e3
    ev_step = statistics.mean(n_ev)
    return {
        "B": B, "H": H, "W": W, "steps_timed": len(t_step),
        "events_per_px_step": ev_step / (B * H * W),
        "step_ms_median": step_ms, "step_ms_min": min(t_step) * 1e3,
        "log_ms_median": log_ms,
        "events_per_s": ev_step / (step_ms * 1e-3) if step_ms > 0 else float("nan"),
        "x_log": step_ms / log_ms,
    }


# ----------------------------------------------------------------------------- memory
_MEM_CHILD = r"""
import json, resource, sys, torch
from dvsland.events import EventEmulator
B, H, W, dev = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
g = torch.Generator().manual_seed(0)
f0 = (torch.rand(B, H, W, generator=g) * 0.9 + 0.1).to(dev)
f1 = ((f0.double() + 1e-4) * torch.exp(torch.tensor(1.05, dtype=torch.float64)) - 1e-4).to(dev)
emu = EventEmulator(device=dev, max_events_per_step=None)
emu.reset(f0, 0)
state_bytes = sum(t.numel() * t.element_size() for t in (emu._lref, emu._l_prev, emu._t_last))
def status_kib(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return None
hwm_reset = False
if dev.startswith("cuda"):
    torch.cuda.synchronize(); torch.cuda.reset_peak_memory_stats(); base = torch.cuda.memory_allocated()
else:
    try:  # reset the peak-RSS counter (VmHWM) so that earlier peaks do not hide the step's
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        hwm_reset = True
        base = status_kib("VmRSS") * 1024
    except OSError:
        base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
import time
t_wall, t_cpu = time.perf_counter(), time.process_time()
ev = emu.step(f1, 100_000)
if dev.startswith("cuda"):
    torch.cuda.synchronize()
t_wall, t_cpu = time.perf_counter() - t_wall, time.process_time() - t_cpu
if dev.startswith("cuda"):
    torch.cuda.synchronize(); peak = torch.cuda.max_memory_allocated() - base; method = "cuda.max_memory_allocated"
elif hwm_reset:
    peak = status_kib("VmHWM") * 1024 - base; method = "VmHWM - VmRSS before (HWM reset)"
else:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - base; method = "ru_maxrss growth"
out_bytes = sum(getattr(ev, k).numel() * getattr(ev, k).element_size() for k in "bxytp")
print(json.dumps({"B": B, "H": H, "W": W, "events": len(ev), "events_per_px": len(ev) / (B * H * W),
                  "peak_step_bytes": peak, "output_bytes": out_bytes, "state_bytes": state_bytes,
                  "method": method, "step_wall_s": t_wall, "step_cpu_s": t_cpu}))
"""


def burst_memory(B, H, W, device):
    """Peak memory of one step with 10 events per pixel, in a fresh subprocess."""
    res = subprocess.run([sys.executable, "-c", _MEM_CHILD, str(B), str(H), str(W), str(device)],
                         capture_output=True, text=True, timeout=1200)
    if res.returncode != 0:
        return {"error": res.stderr.strip()[-500:]}
    return json.loads(res.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, nargs="+", default=[18, 256])
    ap.add_argument("--size", type=int, default=128, help="H = W, pixels")
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 0.5],
                    help="target events/pixel/step of the synthetic frames")
    ap.add_argument("--steps", type=int, default=12, help="frames per run (first 2 steps are warm-up)")
    ap.add_argument("--device", default="all", help="cpu, cuda, or all (cpu + cuda if available)")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = torch default)")
    ap.add_argument("--cpu-time", action="store_true",
                    help="time with process CPU time instead of wall clock (use with --threads 1 on a "
                         "loaded machine: waiting for a core is then not counted)")
    ap.add_argument("--no-real", action="store_true", help="skip rendered descent frames")
    ap.add_argument("--no-memory", action="store_true", help="skip the burst memory measurement")
    ap.add_argument("--json", default=None, help="also write the results to this JSON file")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    devices = ["cpu", "cuda"] if args.device == "all" else [args.device]
    devices = [d for d in devices if d == "cpu" or torch.cuda.is_available()]
    H = W = args.size
    rows, mem = [], []
    clock = time.perf_counter
    if args.cpu_time:
        if "cuda" in devices:
            raise SystemExit("--cpu-time is for CPU runs only (--device cpu)")
        clock = time.process_time
    print(f"# torch {torch.__version__}, CPU threads {torch.get_num_threads()}, "
          f"clock {'process CPU time' if args.cpu_time else 'wall'}, "
          f"load avg {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    for dev in devices:
        for B in args.batch:
            for rate in args.rates:
                frames = calibrated_frames(B, H, W, args.steps, rate, dev)
                r = time_steps(frames, dev, clock=clock)
                r.update(device=dev, frames=f"synthetic ~{rate:g} ev/px")
                rows.append(r)
                _print_row(r)
            if not args.no_real:
                t0 = time.perf_counter()
                frames = descent_frames(B, args.steps, dev)
                if frames is not None:
                    r = time_steps(frames, dev, clock=clock)
                    r.update(device=dev, frames="descent (fast renderer, A-I)",
                             render_s=time.perf_counter() - t0)
                    rows.append(r)
                    _print_row(r)
        if not args.no_memory:
            m = burst_memory(256, H, W, dev)
            m["device"] = dev
            mem.append(m)
            if "error" in m:
                print(f"burst memory {dev}: error {m['error']}")
            else:
                print(f"burst memory {dev}: B={m['B']} {m['H']}x{m['W']}, {m['events']} events "
                      f"({m['events_per_px']:.1f}/px): peak {m['peak_step_bytes'] / 2**30:.2f} GiB during "
                      f"the step ({m['method']}), output {m['output_bytes'] / 2**30:.2f} GiB, "
                      f"state {m['state_bytes'] / 2**20:.0f} MiB; step {m['step_wall_s']:.2f} s wall, "
                      f"{m['step_cpu_s']:.2f} s CPU")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"steps": rows, "burst_memory": mem, "torch": torch.__version__,
                       "threads": torch.get_num_threads()}, fh, indent=2)
    return 0


_HEADER = False


def _print_row(r):
    global _HEADER
    if not _HEADER:
        print(f"{'device':6} {'B':>4} {'frames':32} {'ev/px/step':>10} {'step ms':>9} {'log ms':>8} "
              f"{'x log':>6} {'Mev/s':>7}")
        _HEADER = True
    print(f"{r['device']:6} {r['B']:>4} {r['frames']:32} {r['events_per_px_step']:>10.2f} "
          f"{r['step_ms_median']:>9.2f} {r['log_ms_median']:>8.3f} {r['x_log']:>6.1f} "
          f"{r['events_per_s'] / 1e6:>7.2f}")


if __name__ == "__main__":
    sys.exit(main())
