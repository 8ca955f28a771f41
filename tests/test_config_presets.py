"""Presets compose: ``extends: <preset or path>`` (deep merge of mappings, lists and values
replaced whole), every shipped preset resolves to the values it had as a flat file, and
``dvsland config show --origin`` names the file (or --set) of each value."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from dvsland.cli.main import main
from dvsland.config import ConfigError, config_to_dict, configs_dir, load_config
from dvsland.config.loader import load_config_with_origins, origin_of, resolve_config

#: the shipped presets as flat files, before they extended each other (git show 976b340:dvsland/configs/X.yaml)
FLAT = Path(__file__).parent / "data" / "presets_flat"
SHIPPED = sorted(p.stem for p in configs_dir().glob("*.yaml"))


def write(folder: Path, name: str, data: dict) -> Path:
    p = folder / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


# ------------------------------------------------------------------ shipped presets
def test_smoke_every_shipped_preset_has_its_flat_record():
    assert SHIPPED == sorted(p.stem for p in FLAT.glob("*.yaml"))


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_preset_resolves_to_exactly_the_flat_values(name):
    assert config_to_dict(load_config(name)) == config_to_dict(load_config(FLAT / f"{name}.yaml"))


def test_shipped_presets_extend_instead_of_copying():
    bases = {n: (yaml.safe_load((configs_dir() / f"{n}.yaml").read_text()) or {}).get("extends") for n in SHIPPED}
    assert bases == {"paper": None, "paper_eq2": "paper", "realistic": "paper_eq2", "montecarlo": "realistic",
                     "montecarlo_efference": "montecarlo", "paper_montecarlo": "paper",
                     "realistic_sensor": "montecarlo_efference"}
    for n, base in bases.items():
        if base:  # a child repeats no value of its base
            child = yaml.safe_load((configs_dir() / f"{n}.yaml").read_text())
            parent, _ = resolve_config(configs_dir() / f"{base}.yaml")
            for section, body in child.items():
                if isinstance(body, dict):
                    same = [k for k, v in body.items() if parent.get(section, {}).get(k) == v]
                    assert not same, (n, section, same)


# ------------------------------------------------------------------ extends
class TestExtends:
    def test_deep_merge_lists_replaced(self, tmp_path):
        write(tmp_path, "base.yaml", {"name": "base", "emulator": {"threshold": 0.2, "refractory_us": 30.0},
                                      "controller": {"settings": [{"kp": 1e6, "n_bin": 5}, {"kp": 2e6, "n_bin": 5}]}})
        child = write(tmp_path, "child.yaml", {"extends": "base", "name": "child",
                                               "emulator": {"threshold": 0.3},
                                               "controller": {"settings": [{"kp": 3e6, "n_bin": 7}]}})
        cfg = load_config(child)
        assert cfg.name == "child" and cfg.emulator.threshold == 0.3 and cfg.emulator.refractory_us == 30.0
        assert [(s.kp, s.n_bin) for s in cfg.controller.settings] == [(3e6, 7)]

    def test_user_file_extends_a_shipped_preset_and_chains(self, tmp_path):
        mid = write(tmp_path, "mid.yaml", {"extends": "realistic", "name": "mid", "emulator": {"threshold": 0.15}})
        top = write(tmp_path, "top.yaml", {"extends": str(mid), "name": "top",
                                                             "simulation": {"seed": 7}})
        cfg = load_config(top, ["simulation.n_seeds=2"])
        ref = load_config("realistic", ["emulator.threshold=0.15", "simulation.seed=7", "simulation.n_seeds=2",
                                        "name=top"])
        assert cfg == ref

    def test_relative_path_is_next_to_the_file(self, tmp_path):
        (tmp_path / "a").mkdir()
        write(tmp_path / "a", "paper.yaml", {"name": "local_paper", "emulator": {"threshold": 0.4}})
        child = write(tmp_path / "a", "c.yaml", {"extends": "paper", "name": "c"})
        assert load_config(child).emulator.threshold == 0.4  # the file beside it wins over the shipped name

    @pytest.mark.parametrize("extends,needle", [("no_such_preset", "config file not found"),
                                                (5, "must name a preset or a YAML file"),
                                                ("", "must name a preset")])
    def test_bad_base(self, tmp_path, extends, needle):
        p = write(tmp_path, "c.yaml", {"extends": extends})
        with pytest.raises(ConfigError, match=needle) as exc:
            load_config(p)
        assert "c.yaml" in str(exc.value)

    def test_cycle(self, tmp_path):
        write(tmp_path, "a.yaml", {"extends": "b"})
        write(tmp_path, "b.yaml", {"extends": "a.yaml"})
        with pytest.raises(ConfigError, match="cycle"):
            load_config(tmp_path / "a.yaml")

    def test_unknown_key_in_child_still_named(self, tmp_path):
        p = write(tmp_path, "c.yaml", {"extends": "paper", "emulator": {"treshold": 0.2}})
        with pytest.raises(ConfigError, match="treshold"):
            load_config(p)


# ------------------------------------------------------------------ origins
class TestOrigins:
    def test_each_value_names_its_file(self):
        cfg, origins = load_config_with_origins("montecarlo_efference", ["emulator.threshold=0.2"])
        assert origin_of(origins, "controller.name") == "dvsland/configs/montecarlo_efference.yaml"
        assert origin_of(origins, "dispersion.z0_scale.low") == "dvsland/configs/montecarlo.yaml"
        assert origin_of(origins, "controller.thrust_max_n") == "dvsland/configs/realistic.yaml"
        assert origin_of(origins, "controller.c2") == "dvsland/configs/paper_eq2.yaml"
        assert origin_of(origins, "camera.fov_deg") == "dvsland/configs/paper.yaml"
        assert origin_of(origins, "emulator.threshold") == "--set emulator.threshold=0.2"
        assert origin_of(origins, "emulator.leak_rate_hz") == "default"
        assert cfg.emulator.threshold == 0.2

    def test_config_show_origin_is_the_same_yaml(self, capsys):
        assert main(["config", "show", "realistic", "--set", "simulation.sites.0.z0_m=5000"]) == 0
        plain = yaml.safe_load(capsys.readouterr().out)
        assert main(["config", "show", "realistic", "--origin", "--set", "simulation.sites.0.z0_m=5000"]) == 0
        text = capsys.readouterr().out
        assert yaml.safe_load(text) == plain
        lines = text.splitlines()
        assert "  thrust_max_n: 100000.0  # dvsland/configs/realistic.yaml" in lines
        assert "  c2: 0.5  # dvsland/configs/paper_eq2.yaml" in lines
        assert any(l.strip().startswith("- {name: A, z0_m: 5000.0") and l.endswith("# --set simulation.sites.0.z0_m=5000")
                   for l in lines)

    def test_config_show_origin_bad_config(self, capsys, tmp_path):
        p = write(tmp_path, "c.yaml", {"extends": "nowhere"})
        assert main(["config", "show", str(p), "--origin"]) == 2
        assert "nowhere" in capsys.readouterr().err
