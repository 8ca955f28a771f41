#!/usr/bin/env python
"""Measure the pyrender reference and the agreement of the fast renderer with it.

1. Timing: pyrender seconds per 128x128 frame -- at a new mesh level (terrain sampling, mesh,
   shadow map, render), and at a cached level with and without shadows; fast renderer for
   comparison (B = 1 and B = 18).
2. Agreement over a descent (log-spaced altitudes, e.g. 10 from 5 km to 50 m) on a few sites:
   per-frame Pearson correlation of log-irradiance, mean log ratio (pyrender / fast) and the
   spread of the log difference; also with the reference's emission angle taken from straight
   up (``view="nadir"``, the fast renderer's photometric simplification) to separate geometry
   from photometry.
3. Events (when :class:`dvsland.events.EventEmulator` exists): short descent segments at
   constant divergence rendered by both, fed to the same emulator; relative difference of the
   event counts per step.

Prints a table, writes JSON (``--out``) and a side-by-side PNG (``--png``; per site a row of
fast | pyrender pairs, each pair on a shared log scale).

Example::

    python scripts/compare_renderers.py --sites A E H --n-alt 10 --out logs/compare_renderers.json \
        --png logs/compare_renderers.png
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    a = a.ravel() - a.mean()
    b = b.ravel() - b.mean()
    den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else float("nan")


def _timing(fast, pyr, site: int, altitude_m: float, n: int):
    """Seconds per frame of pyrender (new level, cached level +/- shadows) and of fast."""
    res = {}
    pyr._cache.clear()
    pyr._scene_key = None
    t0 = time.perf_counter()
    pyr.render(torch.tensor([altitude_m]), torch.tensor([site]))
    res["pyrender_new_level_s"] = time.perf_counter() - t0
    lvl = pyr.level_of(altitude_m)
    alts = [altitude_m * (1 - 0.002 * (k + 1)) for k in range(n)]
    alts = [a for a in alts if pyr.level_of(a) == lvl] or [altitude_m]
    for shadows in (True, False):
        pyr.shadows = shadows
        pyr.render(torch.tensor([alts[0]]), torch.tensor([site]))  # warm (shadow map / program)
        t0 = time.perf_counter()
        for a in alts:
            pyr.render(torch.tensor([a]), torch.tensor([site]))
        res[f"pyrender_cached_level_{'shadows' if shadows else 'no_shadows'}_s"] = (time.perf_counter() - t0) / len(alts)
    pyr.shadows = True
    for b in (1, 18):
        a = torch.full((b,), altitude_m)
        s = torch.full((b,), site, dtype=torch.long)
        fast.render(a, s)
        t0 = time.perf_counter()
        for _ in range(5):
            fast.render(a, s)
        res[f"fast_B{b}_s_per_batch"] = (time.perf_counter() - t0) / 5
    return res


def _montage(pairs, path: Path, sites, altitudes_m):
    """pairs: list (rows = sites) of lists (altitudes) of (fast (H,W), pyr (H,W)); saves a labelled PNG
    (:func:`dvsland.report.style.renderer_pairs_figure`: which tile is fast / pyrender, site, altitude)."""
    from dvsland.report.style import renderer_pairs_figure

    renderer_pairs_figure(pairs, sites, altitudes_m, path)


def _events(fast, pyr, site: int, z0_m: float, divergence: float, steps: int, dt_s: float, emu_kwargs,
            fixed_mesh: bool = False):
    """Event counts per step for both renderers over z(t) = z0 exp(D t).

    ``fixed_mesh``: the reference renders the whole segment from one mesh (no level switches)."""
    from dvsland.events import EventEmulator

    t = np.arange(steps + 1) * dt_s
    z = z0_m * np.exp(divergence * t)
    alt = torch.tensor(z, dtype=torch.float32)
    idx = torch.full((steps + 1,), site, dtype=torch.long)
    frames_fast = fast.render(alt, idx)
    if fixed_mesh:
        pyr.fix_mesh_range(float(z.max()), float(z.min()))
    try:
        frames_pyr = pyr.render(alt, idx)
    finally:
        pyr.fix_mesh_range()
    emu = EventEmulator(**emu_kwargs)
    emu.reset(torch.stack([frames_fast[0], frames_pyr[0]]), t_us=0)
    n_fast, n_pyr = [], []
    for k in range(1, steps + 1):
        ev = emu.step(torch.stack([frames_fast[k], frames_pyr[k]]), t_us=int(round(t[k] * 1e6)))
        c = torch.bincount(ev.b, minlength=2).tolist()
        n_fast.append(int(c[0]))
        n_pyr.append(int(c[1]))
    nf, npy = np.array(n_fast, float), np.array(n_pyr, float)
    rel = (npy - nf) / np.maximum(nf, 1.0)
    return {"z_m": z.tolist(), "events_fast": n_fast, "events_pyrender": n_pyr,
            "rel_diff_per_step": rel.tolist(), "rel_diff_mean": float(rel.mean()),
            "rel_diff_median_abs": float(np.median(np.abs(rel))),
            "rel_diff_total": float((npy.sum() - nf.sum()) / max(nf.sum(), 1.0))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sites", nargs="+", default=["A", "E", "H"])
    ap.add_argument("--n-alt", type=int, default=10, help="altitudes of the descent (log-spaced)")
    ap.add_argument("--alt-max", type=float, default=5000.0)
    ap.add_argument("--alt-min", type=float, default=50.0)
    ap.add_argument("--timing-frames", type=int, default=5)
    ap.add_argument("--segments", nargs="*", type=float, default=[1000.0, 100.0],
                    help="start altitudes of the event segments, m (empty: no event comparison)")
    ap.add_argument("--segment-steps", type=int, default=10)
    ap.add_argument("--divergence", type=float, default=-0.2, help="D = v/z of the segments, 1/s")
    ap.add_argument("--dt", type=float, default=0.1, help="frame interval of the segments, s")
    ap.add_argument("--out", type=Path, default=Path("logs/compare_renderers.json"))
    ap.add_argument("--png", type=Path, default=None, help="side-by-side montage (default: next to --out)")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)

    from dvsland.config.schema import CameraConfig, EmulatorConfig, RenderConfig
    from dvsland.render import get_renderer
    from dvsland.render.gl_env import egl_available, egl_unavailable_reason

    if not egl_available():
        print(egl_unavailable_reason(), file=sys.stderr)
        return 2
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, flush=True))
    cam, rc = CameraConfig(), RenderConfig()
    t0 = time.perf_counter()
    fast = get_renderer("fast", args.sites, cam, rc)
    say(f"fast renderer ready in {time.perf_counter() - t0:.1f} s (levels: {fast.sources})")
    pyr = get_renderer("pyrender", args.sites, cam, rc)
    h0_diff = {s: pyr.ground_z_m(i) - fast.h0_m[s] for i, s in enumerate(args.sites)}
    say("landing-point height, pyrender minus fast (m):", {k: round(v, 4) for k, v in h0_diff.items()})

    result = {"command": " ".join([os.path.basename(sys.argv[0])] + (argv if argv is not None else sys.argv[1:])),
              "torch_threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
              "load_avg": os.getloadavg() if hasattr(os, "getloadavg") else None,
              "camera": vars(cam), "render": vars(rc),
              "pyrender": {"oversample": pyr.oversample, "mesh_upsample": pyr.mesh_upsample,
                           "lod_step": pyr.lod_step, "supersample": pyr.supersample,
                           "far_field": pyr.far_field, "lunar_l": dict(zip(args.sites, pyr.lunar_l))},
              "h0_diff_m": h0_diff}

    # 1. timing
    if args.timing_frames > 0:
        tm = _timing(fast, pyr, 0, 500.0, args.timing_frames)
        result["timing"] = tm
        say("timing (s):", {k: round(v, 4) for k, v in tm.items()})

    # 2. agreement over a descent
    alts = np.geomspace(args.alt_max, args.alt_min, args.n_alt)
    rows, montage_rows = [], []
    want = [a for a in (5000.0, 1000.0, 200.0, 50.0) if args.alt_min <= a <= args.alt_max] or list(alts[:4])
    show = sorted({int(np.argmin(np.abs(alts - a))) for a in want})
    say(f"\n{'site':>4} {'alt_m':>8} {'corr_log':>9} {'corr_nadir':>10} {'mean_log_ratio':>14} {'std_log_diff':>12} {'s/frame':>8}")
    for si, s in enumerate(args.sites):
        a = torch.tensor(alts, dtype=torch.float32)
        idx = torch.full((len(alts),), si, dtype=torch.long)
        f = fast.render(a, idx).cpu().numpy()
        t1 = time.perf_counter()
        pyr.view = "camera"
        p = pyr.render(a, idx).cpu().numpy()
        dt = (time.perf_counter() - t1) / len(alts)
        pyr.view = "nadir"  # same meshes (cached), only the emission angle changes
        pn = pyr.render(a, idx).cpu().numpy()
        pyr.view = "camera"
        pairs = []
        for k, alt in enumerate(alts):
            lf, lp, ln = np.log(f[k]), np.log(p[k]), np.log(pn[k])
            d = lp - lf
            row = {"site": s, "altitude_m": float(alt), "corr_log": _corr(lf, lp), "corr_log_nadir": _corr(lf, ln),
                   "mean_log_ratio": float(d.mean()), "std_log_diff": float(d.std()),
                   "std_log_fast": float(lf.std()), "std_log_pyrender": float(lp.std())}
            rows.append(row)
            say(f"{s:>4} {alt:8.1f} {row['corr_log']:9.4f} {row['corr_log_nadir']:10.4f} "
                f"{row['mean_log_ratio']:14.4f} {row['std_log_diff']:12.4f} {dt:8.2f}")
            if k in show:
                pairs.append((f[k], p[k]))
        montage_rows.append(pairs)
    result["agreement"] = rows
    summ = {}
    for s in args.sites:
        c = np.array([r["corr_log"] for r in rows if r["site"] == s])
        cn = np.array([r["corr_log_nadir"] for r in rows if r["site"] == s])
        summ[s] = {"corr_log_min": float(c.min()), "corr_log_mean": float(c.mean()),
                   "corr_log_nadir_min": float(cn.min()), "corr_log_nadir_mean": float(cn.mean())}
    result["summary"] = summ
    say("\nsummary:", json.dumps(summ, indent=1))
    png = args.png if args.png is not None else args.out.with_suffix(".png")
    _montage(montage_rows, png, args.sites, [float(alts[k]) for k in show])
    result["png"] = str(png)
    result["png_layout"] = {"rows": args.sites, "columns": [float(alts[k]) for k in show],
                            "cell": "fast (left) | pyrender (right), shared log scale"}
    say(f"montage: {png}")

    # 3. events
    try:
        import dvsland.events  # noqa: F401
        have_events = hasattr(dvsland.events, "EventEmulator")
    except Exception:
        have_events = False
    if args.segments and have_events:
        ec = EmulatorConfig()
        emu_kwargs = dict(threshold=ec.threshold, refractory_us=ec.refractory_us, log_eps=ec.log_eps,
                          interpolation=ec.interpolation)
        ev_rows = []
        say(f"\n{'site':>4} {'z0_m':>8} {'mesh':>7} {'events_fast':>12} {'events_pyr':>11} {'rel_total':>9} {'rel_med|.|':>10}")
        for si, s in enumerate(args.sites):
            for z0 in args.segments:
                for fixed in (False, True):
                    r = _events(fast, pyr, si, z0, args.divergence, args.segment_steps, args.dt, emu_kwargs,
                                fixed_mesh=fixed)
                    r.update(site=s, z0_m=z0, divergence=args.divergence, dt_s=args.dt,
                             pyrender_mesh="one mesh for the segment" if fixed else "levels")
                    ev_rows.append(r)
                    say(f"{s:>4} {z0:8.1f} {'fixed' if fixed else 'levels':>7} {sum(r['events_fast']):12d} "
                        f"{sum(r['events_pyrender']):11d} {r['rel_diff_total']:9.3f} {r['rel_diff_median_abs']:10.3f}")
        result["events"] = ev_rows
    elif args.segments:
        result["events"] = "dvsland.events.EventEmulator not available"
    result["wall_s"] = time.perf_counter() - t0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    say(f"\nwrote {args.out} ({result['wall_s']:.0f} s)")
    pyr.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
