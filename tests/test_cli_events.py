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


# ------------------------------------------------------------------ several sites, per-frame ground truth
SMALL = ["--set", "camera.width_px=32", "--set", "camera.height_px=24"]


def test_cli_events_several_sites_and_variants(tmp_path, zoom_renderer):
    out = tmp_path / "run"
    assert main(["events", "--sites", "D,E~1", "--from-m", "1000", "--to-m", "950", "--out", str(out),
                 "--quiet", *SMALL]) == 0
    ev, meta = load_events(out / "events.npz", with_meta=True)
    assert meta["batch_size"] == 2 and set(ev.b.unique().tolist()) == {0, 1}
    summary = json.loads((out / "summary.json").read_text())
    assert [s["site"] for s in summary["sites"]] == ["D", "E~1"]
    assert sum(s["events"] for s in summary["sites"]) == summary["events"] == len(ev)
    for s in ("D", "E~1"):
        assert (out / f"event_frame_{s}.png").is_file() and (out / "tb" / s).is_dir()


def test_cli_events_site_and_sites_together_refused(tmp_path, capsys):
    assert main(["events", "--site", "A", "--sites", "B", "--out", str(tmp_path / "x")]) == 2
    assert "--sites or --site" in capsys.readouterr().err and not (tmp_path / "x").exists()


@pytest.mark.parametrize("fmt", ["npz", "h5"])
def test_events_file_carries_per_frame_ground_truth(tmp_path, zoom_renderer, fmt):
    from dvsland.events import read_recording

    out = tmp_path / "run"
    assert main(["events", "--sites", "D,A", "--from-m", "1000", "--to-m", "950", "--format", fmt,
                 "--out", str(out), "--quiet", *SMALL]) == 0
    cfg = load_config("paper")
    for b, site in enumerate(("D", "A")):
        rec = read_recording(out / f"events.{fmt}", b=b)
        t_us, z, v = frame_schedule(cfg, site, 1000.0, 950.0, with_velocity=True)
        gt = rec.ground_truth
        assert gt is not None and np.array_equal(gt.t_us, t_us)
        np.testing.assert_allclose(gt.altitude_m, z)
        np.testing.assert_allclose(gt.velocity_mps, v)
        np.testing.assert_allclose(gt.divergence, v / z)
        assert len(rec.events) == int((load_events(out / f"events.{fmt}").b == b).sum())


def test_evaluate_reads_the_events_ground_truth_back(tmp_path, zoom_renderer):
    """dvsland events -> dvsland evaluate --recording: scored without --ground-truth (the oracle is
    exact against it); --ground-truth FILE still works and --element picks the second site."""
    ev_dir = tmp_path / "events"
    assert main(["events", "--sites", "D,A", "--from-m", "1000", "--to-m", "900", "--out", str(ev_dir),
                 "--quiet", *SMALL]) == 0
    path = ev_dir / "events.npz"
    runs = {"auto": [], "side": ["--ground-truth", str(path)], "element": ["--element", "1"]}
    for key, extra in runs.items():
        out = tmp_path / key
        assert main(["evaluate", "--recording", str(path), "--estimators", "oracle", "--warmup-steps", "1",
                     "--no-figures", "--out", str(out), "--quiet", "--set", "logging.tensorboard=false",
                     *extra]) == 0
        res = json.loads((out / "evaluation.json").read_text())
        assert res["has_ground_truth"] is True, key
        e = res["estimators"]["oracle"]["all_sites"]
        assert e["n_steps"] > 0 and e["median_abs_rel_err"] < 1e-6, key


def test_evaluate_element_needs_recording(tmp_path, capsys):
    assert main(["evaluate", "--element", "1", "--out", str(tmp_path / "x")]) == 2
    assert "--element" in capsys.readouterr().err
