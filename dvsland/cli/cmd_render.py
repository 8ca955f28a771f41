"""``dvsland render``: frames, a labelled montage (altitudes x sites), a descent GIF and meshes.

Writes into the run folder (``--out`` or ``logs/<name>-render-<stamp>/``):

- ``frames/<site>_<altitude>m.png`` and ``frames.npz`` (linear irradiance, float32,
  shape (altitudes, sites, H, W), with the altitudes and site names),
- ``montage.png``: rows = altitudes, columns = sites, labelled,
- ``descent_<site>.gif``: the closed-form ideal descent (:func:`dvsland.dynamics.closed_form_descent`)
  of the first site from its z0 (config ``simulation.sites``, else the paper's) to 50 m,
- ``mesh_<site>_<altitude>m.ply`` for every ``--export-mesh SITE:ALTITUDE`` (the footprint at
  that altitude as a trimesh heightfield),
- TensorBoard event files (montage, frames, GIF frames, the config as text).

Display mapping (PNG and GIF only; the data stay linear): log irradiance, linearly stretched
between its 1st and 99.5th percentile, per image for frames and montage tiles, once over the
whole sequence for the GIF (so brightness changes along the descent are kept).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import List

import numpy as np
import torch

from .common import add_config_args, config_from_args

def register(subparsers) -> None:
    p = subparsers.add_parser("render", help="render sites: frames, montage, descent GIF, meshes",
                              description=__doc__.split("\n\n")[0])
    add_config_args(p)
    p.add_argument("--sites", default=None, help="comma-separated sites (default: the config's sites)")
    p.add_argument("--altitudes", default="5000,1000,200,50", help="comma-separated altitudes, m")
    p.add_argument("--renderer", default=None, metavar="NAME",
                   help="renderer: fast, pyrender or a registered one (default: config render.renderer)")
    p.add_argument("--export-mesh", action="append", default=[], metavar="SITE:ALTITUDE",
                   help="export the footprint at ALTITUDE m of SITE as a .ply mesh (repeatable)")
    p.add_argument("--mesh-texels", type=int, default=256, help="mesh vertices per side (default 256)")
    p.add_argument("--gif-frames", type=int, default=60, help="frames of the descent GIF (0: no GIF)")
    p.add_argument("--scale", type=int, default=2, help="montage pixel scale (default 2)")
    p.add_argument("--device", default=None, help="torch device (default: config simulation.device)")
    p.set_defaults(func=run_render)


def _parse_list(text: str, what: str, cast=float) -> list:
    try:
        return [cast(x.strip()) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--{what}: expected a comma-separated list, got {text!r}") from None


# ------------------------------------------------------------------ command
def run_render(args) -> int:
    from dvsland.dynamics import closed_form_descent
    from dvsland.render import get_renderer
    from dvsland.report.images import montage, to_display
    from dvsland.runs import make_run_dir

    cfg = config_from_args(args)
    quiet = cfg.logging.quiet
    if args.sites:
        sites = _parse_list(args.sites, "sites", str)
    else:
        sites = list(dict.fromkeys(s.name for s in cfg.simulation.sites)) or ["A"]
    alts = _parse_list(args.altitudes, "altitudes")
    if not alts:
        raise ValueError("--altitudes: give at least one altitude")
    rc = cfg.render
    for a in alts:
        if not rc.min_altitude_m <= a <= rc.max_altitude_m:
            raise ValueError(f"--altitudes: {a} m is outside [render.min_altitude_m, render.max_altitude_m] "
                             f"= [{rc.min_altitude_m}, {rc.max_altitude_m}]")
    name = args.renderer or rc.renderer
    device = args.device or cfg.simulation.device
    run_dir = make_run_dir(cfg, args.out, kind="render")
    t0 = time.perf_counter()
    kwargs = {"progress": not quiet} if name == "fast" else {}
    renderer = get_renderer(name, sites, cfg.camera, rc, device=device, **kwargs)
    prep_s = time.perf_counter() - t0

    # ---- frames and montage
    n_a, n_s = len(alts), len(sites)
    alt_t = torch.tensor(alts, dtype=torch.float32).repeat_interleave(n_s)
    idx_t = torch.arange(n_s, dtype=torch.int64).repeat(n_a)
    t1 = time.perf_counter()
    frames = renderer.render(alt_t, idx_t).float().cpu()
    render_s = time.perf_counter() - t1
    h, w = frames.shape[-2:]
    disp = to_display(frames).reshape(n_a, n_s, h, w)
    fdir = run_dir / "frames"
    fdir.mkdir(exist_ok=True)
    from PIL import Image

    for i, a in enumerate(alts):
        for j, s in enumerate(sites):
            Image.fromarray(disp[i, j]).save(fdir / f"{s}_{a:g}m.png")
    np.savez_compressed(run_dir / "frames.npz", irradiance=frames.reshape(n_a, n_s, h, w).numpy(),
                        altitude_m=np.asarray(alts), sites=np.asarray(sites))
    mont = montage(disp, [f"{a:g} m" for a in alts], sites, scale=max(1, args.scale))
    mont.save(run_dir / "montage.png")

    # ---- descent GIF (first site)
    gif_frames = None
    if args.gif_frames > 0:
        site = sites[0]
        z0, v0 = cfg.initial_conditions(site)
        z_end = max(50.0, rc.min_altitude_m)
        z0 = min(z0, rc.max_altitude_m)
        zs = (np.array([z0]) if args.gif_frames == 1 else
              closed_form_descent(z0, v0, cfg.controller.c2, to_m=z_end, n=args.gif_frames)[1])
        seq = renderer.render(torch.tensor(zs, dtype=torch.float32),
                              torch.zeros(len(zs), dtype=torch.int64)).float().cpu()
        gif_frames = to_display(seq, shared=True)
        ims = [Image.fromarray(f).resize((w * 2, h * 2), Image.NEAREST) for f in gif_frames]
        ims[0].save(run_dir / f"descent_{site}.gif", save_all=True, append_images=ims[1:], duration=100, loop=0)

    # ---- meshes
    meshes: List[Path] = []
    for spec in args.export_mesh:
        meshes.append(_export_mesh(spec, renderer, cfg, run_dir, args.mesh_texels))

    # ---- TensorBoard
    if cfg.logging.tensorboard:
        from torch.utils.tensorboard import SummaryWriter

        from dvsland.config import dump_config

        with SummaryWriter(log_dir=str(run_dir)) as tb:
            tb.add_text("config", "```\n" + dump_config(cfg) + "\n```")
            tb.add_image("render/montage", np.asarray(mont)[None], dataformats="CHW")
            for i, a in enumerate(alts):
                tb.add_images(f"render/frames_{a:g}m", disp[i][:, None], dataformats="NCHW")
            if gif_frames is not None:
                for k, f in enumerate(gif_frames):
                    tb.add_image(f"render/descent_{sites[0]}", f[None], global_step=k, dataformats="CHW")
    if not quiet:
        print(f"renderer {name}: prepared {len(sites)} site(s) in {prep_s:.2f} s, "
              f"{len(alts) * len(sites)} frames in {render_s * 1e3:.1f} ms")
        print(f"wrote {run_dir}/montage.png, frames/, frames.npz"
              + (f", descent_{sites[0]}.gif" if gif_frames is not None else "")
              + "".join(f", {m.name}" for m in meshes))
    return 0


def _export_mesh(spec: str, renderer, cfg, run_dir: Path, n: int) -> Path:
    try:
        site, alt = spec.split(":")
        alt_m = float(alt)
    except ValueError:
        raise ValueError(f"--export-mesh: expected SITE:ALTITUDE (e.g. A:200), got {spec!r}") from None
    if not alt_m > 0:
        raise ValueError(f"--export-mesh: altitude must be > 0 m, got {alt_m}")
    if not 8 <= n <= 4096:
        raise ValueError(f"--mesh-texels must be in [8, 4096], got {n}")
    from dvsland.render.mesh import terrain_mesh
    from dvsland.terrain import load_site

    terrain = load_site(site, cfg.render.sun_elevation_deg)
    extent = renderer.footprint_m(alt_m) * 1.1
    mesh = terrain_mesh(terrain, extent, n)
    path = run_dir / f"mesh_{site}_{alt_m:g}m.ply"
    mesh.export(path)
    return path
