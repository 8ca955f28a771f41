"""Heightfield triangle meshes of a terrain patch (trimesh), for the pyrender reference and export.

World frame: x east, y north, z up, metres; the landing point is (0, 0). A patch is the square
of side ``extent_m`` centred on ``center_xy_m``, sampled by :meth:`Terrain.heightmap` on ``n x n``
texel centres (spacing ``extent_m / n``, already band-limited to that spacing by the terrain).
Every texel centre becomes one vertex, so the mesh spans ``extent_m * (1 - 1/n)`` per side,
has ``n * n`` vertices and ``2 (n - 1)^2`` triangles, wound counter-clockwise seen from above
(face normals point up).

The heightmap's row/column order follows the terrain's image convention (row 0 = north edge,
column 0 = west edge, like an image with north up); :func:`grid_xy` is the one place that
turns indices into world coordinates.
"""

from __future__ import annotations

from typing import Tuple

import numpy as np
import torch
import trimesh

__all__ = ["grid_xy", "heightfield_mesh", "terrain_mesh"]


def grid_xy(extent_m: float, n: int, center_xy_m: Tuple[float, float] = (0.0, 0.0)) -> Tuple[np.ndarray, np.ndarray]:
    """World coordinates of the ``n x n`` texel centres of a heightmap.

    Returns:
        (x_m, y_m): two (n, n) float64 arrays; ``[i, j]`` is row i (north to south), column j
        (west to east).
    """
    if not (extent_m > 0 and np.isfinite(extent_m)):
        raise ValueError(f"extent_m must be a finite number > 0, got {extent_m}")
    if int(n) < 2:
        raise ValueError(f"n must be an integer >= 2, got {n}")
    n = int(n)
    cx, cy = float(center_xy_m[0]), float(center_xy_m[1])
    t = (np.arange(n, dtype=np.float64) + 0.5) / n - 0.5  # texel centres in (-1/2, 1/2)
    x = cx + extent_m * t                                   # west -> east along columns
    y = cy - extent_m * t                                   # north -> south along rows
    return np.broadcast_to(x[None, :], (n, n)).copy(), np.broadcast_to(y[:, None], (n, n)).copy()


def _grid_faces(n: int) -> np.ndarray:
    """(2 (n-1)^2, 3) int64 triangle indices over an n x n vertex grid (row-major), CCW from above."""
    idx = np.arange(n * n, dtype=np.int64).reshape(n, n)
    nw = idx[:-1, :-1].ravel()  # row i (north), column j (west)
    ne = idx[:-1, 1:].ravel()
    sw = idx[1:, :-1].ravel()
    se = idx[1:, 1:].ravel()
    # Rows run south-wards (decreasing y) and columns east-wards (increasing x), so the order
    # sw -> se -> ne is counter-clockwise seen from +z.
    t1 = np.stack([sw, se, ne], axis=1)
    t2 = np.stack([sw, ne, nw], axis=1)
    return np.concatenate([t1, t2], axis=0)


def _grid_normals(height_m: np.ndarray, spacing_m: float) -> np.ndarray:
    """(n*n, 3) unit vertex normals of a heightfield from central differences (one-sided at edges)."""
    dz_drow, dz_dcol = np.gradient(height_m, spacing_m)
    dz_dx = dz_dcol          # columns run east (+x)
    dz_dy = -dz_drow         # rows run south (-y)
    nrm = np.stack([-dz_dx, -dz_dy, np.ones_like(height_m)], axis=-1).reshape(-1, 3)
    return nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def heightfield_mesh(height_m, albedo, extent_m: float, center_xy_m: Tuple[float, float] = (0.0, 0.0)) -> trimesh.Trimesh:
    """A triangle mesh of a sampled heightfield.

    Args:
        height_m: (n, n) heights, metres (numpy or torch, any float dtype).
        albedo: (n, n) normal albedo in [0, 1] (numpy or torch).
        extent_m: side of the sampled square, metres (texel spacing ``extent_m / n``).
        center_xy_m: centre of the square in world metres.

    Returns:
        ``trimesh.Trimesh`` with n*n vertices (float64, metres), 2 (n-1)^2 faces, smooth vertex
        normals from central differences, vertex colours = grey ``albedo`` (uint8 RGBA), and the
        unquantised albedo in ``mesh.vertex_attributes["albedo"]`` (float32, (n*n,)).
    """
    h = height_m.detach().cpu().double().numpy() if isinstance(height_m, torch.Tensor) else np.asarray(height_m, np.float64)
    a = albedo.detach().cpu().double().numpy() if isinstance(albedo, torch.Tensor) else np.asarray(albedo, np.float64)
    if h.ndim != 2 or h.shape[0] != h.shape[1]:
        raise ValueError(f"height_m must be a square (n, n) array, got shape {h.shape}")
    if a.shape != h.shape:
        raise ValueError(f"albedo must have the shape of height_m {h.shape}, got {a.shape}")
    if not np.all(np.isfinite(h)):
        raise ValueError("height_m must be finite everywhere")
    n = h.shape[0]
    x, y = grid_xy(extent_m, n, center_xy_m)
    vertices = np.stack([x, y, h], axis=-1).reshape(-1, 3)
    faces = _grid_faces(n)
    normals = _grid_normals(h, extent_m / n)
    grey = np.clip(np.rint(a.reshape(-1) * 255.0), 0, 255).astype(np.uint8)
    colors = np.stack([grey, grey, grey, np.full_like(grey, 255)], axis=1)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_normals=normals,
                           vertex_colors=colors, process=False, validate=False)
    mesh.vertex_attributes["albedo"] = a.reshape(-1).astype(np.float32)
    return mesh


def terrain_mesh(terrain, extent_m: float, n: int, center_xy_m: Tuple[float, float] = (0.0, 0.0),
                 upsample: int = 1) -> trimesh.Trimesh:
    """A heightfield mesh of ``terrain`` over the square of side ``extent_m`` around ``center_xy_m``.

    Args:
        terrain: a :class:`dvsland.terrain.Terrain` (anything with ``heightmap(extent_m, n,
            center_xy_m=..., device=..., dtype=...) -> (height_m (n, n), albedo (n, n))``).
        extent_m: side of the square, metres (> 0).
        n: vertices per side (>= 2); the terrain is band-limited to the spacing ``extent_m / n``.
        center_xy_m: centre of the square, world metres.
        upsample: >= 1; the ``n x n`` band-limited samples are interpolated (bicubic heights,
            bilinear albedo) onto ``n * upsample`` texel centres per side, so the triangles are
            finer than the content: smooth shading without the faceting / diagonal moire of a
            mesh whose content reaches its own Nyquist limit.

    Returns:
        see :func:`heightfield_mesh` (m*m vertices, 2 (m-1)^2 faces, m = n * upsample).
    """
    if not (extent_m > 0 and np.isfinite(extent_m)):
        raise ValueError(f"extent_m must be a finite number > 0, got {extent_m}")
    if int(n) != n or int(n) < 2:
        raise ValueError(f"n must be an integer >= 2, got {n}")
    if int(upsample) != upsample or int(upsample) < 1:
        raise ValueError(f"upsample must be an integer >= 1, got {upsample}")
    height_m, albedo = terrain.heightmap(float(extent_m), int(n), center_xy_m=(float(center_xy_m[0]), float(center_xy_m[1])),
                                         device="cpu", dtype=torch.float64)
    u = int(upsample)
    if u > 1:
        # align_corners=False: output samples are the texel centres of the u-times finer grid
        height_m = torch.nn.functional.interpolate(height_m[None, None], scale_factor=u, mode="bicubic",
                                                   align_corners=False)[0, 0]
        albedo = torch.nn.functional.interpolate(albedo[None, None], scale_factor=u, mode="bilinear",
                                                 align_corners=False)[0, 0].clamp(min=1e-6)
    return heightfield_mesh(height_m, albedo, extent_m, center_xy_m)
