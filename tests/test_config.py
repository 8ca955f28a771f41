"""Config loading, validation errors (each names the parameter and range), overrides."""

from __future__ import annotations

import dataclasses

import pytest
import yaml

from dvsland.config import (SITE_NAMES, Config, ConfigError, apply_overrides, config_to_dict, dump_config,
                            load_config)


def write(tmp_path, data, name="c.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


class TestLoad:
    def test_paper_preset(self, paper_yaml):
        cfg = load_config(paper_yaml)
        assert isinstance(cfg, Config)
        assert [s.name for s in cfg.simulation.sites] == list(SITE_NAMES)
        for s in cfg.simulation.sites:
            if s.name in "ABC":
                assert (s.z0_m, s.v0_mps) == (10000.0, -200.0)
            else:
                assert (s.z0_m, s.v0_mps) == (4000.0, -100.0)
        assert [(c.kp, c.n_bin) for c in cfg.controller.settings] == [(5e6, 5), (4e6, 10)]
        assert cfg.emulator.threshold == 0.1 and cfg.camera.frame_rate_hz == 10.0
        assert cfg.dt_s == pytest.approx(0.1)
        d = cfg.estimator.dpr
        assert (d.n_max, d.n_min, d.radius_px, d.c_min, d.r_min_px, d.memory_ms) == (15, 15, 4.0, 3, 3.0, 500.0)
        # the paper preset flies the released implementation's law and constants
        assert cfg.controller.name == "div_p" and cfg.controller.c2 == 0.25 and not cfg.controller.div_p.feedforward_mg
        assert cfg.dynamics.isp_s == 300.0 and cfg.dynamics.g_mps2 == 1.623 and cfg.dynamics.mass_kg == 1e4
        assert cfg.dynamics.integrator == "euler" and cfg.controller.thrust_max_n is None
        eq2 = load_config(paper_yaml.parent / "paper_eq2.yaml")  # Eq. 2 literal, the text's constants
        assert eq2.controller.name == "tau_p" and eq2.controller.c2 == 0.5 and eq2.dynamics.isp_s == 600.0
        assert eq2.dynamics.g_mps2 == 1.62 and eq2.dynamics.integrator == "exact"

    def test_paper_yaml_says_where_each_number_comes_from(self, paper_yaml):
        import re

        section = None
        for line in paper_yaml.read_text().splitlines():
            if re.match(r"^[a-z]", line):
                section = line.split(":")[0]
                continue
            body = line.split("#")[0]
            if section in ("camera", "emulator", "controller", "dynamics") and re.search(r"[:{]\s*[-0-9.]", body):
                assert re.search(r"paper text|released code|not in paper", line), line

    def test_paper_yaml_marks_numbers_not_in_paper(self, paper_yaml):
        text = paper_yaml.read_text()
        for key in ("mass_kg", "thrust_max_n", "fov_deg", "sun_elevation_deg", "blur_sigma_px"):
            line = next(l for l in text.splitlines() if l.strip().startswith(key + ":"))
            assert "not in paper" in line, line

    def test_defaults_without_file(self, tmp_path):
        cfg = load_config(write(tmp_path, {}))
        assert cfg == dataclasses.replace(Config())

    def test_round_trip_dump(self, paper_yaml, tmp_path):
        cfg = load_config(paper_yaml)
        p = tmp_path / "out.yaml"
        dump_config(cfg, p)
        assert load_config(p) == cfg

    def test_yaml_1_1_exponent_strings_are_numbers(self, tmp_path):
        cfg = load_config(write(tmp_path, {"controller": {"settings": [{"kp": "5e6", "n_bin": 5}]}}))
        assert cfg.controller.settings[0].kp == 5e6


class TestErrors:
    @pytest.mark.parametrize("section,key,value,needle", [
        ("emulator", "threshold", 0.0, "emulator.threshold"),
        ("emulator", "threshold", -0.1, "(0.0, 10.0]"),
        ("dynamics", "isp_s", 0.0, "dynamics.isp_s"),
        ("dynamics", "mass_kg", -5.0, "dynamics.mass_kg"),
        ("camera", "fov_deg", 200.0, "camera.fov_deg"),
        ("camera", "width_px", 3, "camera.width_px"),
        ("controller", "c2", 1.5, "controller.c2"),
        ("simulation", "t_max_s", 0, "simulation.t_max_s"),
        ("emulator", "interpolation", "cubic", "choose one of"),
    ])
    def test_out_of_range(self, tmp_path, section, key, value, needle):
        with pytest.raises(ConfigError, match="out of range|not allowed") as exc:
            load_config(write(tmp_path, {section: {key: value}}))
        assert needle in str(exc.value)
        assert "c.yaml" in str(exc.value)

    def test_unknown_renderer_checked_where_built(self, tmp_path):
        from dvsland.stages import check_names

        cfg = load_config(write(tmp_path, {"render": {"renderer": "raytracer"}}))  # the registry decides
        with pytest.raises(ConfigError, match=r"render\.renderer.*'raytracer'.*known: \['fast', 'pyrender'"):
            check_names(cfg, source="c.yaml")

    def test_negative_altitude(self, tmp_path):
        with pytest.raises(ConfigError, match=r"simulation\.sites\[0\]\.z0_m.*out of range"):
            load_config(write(tmp_path, {"simulation": {"sites": [{"name": "A", "z0_m": -10}]}}))

    def test_unknown_site(self, tmp_path):
        with pytest.raises(ConfigError, match=r"simulation\.sites\[0\]\.name.*'Z'.*choose one of"):
            load_config(write(tmp_path, {"simulation": {"sites": [{"name": "Z"}]}}))

    def test_duplicate_sites(self, tmp_path):
        with pytest.raises(ConfigError, match="unique"):
            load_config(write(tmp_path, {"simulation": {"sites": [{"name": "A"}, {"name": "A"}]}}))

    def test_unknown_estimator_lists_known(self, tmp_path):
        from dvsland.stages import check_names

        cfg = load_config(write(tmp_path, {"estimator": {"name": "nope"}}))  # checked where it is built
        with pytest.raises(ConfigError, match=r"estimator\.name.*'nope'.*known:.*oracle"):
            check_names(cfg)

    def test_unknown_key_names_key_and_file(self, tmp_path):
        with pytest.raises(ConfigError, match=r"unknown key 'emulator\.thresh'.*c\.yaml"):
            load_config(write(tmp_path, {"emulator": {"thresh": 0.2}}))

    def test_unknown_section(self, tmp_path):
        with pytest.raises(ConfigError, match="unknown key 'camra'"):
            load_config(write(tmp_path, {"camra": {}}))

    def test_wrong_type(self, tmp_path):
        with pytest.raises(ConfigError, match=r"camera\.width_px.*integer"):
            load_config(write(tmp_path, {"camera": {"width_px": "wide"}}))
        with pytest.raises(ConfigError, match=r"logging\.tensorboard.*true or false"):
            load_config(write(tmp_path, {"logging": {"tensorboard": "maybe"}}))

    def test_section_not_mapping(self, tmp_path):
        with pytest.raises(ConfigError, match="expected a mapping"):
            load_config(write(tmp_path, {"camera": 5}))

    def test_missing_file(self, tmp_path):
        with pytest.raises(ConfigError, match="not found"):
            load_config(tmp_path / "missing.yaml")

    def test_bad_yaml(self, tmp_path):
        p = tmp_path / "bad.yaml"
        p.write_text("camera: [1, 2\n")
        with pytest.raises(ConfigError, match="not valid YAML"):
            load_config(p)

    def test_top_level_not_mapping(self, tmp_path):
        p = tmp_path / "list.yaml"
        p.write_text("- 1\n- 2\n")
        with pytest.raises(ConfigError, match="mapping"):
            load_config(p)

    def test_dry_mass_above_mass(self, tmp_path):
        with pytest.raises(ConfigError, match="dry_mass_kg"):
            load_config(write(tmp_path, {"dynamics": {"mass_kg": 1000, "dry_mass_kg": 2000}}))

    def test_thrust_bounds_inverted(self, tmp_path):
        with pytest.raises(ConfigError, match="thrust_max_n"):
            load_config(write(tmp_path, {"controller": {"thrust_min_n": 10, "thrust_max_n": 5}}))

    def test_empty_settings(self, tmp_path):
        with pytest.raises(ConfigError, match="at least one"):
            load_config(write(tmp_path, {"controller": {"settings": []}}))

    def test_bad_device(self, tmp_path):
        with pytest.raises(ConfigError, match="simulation.device"):
            load_config(write(tmp_path, {"simulation": {"device": "tpu"}}))

    def test_null_not_allowed(self, tmp_path):
        with pytest.raises(ConfigError, match="must not be null"):
            load_config(write(tmp_path, {"emulator": {"threshold": None}}))

    def test_nan_rejected(self, tmp_path):
        with pytest.raises(ConfigError, match="out of range"):
            load_config(write(tmp_path, {"emulator": {"threshold": float("nan")}}))


class TestOverrides:
    def test_typed_by_field(self, paper_yaml):
        cfg = load_config(paper_yaml, ["emulator.threshold=0.2", "camera.width_px=64", "logging.quiet=true",
                                       "controller.thrust_max_n=1e5", "estimator.name=oracle"])
        assert cfg.emulator.threshold == 0.2 and isinstance(cfg.emulator.threshold, float)
        assert cfg.camera.width_px == 64 and isinstance(cfg.camera.width_px, int)
        assert cfg.logging.quiet is True
        assert cfg.controller.thrust_max_n == 1e5
        assert cfg.estimator.name == "oracle"

    def test_list_index(self, paper_yaml):
        cfg = load_config(paper_yaml, ["simulation.sites.3.z0_m=5000", "controller.settings.1.n_bin=7"])
        assert cfg.simulation.sites[3].z0_m == 5000.0
        assert cfg.controller.settings[1].n_bin == 7

    def test_whole_list(self, paper_yaml):
        cfg = load_config(paper_yaml, ["controller.settings=[{kp: 1e6, n_bin: 1}]"])
        assert [(s.kp, s.n_bin) for s in cfg.controller.settings] == [(1e6, 1)]

    def test_null_override(self, paper_yaml):
        cfg = load_config(paper_yaml, ["controller.thrust_max_n=100000", "controller.thrust_max_n=null"])
        assert cfg.controller.thrust_max_n is None

    def test_free_params(self, paper_yaml):
        cfg = load_config(paper_yaml, ["estimator.params.gain=3"])
        assert cfg.estimator.params == {"gain": 3}

    def test_unknown_key(self, paper_yaml):
        with pytest.raises(ConfigError, match=r"--set emulator\.nope=1: unknown key 'emulator\.nope'"):
            load_config(paper_yaml, ["emulator.nope=1"])

    def test_out_of_range_names_override(self, paper_yaml):
        with pytest.raises(ConfigError, match=r"emulator\.threshold.*--set.*out of range"):
            load_config(paper_yaml, ["emulator.threshold=-1"])

    def test_malformed(self, paper_yaml):
        with pytest.raises(ConfigError, match="expected section.key=value"):
            load_config(paper_yaml, ["emulator.threshold"])
        with pytest.raises(ConfigError, match="no sub-key"):
            load_config(paper_yaml, ["emulator.threshold.x=1"])
        with pytest.raises(ConfigError, match="out of range"):
            load_config(paper_yaml, ["simulation.sites.42.z0_m=1"])

    def test_apply_does_not_mutate(self):
        raw = {"emulator": {"threshold": 0.1}}
        out = apply_overrides(raw, ["emulator.threshold=0.3"])
        assert raw["emulator"]["threshold"] == 0.1 and out["emulator"]["threshold"] == 0.3

    def test_config_to_dict_is_plain(self, paper_yaml):
        d = config_to_dict(load_config(paper_yaml))
        yaml.safe_dump(d)  # only plain types
        assert d["simulation"]["sites"][0]["name"] == "A"


def test_realistic_preset_is_paper_eq2_with_100kN(paper_yaml):
    paper = load_config(paper_yaml.parent / "paper_eq2.yaml")  # Eq. 2 literal (paper.yaml flies div_p now)
    real = load_config(paper_yaml.parent / "realistic.yaml")
    assert real.controller.thrust_max_n == 1e5 and paper.controller.thrust_max_n is None
    real.controller.thrust_max_n, real.name = None, paper.name
    assert real == paper


def test_torch_threads_range(tmp_path):
    with pytest.raises(ConfigError, match=r"simulation\.torch_threads.*out of range"):
        load_config(write(tmp_path, {"simulation": {"torch_threads": -1}}))


def test_recommended_settings_apply_to_their_estimator_unless_set():
    """A preset's `recommended:` section sets what it flies an estimator with; a --set of the same key wins."""
    from dvsland.config.loader import load_config_with_origins, origin_of

    assert load_config("montecarlo_efference").controller.efference.min_confidence == 0.5
    cfg, origins = load_config_with_origins("montecarlo_efference", ["estimator.name=learned"])
    assert cfg.controller.efference.min_confidence == 0.05
    assert origin_of(origins, "controller.efference.min_confidence").startswith("recommended for estimator 'learned'")
    mine = load_config("montecarlo_efference", ["estimator.name=learned", "controller.efference.min_confidence=0.3"])
    assert mine.controller.efference.min_confidence == 0.3


def test_recommended_section_must_be_a_mapping(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("extends: paper\nrecommended: [1, 2]\n")
    with pytest.raises(ConfigError, match=r"recommended \(in .*bad.yaml\): expected \{estimator name"):
        load_config(p)
