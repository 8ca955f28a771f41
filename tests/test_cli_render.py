"""``dvsland render``: montage, frames, GIF, mesh and TensorBoard files in the run folder."""

from __future__ import annotations

import numpy as np

from dvsland.cli.main import main

SMALL = ["--set", "camera.width_px=32", "--set", "camera.height_px=32", "--quiet"]


def test_render_cli_writes_everything(tmp_path, monkeypatch):
    monkeypatch.setenv("DVSLAND_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "run"
    rc = main(["render", "--sites", "A,H", "--altitudes", "1000,50", "--out", str(out), "--gif-frames", "4",
               "--export-mesh", "A:100", "--mesh-texels", "16", *SMALL])
    assert rc == 0
    assert (out / "config.yaml").is_file()
    from PIL import Image

    mont = Image.open(out / "montage.png")
    assert mont.size[0] > 2 * 32 and mont.size[1] > 2 * 32
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["A_1000m.png", "A_50m.png", "H_1000m.png",
                                                                   "H_50m.png"]
    gif = Image.open(out / "descent_A.gif")
    assert gif.n_frames == 4
    data = np.load(out / "frames.npz")
    assert data["irradiance"].shape == (2, 2, 32, 32) and (data["irradiance"] > 0).all()
    assert list(data["sites"]) == ["A", "H"]
    import trimesh

    mesh = trimesh.load(out / "mesh_A_100m.ply")
    assert len(mesh.vertices) == 16 * 16
    assert any(p.name.startswith("events.out.tfevents") for p in (out / "tb").iterdir())


def test_render_cli_bad_altitude(tmp_path, capsys):
    rc = main(["render", "--sites", "A", "--altitudes", "5", "--out", str(tmp_path / "r"), *SMALL])
    assert rc == 2
    assert "render.min_altitude_m" in capsys.readouterr().err


def test_render_cli_bad_site(tmp_path, capsys):
    rc = main(["render", "--sites", "A,X", "--altitudes", "100", "--out", str(tmp_path / "r"), *SMALL])
    assert rc == 2
    assert "unknown site 'X'" in capsys.readouterr().err


def test_render_cli_bad_mesh_spec(tmp_path, capsys):
    rc = main(["render", "--sites", "A", "--altitudes", "100", "--gif-frames", "0", "--export-mesh", "A-100",
               "--out", str(tmp_path / "r"), *SMALL])
    assert rc == 2
    assert "SITE:ALTITUDE" in capsys.readouterr().err
