"""The face of the command line: one device check for every command (before any run folder),
--quiet prints the run folder, evaluate honours simulation.torch_threads, help texts for users,
estimators loaded by import path."""

from __future__ import annotations

import json
import re

import pytest
import torch

from dvsland.cli.common import available_devices, check_device
from dvsland.cli.main import build_parser, main

SMALL = ["--set", "camera.width_px=32", "--set", "camera.height_px=32"]
COMMANDS = {
    "simulate": ["simulate", "--sites", "D", "--estimator", "oracle"],
    "render": ["render", "--sites", "A", "--altitudes", "100", "--gif-frames", "0"],
    "events": ["events", "--site", "D", "--from-m", "1000", "--to-m", "990"],
    "evaluate": ["evaluate", "--estimators", "oracle", "--sites", "D", "--max-steps", "3"],
}
MISSING = ["cuda:7" if torch.cuda.is_available() else "cuda", "mps", "tpu"]


def test_check_device():
    assert check_device("cpu").type == "cpu"
    assert available_devices()[0] == "cpu"
    with pytest.raises(ValueError, match=r"--device='nonsense!' is not a torch device; available on this machine: cpu"):
        check_device("nonsense!", "--device")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"simulation.device='cuda'.*CUDA is not available.*available on this machine: cpu"):
            check_device("cuda")


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("device", MISSING)
def test_unavailable_device_is_one_clear_error_and_no_run_folder(command, device, tmp_path, capsys):
    if device == "mps" and "mps" in available_devices():
        pytest.skip("this machine has mps")
    out = tmp_path / "run"
    rc = main([*COMMANDS[command], "--device", device, "--out", str(out), *SMALL, "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "--device" in err and "available on this machine: cpu" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    assert not out.exists(), "the device check must come before the run folder"


def test_device_set_in_the_config_is_named_as_such(tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("CUDA present")
    rc = main([*COMMANDS["render"], "--set", "simulation.device=cuda", "--out", str(tmp_path / "r"), *SMALL])
    assert rc == 2 and "simulation.device='cuda'" in capsys.readouterr().err


def test_evaluate_uses_torch_threads_and_quiet_prints_the_run_folder(tmp_path, capsys, monkeypatch):
    calls = []
    monkeypatch.setattr(torch, "set_num_threads", lambda n: calls.append(n))
    out = tmp_path / "ev"
    rc = main([*COMMANDS["evaluate"], "--warmup-steps", "0", "--no-figures", "--out", str(out), *SMALL,
               "--set", "simulation.torch_threads=3", "--quiet"])
    # the first call is the run's setting (render.threads = 1: the renderer leaves it alone)
    assert rc == 0 and calls[0] == 3
    assert capsys.readouterr().out.strip().splitlines() == [f"run folder: {out}"]
    calls.clear()
    rc = main([*COMMANDS["evaluate"], "--warmup-steps", "0", "--no-figures", "--out", str(tmp_path / "ev2"), *SMALL,
               "--set", "simulation.torch_threads=3", "--threads", "2", "--quiet"])
    assert rc == 0 and calls[0] == 2


def test_quiet_simulate_prints_only_the_run_folder(tmp_path, capsys):
    out = tmp_path / "sim"
    rc = main([*COMMANDS["simulate"], "--out", str(out), "--set", "simulation.t_max_s=1", "--set",
               "logging.figures=false", "--quiet"])
    assert rc == 0
    assert capsys.readouterr().out.strip().splitlines() == [f"run folder: {out}"]


def _help(capsys, *argv) -> str:
    with pytest.raises(SystemExit):
        build_parser().parse_args([*argv, "--help"])
    return capsys.readouterr().out


def test_help_texts_are_for_users(capsys):
    from dvsland.estimators import available_estimators, register_estimator

    @register_estimator("helptest_est")
    class _Est:  # noqa: N801 - only its name is listed
        pass

    try:
        text = _help(capsys, "simulate")
        for name in available_estimators():
            assert name in text, name
        assert "snn" in text and "helptest_est" in text and "package.module:Class" in text
    finally:
        from dvsland.estimators import registry

        registry._REGISTRY.pop("helptest_est", None)
    for cmd in ("render", "events", "evaluate", "simulate"):
        text = _help(capsys, cmd)
        assert not re.search(r"``|:func:|:class:|DESIGN", text), (cmd, text)
        assert "run folder" in text, cmd


def test_estimator_by_import_path(tmp_path, monkeypatch, repo_root, half_estimator_source):
    mod = tmp_path / "my_user_estimators.py"
    mod.write_text(half_estimator_source)
    monkeypatch.chdir(tmp_path)  # the module is found in the current directory
    from dvsland.estimators import get_estimator

    est = get_estimator("my_user_estimators:Half", 2, (32, 32))
    assert type(est).__name__ == "Half" and est.batch_size == 2
    with pytest.raises(ValueError, match="has no class 'Nope'"):
        get_estimator("my_user_estimators:Nope", 2, (32, 32))
    with pytest.raises(ValueError, match="cannot import 'no_such_module_xyz'"):
        get_estimator("no_such_module_xyz:Cls", 2, (32, 32))
    with pytest.raises(ValueError, match="unknown estimator 'nope'.*package.module:Class"):
        get_estimator("nope", 2, (32, 32))
    # a file path works too, from the command line
    out = tmp_path / "run"
    script = repo_root / "scripts" / "custom_estimator.py"
    rc = main(["simulate", "--sites", "D", "--estimator", f"{script}:ZoomCorr", "--out", str(out), *SMALL,
               "--set", "simulation.t_max_s=0.3", "--set", "logging.figures=false", "--quiet"])
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    assert res["estimator"].endswith("custom_estimator.py:ZoomCorr") and res["status"] == "complete"


@pytest.mark.parametrize("command", ["render", "events"])
def test_quiet_render_and_events_print_only_the_run_folder(command, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DVSLAND_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / command
    assert main([*COMMANDS[command], "--out", str(out), *SMALL, "--quiet"]) == 0
    assert capsys.readouterr().out.strip().splitlines() == [f"run folder: {out}"]
    assert any((out / "tb").glob("events.out.tfevents*"))
