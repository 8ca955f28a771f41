"""The package's layering: loading a config imports no stage; lower layers never import upper ones."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("torch", "kornia", "dvsland.estimators", "dvsland.render", "dvsland.events", "dvsland.sim",
         "dvsland.evaluate", "dvsland.terrain", "dvsland.control", "dvsland.dynamics", "dvsland.report")


def _modules_after(code: str) -> set:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys, json; print(json.dumps(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True)
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def _loaded(mods: set, prefixes) -> list:
    return sorted(m for m in mods if any(m == p or m.startswith(p + ".") for p in prefixes))


def test_config_imports_no_stage():
    mods = _modules_after("import dvsland.config as c; c.load_config('paper', ['estimator.name=oracle'])")
    assert "dvsland.config" in mods
    assert _loaded(mods, HEAVY) == []


def test_package_root_and_stages_layer_are_cheap():
    mods = _modules_after("import dvsland, dvsland.stages, dvsland.checks")
    assert _loaded(mods, HEAVY) == []


def test_stage_packages_do_not_import_upper_layers():
    """One interpreter for both (each must import none of these on its own, so together neither may)."""
    mods = _modules_after("import dvsland.estimators.snn.train, dvsland.render")
    assert "kornia" in mods  # the stages really were imported
    assert _loaded(mods, ("dvsland.evaluate", "dvsland.sim", "dvsland.stages")) == []


def test_simulator_does_not_import_the_evaluation():
    assert _loaded(_modules_after("import dvsland.sim.api"), ("dvsland.evaluate",)) == []


def test_config_validation_does_not_check_stage_names():
    from dvsland.config import ConfigError, load_config
    from dvsland.stages import check_names

    cfg = load_config("paper", ["estimator.name=nope"])  # loads: the name is checked where it is built
    with pytest.raises(ConfigError, match=r"estimator.name: unknown estimator 'nope'; known: \[.*'dpr'"):
        check_names(cfg)


def test_no_file_points_to_the_team_design_notes(repo_root):
    """Code, configs, scripts and tests stand on their own: no pointer to design notes that the
    repository does not contain."""
    needle = "DESIGN" + ".md"
    roots = [repo_root / d for d in ("dvsland", "scripts", "tests")]
    files = [p for r in roots for p in r.rglob("*") if p.is_file() and p.suffix in (".py", ".yaml", ".md", ".sh", ".txt")]
    files += [repo_root / "README.md", repo_root / "pyproject.toml", repo_root / "docs" / "architecture.md"]
    hits = [str(p.relative_to(repo_root)) for p in files if p.is_file() and needle in p.read_text(errors="ignore")]
    assert hits == []
