"""``dvsland events`` smoke tests (a cheap zooming renderer stands in for the real one)."""

import json

import numpy as np
import pytest
import torch

import dvsland.render as render_pkg
from dvsland.cli.cmd_events import frame_schedule
from dvsland.config import load_config
from dvsland.report.images import event_frame_rgb
from dvsland.cli.main import main
from dvsland.events import Events, load_events
from dvsland.render import Renderer


class ZoomRenderer(Renderer):
    """Flat ground with a smooth albedo pattern: zooms in as the altitude drops."""

    name = "zoom"

    def _render(self, altitude_m, site_idx):
        tx, ty = self.ray_tangents(torch.float32)
        gx = tx[None] * altitude_m[:, None, None]
        gy = ty[None] * altitude_m[:, None, None]
        pat = torch.sin(gx / 7.0) * torch.cos(gy / 5.0) + 0.5 * torch.sin((gx + gy) / 3.0)
        return 0.3 * torch.exp(0.8 * pat) + 0.02


@pytest.fixture
def zoom_renderer(monkeypatch):
    def fake_get_renderer(name, site_names, camera=None, render=None, device="cpu", **kw):
        return ZoomRenderer(site_names, camera, render, device=device)

    monkeypatch.setattr(render_pkg, "get_renderer", fake_get_renderer)


@pytest.mark.parametrize("fmt", ["npz", "h5"])
def test_cli_events_smoke(tmp_path, zoom_renderer, fmt):
    out = tmp_path / "run"
    rc = main(["events", "--site", "D", "--from-m", "1000", "--to-m", "900", "--format", fmt,
               "--out", str(out), "--quiet", "--set", "camera.width_px=32", "--set", "camera.height_px=24"])
    assert rc == 0
    for name in ("config.yaml", f"events.{fmt}", "event_frame.png", "events_xyt.png", "frame_last.png",
                 "summary.json"):
        assert (out / name).is_file(), name
    ev, meta = load_events(out / f"events.{fmt}", with_meta=True)
    summary = json.loads((out / "summary.json").read_text())
    assert len(ev) == summary["events"] > 0
    assert meta["sensor_size"] == (32, 24, 2) and meta["threshold"] == 0.1
    ev.validate(1, 24, 32)
    assert int(ev.t.min()) > summary["t_first_us"] and int(ev.t.max()) <= summary["t_last_us"]
    assert summary["altitude_first_m"] == pytest.approx(1000.0, abs=0.01)
    assert summary["altitude_last_m"] <= 900.0


def test_cli_events_bad_range(tmp_path, zoom_renderer, capsys):
    rc = main(["events", "--site", "A", "--from-m", "800", "--to-m", "900", "--out", str(tmp_path / "x"),
               "--quiet"])
    assert rc == 2
    assert "--from-m" in capsys.readouterr().err


def test_frame_schedule_closed_form():
    t_us, z = frame_schedule(load_config("paper_eq2"), "A", 1000.0, 800.0)  # z0 10 km, v0 -200 m/s, c2 0.5 (paper.yaml: 0.25)
    # s = (z / z0)^c2, t = (s - 1) z0 / (c2 v0)
    t0 = ((1000 / 10000) ** 0.5 - 1) * 10000 / (0.5 * -200)
    assert t_us[0] == round(t0 * 1e6) and np.all(np.diff(t_us) == 100_000)
    assert z[0] == pytest.approx(1000.0, abs=1e-3) and z[-1] <= 800.0 < z[-2]


def test_event_frame_colours():
    ev = Events(b=[0, 0, 0], x=[0, 1, 1], y=[0, 0, 0], t=[1, 2, 3], p=[1, -1, -1])
    img = event_frame_rgb(ev, 2, 2, 0, 10)
    assert tuple(img[0, 0]) == (220, 30, 30) and tuple(img[0, 1]) == (30, 60, 220)
    assert tuple(img[1, 1]) == (255, 255, 255)


@pytest.mark.slow
def test_cli_events_fast_renderer(tmp_path):
    """The real fast renderer (site preparation can take a minute when not cached)."""
    out = tmp_path / "run"
    assert main(["events", "--site", "A", "--from-m", "1000", "--to-m", "950", "--out", str(out),
                 "--quiet", "--set", "camera.width_px=64", "--set", "camera.height_px=64"]) == 0
    assert len(load_events(out / "events.npz")) > 0
