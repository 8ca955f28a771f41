"""Sensor presets (camera.sensor) and the render -> emulate -> estimate chain on non-square sensors."""

import math

import pytest
import torch

from dvsland.config import CameraConfig, ConfigError, RenderConfig, dump_config, load_config
from dvsland.config.schema import SENSOR_PRESETS
from dvsland.estimators import Truth, make_estimator
from dvsland.events import EventEmulator


@pytest.mark.parametrize("name,w,h,pitch", [("davis346", 346, 260, 18.5), ("gen4", 1280, 720, 4.86),
                                            ("square640", 640, 640, 10.0), ("dvs128", 128, 128, 40.0)])
def test_presets_fill_geometry_and_fov(name, w, h, pitch):
    cam = CameraConfig(sensor=name)
    assert (cam.width_px, cam.height_px, cam.pixel_pitch_um) == (w, h, pitch)
    focal = SENSOR_PRESETS[name][3]
    if focal is None:
        assert cam.fov_deg == 60.0  # DVS128 keeps the paper's field of view
    else:
        assert cam.focal_length_mm == focal
        assert cam.fov_deg == pytest.approx(math.degrees(2 * math.atan(w * pitch * 1e-3 / 2 / focal)), rel=1e-12)
        assert 55 < cam.fov_deg < 65


def test_preset_lens_override_conflicts_and_round_trip(tmp_path):
    cam = CameraConfig(sensor="gen4", focal_length_mm=8.0)
    assert cam.fov_deg == pytest.approx(math.degrees(2 * math.atan(1280 * 4.86e-3 / 16)))
    with pytest.raises(ConfigError, match="camera.width_px"):
        load_config("paper", ["camera.sensor=davis346", "camera.width_px=200"])
    with pytest.raises(ConfigError, match="camera.fov_deg"):
        CameraConfig(sensor="davis346", fov_deg=45.0)
    with pytest.raises(ConfigError, match="camera.sensor"):
        load_config("paper", ["camera.sensor=dvs999"])
    cfg = load_config("paper", ["camera.sensor=davis346"])
    p = tmp_path / "c.yaml"
    dump_config(cfg, p)
    assert load_config(p).camera == cfg.camera
    # custom: the fields as given, fov from a lens when both pitch and focal length are set
    c = CameraConfig(width_px=200, height_px=100, pixel_pitch_um=10.0, focal_length_mm=2.0)
    assert c.fov_deg == pytest.approx(math.degrees(2 * math.atan(1.0 / 2.0)))
    assert CameraConfig(width_px=64, height_px=48).fov_deg == 60.0


def _chain(cfg, frames_of, altitudes, B):
    """Emulate frames along a descent and feed dpr, cmax and oracle; returns the last estimates."""
    W, H = cfg.camera.width_px, cfg.camera.height_px
    emu = EventEmulator.from_config(cfg.emulator)
    idx = torch.arange(B)
    f0 = frames_of(altitudes[0], idx)
    assert f0.shape == (B, H, W)
    emu.reset(f0, 0)
    ests = {n: make_estimator(cfg, B, name=n) for n in ("dpr", "cmax", "oracle")}
    n_ev = 0
    out = {}
    for k, a in enumerate(altitudes[1:], start=1):
        ev = emu.step(frames_of(a, idx), 100_000 * k)
        ev.validate(B, H, W)
        n_ev += len(ev)
        truth = Truth(a.double(), torch.full((B,), -8.0, dtype=torch.float64))
        for n, e in ests.items():
            d = e.update(ev, 100_000 * k, truth)
            assert d.shape == (B,) and d.is_floating_point()
            out[n] = d
    assert n_ev > 0
    return out


@pytest.mark.slow  # 13 s: a 346 x 260 sensor through render, emulator and estimator
def test_davis346_render_emulate_estimate():
    """DAVIS346 (346 x 260, non-square) end to end with the fast terrain renderer."""
    from dvsland.render import get_renderer

    cfg = load_config("paper", ["camera.sensor=davis346"])
    r = get_renderer("fast", ["A", "E"], cfg.camera, RenderConfig(min_altitude_m=500, max_altitude_m=1200),
                     disk_cache=False)
    alts = [torch.tensor([1000.0, 900.0]) * (1 - 0.008 * k) for k in range(8)]
    out = _chain(cfg, r.render, alts, 2)
    assert torch.isfinite(out["oracle"]).all()
    assert torch.isfinite(out["dpr"]).any() or torch.isfinite(out["cmax"]).any()


@pytest.mark.parametrize("sensor", ["gen4", "square640"])
def test_large_sensors_with_stand_in_frames(sensor):
    from dvsland.evaluate import ZoomTextureFrames

    cfg = load_config("paper", [f"camera.sensor={sensor}"])
    src = ZoomTextureFrames(1, (cfg.camera.width_px, cfg.camera.height_px), cfg.camera.fov_deg, seed=1)
    alts = [torch.tensor([800.0]) * (1 - 0.01 * k) for k in range(4)]
    _chain(cfg, src, alts, 1)
