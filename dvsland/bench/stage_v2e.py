#!/usr/bin/env python
"""dvsland's emulator against v2e on the same frames, and the pixel model's cost against the ideal one.

v2e is not on PyPI: copy its emulator (v2ecore/emulator.py and emulator_utils.py of
github.com/SensorsINI/v2e) into a folder outside the package (default bench_env/v2e/, git-ignored;
see docs/events.md) and point --v2e-dir at it. Without it, the dvsland rows are still measured.

    python scripts/bench_v2e.py [--batch 18] [--steps 12] [--frames descent|synthetic]
                                [--rate 0.6] [--identical] [--v2e-dir bench_env/v2e] [--threads 1]
                                [--json out.json]

dvsland is timed on the torch path and, where the compiled kernels can be built (a C++ compiler), on the
compiled kernels; the noise table is given for each.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=18, help="streams (B)")
    ap.add_argument("--steps", type=int, default=12, help="frames per stream (first = reset)")
    ap.add_argument("--frames", choices=("descent", "synthetic"), default="descent")
    ap.add_argument("--omega", type=float, default=0.1, help="synthetic frames: phase step per frame "
                    "(0.1: about 0.5 events per pixel per frame)")
    ap.add_argument("--rate", type=float, default=None, help="synthetic frames: calibrate omega to about this "
                    "many events per pixel per frame (e.g. 0.6; overrides --omega)")
    ap.add_argument("--identical", action="store_true", help="the setting in which both emulators emit the same "
                    "per-pixel counts: frames scaled into v2e's log region, log_eps 1e-9, refractory 0 "
                    "(dvsland.events.benchmark)")
    ap.add_argument("--size", type=int, nargs=2, default=(128, 128), metavar=("W", "H"))
    ap.add_argument("--v2e-dir", default=None, help="folder with v2ecore/ (default: bench_env/v2e in the repository)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-noise", action="store_true", help="skip the pixel-model table")
    ap.add_argument("--denoise", action="store_true", help="also time the front-end denoising chains on the "
                    "events of the noisy pixel (dvsland.events.denoise)")
    ap.add_argument("--preset", default=None, help="with --denoise: take the noisy pixel from this config's "
                    "emulator section (e.g. realistic_sensor; default: the NOISY settings of the table)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    from dvsland.config import CameraConfig
    from dvsland.events import native
    from dvsland.events.benchmark import bench_noise, bench_vs_v2e, calibrated_omega, format_results, smooth_frames

    from .frames import descent_frames

    if args.v2e_dir is None:
        from dvsland.config import repo_root

        args.v2e_dir = str(repo_root() / "bench_env" / "v2e")
    W, H = args.size
    if args.frames == "descent":
        frames = descent_frames(args.batch, args.steps, CameraConfig(width_px=W, height_px=H))
    else:
        if args.rate is not None:
            args.omega = calibrated_omega(args.batch, H, W, args.rate)
        frames = smooth_frames(args.batch, H, W, args.steps, omega=args.omega)
    v2e_dir = args.v2e_dir if Path(args.v2e_dir).exists() else None
    res = bench_vs_v2e(frames, v2e_dir, threads=args.threads, identical=args.identical)
    if v2e_dir is None:
        res["v2e_error"] = f"no v2e folder at {args.v2e_dir}"
    noise = {}
    for path in ([] if args.no_noise else list(res["paths"])):
        with native.native_sort_mode(path == "compiled"):
            noise[path] = bench_noise(frames, threads=args.threads)
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    print(format_results(res, None))
    for path, table in noise.items():
        print(f"\n[{path} path]" + format_results(None, table))
    den = None
    if args.denoise:
        from dvsland.events.benchmark import bench_denoise, format_denoise

        kw = None
        if args.preset:
            import dataclasses

            from dvsland.config import load_config
            from dvsland.events.pixel_model import PixelModelParams

            em = load_config(args.preset).emulator
            keys = [f.name for f in dataclasses.fields(PixelModelParams)] + ["mismatch_sigma", "background_rate_hz",
                                                                             "threshold", "refractory_us"]
            kw = {k: getattr(em, k) for k in keys}
        den = bench_denoise(frames, kw, threads=args.threads)
        print(format_denoise(den))
    print(f"load average {load}, frames: {args.frames}" + (f", omega {args.omega:.4g}" if args.frames == "synthetic" else ""))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"v2e": res, "noise": noise, "denoise": den, "load_average": load,
                                               "frames": args.frames,
                                               "omega": args.omega if args.frames == "synthetic" else None},
                                              indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
