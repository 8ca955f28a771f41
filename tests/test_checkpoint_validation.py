"""One checkpoint validation (:mod:`dvsland.estimators.state_dict_check`) behind every loader and
behind ``dvsland train --resume`` / ``--init`` (issue 37, items 5, 6, 7, 16): a damaged, foreign or
diverged checkpoint is one error naming the parameter, the file and what is wrong, before any
training, and nothing is written."""

from __future__ import annotations

import hashlib

import pytest
import torch

from dvsland.cli import cmd_train
from dvsland.cli.main import main
from dvsland.estimators.snn import DEFAULT_CHECKPOINT, load_checkpoint

SETS = ["render.threads=1", "simulation.torch_threads=1", "simulation.t_max_s=1.0"]
RECIPE = ["--model", "cnn", "--epochs", "2", "--batch", "4", "--model-set", "width=4", "--quiet"]
SNN_TINY = ["--sites", "A~1", "--n-seq", "4", "--steps", "6", "--epochs", "1", "--batch", "2", "--warmup-steps", "2",
            "--quiet"]


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from dvsland.data import build_dataset

    out = tmp_path_factory.mktemp("ds") / "tiny5"
    build_dataset("montecarlo_efference", out=out, n_seeds=5, sites="A", shard_size=5, overrides=SETS, quiet=True)
    return out


@pytest.fixture(scope="module")
def cnn_ckpt(data, tmp_path_factory):
    """A one-epoch cnn checkpoint of the recipe (resumable: it holds ``last``)."""
    from dvsland.learn import RecipeSettings, train

    out = tmp_path_factory.mktemp("ck") / "cnn.pt"
    train(data, out, RecipeSettings(epochs=1, batch_size=4, val_max_samples=100, model_settings={"width": 4}),
          progress=False, log=lambda *a: None)
    return out


@pytest.fixture
def no_data(monkeypatch):
    """Fail if any snn training data would be made (the refusals come first)."""
    def boom(*a, **k):
        raise AssertionError("data were made before the checks")

    monkeypatch.setattr(cmd_train, "_sequences", boom)


def _damaged(src, dst, damage):
    ck = torch.load(src, map_location="cpu", weights_only=True)
    damage(ck)
    torch.save(ck, dst)
    return dst


def _one_line_error(capsys):
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


# ------------------------------------------------------------------ item 16: the description's numbers
@pytest.mark.parametrize("value", [float("nan"), float("inf"), 0.0, -0.1])
def test_snn_d_scale_must_be_a_positive_number(tmp_path, value):
    """d_scale = NaN loaded: every estimate missing, exit 0."""
    path = _damaged(DEFAULT_CHECKPOINT, tmp_path / "d.pt", lambda ck: ck["model"].update(d_scale=value))
    with pytest.raises(ValueError) as info:
        load_checkpoint(path)
    msg = str(info.value)
    assert msg.startswith(f"estimator.snn.checkpoint: {path}") and "d_scale" in msg, msg


def test_snn_d_scale_nan_fails_the_command(tmp_path, capsys):
    path = _damaged(DEFAULT_CHECKPOINT, tmp_path / "d.pt", lambda ck: ck["model"].update(d_scale=float("nan")))
    run = tmp_path / "run"
    assert main(["simulate", "--sites", "D", "--estimator", "snn", "--quiet", "--out", str(run),
                 "--set", f"estimator.snn.checkpoint={path}", "--set", "simulation.t_max_s=1"]) == 2
    err = _one_line_error(capsys)
    assert "estimator.snn.checkpoint" in err and "d_scale" in err


def test_snn_encoder_numbers_must_be_finite(tmp_path):
    path = _damaged(DEFAULT_CHECKPOINT, tmp_path / "e.pt", lambda ck: ck["encoder"].update(r_max_px=float("nan")))
    with pytest.raises(ValueError, match=r"estimator.snn.checkpoint: .*r_max_px"):
        load_checkpoint(path)


def test_learned_description_numbers_must_be_finite(tmp_path, cnn_ckpt):
    from dvsland.estimators.learned import load_checkpoint as load_learned

    path = _damaged(cnn_ckpt, tmp_path / "c.pt", lambda ck: ck["input"].update(coord_scale_px=float("nan")))
    with pytest.raises(ValueError, match=r"estimator.learned.checkpoint: .*coord_scale_px"):
        load_learned(path)
