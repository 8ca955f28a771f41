"""Per-seed dispersions: config validation, sampling, layout expansion (independent of sharding),
the emulator's per-element values, cheap sun-elevation scenes, and bit-identity of undispersed runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from dvsland.config import ConfigError, load_config
from dvsland.config.schema import Dispersion
from dvsland.sim import build_layout, simulate
from dvsland.layout.dispersion import element_rng, sample_elements, sample_one

QUIET = ["logging.figures=false", "logging.tensorboard=false"]
REF = Path(__file__).parent / "data" / "undispersed_runs_reference.json"


def _u(name, lo, hi):
    return [f"dispersion.{name}.kind=uniform", f"dispersion.{name}.low={lo}", f"dispersion.{name}.high={hi}"]


class TestDistributions:
    def test_kinds(self):
        rng = element_rng(0, "A", 3, "z0_scale")
        assert sample_one(Dispersion(kind="off"), rng) is None
        assert sample_one(Dispersion(kind="fixed", value=1.5), rng) == 1.5
        u = [sample_one(Dispersion(kind="uniform", low=2.0, high=3.0), element_rng(0, "A", k, "z0_scale"))
             for k in range(400)]
        assert min(u) >= 2.0 and max(u) <= 3.0 and abs(np.mean(u) - 2.5) < 0.05
        n = [sample_one(Dispersion(kind="normal", mean=0.0, std=1.0, low=-1.0, high=1.0),
                        element_rng(0, "A", k, "v0_scale")) for k in range(400)]
        assert min(n) == -1.0 and max(n) == 1.0  # clipped at the bounds
        assert 0.5 < np.std(n) < 0.8

    def test_streams_keys(self):
        d = Dispersion(kind="uniform", low=0.0, high=1.0)
        a = sample_elements(d, "z0_scale", 0, ["A", "A", "B"], [0, 1, 0])
        assert len(set(a.tolist())) == 3  # sites and seeds differ
        assert not np.array_equal(a, sample_elements(d, "v0_scale", 0, ["A", "A", "B"], [0, 1, 0]))
        assert not np.array_equal(a, sample_elements(d, "z0_scale", 1, ["A", "A", "B"], [0, 1, 0]))
        assert sample_elements(Dispersion(), "z0_scale", 0, ["A"], [0]) is None
        with pytest.raises(ValueError, match="stream"):
            element_rng(0, "A", 0, "nope")


class TestConfig:
    def test_default_off(self):
        cfg = load_config("realistic")
        assert not cfg.dispersion.enabled and cfg.dispersion.z0_scale.kind == "off"
        assert cfg.simulation.seed_offset == 0

    @pytest.mark.parametrize("overrides,match", [
        (_u("z0_scale", 1.1, 0.9), "low <= high"),
        (["dispersion.sun_elevation_deg.kind=fixed", "dispersion.sun_elevation_deg.value=0"], r"\[1.0, 90.0\]"),
        (_u("mismatch_sigma", 0.0, 2.0), "mismatch_sigma"),
        (["dispersion.z0_scale.kind=gauss"], "dispersion.z0_scale.kind"),
        (["dispersion.terrain_variants=-1"], "terrain_variants"),
        (["dispersion.v0_scale.std=-1"], "v0_scale.std"),
    ])
    def test_errors_name_the_parameter(self, overrides, match):
        with pytest.raises(ConfigError, match=match):
            load_config("realistic", overrides)


class TestLayout:
    OV = ["dispersion.enabled=true", "dispersion.terrain_variants=3", *_u("z0_scale", 0.8, 1.2),
          *_u("sun_elevation_deg", 10, 20), *_u("background_rate_hz", 0, 1), "dispersion.sun_step_deg=5"]

    def test_values_independent_of_sharding_and_setting(self):
        full = build_layout(load_config("realistic", self.OV + ["simulation.n_seeds=4"]))
        part = build_layout(load_config("realistic", self.OV + ["simulation.n_seeds=2", "simulation.seed_offset=2"]))
        sel = full.seed_idx >= 2
        assert part.run_label == [r for r, s in zip(full.run_label, sel) if s]
        np.testing.assert_array_equal(part.z0_m, full.z0_m[sel])
        np.testing.assert_array_equal(part.seed, full.seed[sel])
        assert part.scene == [x for x, s in zip(full.scene, sel) if s]
        np.testing.assert_array_equal(part.sensor["background_rate_hz"], full.sensor["background_rate_hz"][sel])
        # both controller settings of a (site, seed) meet the same dispersed descent
        a = (full.site_idx == 0) & (full.seed_idx == 1)
        assert len(set(full.z0_m[a].tolist())) == 1 and len(set(np.asarray(full.scene)[a].tolist())) == 1
        # scenes: variant k mod 3, sun rounded to the 5 deg step
        assert set(full.dispersed["terrain_variant"].tolist()) == {0, 1, 2}
        assert set(full.dispersed["sun_elevation_deg"].tolist()) <= {10.0, 15.0, 20.0}
        assert full.scene_names[full.scene_idx[0]] == full.scene[0]
        assert 0.8 * 10000 <= full.z0_m[0] <= 1.2 * 10000

    def test_off_is_plain_layout(self):
        plain = build_layout(load_config("realistic", ["simulation.n_seeds=2"]))
        off = build_layout(load_config("realistic", ["simulation.n_seeds=2", *_u("z0_scale", 0.8, 1.2)]))
        np.testing.assert_array_equal(plain.seed, off.seed)
        np.testing.assert_array_equal(plain.z0_m, off.z0_m)
        assert plain.scene_names == plain.site_names and not off.dispersed


class TestEmulatorElements:
    def _frames(self, B, k):
        g = torch.Generator().manual_seed(k)
        return 0.2 + torch.rand(B, 16, 16, generator=g)

    def test_background_rate_per_element(self):
        from dvsland.events import EventEmulator

        emu = EventEmulator(threshold=10.0)  # no pixel events at all
        emu.set_element_params(background_rate_hz=[0.0, 500.0, 0.0])
        f = torch.full((3, 16, 16), 0.5)
        emu.reset(f, 0)
        ev = emu.step(f.clone(), 100_000)
        b = ev.b.tolist()
        assert len(b) > 500 and set(b) == {1}

    def test_threshold_and_refractory_per_element(self):
        from dvsland.events import EventEmulator

        f0, f1 = self._frames(3, 0), self._frames(3, 1) * 3.0
        counts = []
        for params in ({}, {"threshold_scale": [1.0, 2.0, 1.0], "refractory_us": [0.0, 0.0, 1e6]}):
            emu = EventEmulator(threshold=0.1, refractory_us=0.0)
            if params:
                emu.set_element_params(**params)
            emu.reset(f0.clone(), 0)
            ev = emu.step(f1.clone(), 100_000)
            counts.append(torch.bincount(ev.b.long(), minlength=3).tolist())
        plain, disp = counts
        assert disp[0] == plain[0]  # unchanged element: the same events
        assert disp[1] < 0.7 * plain[1]  # doubled threshold: fewer crossings
        assert disp[2] <= 16 * 16 < plain[2]  # refractory 1 s: at most one event per pixel per step

    def test_errors(self):
        from dvsland.events import EventEmulator

        emu = EventEmulator()
        with pytest.raises(ValueError, match="background_rate_hz"):
            emu.set_element_params(background_rate_hz=[-1.0])
        with pytest.raises(ValueError, match="batch size"):
            emu.set_element_params(mismatch_sigma=[0.1, 0.1], refractory_us=[1.0])
        with pytest.raises(ValueError, match="B=2"):
            emu.set_element_params(mismatch_sigma=[0.1, 0.1])
            emu.reset(torch.ones(3, 8, 8), 0)


def test_sun_elevation_scene_reuses_fields_bit_identically(monkeypatch):
    monkeypatch.setenv("DVSLAND_CACHE_DIR", "off")
    from dvsland.render.lod import LevelParams, prepare_levels
    from dvsland.render.scenes import _FIELDS, load_scene, parse_scene, prepare_scene_levels
    from dvsland.terrain import load_site

    p = LevelParams(level_size=48, base_texel_m=2.0, n_levels=3)
    a = prepare_scene_levels(load_scene("E~7@el12"), p, "E~7@el12", disk_cache=False)
    n_fields = len(_FIELDS)
    b = prepare_scene_levels(load_scene("E~7@el20"), p, "E~7@el20", disk_cache=False)
    assert len(_FIELDS) == n_fields  # the second elevation only re-shaded
    ref = prepare_levels(load_site("E~7", 20.0), p, disk_cache=False)
    assert torch.equal(b.irradiance, ref.irradiance) and torch.equal(b.height_m, ref.height_m)
    assert not torch.equal(a.irradiance, b.irradiance)
    assert parse_scene("E~2@el12@az+5") == ("E~2", 12.0, 5.0)
    with pytest.raises(ValueError, match="scene label"):
        parse_scene("E@x1")


def test_seeds_differ_once_dispersed_identical_when_off(tmp_path):
    cfg = ["simulation.n_seeds=4", "simulation.sites=[{name: D, z0_m: 4000.0, v0_mps: -100.0}]"] + QUIET
    off = simulate("realistic", estimator="oracle", out=tmp_path / "off", quiet=True, overrides=cfg)
    t_off = {r["t_end_s"] for r in off.runs if r["label"] == off.runs[0]["label"]}
    assert len(t_off) == 1  # all dispersions off: every seed flies the same descent
    on = simulate("realistic", estimator="oracle", out=tmp_path / "on", quiet=True,
                  overrides=cfg + ["dispersion.enabled=true", *_u("z0_scale", 0.8, 1.2), *_u("v0_scale", 0.9, 1.1)])
    t_on = [r["t_end_s"] for r in on.runs if r["label"] == on.runs[0]["label"]]
    assert len(set(t_on)) == 4 and max(t_on) - min(t_on) > 1.0  # outcome times spread across seeds
    assert all("dispersion" in r and "z0_scale" in r["dispersion"] for r in on.runs)


def test_undispersed_runs_bit_identical_to_reference(tmp_path):
    """The reference was written by the code before dispersions existed (same command):
    an undispersed config must reproduce it exactly, dpr (renderer + emulator) and noisy oracle."""
    ref = json.loads(REF.read_text())
    for est in ("dpr", "oracle"):
        r = simulate("realistic", estimator=est, sites="A,E", quiet=True, out=tmp_path / est,
                     overrides=["simulation.t_max_s=3", "simulation.n_seeds=2", "estimator.oracle.noise_rel=0.05"] + QUIET)
        runs = json.loads(json.dumps(r.runs))
        assert len(runs) == len(ref[est])
        for run, want in zip(runs, ref[est]):  # every field the reference has (newer fields may be added)
            assert {k: run.get(k) for k in want} == want


def test_lazy_levels_render_like_full_levels(monkeypatch):
    monkeypatch.setenv("DVSLAND_CACHE_DIR", "off")
    from dvsland.config import CameraConfig, RenderConfig
    from dvsland.render.fast import FastRenderer

    cam, rc = CameraConfig(width_px=32, height_px=32), RenderConfig(threads=1)
    full = FastRenderer(["E~7"], cam, rc, disk_cache=False)
    lazy = FastRenderer(["E~7"], cam, rc, disk_cache=False, suns=[(None, 0.0)], altitude_ranges=[(50.0, 4400.0)])
    assert float(lazy._lam_lo[0]) == 2.0 and 8.9 < float(lazy._lam_hi[0]) < 9.0  # levels 2-9 of 13
    alt = torch.tensor([60.0, 400.0, 4000.0])
    idx = torch.zeros(3, dtype=torch.int64)
    a, b = full.render(alt, idx), lazy.render(alt, idx)
    # same tiles; only the landing-point height (from level 2 instead of 0) moves the parallax a little
    assert float((a.log() - b.log()).abs().mean()) < 0.05
    low = lazy.render(torch.tensor([12.0, 19000.0]), torch.zeros(2, dtype=torch.int64))
    assert bool(torch.isfinite(low).all()) and bool((low > 0).all())  # clamped to the prepared levels
    with pytest.raises(ValueError, match="altitude_ranges"):
        FastRenderer(["E~7"], cam, rc, disk_cache=False, altitude_ranges=[(50.0, 4400.0)])
