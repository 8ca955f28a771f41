#!/usr/bin/env python
"""Benchmark of the fast renderer: site preparation, throughput, temporal smoothness.

    python scripts/bench_render.py [--sites A,...,I] [--batches 18,256] [--device cpu]
                                   [--fresh] [--json out.json] [--threads N]
                                   [--render-threads N]

- Preparation: seconds per site to build its levels (``--fresh``: recomputed, no caches).
- Throughput: ms per ``render`` call and frames/s for each batch size at the camera of
  ``configs/paper.yaml`` (128x128, 60 deg), altitudes spread over 50 m - 10 km, sites mixed.
- Temporal smoothness: a pure-zoom descent of a static scene on the closed-form
  trajectory (dvsland.dynamics.closed_form) at the frame rate (10 Hz) down to 50 m; d_t = log I_{t+1} -
  log I_t per pixel; the flicker metric is the fraction of pixels whose change reverses sign
  between consecutive steps (d_t * d_{t+1} < 0, both |d| > 1e-3), for the fast renderer and for
  an ablation without the blend between levels (nearest level), which pops.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import torch


def _sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def time_render(renderer, b: int, repeat: int, device):
    """Median wall ms and median process-CPU ms per render call of a batch of b frames (the CPU
    time excludes time the process waited for a core: on a shared machine, with one torch
    thread, it is the better estimate of the uncontended cost)."""
    g = torch.Generator().manual_seed(0)
    n_sites = len(renderer.site_names)
    alt = torch.exp(torch.empty(b).uniform_(math.log(50.0), math.log(10000.0), generator=g)).to(device)
    idx = (torch.arange(b) % n_sites).to(device)
    for _ in range(3):
        renderer.render(alt, idx)
    _sync(device)
    times, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        renderer.render(alt, idx)
        _sync(device)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(times) * 1e3, statistics.median(cpu) * 1e3


def descent(z0: float, v0: float, rate_hz: float, c2: float = 0.5, z_end: float = 50.0) -> torch.Tensor:
    """Closed-form altitudes sampled at rate_hz until z_end."""
    from dvsland.dynamics import closed_form_state, closed_form_time_to_altitude

    t = torch.arange(0.0, closed_form_time_to_altitude(z_end, z0, v0, c2), 1.0 / rate_hz, dtype=torch.float64)
    return torch.from_numpy(closed_form_state(t.numpy(), z0, v0, c2)[0]).float()


def reversal_fraction(renderer, site_i: int, z: torch.Tensor, chunk: int = 64, eps: float = 1e-3):
    """Flicker metric of a pure-zoom sequence (see module doc): (overall fraction, largest
    per-step fraction); a level pop shows as a large per-step fraction."""
    rev = 0
    both = 0
    worst = 0.0
    prev_log, prev_d = None, None
    for start in range(0, len(z), chunk):
        zz = z[start:start + chunk]
        logs = torch.log(renderer.render(zz, torch.full((len(zz),), site_i, dtype=torch.long))).cpu()
        if prev_log is not None:
            logs = torch.cat([prev_log[None], logs])
        d = logs[1:] - logs[:-1]
        if prev_d is not None:
            d = torch.cat([prev_d[None], d])
        ok = (d[1:].abs() > eps) & (d[:-1].abs() > eps)
        r = ((d[1:] * d[:-1]) < 0) & ok
        rev += int(r.sum())
        both += int(ok.sum())
        per_step = r.flatten(1).sum(1).float() / ok.flatten(1).sum(1).clamp(min=1).float()
        if per_step.numel():
            worst = max(worst, float(per_step.max()))
        prev_log, prev_d = logs[-1], d[-1]
    return rev / max(both, 1), worst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sites", default="A,B,C,D,E,F,G,H,I")
    ap.add_argument("--batches", default="18,256")
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--fresh", action="store_true", help="recompute the levels (no memory/disk cache)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads of the process (the closed loop uses 1)")
    ap.add_argument("--render-threads", type=int, default=None,
                    help="threads inside a render call (render.threads; default 0 = all cores)")
    ap.add_argument("--flicker-sites", default="A,E,H", help="sites of the smoothness test ('' = skip)")
    ap.add_argument("--json", default=None, help="write the results as JSON to this path")
    args = ap.parse_args(argv)

    from dvsland.config import load_config
    from dvsland.render import get_renderer

    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = load_config()
    sites = [s for s in args.sites.split(",") if s]
    if args.fresh:
        from dvsland.render import lod
        lod._MEMORY.clear()
    t0 = time.perf_counter()
    if args.render_threads is not None:
        cfg.render.threads = args.render_threads
    renderer = get_renderer("fast", sites, cfg.camera, cfg.render, device=args.device,
                            disk_cache=not args.fresh)
    total_prep = time.perf_counter() - t0
    res = {"device": str(renderer.device), "threads": torch.get_num_threads(), "render_threads": renderer.threads,
           "camera": f"{cfg.camera.width_px}x{cfg.camera.height_px} fov {cfg.camera.fov_deg}",
           "levels": renderer.levels.__dict__, "prep_s_per_site": renderer.prep_s,
           "prep_cpu_s_per_site": renderer.prep_cpu_s,
           "prep_total_s": total_prep, "throughput": {}, "flicker": {}}
    print(f"device {res['device']}, torch threads {res['threads']}, render threads {res['render_threads']}, "
          f"camera {res['camera']}")
    print(f"levels: {renderer.levels.n_levels} x {renderer.levels.tile_size}^2 texels per site, "
          f"texel0 {renderer.levels.base_texel_m:.3f} m")
    print("preparation (wall s / cpu s): " + ", ".join(
        f"{k} {v:.2f}/{renderer.prep_cpu_s[k]:.2f} ({renderer.sources[k]})" for k, v in renderer.prep_s.items())
          + f"; total {total_prep:.2f} s")
    print(f"\n{'batch':>6} {'ms/call':>9} {'cpu ms':>8} {'frames/s':>10}")
    for b in [int(x) for x in args.batches.split(",") if x]:
        ms, cpu_ms = time_render(renderer, b, args.repeat, args.device)
        res["throughput"][b] = {"ms_per_call": ms, "cpu_ms_per_call": cpu_ms, "frames_per_s": b / ms * 1e3}
        print(f"{b:>6} {ms:>9.2f} {cpu_ms:>8.2f} {b / ms * 1e3:>10.0f}")
    fl_sites = [s for s in args.flicker_sites.split(",") if s and s in sites]
    if fl_sites:
        nearest = get_renderer("fast", sites, cfg.camera, cfg.render, device=args.device, blend_levels=False)
        rate = cfg.camera.frame_rate_hz
        print(f"\nflicker: fraction of sign reversals of d log I between steps, pure zoom at {rate:g} Hz")
        print(f"{'site':>5} {'frames':>7} {'fast':>8} {'worst step':>11} {'nearest-level':>14} {'worst step':>11}")
        for s in fl_sites:
            z0, v0 = cfg.initial_conditions(s)
            z = descent(z0, v0, rate, cfg.controller.c2)
            i = sites.index(s)
            f_fast, w_fast = reversal_fraction(renderer, i, z)
            f_near, w_near = reversal_fraction(nearest, i, z)
            res["flicker"][s] = {"frames": len(z), "fast": f_fast, "fast_worst_step": w_fast,
                                 "nearest_level": f_near, "nearest_level_worst_step": w_near}
            print(f"{s:>5} {len(z):>7} {f_fast:>8.4f} {w_fast:>11.4f} {f_near:>14.4f} {w_near:>11.4f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=2, default=str)
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
