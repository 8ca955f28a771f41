"""Levels of detail of one site for the fast renderer: a pyramid of shaded, sun-aligned tiles.

Level k covers a square window around the landing point with ``level_size`` texels of side
``base_texel_m * 2^k`` (each level twice the extent of the previous, same texel count), plus a
``gutter`` of real texels on every side so bilinear sampling never bleeds into a neighbour in
the atlas. Each tile holds the shaded irradiance (lunar-Lambert, cast shadows computed over an
extra ``shadow_pad`` of the window toward the sun, ambient floor) and the height relative to
the landing point (for parallax). Tiles are on a sun-aligned grid (columns toward the sun).

Preparation is cached per process and, unless disabled, on disk under
``$DVSLAND_CACHE_DIR`` (default ``~/.cache/dvsland/levels``), keyed by the site spec hash and
the level parameters.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import torch

from dvsland.config.level_grid import GUTTER, level_grid
from dvsland.terrain import Terrain, shaded_sun_grid
from dvsland.terrain.grid import compute_threads

#: bump when the terrain or shading algorithm changes (invalidates disk caches)
ALGO_VERSION = 6


@dataclass(frozen=True)
class LevelParams:
    level_size: int = 384        # window texels per side
    gutter: int = GUTTER         # extra real texels on every side
    base_texel_m: float = 0.09   # texel of level 0, m
    n_levels: int = 13
    ambient: float = 0.02        # ambient floor, fraction of full sun
    shadow_pad: float = 0.35     # heights sampled this fraction of the window further upsun

    @property
    def tile_size(self) -> int:
        return self.level_size + 2 * self.gutter

    def texel_m(self, k: int) -> float:
        return self.base_texel_m * 2.0 ** k

    def key(self) -> str:
        text = json.dumps({**asdict(self), "algo": ALGO_VERSION}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:12]


@dataclass
class SiteLevels:
    """Prepared tiles of one site: ``irradiance``, ``height_m`` (K, T, T) float32 CPU (height
    relative to the landing point ``h0_m``), ``angle_rad`` of the tile column axis (toward the
    sun, from east counter-clockwise), ``prep_s`` the preparation time (0 when cached)."""

    name: str
    irradiance: torch.Tensor
    height_m: torch.Tensor
    h0_m: float
    angle_rad: float
    prep_s: float
    source: str  # "computed", "memory" or "disk"
    prep_cpu_s: float = 0.0  # process CPU time of the preparation (excludes waiting for a core)


_MEMORY: dict = {}


def cache_dir() -> Optional[Path]:
    """Disk cache folder, or None when ``DVSLAND_CACHE_DIR`` is "off"."""
    env = os.environ.get("DVSLAND_CACHE_DIR")
    if env is not None and env.strip().lower() in ("off", "0", "none", ""):
        return None
    return Path(env) if env else Path.home() / ".cache" / "dvsland" / "levels"


def load_cached(path: Path) -> dict:
    """A disk cache file's dict, its tensors mapped from the file (``torch.load(mmap=True)``): the
    page cache's pages are read in place, not copied into fresh process memory. A batch of 63
    dispersed scenes loads 1 GB of levels; copying them faulted in 1 GB of new pages, which on a
    virtual machine cost up to 2.5 s per GB (docs/benchmarks.md). The tensors are read-only in
    effect (a write would stay private to the process). Files in torch's legacy format (not
    written by this project) are read the plain way.

    Raises:
        whatever ``torch.load`` raises for a missing or broken file (callers recompute).
    """
    try:
        return torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except RuntimeError:  # not a zip-format file: no mmap
        return torch.load(path, map_location="cpu", weights_only=True)


def prepare_levels(terrain: Terrain, params: LevelParams, disk_cache: bool = True,
                   progress=None, threads: Optional[int] = None) -> SiteLevels:
    """Shade every level of ``terrain`` (see module doc). Cached in memory and on disk.

    ``threads``: torch intra-op threads while computing (restored afterwards); None = the
    terrain default (:class:`dvsland.terrain.grid.compute_threads`: 1, or
    ``$DVSLAND_TERRAIN_THREADS``). The preparation is many small float64 CPU ops, which run
    faster on one thread than on an oversubscribed pool (measured: 97 s -> 7.5 s for four
    48-px sites on the shared 2-core machine).
    """
    key = f"{terrain.name}-{terrain.spec.digest()}-{params.key()}"
    if key in _MEMORY:
        lv = _MEMORY[key]
        return SiteLevels(lv.name, lv.irradiance, lv.height_m, lv.h0_m, lv.angle_rad, 0.0, "memory")
    folder = cache_dir() if disk_cache else None
    path = folder / f"{key}.pt" if folder is not None else None
    if path is not None and path.is_file():
        try:
            d = load_cached(path)
            lv = SiteLevels(terrain.name, d["irradiance"], d["height_m"], float(d["h0_m"]),
                            float(d["angle_rad"]), 0.0, "disk")
            _MEMORY[key] = lv
            return lv
        except Exception:  # a broken cache file is recomputed
            pass
    t0, c0 = time.perf_counter(), time.process_time()
    with compute_threads(threads if threads is not None else 0):
        irr, hgt = _compute(terrain, params, progress)
    # landing point height from the finest level: (0, 0) is the centre of the even-sized tile
    c = params.tile_size // 2
    h0 = float(hgt[0, c - 1:c + 1, c - 1:c + 1].to(torch.float64).mean())
    hgt -= h0
    lv = SiteLevels(terrain.name, irr, hgt, h0, terrain.sun_grid_angle_rad, time.perf_counter() - t0, "computed",
                    time.process_time() - c0)
    _MEMORY[key] = lv
    save_levels(path, lv)
    return lv


def save_levels(path, lv: "SiteLevels") -> None:
    """Write prepared levels to the disk cache atomically (tmp file + rename); ``path`` None or
    an unwritable cache is skipped silently (the cache only saves time)."""
    if path is None:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        torch.save({"irradiance": lv.irradiance, "height_m": lv.height_m, "h0_m": lv.h0_m,
                    "angle_rad": lv.angle_rad}, tmp)
        os.replace(tmp, path)
    except OSError:
        pass


def _compute(terrain: Terrain, params: LevelParams, progress=None):
    """(irradiance, height) tiles, each (K, T, T) float32 CPU; height not yet relative."""
    k_max = params.n_levels
    m = params.tile_size
    irr = torch.empty(k_max, m, m, dtype=torch.float32)
    hgt = torch.empty(k_max, m, m, dtype=torch.float32)
    for k in range(k_max):
        s = params.texel_m(k)
        ik, hk, _ = shaded_sun_grid(terrain, (0.0, 0.0), m, s, params.ambient, params.shadow_pad)
        irr[k] = ik.to(torch.float32)
        hgt[k] = hk.to(torch.float32)
        if progress is not None:
            progress(k)
    return irr, hgt


def level_params_for(camera, render_config, level_size: Optional[int] = None, gutter: int = GUTTER,
                     shadow_pad: float = 0.35) -> LevelParams:
    """Level parameters that cover the camera's altitude range (the grid of
    :func:`dvsland.config.level_grid.level_grid`)."""
    g = level_grid(camera, render_config, level_size)
    return LevelParams(level_size=g.level_size, gutter=gutter, base_texel_m=g.base_texel_m, n_levels=g.n_levels,
                       ambient=float(render_config.ambient), shadow_pad=shadow_pad)
