"""Dispersed scenes for the fast renderer: a site (or variant ``A~k``) under another sun.

A scene label is ``<site>[@el<deg>][@az<+deg>]`` (:func:`dvsland.layout.batch.scene_label`):
``E~2@el12@az+5`` is variant 2 of site E lit from 12 deg elevation, its sun azimuth turned by
+5 deg. Preparing a scene's levels costs what preparing a site costs (about 2 s of CPU), except
that scenes differing only in sun elevation share their height and albedo fields (the expensive
part: fBm noise and feature stamping, about 95 % of the time): the fields of each level are kept
per process and on disk (``<cache>/fields/``, see :func:`dvsland.render.lod.cache_dir`), and another
elevation only re-shades them (shadows and lunar-Lambert, about 0.1-0.2 s of CPU per scene), which
is bit-identical to preparing that scene from scratch. A campaign therefore computes each terrain
variant's fields once per machine, whatever its seeds and shards.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from pathlib import Path
from typing import Optional, Tuple

import torch

from dvsland.terrain import Terrain
from dvsland.terrain.grid import Grid, compute_threads
from dvsland.terrain.photometry import shade
from dvsland.terrain.spec import load_spec

from .lod import LevelParams, SiteLevels, _MEMORY, cache_dir, load_cached, save_levels

#: height and albedo fields per (spec without sun elevation, level params, level): float64 CPU
_FIELDS: dict = {}
#: at most this many levels' fields are kept (each ~3.3 MB at 388 px tiles: 130 levels = 10 terrains,
#: ~420 MB); ``$DVSLAND_FIELD_CACHE_LEVELS`` changes it
FIELD_CACHE_LEVELS = int(os.environ.get("DVSLAND_FIELD_CACHE_LEVELS", "130"))
_TERRAINS: dict = {}


def parse_scene(label: str) -> Tuple[str, Optional[float], float]:
    """``"E~2@el12@az+5"`` -> ("E~2", 12.0, 5.0); ``"E"`` -> ("E", None, 0.0)."""
    parts = str(label).split("@")
    el, az = None, 0.0
    for p in parts[1:]:
        try:
            if p.startswith("el"):
                el = float(p[2:])
                continue
            if p.startswith("az"):
                az = float(p[2:])
                continue
        except ValueError:
            pass
        raise ValueError(f"scene label {label!r}: expected '<site>[@el<deg>][@az<+deg>]', e.g. 'E~2@el12@az+5'")
    return parts[0], el, az


def load_scene(label: str, default_elevation_deg: Optional[float] = None) -> Terrain:
    """The terrain of a scene label (see module doc); ``default_elevation_deg`` (the config's
    ``render.sun_elevation_deg``) applies when the label sets no elevation."""
    name, el, az = parse_scene(label)
    spec = load_spec(name).with_sun_elevation(el if el is not None else default_elevation_deg)
    if az:
        spec = dataclasses.replace(spec, sun=dataclasses.replace(spec.sun, azimuth_deg=spec.sun.azimuth_deg + az))
    key = spec.digest()
    if key not in _TERRAINS:
        _TERRAINS[key] = Terrain(spec)
    return _TERRAINS[key]


def _fields_key(terrain: Terrain, params: LevelParams, k: int) -> str:
    spec = dataclasses.replace(terrain.spec, sun=dataclasses.replace(terrain.spec.sun, elevation_deg=45.0))
    return f"{spec.digest()}-{params.key()}-{k}"


def fields_path(key: str) -> Optional[Path]:
    """Disk cache file of one level's height and albedo fields (None when the cache is off)."""
    folder = cache_dir()
    return None if folder is None else folder / "fields" / f"{key}.pt"


def _load_fields(key: str):
    """(height, albedo) float64 from the disk cache, or None (missing or unreadable: recomputed)."""
    path = fields_path(key)
    if path is None or not path.is_file():
        return None
    try:
        d = load_cached(path)
        return d["height"], d["albedo"]
    except Exception:  # a broken cache file is recomputed
        return None


def _save_fields(key: str, hit) -> None:
    """Write (height, albedo) to the disk cache atomically; an unwritable cache is skipped."""
    path = fields_path(key)
    if path is None:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        torch.save({"height": hit[0], "albedo": hit[1]}, tmp)
        os.replace(tmp, path)
    except OSError:
        pass


def _level(terrain: Terrain, params: LevelParams, k: int, disk_cache: bool = True):
    """Irradiance and height (T, T) float64 of level k (as :func:`shaded_sun_grid`), the fields
    shared between sun elevations: kept per process and, with ``disk_cache``, on disk
    (``<cache>/fields/``, float64 as computed, about 3.3 MB per level at 388-texel tiles), so a
    scene under a new sun costs only its shading (about 0.1 s of CPU for 13 levels, against about
    2 s for the fields)."""
    m, s = params.tile_size, params.texel_m(k)
    ang = terrain.sun_grid_angle_rad
    pad = int(math.ceil(params.shadow_pad * m))
    ec = (math.cos(ang), math.sin(ang))
    cx, cy = 0.5 * pad * s * ec[0], 0.5 * pad * s * ec[1]
    key = _fields_key(terrain, params, k)
    hit = _FIELDS.get(key)
    if hit is None:
        hit = _load_fields(key) if disk_cache else None
        if hit is None:
            hit = terrain.fields(Grid.centered((cx, cy), m, m + pad, s, ang))
            if disk_cache:
                _save_fields(key, hit)
        if len(_FIELDS) >= FIELD_CACHE_LEVELS:
            _FIELDS.pop(next(iter(_FIELDS)))
        _FIELDS[key] = hit
    h, a = hit
    irr, _ = shade(h, a, s, terrain.sun_elevation_deg, params.ambient)
    return irr[:, :m].contiguous(), h[:, :m].contiguous()


def prepare_scene_levels(terrain: Terrain, params: LevelParams, label: str, disk_cache: bool = True,
                         levels: Optional[Tuple[int, int]] = None) -> SiteLevels:
    """Levels of a dispersed scene (as :func:`dvsland.render.lod.prepare_levels`, same cache
    folder and key scheme, named ``label``), re-using the fields of a scene that differs only in
    sun elevation.

    ``levels``: ``(k_lo, k_hi)`` inclusive: prepare only these (lazy levels: the levels a
    descent between two altitudes samples); the others hold a copy of the nearest prepared one
    and must not be sampled (the fast renderer clamps to the range). The landing point height
    then comes from level ``k_lo``. None = all levels."""
    k_max, m = params.n_levels, params.tile_size
    k_lo, k_hi = (0, k_max - 1) if levels is None else (int(levels[0]), int(levels[1]))
    if not (0 <= k_lo <= k_hi <= k_max - 1):
        raise ValueError(f"levels must satisfy 0 <= k_lo <= k_hi <= {k_max - 1}, got {levels}")
    full = (k_lo, k_hi) == (0, k_max - 1)
    key = f"{terrain.name}-{terrain.spec.digest()}-{params.key()}" + ("" if full else f"-L{k_lo}-{k_hi}")
    if key in _MEMORY:
        lv = _MEMORY[key]
        out = SiteLevels(label, lv.irradiance, lv.height_m, lv.h0_m, lv.angle_rad, 0.0, "memory")
        out.levels = None if full else (k_lo, k_hi)
        return out
    folder = cache_dir() if disk_cache else None
    path = folder / f"{key}.pt" if folder is not None else None
    if path is not None and path.is_file():
        try:
            d = load_cached(path)
            lv = SiteLevels(label, d["irradiance"], d["height_m"], float(d["h0_m"]), float(d["angle_rad"]), 0.0, "disk")
            lv.levels = None if full else (k_lo, k_hi)
            _MEMORY[key] = lv
            return lv
        except Exception:  # a broken cache file is recomputed
            pass
    t0, c0 = time.perf_counter(), time.process_time()
    irr = torch.empty(k_max, m, m, dtype=torch.float32)
    hgt = torch.empty(k_max, m, m, dtype=torch.float32)
    with compute_threads(0):
        for k in range(k_lo, k_hi + 1):
            ik, hk = _level(terrain, params, k, disk_cache)
            irr[k] = ik.to(torch.float32)
            hgt[k] = hk.to(torch.float32)
    irr[:k_lo], hgt[:k_lo] = irr[k_lo], hgt[k_lo]
    irr[k_hi + 1:], hgt[k_hi + 1:] = irr[k_hi], hgt[k_hi]
    c = m // 2
    h0 = float(hgt[k_lo, c - 1:c + 1, c - 1:c + 1].to(torch.float64).mean())
    hgt -= h0
    lv = SiteLevels(label, irr, hgt, h0, terrain.sun_grid_angle_rad, time.perf_counter() - t0, "computed",
                    time.process_time() - c0)
    lv.levels = None if full else (k_lo, k_hi)
    _MEMORY[key] = lv
    save_levels(path, lv)
    return lv
