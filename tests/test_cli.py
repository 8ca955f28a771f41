"""The ``dvsland`` command line: --version, config show, errors, run folders."""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from dvsland import __version__
from dvsland.cli.main import build_parser, main
from dvsland.config import load_config
from dvsland.runs import make_run_dir


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert __version__ in capsys.readouterr().out


def test_console_script_installed():
    out = subprocess.run([sys.executable, "-m", "dvsland.cli.main", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and __version__ in out.stdout


def test_config_show_paper(capsys, paper_yaml):
    assert main(["config", "show", str(paper_yaml)]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["camera"]["width_px"] == 128
    assert len(shown["simulation"]["sites"]) == 9


def test_config_show_default_is_paper(capsys):
    assert main(["config", "show"]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["name"] == "paper"


def test_config_show_set(capsys, paper_yaml):
    assert main(["config", "show", str(paper_yaml), "--set", "emulator.threshold=0.25",
                 "--set", "simulation.seed=7"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["emulator"]["threshold"] == 0.25 and shown["simulation"]["seed"] == 7


@pytest.mark.parametrize("override,needle", [
    ("emulator.threshold=0", "emulator.threshold"),
    ("dynamics.isp_s=-3", "dynamics.isp_s"),
    ("bogus.key=1", "unknown key 'bogus'"),
    ("estimator.name=nope", "unknown estimator"),
])
def test_config_show_errors(capsys, paper_yaml, override, needle):
    assert main(["config", "show", str(paper_yaml), "--set", override]) == 2
    err = capsys.readouterr().err
    assert "config error" in err and needle in err


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "usage" in capsys.readouterr().out


def test_subcommands_discovered():
    text = build_parser().format_help()
    assert "config" in text


def test_run_dir_writes_config_first(tmp_path, paper_yaml):
    cfg = load_config(paper_yaml, [f"logging.root={tmp_path}"])
    run = make_run_dir(cfg)
    assert run.parent == tmp_path and run.name.startswith("paper-")
    assert load_config(run / "config.yaml") == cfg
    run2 = make_run_dir(cfg)
    assert run2 != run  # same second: a new folder, never overwritten
    out = make_run_dir(cfg, out=tmp_path / "explicit", kind="render")
    assert (out / "config.yaml").is_file()


def test_help_and_argument_errors_answer_without_torch():
    """`dvsland --help`, a command's --help and an unknown --model are answered before torch loads
    (issue: a command line that answers at once)."""
    import subprocess
    import sys

    code = ("import sys\nfrom dvsland.cli.main import main\n"
            "for argv in (['--help'], ['simulate', '--help'], ['bench', '--help'], ['train', '--model', 'cnnn']):\n"
            "    try:\n        main(argv)\n    except SystemExit:\n        pass\n"
            "print('TORCH', 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "TORCH False" in out.stdout, out.stdout[-500:] + out.stderr[-500:]
    assert "--model 'cnnn': unknown model; choose one of ['cnn', 'spiking']" in out.stderr
