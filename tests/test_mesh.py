"""Heightfield meshes of a terrain patch (dvsland.render.mesh)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from dvsland.render.mesh import grid_xy, heightfield_mesh, terrain_mesh


class PlaneTerrain:
    """z = a x + b y + c, albedo varying with x: a closed-form terrain with the Terrain API."""

    def __init__(self, a=0.1, b=-0.05, c=3.0):
        self.a, self.b, self.c = a, b, c
        self.calls = []

    def heightmap(self, extent_m, n, center_xy_m=(0.0, 0.0), device="cpu", dtype=torch.float32):
        self.calls.append((extent_m, n, tuple(center_xy_m), dtype))
        x, y = grid_xy(extent_m, n, center_xy_m)
        h = self.a * x + self.b * y + self.c
        alb = 0.1 + 0.05 * np.sin(x / 7.0) ** 2
        return torch.as_tensor(h, dtype=dtype, device=device), torch.as_tensor(alb, dtype=dtype, device=device)


def test_smoke_counts():
    mesh = terrain_mesh(PlaneTerrain(), 100.0, 17)
    assert isinstance(mesh, trimesh.Trimesh)
    assert mesh.vertices.shape == (17 * 17, 3)
    assert mesh.faces.shape == (2 * 16 * 16, 3)
    assert mesh.vertex_attributes["albedo"].shape == (17 * 17,)
    assert mesh.visual.vertex_colors.shape == (17 * 17, 4)


@pytest.mark.parametrize("center", [(0.0, 0.0), (120.0, -35.5)])
def test_extent_and_orientation(center):
    n, ext = 33, 250.0
    mesh = terrain_mesh(PlaneTerrain(), ext, n, center)
    half = ext / 2 * (1 - 1 / n)  # vertices sit on texel centres
    lo, hi = mesh.vertices[:, :2].min(0), mesh.vertices[:, :2].max(0)
    np.testing.assert_allclose(lo, [center[0] - half, center[1] - half], atol=1e-9)
    np.testing.assert_allclose(hi, [center[0] + half, center[1] + half], atol=1e-9)
    v = mesh.vertices.reshape(n, n, 3)
    # row 0 = north edge, column 0 = west edge (map view, as Terrain.heightmap)
    assert v[0, 0, 1] == pytest.approx(center[1] + half) and v[0, 0, 0] == pytest.approx(center[0] - half)
    assert np.all(np.diff(v[:, 0, 1]) < 0) and np.all(np.diff(v[0, :, 0]) > 0)


def test_heights_and_albedo_match_heightmap():
    terr = PlaneTerrain()
    n, ext, c = 21, 80.0, (5.0, 7.0)
    mesh = terrain_mesh(terr, ext, n, c)
    h, a = terr.heightmap(ext, n, c, dtype=torch.float64)
    assert terr.calls[0][3] == torch.float64  # the mesh asks for float64 (no float32 rounding)
    np.testing.assert_array_equal(mesh.vertices[:, 2].reshape(n, n), h.numpy())
    np.testing.assert_allclose(mesh.vertex_attributes["albedo"].reshape(n, n), a.numpy(), rtol=1e-6)
    grey = mesh.visual.vertex_colors[:, 0].reshape(n, n).astype(float)
    np.testing.assert_allclose(grey / 255.0, a.numpy(), atol=0.5 / 255 + 1e-9)


def test_normals_of_a_plane():
    terr = PlaneTerrain(a=0.3, b=-0.2)
    mesh = terrain_mesh(terr, 50.0, 9)
    expect = np.array([-0.3, 0.2, 1.0]) / math.sqrt(1 + 0.09 + 0.04)
    np.testing.assert_allclose(mesh.vertex_normals, np.broadcast_to(expect, mesh.vertex_normals.shape), atol=1e-9)
    # faces wound counter-clockwise from above: face normals equal the plane normal too
    np.testing.assert_allclose(mesh.face_normals, np.broadcast_to(expect, mesh.face_normals.shape), atol=1e-9)


def test_real_terrain_heights_match():
    from dvsland.terrain import load_site

    terr = load_site("E")
    n, ext = 48, 300.0
    mesh = terrain_mesh(terr, ext, n, (10.0, -20.0))
    h, a = terr.heightmap(ext, n, (10.0, -20.0), dtype=torch.float64)
    np.testing.assert_array_equal(mesh.vertices[:, 2].reshape(n, n), h.numpy())
    np.testing.assert_allclose(mesh.vertex_attributes["albedo"].reshape(n, n), a.numpy(), rtol=1e-6)
    assert np.all(mesh.face_normals[:, 2] > 0)  # a heightfield: every face looks up


@pytest.mark.parametrize("ext", ["ply", "obj"])
def test_export_roundtrip(tmp_path, ext):
    mesh = terrain_mesh(PlaneTerrain(), 40.0, 12)
    path = tmp_path / f"patch.{ext}"
    mesh.export(path)
    back = trimesh.load(path, process=False)
    assert back.vertices.shape == mesh.vertices.shape
    assert back.faces.shape == mesh.faces.shape
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-5)


def test_errors():
    terr = PlaneTerrain()
    with pytest.raises(ValueError, match="extent_m"):
        terrain_mesh(terr, 0.0, 8)
    with pytest.raises(ValueError, match="extent_m"):
        terrain_mesh(terr, float("nan"), 8)
    with pytest.raises(ValueError, match="n must"):
        terrain_mesh(terr, 10.0, 1)
    with pytest.raises(ValueError, match="height_m"):
        heightfield_mesh(np.zeros((3, 4)), np.zeros((3, 4)), 10.0)
    with pytest.raises(ValueError, match="albedo"):
        heightfield_mesh(np.zeros((4, 4)), np.zeros((3, 3)), 10.0)
