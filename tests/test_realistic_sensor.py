"""The realistic-sensor preset (configs/realistic_sensor.yaml): every noise number carries its
source, it loads on the three sensors, and its pixel emits the noise it says it does."""

import re

import pytest
import torch

from dvsland.config import CameraConfig, configs_dir, load_config
from dvsland.events import EventEmulator

NOISE_KEYS = ("mismatch_sigma", "photoreceptor_cutoff_hz", "full_irradiance", "shot_noise_rate_hz",
              "shot_noise_bright_factor", "leak_rate_hz", "leak_rate_sigma", "hot_pixel_fraction",
              "hot_pixel_rate_hz")


def test_every_noise_number_names_its_source():
    text = (configs_dir() / "realistic_sensor.yaml").read_text()
    section = text.split("emulator:", 1)[1].split("\ndispersion:", 1)[0]
    for key in NOISE_KEYS:
        line = next((ln for ln in section.splitlines() if ln.strip().startswith(key + ":")), None)
        assert line is not None, key
        comment = line.split("#", 1)[1] if "#" in line else ""
        # a source (author and year, or a named preset) or an explicit "no published figure"
        assert re.search(r"(19|20)\d\d|v2e|no published", comment), (key, comment)


def test_preset_values_and_dispersion():
    cfg = load_config("realistic_sensor")
    e = cfg.emulator
    assert (e.shot_noise_rate_hz, e.leak_rate_hz, e.photoreceptor_cutoff_hz) == (5.0, 0.1, 300.0)
    assert e.hot_pixel_fraction > 0 and e.mismatch_sigma == pytest.approx(0.21)
    assert cfg.dispersion.mismatch_sigma.kind == "off"
    assert cfg.controller.name == "div_gs"  # the montecarlo_efference experiment underneath
    assert e.denoise == "hot_pixel+baf"  # shipped with the front end its estimators need (raw: denoise=none)


@pytest.mark.parametrize("sensor,wh", [("dvs128", (128, 128)), ("davis346", (346, 260)), ("gen4_bin2", (640, 360))])
def test_preset_on_each_sensor(sensor, wh):
    cfg = load_config("realistic_sensor", [f"camera.sensor={sensor}"])
    assert (cfg.camera.width_px, cfg.camera.height_px) == wh
    assert 55.0 < cfg.camera.fov_deg < 65.0


def test_binned_gen4_with_off_centre_principal_point():
    cam = CameraConfig(sensor="gen4_bin2", principal_point_px=[400.0, 120.0])
    assert (cam.width_px, cam.height_px, cam.pixel_pitch_um) == (640, 360, 9.72)
    cfg = load_config("realistic_sensor", ["camera.sensor=gen4_bin2", "camera.principal_point_px=[400.0, 120.0]"])
    assert cfg.camera.principal_point_px == [400.0, 120.0]


def test_preset_pixel_emits_its_noise_on_a_static_scene():
    """On a static dark scene the ideal pixel is silent; the preset's emits shot noise near its
    dark rate (5 Hz ON+OFF) plus leak and hot-pixel events, ON and OFF (the raw pixel: no denoising)."""
    cfg = load_config("realistic_sensor", ["emulator.denoise=none"])
    f = torch.full((2, 64, 64), 0.002)  # far below full_irradiance: the dark shot rate
    ideal, noisy = EventEmulator(), EventEmulator.from_config(cfg.emulator, seed=1)
    for e in (ideal, noisy):
        e.reset(f, 0)
    n_ideal = n_noisy = n_off = 0
    for k in range(1, 11):
        a, b = ideal.step(f, k * 100_000), noisy.step(f, k * 100_000)
        n_ideal, n_noisy, n_off = n_ideal + len(a), n_noisy + len(b), n_off + int((b.p < 0).sum())
    assert n_ideal == 0
    expect_shot = 5.0 * (1 + (0.25 - 1) * 0.01) * 2 * 64 * 64 * 1.0  # rate x pixels x 1 s
    assert 0.9 * expect_shot < n_noisy < 1.3 * expect_shot
    assert 0.35 * n_noisy < n_off < 0.55 * n_noisy
