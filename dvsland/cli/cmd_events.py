"""``dvsland events [CONFIG] --sites A[,B~1,...] --from-m 1000 --to-m 800 [--renderer fast|pyrender]
[--format npz|h5] [--threads N] [--out DIR] [--set key=value ...] [--quiet]``: the events of a
descent segment.

Renders each site along the ideal (closed-form) descent (s = 1 + c^2 v0 t / z0,
z = z0 s^(1/c^2)) from ``--from-m`` down to ``--to-m`` at the camera frame rate, emulates the
event camera (config ``emulator``) and writes into the run folder (``--out`` or
``logs/<name>-events-<stamp>/``):

- ``events.npz`` or ``events.h5``: all events, b = the site's index in ``--sites`` (0 for one
  site), t in µs of flight time since the start of that site's descent (z = z0 at t = 0), with
  sensor size and thresholds as metadata, and the per-frame ground truth (``gt_b``, ``gt_t_us``,
  ``gt_altitude_m``, ``gt_velocity_mps``, ``gt_divergence``) that ``dvsland evaluate --recording``
  reads back;
- ``event_frame.png``: the events of the last ``--window-ms`` (default: one frame interval),
  ON red, OFF blue, on white (as the paper's Figure 1);
- ``events_xyt.png``: a 3-D x-y-t scatter of the events of the last ``--scatter-ms`` (default
  500 ms, at most ``--max-points`` points), ON red, OFF blue (as the paper's Figure 3);
- ``frame_last.png``: the last rendered frame (log irradiance, percentile stretch);
- ``summary.json``: frames, times, altitudes, event counts;
- ``tb/``: TensorBoard (altitude and events per step against flight time, the event frame, the
  last frame, the config).

With several sites the figures are ``event_frame_<site>.png``, ``events_xyt_<site>.png`` and
``frame_last_<site>.png``, TensorBoard has one sub-folder per site, and ``summary.json`` one entry
per site under ``sites``.
"""

from __future__ import annotations

import time

from dvsland.report.results import write_json

from .common import add_config_args, add_threads_arg, apply_threads, config_from_args, parse_sites, ranged


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "events", help="render a descent segment and write its events and figures",
        description="Render each site along the ideal descent from --from-m down to --to-m at the camera "
                    "frame rate, emulate the event camera and write the events with their per-frame ground "
                    "truth (.npz or .h5; dvsland evaluate --recording reads both), an event frame (ON red, "
                    "OFF blue), an x-y-t scatter, the last frame, summary.json and TensorBoard files into the "
                    "run folder.")
    add_config_args(p)
    p.add_argument("--sites", default=None, metavar="A,B~1,...",
                   help="sites A-I or terrain variants such as A~1, comma-separated (default A); each gets "
                        "its own batch index b in the event file")
    p.add_argument("--site", default=None, metavar="SITE", help="one site (the same as --sites SITE)")
    p.add_argument("--from-m", type=float, default=1000.0, help="start altitude, m (default 1000)")
    p.add_argument("--to-m", type=float, default=800.0, help="end altitude, m (default 800)")
    p.add_argument("--renderer", default=None, help="renderer (default: config render.renderer)")
    p.add_argument("--format", default="npz", choices=("npz", "h5"), help="event file format (default npz)")
    p.add_argument("--device", default=None, help="torch device (default: config simulation.device)")
    add_threads_arg(p)
    p.add_argument("--window-ms", type=ranged(float, 0.001, 1e6, "--window-ms"), default=None,
                   help="event frame window, ms (default: one frame interval)")
    p.add_argument("--scatter-ms", type=ranged(float, 0.001, 1e6, "--scatter-ms"), default=500.0, help="x-y-t scatter window, ms (default 500)")
    p.add_argument("--max-points", type=ranged(int, 1, 10_000_000, "--max-points"), default=30000, help="most points in the x-y-t scatter")
    p.set_defaults(func=run_events)


def frame_schedule(cfg, site: str, from_m: float, to_m: float, with_velocity: bool = False):
    """Frame times (µs, int64 numpy) and altitudes (m) of ``site``'s ideal descent from ``from_m``
    to ``to_m`` (:func:`dvsland.dynamics.closed_form_descent` at the frame interval; the altitude is
    taken at the frame time rounded to the µs event clock); with ``with_velocity`` also the
    vertical velocities (m/s, negative descending) at those times."""
    import numpy as np

    from dvsland.dynamics import closed_form_descent, closed_form_state

    z0, v0 = cfg.initial_conditions(site)
    if not (from_m > to_m > 0):
        raise ValueError(f"--from-m must be > --to-m > 0, got from {from_m} to {to_m}")
    if from_m > z0:
        raise ValueError(f"--from-m must be <= the site's z0 = {z0} m, got {from_m}")
    t_s, _, _ = closed_form_descent(z0, v0, cfg.controller.c2, from_m=from_m, to_m=to_m, dt_s=cfg.dt_s)
    t_us = np.round(t_s * 1e6).astype(np.int64)
    z, v = closed_form_state(t_us * 1e-6, z0, v0, cfg.controller.c2)
    return (t_us, z, v) if with_velocity else (t_us, z)


def _site_list(args) -> list:
    if args.site is not None and args.sites is not None:
        raise ValueError("give --sites or --site, not both")
    if args.site is not None:
        return parse_sites(args.site, "--site")
    return parse_sites(args.sites) if args.sites is not None else ["A"]


def run_events(args) -> int:
    import numpy as np
    import torch

    from dvsland.events import Events, GroundTruth, save_events
    from dvsland.report.images import draw_event_frame, draw_xyt_scatter, event_frame_rgb, save_frame_png
    from dvsland.runs import make_run_dir
    from dvsland.stages import build_event_source

    sites = _site_list(args)  # before anything is loaded or written
    cfg = config_from_args(args)
    quiet = cfg.logging.quiet
    lo, hi = cfg.render.min_altitude_m, cfg.render.max_altitude_m
    plans = []
    for site in sites:  # every schedule is checked before the run folder exists
        z0, v0 = cfg.initial_conditions(site)
        t_us, z, v = frame_schedule(cfg, site, args.from_m, args.to_m, with_velocity=True)
        if z.min() < lo or z.max() > hi:
            raise ValueError(f"altitudes {z.min():.1f}-{z.max():.1f} m are outside the renderer's range "
                             f"[render.min_altitude_m, render.max_altitude_m] = [{lo}, {hi}] m")
        plans.append((site, z0, v0, t_us, z, v))
    apply_threads(cfg)
    run_dir = make_run_dir(cfg, args.out, kind="events")
    dev = torch.device(cfg.simulation.device)
    H, W = cfg.camera.height_px, cfg.camera.width_px
    many = len(sites) > 1
    window_us = int(round((args.window_ms if args.window_ms is not None else cfg.dt_s * 1e3) * 1e3))
    all_events, truths, per_site, last_frames = [], [], [], []
    t_start = time.perf_counter()
    emu = None
    for i, (site, z0, v0, t_us, z, v) in enumerate(plans):
        t_site = time.perf_counter()
        source = build_event_source(cfg, [site], dev)
        emu = source.emulator
        site_idx = torch.zeros(1, dtype=torch.int64)

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
        ev = Events.cat(chunks).to("cpu") if chunks else Events.empty()
        all_events.append(Events(torch.full_like(ev.b, i), ev.x, ev.y, ev.t, ev.p))
        truths.append(GroundTruth.from_altitude(t_us, z, v))
        last_frames.append(frame[0])
        t_end = int(t_us[-1])
        per_site.append({
            "site": site, "b": i, "z0_m": z0, "v0_mps": v0, "from_m": args.from_m, "to_m": args.to_m,
            "frames": int(len(t_us)), "t_first_us": int(t_us[0]), "t_last_us": t_end,
            "altitude_first_m": float(z[0]), "altitude_last_m": float(z[-1]),
            "events": len(ev), "events_on": int((ev.p > 0).sum()), "events_per_step": per_step,
            "events_per_px_step": (len(ev) / max(1, len(per_step)) / (H * W)),
            "seconds": time.perf_counter() - t_site})
    events = Events.cat(all_events)
    elapsed = time.perf_counter() - t_start

    path = save_events(run_dir / f"events.{args.format}", events, sensor_size=(W, H), batch_size=len(sites),
                       threshold=emu.threshold, threshold_off=emu.threshold_off,
                       refractory_us=emu.refractory_us, ground_truth=truths)
    for i, (site, z0, v0, t_us, z, v) in enumerate(plans):
        sfx = f"_{site}" if many else ""
        ev = all_events[i]
        t_end = int(t_us[-1])
        draw_event_frame(ev, H, W, t_end - window_us, t_end, run_dir / f"event_frame{sfx}.png",
                         title=f"site {site}, {z[-1]:.0f} m, last {window_us / 1e3:g} ms")
        draw_xyt_scatter(ev, H, W, t_end - int(args.scatter_ms * 1e3), t_end, run_dir / f"events_xyt{sfx}.png",
                         max_points=args.max_points, seed=cfg.simulation.seed,
                         title=f"site {site}, events of the last {args.scatter_ms:g} ms")
        save_frame_png(last_frames[i], run_dir / f"frame_last{sfx}.png")
    common = {"renderer": cfg.render.renderer, "events_file": path.name, "ground_truth": "per frame, in the events file"}
    if many:
        summary = {"sites": per_site, "events": len(events), "seconds": elapsed, **common}
    else:
        summary = {**per_site[0], "seconds": elapsed, **common}
        summary.pop("b")
    write_json(run_dir / "summary.json", summary)
    if cfg.logging.tensorboard:
        from PIL import Image

        from dvsland.config import dump_config
        from dvsland.report.tensorboard import write_events_tensorboard

        for i, (site, z0, v0, t_us, z, v) in enumerate(plans):
            sfx = f"_{site}" if many else ""
            t_end = int(t_us[-1])
            write_events_tensorboard(run_dir / "tb" / site if many else run_dir / "tb", t_us, z,
                                     per_site[i]["events_per_step"],
                                     event_frame=event_frame_rgb(all_events[i], H, W, t_end - window_us, t_end),
                                     last_frame=np.asarray(Image.open(run_dir / f"frame_last{sfx}.png")),
                                     cfg_yaml=dump_config(cfg), summary=per_site[i])
    if quiet:
        print(f"run folder: {run_dir}")
    else:
        for r in per_site:
            print(f"site {r['site']}: {r['events']} events from {r['frames']} frames ({r['altitude_first_m']:.0f} m -> "
                  f"{r['altitude_last_m']:.0f} m, {r['events_per_px_step']:.3f} events/pixel/step) in "
                  f"{r['seconds']:.1f} s")
        print(f"wrote {path.name} ({len(events)} events, per-frame ground truth) and figures -> {run_dir}")
    return 0
