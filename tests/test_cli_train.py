"""``dvsland train``: trains the spiking estimator into --out or a new run folder under logs/, and
never replaces the shipped checkpoint unless --overwrite-shipped says so (checked before any
data is made)."""

from __future__ import annotations

import hashlib
import json

import pytest

from dvsland.cli import cmd_train
from dvsland.cli.main import build_parser, main
from dvsland.estimators.snn import DEFAULT_CHECKPOINT, load_checkpoint

TINY = ["--sites", "A~1", "--n-seq", "4", "--steps", "6", "--epochs", "1", "--batch", "2", "--warmup-steps", "2",
        "--quiet"]


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def no_data(monkeypatch):
    """Fail if any training data would be made (for the refusals)."""
    def boom(*a, **k):
        raise AssertionError("data were made before the checks")

    monkeypatch.setattr(cmd_train, "_sequences", boom)


def test_smoke_train_to_out(tmp_path, capsys):
    out = tmp_path / "ck" / "mine.pt"
    assert main(["train", *TINY, "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    model, enc, meta = load_checkpoint(out)
    assert meta["epochs_run"] == 1 and meta["sites"] == ["A~1"] and meta["n_seq"] == 4
    assert enc.n_sub == 4


def test_default_writes_a_run_folder_under_logging_root(tmp_path):
    shipped = _digest(DEFAULT_CHECKPOINT)
    assert main(["train", *TINY, "--set", f"logging.root={tmp_path / 'logs'}"]) == 0
    (run,) = list((tmp_path / "logs").glob("paper-train-*"))
    assert {p.name for p in run.iterdir()} >= {"snn.pt", "train.json", "config.yaml"}
    assert json.loads((run / "train.json").read_text())["epochs_run"] == 1
    assert _digest(DEFAULT_CHECKPOINT) == shipped


def test_shipped_checkpoint_refused_before_any_data(tmp_path, capsys, no_data):
    shipped = _digest(DEFAULT_CHECKPOINT)
    assert main(["train", *TINY, "--out", str(DEFAULT_CHECKPOINT)]) == 2
    err = capsys.readouterr().err
    assert "--overwrite-shipped" in err and "inside the installed dvsland package" in err
    assert _digest(DEFAULT_CHECKPOINT) == shipped
    # anything else inside the package too
    assert main(["train", *TINY, "--out", str(cmd_train.package_dir() / "configs" / "x.pt")]) == 2
    assert "--overwrite-shipped" in capsys.readouterr().err


def test_overwrite_shipped_allows_the_package_path():
    # checked only (no training): the flag lets the shipped path through, existing or not
    assert cmd_train.check_out_path(DEFAULT_CHECKPOINT, overwrite_shipped=True) == DEFAULT_CHECKPOINT


@pytest.mark.parametrize("extra,needle", [
    (["--n-seq", "1"], "--n-seq must be >= 2"),
    (["--warmup-steps", "6"], "--warmup-steps"),
    (["--channels", "16"], "--channels"),
    (["--lr", "0"], None),  # the parser refuses it (range 1e-8 to 10)
    (["--sites", "Q~1"], "unknown site 'Q~1'"),
    (["--threads", "0"], None),
])
def test_bad_options_refused_before_any_data(tmp_path, capsys, no_data, extra, needle):
    args = ["train", *TINY, *extra, "--out", str(tmp_path / "x.pt")]
    if needle is None:  # argparse refuses it
        with pytest.raises(SystemExit):
            main(args)
        assert "--threads" in capsys.readouterr().err
    else:
        assert main(args) == 2
        assert needle in capsys.readouterr().err
    assert not (tmp_path / "x.pt").exists()


def test_existing_file_and_folder(tmp_path, capsys, no_data):
    f = tmp_path / "old.pt"
    f.write_bytes(b"mine")
    assert main(["train", *TINY, "--out", str(f)]) == 2
    assert "--overwrite" in capsys.readouterr().err and f.read_bytes() == b"mine"
    assert main(["train", *TINY, "--out", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err


def test_arguments_in_groups_one_function():
    """The options come from add_train_arguments, grouped so that new data and model options have
    one place to go."""
    p = build_parser()
    sub = next(a for a in p._actions if a.dest == "command").choices["train"]
    groups = {g.title: {a.dest for a in g._group_actions} for g in sub._action_groups}
    assert {"output", "data", "model", "training"} <= set(groups)
    assert {"sites", "n_seq", "steps"} <= groups["data"] and {"init", "channels"} <= groups["model"]
    assert {"epochs", "lr"} <= groups["training"] and {"out", "overwrite_shipped"} <= groups["output"]
    args = p.parse_args(["train"])
    assert args.out is None and args.overwrite_shipped is False and args.func is cmd_train.run_train


def test_script_is_a_thin_wrapper(repo_root, monkeypatch, no_data, capsys):
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_snn_script", repo_root / "scripts" / "train_snn.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--quiet", "--out", str(DEFAULT_CHECKPOINT)]) == 2  # the command's refusal
    assert "--overwrite-shipped" in capsys.readouterr().err


def test_help_describes_the_recipe_first_and_names_each_clock(capsys):
    """``train --help`` leads with the recipe of the learned estimator (the snn mode comes after, as
    the older one) and says which time each cap counts."""
    try:
        main(["train", "--help"])
    except SystemExit as exc:
        assert exc.code in (0, None)
    out = " ".join(capsys.readouterr().out.split())
    assert "--recipe" in out and "estimator.learned.checkpoint" in out
    assert out.index("estimator.learned.checkpoint") < out.index("estimator.snn.checkpoint")
    assert "wall-clock minutes" in out and "CPU-minutes of this process" in out
