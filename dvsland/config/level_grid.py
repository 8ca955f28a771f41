"""The fast renderer's level-of-detail grid as a function of the camera and the render settings.

Pure arithmetic on the config, so the memory estimate (:mod:`dvsland.config.validate`) and the
renderer (:func:`dvsland.render.lod.level_params_for`) share one definition without the config
importing the renderer.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

#: real texels added on every side of a level's window (the tile is ``level_size + 2 * GUTTER``)
GUTTER = 2


class LevelGrid(NamedTuple):
    """``level_size`` window texels per side, ``n_levels`` levels, ``base_texel_m`` level 0's texel (m)."""

    level_size: int
    n_levels: int
    base_texel_m: float


def level_grid(camera, render_config, level_size: Optional[int] = None) -> LevelGrid:
    """Levels that cover the camera's altitude range.

    Level 0's texel equals the ground pixel at ``min_altitude_m``; there are enough levels for
    ``max_altitude_m`` plus one (the blend needs the next coarser level). The window is wide
    enough that the finer of the two blended levels (texel >= pixel / 2) holds the rotated
    footprint (half-diagonal) with 6 % margin for parallax.
    """
    w, h = camera.width_px, camera.height_px
    tan_half = math.tan(math.radians(camera.fov_deg) / 2)
    pitch = 2 * tan_half / w  # m per m of altitude
    base = pitch * render_config.min_altitude_m
    # a planar pinhole sensor parallel to flat ground has the same ground pixel everywhere
    lam_max = math.log2(render_config.max_altitude_m / render_config.min_altitude_m)
    n_levels = int(math.ceil(lam_max)) + 2
    if level_size is None:
        need = 2 * math.sqrt(1 + (h / w) ** 2) * w * 1.06
        level_size = int(math.ceil(need / 16) * 16)
    return LevelGrid(int(level_size), n_levels, base)
