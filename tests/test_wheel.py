"""The installed package works without the source tree: build the wheel, install it in a fresh
virtual environment outside the checkout and fly a short descent there from a temporary folder.

The fresh environment gets the wheel alone (``--no-deps``); its dependencies (torch, kornia, ...)
come from the test's own environment through a ``.pth`` line, so nothing is downloaded. Only the
folder is added, not that environment's ``.pth`` hooks, so the editable install of the checkout
is not visible there.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def _run(cmd, cwd, env=None, timeout=600):
    out = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, f"{' '.join(map(str, cmd))} failed ({out.returncode}):\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    return out.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(python of a fresh venv with the built wheel installed, a temp cwd outside the checkout)."""
    base = tmp_path_factory.mktemp("wheel")
    # build from a copy, so that build/ and *.egg-info never land in the checkout
    src = base / "src"
    src.mkdir()
    shutil.copytree(ROOT / "dvsland", src / "dvsland", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    dist = base / "dist"
    _run([sys.executable, "-m", "pip", "wheel", ".", "--no-deps", "--no-build-isolation", "-q", "-w", dist], cwd=src)
    wheels = list(dist.glob("dvsland-*.whl"))
    assert len(wheels) == 1, wheels
    venv = base / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=base)
    py = venv / "bin" / "python"
    site = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=base).strip())
    (site / "_dvsland_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", "--no-index", "-q", wheels[0]], cwd=base)
    cwd = base / "elsewhere"
    cwd.mkdir()
    return py, cwd


def _env():
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.setdefault("PYOPENGL_PLATFORM", "egl")
    env.setdefault("EGL_PLATFORM", "surfaceless")
    return env


def test_wheel_holds_configs_sites_and_checkpoint(installed):
    py, cwd = installed
    code = (
        "import json, dvsland\n"
        "from dvsland.config import configs_dir, load_config\n"
        "from dvsland.terrain.spec import available_sites, load_spec, sites_dir\n"
        "from dvsland.estimators.snn import DEFAULT_CHECKPOINT\n"
        "cfg = load_config('paper')\n"
        "print(json.dumps({'pkg': dvsland.__file__, 'configs': str(configs_dir()), 'sites_dir': str(sites_dir()),\n"
        "  'sites': available_sites(), 'H_seed': load_spec('H').seed, 'ckpt': str(DEFAULT_CHECKPOINT),\n"
        "  'ckpt_ok': DEFAULT_CHECKPOINT.is_file(), 'name': cfg.name,\n"
        "  'realistic': load_config('configs/realistic.yaml').name}))\n")
    info = json.loads(_run([py, "-c", code], cwd=cwd, env=_env()).strip().splitlines()[-1])
    venv = str(py.parents[1])
    for key in ("pkg", "configs", "sites_dir", "ckpt"):
        assert info[key].startswith(venv), (key, info[key])  # the installed copy, not the checkout
        assert not info[key].startswith(str(ROOT))
    assert info["sites"] == list("ABCDEFGHI") and info["ckpt_ok"]
    assert info["name"] == "paper" and info["realistic"] == "realistic"


def test_wheel_simulate_from_a_temp_folder(installed):
    py, cwd = installed
    dvsland = py.parent / "dvsland"
    out = _run([dvsland, "simulate", "paper", "--sites", "A", "--set", "simulation.t_max_s=1", "--estimator", "oracle",
                "--quiet", "--out", "run"], cwd=cwd, env=_env())
    res = json.loads((cwd / "run" / "results.json").read_text())
    assert res["status"] == "complete" and res["estimator"] == "oracle" and res["n_steps"] == 10, out
    assert [r["run"] for r in res["runs"]] == ["A/Kp5e6-n5", "A/Kp4e6-n10"]
    assert (cwd / "run" / "config.yaml").is_file() and (cwd / "run" / "traces.npz").is_file()
