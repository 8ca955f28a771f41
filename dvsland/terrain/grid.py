"""Regular (possibly rotated) sampling grids over the world plane.

World frame: x east, y north, metres. A grid's texel (i, j) centre lies at
``origin + i * spacing * e_row + j * spacing * e_col`` with ``e_col = (cos a, sin a)`` and
``e_row = (sin a, -cos a)`` (e_col turned clockwise by 90 deg). ``angle_rad = 0`` is the map
view: columns go east, rows go south (row 0 at the top = north, as seen from above).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Grid:
    """A regular grid of ``n_rows x n_cols`` texels of side ``spacing_m``."""

    origin_x_m: float
    origin_y_m: float
    angle_rad: float
    n_rows: int
    n_cols: int
    spacing_m: float

    @staticmethod
    def centered(center_xy_m, n_rows: int, n_cols: int, spacing_m: float, angle_rad: float = 0.0) -> "Grid":
        """Grid whose texel centres are centred on ``center_xy_m``."""
        ec, er = _axes(angle_rad)
        oi = -(n_rows - 1) / 2 * spacing_m
        oj = -(n_cols - 1) / 2 * spacing_m
        ox = float(center_xy_m[0]) + oi * er[0] + oj * ec[0]
        oy = float(center_xy_m[1]) + oi * er[1] + oj * ec[1]
        return Grid(ox, oy, float(angle_rad), int(n_rows), int(n_cols), float(spacing_m))

    @property
    def e_col(self):
        return _axes(self.angle_rad)[0]

    @property
    def e_row(self):
        return _axes(self.angle_rad)[1]

    def world(self, i: torch.Tensor, j: torch.Tensor):
        """World (x, y) in metres of fractional texel coordinates (float64 tensors)."""
        ec, er = _axes(self.angle_rad)
        s = self.spacing_m
        x = self.origin_x_m + s * (i * er[0] + j * ec[0])
        y = self.origin_y_m + s * (i * er[1] + j * ec[1])
        return x, y

    def texel(self, x_m: torch.Tensor, y_m: torch.Tensor):
        """Fractional texel coordinates (i, j) of world points (inverse of :meth:`world`)."""
        ec, er = _axes(self.angle_rad)
        dx = x_m - self.origin_x_m
        dy = y_m - self.origin_y_m
        return (dx * er[0] + dy * er[1]) / self.spacing_m, (dx * ec[0] + dy * ec[1]) / self.spacing_m

    def coords(self):
        """World (x, y) of all texel centres, each (n_rows, n_cols) float64 (CPU)."""
        i = torch.arange(self.n_rows, dtype=torch.float64)[:, None]
        j = torch.arange(self.n_cols, dtype=torch.float64)[None, :]
        return self.world(i, j)


def _axes(angle_rad: float):
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return (c, s), (s, -c)


class compute_threads:
    """Context manager: torch intra-op threads for terrain computations, restored on exit.

    Terrain sampling is many small float64 CPU ops; on a shared, oversubscribed CPU one thread
    is 5-10x faster than a thread pool that waits on descheduled workers. Default: 1, or the
    ``DVSLAND_TERRAIN_THREADS`` environment variable (0 = leave torch's setting alone).
    """

    def __init__(self, threads=None):
        import os

        if threads is None:
            threads = int(os.environ.get("DVSLAND_TERRAIN_THREADS", "1"))
        self.threads = int(threads)
        self._old = None

    def __enter__(self):
        if self.threads > 0:
            self._old = torch.get_num_threads()
            if self._old != self.threads:
                torch.set_num_threads(self.threads)
        return self

    def __exit__(self, *exc):
        if self._old is not None and torch.get_num_threads() != self._old:
            torch.set_num_threads(self._old)
        return False
