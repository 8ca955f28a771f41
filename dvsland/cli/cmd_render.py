"""``dvsland render``: frames, a labelled montage (altitudes x sites), a descent GIF and meshes.

Writes into the run folder (``--out`` or ``logs/<name>-render-<stamp>/``):

- ``frames/<site>_<altitude>m.png`` and ``frames.npz`` (linear irradiance, float32, shape
  (altitudes, sites, H, W), with the altitudes and site names);
- ``montage.png``: rows = altitudes, columns = sites, with labels and a colorbar;
- ``descent_<site>.gif``: the ideal (closed-form) descent of the first site from its z0 (config
  ``simulation.sites``, else the paper's) to 50 m, with the altitude and time on every frame;
- ``mesh_<site>_<altitude>m.ply`` for every ``--export-mesh SITE:ALTITUDE`` (the footprint at
  that altitude as a trimesh heightfield);
- ``tb/``: TensorBoard (montage, frames, GIF frames at step = flight time in ms, the config).

Display mapping (PNG and GIF only; the data stay linear): log irradiance, linearly stretched
between its 1st and 99.5th percentile: once over all tiles of the montage and once over the whole
GIF (so brightness differences between sites, altitudes and along the descent stay visible), and
per image for ``frames/*.png``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import List

from .common import add_config_args, add_threads_arg, apply_threads, config_from_args, parse_sites, ranged


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="render sites: frames, montage, descent GIF, meshes",
        description="Render the chosen sites at the chosen altitudes and write frames (PNG and .npz), a "
                    "labelled montage (altitudes x sites), a descent GIF with the altitude on every frame, "
                    "optional .ply meshes and TensorBoard files into the run folder. Display images show "
                    "log irradiance stretched between its 1st and 99.5th percentile (one stretch over the "
                    "montage, one over the GIF).")
    add_config_args(p)
    p.add_argument("--sites", default=None, metavar="A,B~1,...",
                   help="comma-separated sites A-I or terrain variants such as A~1 (default: the config's sites)")
    p.add_argument("--altitudes", default="5000,1000,200,50", help="comma-separated altitudes, m")
    p.add_argument("--renderer", default=None, metavar="NAME",
                   help="renderer: fast, pyrender or a registered one (default: config render.renderer)")
    p.add_argument("--export-mesh", action="append", default=[], metavar="SITE:ALTITUDE",
                   help="export the footprint at ALTITUDE m of SITE as a .ply mesh (repeatable)")
    p.add_argument("--mesh-texels", type=ranged(int, 8, 4096, "--mesh-texels"), default=256,
                   help="mesh vertices per side of --export-mesh (8 to 4096, default 256)")
    p.add_argument("--gif-frames", type=ranged(int, 0, 10_000, "--gif-frames"), default=60,
                   help="frames of the descent GIF (0: no GIF)")
    p.add_argument("--scale", type=ranged(int, 1, 16, "--scale"), default=2,
                   help="montage tile size, x 0.8 inch (1 to 16, default 2)")
    p.add_argument("--device", default=None, help="torch device (default: config simulation.device)")
    add_threads_arg(p)
    p.set_defaults(func=run_render)


#: short notes under a site's montage column heading, for tiles that could read as a failed render
SITE_NOTES = {"H": "flat, dusty,\nfew features"}


def montage_labels(sites) -> List[str]:
    """Column names for the montage: the site (``A``, ``H~1``), and for a site whose tiles are nearly
    uniform by nature (H: flat and dusty) a second line, written on its tiles
    (:func:`dvsland.report.style.image_grid`), so they do not read as a failed render."""
    out = []
    for s in sites:
        note = SITE_NOTES.get(str(s).split("~")[0])
        out.append(f"{s}\n{s}: {note}" if note else str(s))
    return out


def _parse_list(text: str, what: str, cast=float) -> list:
    try:
        return [cast(x.strip()) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--{what}: expected a comma-separated list, got {text!r}") from None


# ------------------------------------------------------------------ command
def run_render(args) -> int:
    import numpy as np
    import torch

    from dvsland.dynamics import closed_form_descent
    from dvsland.render import get_renderer
    from dvsland.report.images import annotated_gif, montage, to_display
    from dvsland.runs import make_run_dir

    sites = parse_sites(args.sites)  # before anything is loaded or written
    cfg = config_from_args(args)
    quiet = cfg.logging.quiet
    if not sites:
        sites = list(dict.fromkeys(s.name for s in cfg.simulation.sites)) or ["A"]
    alts = _parse_list(args.altitudes, "altitudes")
    if not alts:
        raise ValueError("--altitudes: give at least one altitude")
    rc = cfg.render
    for a in alts:
        if not rc.min_altitude_m <= a <= rc.max_altitude_m:
            raise ValueError(f"--altitudes: {a} m is outside [render.min_altitude_m, render.max_altitude_m] "
                             f"= [{rc.min_altitude_m}, {rc.max_altitude_m}]")
    mesh_specs = [_parse_mesh_spec(spec, args.mesh_texels) for spec in args.export_mesh]
    name = args.renderer or rc.renderer
    device = args.device or cfg.simulation.device
    apply_threads(cfg)
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
    mont = montage(frames.reshape(n_a, n_s, h, w).numpy(), alts, montage_labels(sites), run_dir / "montage.png",
                   scale=max(1, args.scale), renderer=name)

    # ---- descent GIF (first site)
    gif_frames = t_gif = None
    if args.gif_frames > 0:
        site = sites[0]
        z0, v0 = cfg.initial_conditions(site)
        z_end = max(50.0, rc.min_altitude_m)
        z0 = min(z0, rc.max_altitude_m)
        t_gif, zs = ((np.array([0.0]), np.array([z0])) if args.gif_frames == 1 else
                     closed_form_descent(z0, v0, cfg.controller.c2, to_m=z_end, n=args.gif_frames)[:2])
        seq = renderer.render(torch.tensor(zs, dtype=torch.float32),
                              torch.zeros(len(zs), dtype=torch.int64)).float().cpu()
        gif_frames = to_display(seq, shared=True)
        annotated_gif(gif_frames, [f"site {site}  {z:,.0f} m  t = {t:.1f} s" for z, t in zip(zs, t_gif)],
                      run_dir / f"descent_{site}.gif")

    # ---- meshes
    meshes: List[Path] = []
    for site, alt_m in mesh_specs:
        meshes.append(_export_mesh(site, alt_m, renderer, cfg, run_dir, args.mesh_texels))

    # ---- TensorBoard
    if cfg.logging.tensorboard:
        from dvsland.config import dump_config
        from dvsland.report.tensorboard import flight_step, fresh_log_dir, summary_writer

        with summary_writer(fresh_log_dir(run_dir / "tb")) as tb:
            tb.add_text("config", "```yaml\n" + dump_config(cfg) + "\n```")
            tb.add_image("render/montage", mont, dataformats="HWC")
            for i, a in enumerate(alts):
                tb.add_images(f"render/frames_{a:g}m", disp[i][:, None], dataformats="NCHW")
            if gif_frames is not None:
                for f, t in zip(gif_frames, t_gif):  # step = flight time, ms
                    tb.add_image(f"render/descent_{sites[0]}", f[None], global_step=flight_step(t), dataformats="CHW")
    if quiet:
        print(f"run folder: {run_dir}")
    else:
        print(f"renderer {name}: prepared {len(sites)} site(s) in {prep_s:.2f} s, "
              f"{len(alts) * len(sites)} frames in {render_s * 1e3:.1f} ms")
        print(f"wrote {run_dir}/montage.png, frames/, frames.npz"
              + (f", descent_{sites[0]}.gif" if gif_frames is not None else "")
              + "".join(f", {m.name}" for m in meshes))
    return 0


def _parse_mesh_spec(spec: str, n: int) -> tuple:
    """``SITE:ALTITUDE`` of --export-mesh, checked before the run folder is made."""
    try:
        site, alt = spec.split(":")
        alt_m = float(alt)
    except ValueError:
        raise ValueError(f"--export-mesh: expected SITE:ALTITUDE (e.g. A:200), got {spec!r}") from None
    parse_sites(site, "--export-mesh")
    if not alt_m > 0:
        raise ValueError(f"--export-mesh: altitude must be > 0 m, got {alt_m}")
    if not 8 <= n <= 4096:
        raise ValueError(f"--mesh-texels must be in [8, 4096], got {n}")
    return site.strip(), alt_m


def _export_mesh(site: str, alt_m: float, renderer, cfg, run_dir: Path, n: int) -> Path:
    from dvsland.render.mesh import terrain_mesh
    from dvsland.terrain import load_site

    terrain = load_site(site, cfg.render.sun_elevation_deg)
    extent = renderer.footprint_m(alt_m) * 1.1
    mesh = terrain_mesh(terrain, extent, n)
    path = run_dir / f"mesh_{site}_{alt_m:g}m.ply"
    mesh.export(path)
    return path
