"""Cost of one more scene variant of a site for the fast renderer: CPU seconds and memory.

before: a new terrain realisation ``<site>~k`` prepared as a site is (all 13 levels);
after:  the same with lazy levels (only the levels a descent from 1.1 z0 to 50 m samples),
        and a sun-elevation variant of an already prepared terrain (fields re-used, re-shaded).

    python scripts/bench_scene_variants.py [--sites B,E] [--variant 31]

CPU seconds are process time (one torch thread), so they hold on a loaded machine; the wall
time is printed beside them with the load.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import time

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sites", default="B,E", help="sites (B: from 10 km, E: from 4 km)")
    ap.add_argument("--variant", type=int, default=31, help="terrain variant index used (not cached)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    from dvsland.config import load_config
    from dvsland.render.lod import level_params_for, prepare_levels
    from dvsland.render.scenes import load_scene, prepare_scene_levels
    from dvsland.terrain import load_site

    cfg = load_config("realistic")
    p = level_params_for(cfg.camera, cfg.render)
    pitch = 2 * math.tan(math.radians(cfg.camera.fov_deg) / 2) / cfg.camera.width_px

    def lam(z):
        return math.log2(z * pitch / p.base_texel_m)

    z0 = {s.name: s.z0_m for s in cfg.simulation.sites}
    print(f"load: {os.getloadavg()[0]:.1f} (1 min), levels: {p.n_levels} x {p.tile_size}^2 texels")
    print(f"{'case':<44} {'cpu_s':>6} {'wall_s':>7} {'levels':>7} {'atlas_MB_per_scene':>18}")

    def run(label, fn, n_levels):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        mb = n_levels * p.tile_size ** 2 * 4 * 2 / 2 ** 20
        print(f"{label:<44} {time.process_time() - c0:6.2f} {time.perf_counter() - w0:7.2f} {n_levels:>7} "
              f"{p.n_levels * p.tile_size ** 2 * 8 / 2 ** 20:18.1f}")
        return mb

    for site in args.sites.split(","):
        k1, k2 = args.variant, args.variant + 1
        rng = (int(math.floor(lam(cfg.simulation.success_altitude_m))), min(int(math.floor(lam(1.1 * z0[site]))) + 1,
                                                                             p.n_levels - 1))
        n_lazy = rng[1] - rng[0] + 1
        run(f"before: {site}~{k1} full prep", lambda: prepare_levels(load_site(f"{site}~{k1}"), p, disk_cache=False),
            p.n_levels)
        run(f"after: {site}~{k2} lazy levels {rng[0]}-{rng[1]}",
            lambda: prepare_scene_levels(load_scene(f"{site}~{k2}@el15"), p, "a", disk_cache=False, levels=rng), n_lazy)
        run(f"after: {site}~{k2} other sun elevation (re-shade)",
            lambda: prepare_scene_levels(load_scene(f"{site}~{k2}@el13"), p, "b", disk_cache=False, levels=rng), n_lazy)
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB (includes the field cache: "
          f"{p.tile_size * math.ceil(p.tile_size * 1.35) * 16 / 2 ** 20:.1f} MB per level kept)")


if __name__ == "__main__":
    main()
