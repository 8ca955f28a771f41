"""``dvsland events [CONFIG] --site A --from-m 1000 --to-m 800 [--renderer fast|pyrender]
[--format npz|h5] [--out DIR] [--set key=value ...] [--quiet]``: the events of a descent segment.

Renders one site along the ideal (closed-form) descent (s = 1 + c^2 v0 t / z0,
z = z0 s^(1/c^2)) from ``--from-m`` down to ``--to-m`` at the camera frame rate, emulates the
event camera (config ``emulator``) and writes into the run folder (``--out`` or
``logs/<name>-events-<stamp>/``):

- ``events.npz`` or ``events.h5``: all events (b = 0), t in µs of flight time since the start
  of the descent (z = z0 at t = 0), with sensor size and thresholds as metadata;
- ``event_frame.png``: the events of the last ``--window-ms`` (default: one frame interval),
  ON red, OFF blue, on white (as the paper's Figure 1);
- ``events_xyt.png``: a 3-D x-y-t scatter of the events of the last ``--scatter-ms`` (default
  500 ms, at most ``--max-points`` points), ON red, OFF blue (as the paper's Figure 3);
- ``frame_last.png``: the last rendered frame (log irradiance, percentile stretch);
- ``summary.json``: frames, times, altitudes, event counts;
- ``tb/``: TensorBoard (altitude and events per step against flight time, the event frame, the
  last frame, the config).
"""

from __future__ import annotations

import time

import numpy as np
import torch

from dvsland.report.results import write_json

from .common import add_config_args, config_from_args


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "events", help="render a descent segment and write its events and figures",
        description="Render one site along the ideal descent from --from-m down to --to-m at the camera "
                    "frame rate, emulate the event camera and write the events (.npz or .h5), an event "
                    "frame (ON red, OFF blue), an x-y-t scatter, the last frame, summary.json and "
                    "TensorBoard files into the run folder.")
    add_config_args(p)
    p.add_argument("--site", default="A", help="site name A-I (default A)")
    p.add_argument("--from-m", type=float, default=1000.0, help="start altitude, m (default 1000)")
    p.add_argument("--to-m", type=float, default=800.0, help="end altitude, m (default 800)")
    p.add_argument("--renderer", default=None, help="renderer (default: config render.renderer)")
    p.add_argument("--format", default="npz", choices=("npz", "h5"), help="event file format (default npz)")
    p.add_argument("--device", default=None, help="torch device (default: config simulation.device)")
    p.add_argument("--window-ms", type=float, default=None,
                   help="event frame window, ms (default: one frame interval)")
    p.add_argument("--scatter-ms", type=float, default=500.0, help="x-y-t scatter window, ms (default 500)")
    p.add_argument("--max-points", type=int, default=30000, help="most points in the x-y-t scatter")
    p.set_defaults(func=run_events)


def frame_schedule(cfg, site: str, from_m: float, to_m: float):
    """Frame times (µs, int64 numpy) and altitudes (m) of ``site``'s ideal descent from ``from_m``
    to ``to_m`` (:func:`dvsland.dynamics.closed_form_descent` at the frame interval; the altitude is
    taken at the frame time rounded to the µs event clock)."""
    from dvsland.dynamics import closed_form_descent, closed_form_state

    z0, v0 = cfg.initial_conditions(site)
    if not (from_m > to_m > 0):
        raise ValueError(f"--from-m must be > --to-m > 0, got from {from_m} to {to_m}")
    if from_m > z0:
        raise ValueError(f"--from-m must be <= the site's z0 = {z0} m, got {from_m}")
    t_s, _, _ = closed_form_descent(z0, v0, cfg.controller.c2, from_m=from_m, to_m=to_m, dt_s=cfg.dt_s)
    t_us = np.round(t_s * 1e6).astype(np.int64)
    return t_us, closed_form_state(t_us * 1e-6, z0, v0, cfg.controller.c2)[0]


def run_events(args) -> int:
    from dvsland.events import Events, save_events
    from dvsland.report.images import draw_event_frame, draw_xyt_scatter, event_frame_rgb, save_frame_png
    from dvsland.runs import make_run_dir
    from dvsland.stages import build_event_source

    cfg = config_from_args(args)
    quiet = cfg.logging.quiet
    site = args.site
    z0, v0 = cfg.initial_conditions(site)
    t_us, z = frame_schedule(cfg, site, args.from_m, args.to_m)
    lo, hi = cfg.render.min_altitude_m, cfg.render.max_altitude_m
    if z.min() < lo or z.max() > hi:
        raise ValueError(f"altitudes {z.min():.1f}-{z.max():.1f} m are outside the renderer's range "
                         f"[render.min_altitude_m, render.max_altitude_m] = [{lo}, {hi}] m")
    run_dir = make_run_dir(cfg, args.out, kind="events")
    dev = torch.device(cfg.simulation.device)
    t_start = time.perf_counter()
    source = build_event_source(cfg, [site], dev)
    emu = source.emulator
    site_idx = torch.zeros(1, dtype=torch.int64)
    H, W = cfg.camera.height_px, cfg.camera.width_px

    def alt(k):
        return torch.tensor([z[k]], dtype=torch.float32)

    frame = source.reset(alt(0), site_idx, int(t_us[0]))
    chunks, per_step = [], []
    steps = range(1, len(t_us))
    if not quiet:
        from tqdm import tqdm

        steps = tqdm(steps, desc=f"events site {site}", unit="frame")
    for k in steps:
        frame, ev = source.step(alt(k), site_idx, int(t_us[k]))
        chunks.append(ev)
        per_step.append(len(ev))
    events = Events.cat(chunks).to("cpu") if chunks else Events.empty()
    elapsed = time.perf_counter() - t_start

    path = save_events(run_dir / f"events.{args.format}", events, sensor_size=(W, H), batch_size=1,
                       threshold=emu.threshold, threshold_off=emu.threshold_off,
                       refractory_us=emu.refractory_us)
    window_us = int(round((args.window_ms if args.window_ms is not None else cfg.dt_s * 1e3) * 1e3))
    t_end = int(t_us[-1])
    draw_event_frame(events, H, W, t_end - window_us, t_end, run_dir / "event_frame.png",
                     title=f"site {site}, {z[-1]:.0f} m, last {window_us / 1e3:g} ms")
    draw_xyt_scatter(events, H, W, t_end - int(args.scatter_ms * 1e3), t_end, run_dir / "events_xyt.png",
                     max_points=args.max_points, seed=cfg.simulation.seed,
                     title=f"site {site}, events of the last {args.scatter_ms:g} ms")
    save_frame_png(frame[0], run_dir / "frame_last.png")
    summary = {
        "site": site, "z0_m": z0, "v0_mps": v0, "from_m": args.from_m, "to_m": args.to_m,
        "frames": int(len(t_us)), "t_first_us": int(t_us[0]), "t_last_us": t_end,
        "altitude_first_m": float(z[0]), "altitude_last_m": float(z[-1]),
        "events": len(events), "events_on": int((events.p > 0).sum()),
        "events_per_step": per_step,
        "events_per_px_step": (len(events) / max(1, len(per_step)) / (H * W)),
        "renderer": cfg.render.renderer, "seconds": elapsed, "events_file": path.name,
    }
    write_json(run_dir / "summary.json", summary)
    if cfg.logging.tensorboard:
        from PIL import Image

        from dvsland.config import dump_config
        from dvsland.report.tensorboard import write_events_tensorboard

        write_events_tensorboard(run_dir / "tb", t_us, z, per_step,
                                 event_frame=event_frame_rgb(events, H, W, t_end - window_us, t_end),
                                 last_frame=np.asarray(Image.open(run_dir / "frame_last.png")),
                                 cfg_yaml=dump_config(cfg), summary=summary)
    if quiet:
        print(f"run folder: {run_dir}")
    else:
        print(f"{len(events)} events from {len(t_us)} frames ({z[0]:.0f} m -> {z[-1]:.0f} m, "
              f"{summary['events_per_px_step']:.3f} events/pixel/step) in {elapsed:.1f} s -> {run_dir}")
    return 0
