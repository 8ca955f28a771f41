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

RECIPE = ["--model", "cnn", "--epochs", "2", "--batch", "4", "--model-set", "width=4", "--quiet"]
SNN_TINY = ["--sites", "A~1", "--n-seq", "4", "--steps", "6", "--epochs", "1", "--batch", "2", "--warmup-steps", "2",
            "--quiet"]


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def data(tiny_dataset):
    return tiny_dataset


@pytest.fixture(scope="module")
def cnn_ckpt(data, tmp_path_factory):
    """A one-epoch cnn checkpoint of the recipe (resumable: it holds ``last``)."""
    from dvsland.learn import RecipeSettings, train

    out = tmp_path_factory.mktemp("ck") / "cnn.pt"
    train(data, out, RecipeSettings(epochs=1, batch_size=4, model_settings={"width": 4}),
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


# ------------------------------------------------------------------ item 5: --resume
def _nan_best(ck):
    ck["state_dict"]["head.2.bias"].fill_(float("nan"))


def _nan_last(ck):
    next(v for v in ck["last"]["state_dict"].values() if v.is_floating_point()).fill_(float("nan"))


def _nan_optimizer(ck):
    for st in ck["last"]["optimizer"]["state"].values():
        st["exp_avg"].fill_(float("inf"))


@pytest.mark.parametrize("damage, needle", [(_nan_best, "tensor 'head.2.bias'"), (_nan_last, "last"),
                                            (_nan_optimizer, "optimizer")])
def test_resume_from_a_nan_checkpoint_is_refused(cnn_ckpt, tmp_path, capsys, damage, needle):
    """It trained on, exited 0 and wrote a NaN checkpoint."""
    path = _damaged(cnn_ckpt, tmp_path / "nan.pt", damage)
    before = _digest(path)
    assert main(["train", *RECIPE, "--data", str(data_of(cnn_ckpt)), "--out", str(path), "--resume"]) == 2
    err = _one_line_error(capsys)
    assert f"--resume: {path}" in err and needle in err and "NaN or infinite" in err, err
    assert _digest(path) == before and not path.with_name("nan.tb").exists()


def data_of(ckpt):
    return torch.load(ckpt, map_location="cpu", weights_only=True)["data"]["root"]


def test_resume_of_a_missing_or_foreign_file_names_resume(tmp_path, capsys, cnn_ckpt):
    ds = data_of(cnn_ckpt)
    assert main(["train", *RECIPE, "--data", ds, "--out", str(tmp_path / "none.pt"), "--resume"]) == 2
    assert "--resume: file not found" in _one_line_error(capsys)
    (tmp_path / "junk.pt").write_bytes(b"junk" * 40)
    assert main(["train", *RECIPE, "--data", ds, "--out", str(tmp_path / "junk.pt"), "--resume"]) == 2
    assert "--resume: " in _one_line_error(capsys)


# ------------------------------------------------------------------ item 6: --data "", --model ""
@pytest.mark.parametrize("args, needle", [
    (["--data", ""], "--data"), (["--data", " , "], "--data"),
    (["--model", "", "--data", "DS"], "--model"), (["--model", "  ", "--data", "DS"], "--model"),
])
def test_empty_data_or_model_is_refused(tmp_path, capsys, cnn_ckpt, args, needle):
    """--data "": IndexError in learn/resample.py; --model "": trained a cnn without a word."""
    args = [data_of(cnn_ckpt) if a == "DS" else a for a in args]
    out = tmp_path / "x.pt"
    assert main(["train", *args, "--epochs", "1", "--batch", "4", "--quiet", "--out", str(out)]) == 2
    err = _one_line_error(capsys)
    assert err.startswith(f"dvsland: error: {needle}") and "empty" in err, err
    assert not out.exists()


# ------------------------------------------------------------------ item 7: --init
def _not_a_checkpoint(tmp_path, cnn_ckpt):
    p = tmp_path / "notes.txt"
    p.write_text("hello\n" * 50)
    return p


@pytest.mark.parametrize("make, needle", [
    (lambda tmp, ck: tmp / "missing.pt", "file not found"),
    (_not_a_checkpoint, "not a readable dvsland snn checkpoint"),
    (lambda tmp, ck: ck, "not a readable dvsland snn checkpoint"),  # a cnn checkpoint of the recipe
    (lambda tmp, ck: tmp, "is a folder"),
])
def test_snn_init_refuses_bad_files_before_any_data(tmp_path, capsys, no_data, cnn_ckpt, make, needle):
    """FileNotFoundError / UnpicklingError / KeyError: 'encoder' tracebacks, before."""
    init = make(tmp_path, cnn_ckpt)
    out = tmp_path / "out.pt"
    assert main(["train", *SNN_TINY, "--init", str(init), "--out", str(out)]) == 2
    err = _one_line_error(capsys)
    assert err.startswith("dvsland: error: --init") and str(init) in err and needle in err, err
    assert not out.exists()


def test_snn_init_with_nan_d_scale_is_refused(tmp_path, capsys, no_data):
    path = _damaged(DEFAULT_CHECKPOINT, tmp_path / "d.pt", lambda ck: ck["model"].update(d_scale=float("nan")))
    assert main(["train", *SNN_TINY, "--init", str(path), "--out", str(tmp_path / "o.pt")]) == 2
    err = _one_line_error(capsys)
    assert "--init" in err and "d_scale" in err, err


def test_snn_init_starts_from_the_checkpoint(tmp_path, capsys):
    out = tmp_path / "o.pt"
    assert main(["train", *SNN_TINY, "--init", str(DEFAULT_CHECKPOINT), "--out", str(out)]) == 0
    model, enc, meta = load_checkpoint(out)
    ref, ref_enc, _ = load_checkpoint(DEFAULT_CHECKPOINT)
    assert meta["init"] == str(DEFAULT_CHECKPOINT) and model.channels == ref.channels
    assert enc.n_sub == ref_enc.n_sub and model.d_scale == ref.d_scale


def test_recipe_init_is_used_and_checked(tmp_path, capsys, cnn_ckpt):
    """With --model, --init was silently ignored: now the training starts from its weights, and a
    bad file is refused by the same check, naming --init."""
    ds = data_of(cnn_ckpt)
    out = tmp_path / "ft.pt"
    assert main(["train", *RECIPE, "--epochs", "1", "--data", ds, "--init", str(cnn_ckpt), "--out", str(out)]) == 0
    capsys.readouterr()
    ck = torch.load(out, map_location="cpu", weights_only=True)
    assert ck["data"]["init"] == str(cnn_ckpt) and ck["epoch"] == 1
    for init, needle in ((tmp_path / "none.pt", "file not found"), (DEFAULT_CHECKPOINT, "not a dvsland learned"),
                         (_damaged(cnn_ckpt, tmp_path / "n.pt", _nan_best), "NaN or infinite")):
        o = tmp_path / "o.pt"
        assert main(["train", *RECIPE, "--data", ds, "--init", str(init), "--out", str(o)]) == 2
        err = _one_line_error(capsys)
        assert err.startswith(f"dvsland: error: --init: ") and needle in err, err
        assert not o.exists()
    other = ["--model-set", "width=8"]
    assert main(["train", *RECIPE, *other, "--data", ds, "--init", str(cnn_ckpt), "--out", str(tmp_path / "w.pt")]) == 2
    assert "--init" in _one_line_error(capsys)
    assert main(["train", *RECIPE, "--data", ds, "--init", str(cnn_ckpt), "--out", str(out), "--resume"]) == 2
    assert "--init" in _one_line_error(capsys)


def test_recipe_init_onto_other_cells(tmp_path, capsys, cnn_ckpt):
    """--init may start a run on cells of another size (--pool-px: the networks pool over space, so
    the weights fit); the run's checkpoint records its own cells. Other bins are still refused."""
    ds = data_of(cnn_ckpt)
    out = tmp_path / "p4.pt"
    assert main(["train", *RECIPE, "--epochs", "1", "--pool-px", "4", "--data", ds, "--init", str(cnn_ckpt),
                 "--out", str(out)]) == 0
    capsys.readouterr()
    ck = torch.load(out, map_location="cpu", weights_only=True)
    before = torch.load(cnn_ckpt, map_location="cpu", weights_only=True)
    assert ck["input"]["pool_px"] == 4 and before["input"]["pool_px"] == 2 and ck["data"]["init"] == str(cnn_ckpt)
    assert main(["train", *RECIPE, "--n-bins", "2", "--data", ds, "--init", str(cnn_ckpt),
                 "--out", str(tmp_path / "b.pt")]) == 2
    err = _one_line_error(capsys)
    assert "--init" in err and "n_bins" in err, err


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


def test_empty_init_is_refused_on_both_paths(tmp_path, capsys, no_data, cnn_ckpt):
    """--init "" silently trained from scratch (snn) or was ignored (--model)."""
    for args in (SNN_TINY, [*RECIPE, "--data", data_of(cnn_ckpt)]):
        out = tmp_path / "o.pt"
        assert main(["train", *args, "--init", "", "--out", str(out)]) == 2
        err = _one_line_error(capsys)
        assert err.startswith("dvsland: error: --init ''") and "empty" in err, err
        assert not out.exists()


def test_recipe_refusals_come_before_the_run_folder(tmp_path, capsys, cnn_ckpt):
    """A bad --init or --data with the default --out: one error, no run folder under logging.root."""
    logs = tmp_path / "logs"
    nan = _damaged(cnn_ckpt, tmp_path / "n.pt", _nan_best)
    for extra, needle in ((["--data", data_of(cnn_ckpt), "--init", str(nan)], "--init: "),
                          (["--data", str(tmp_path / "none")], f"--data {tmp_path / 'none'}: "),
                          (["--data", data_of(cnn_ckpt), "--resume"], "--resume: ")):
        assert main(["train", *RECIPE, *extra, "--set", f"logging.root={logs}"]) == 2
        assert needle in _one_line_error(capsys)
        assert not logs.exists()


def test_resume_on_the_snn_path_is_refused(tmp_path, capsys, no_data):
    """--resume without --model was silently ignored (a new snn trained into --out)."""
    assert main(["train", *SNN_TINY, "--resume", "--out", str(tmp_path / "o.pt")]) == 2
    assert "--resume" in _one_line_error(capsys) and not (tmp_path / "o.pt").exists()


def test_data_cache_is_read_by_the_same_reader_and_never_clobbers_a_foreign_file(tmp_path, capsys, cnn_ckpt):
    """--data-cache: a corrupt file gave torch's RuntimeError traceback, and any other torch file
    (a checkpoint of the user's) was overwritten by the cache without a word (and unpickled
    with weights_only=False)."""
    mine = tmp_path / "mine.pt"
    mine.write_bytes(cnn_ckpt.read_bytes())
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"junk" * 100)
    for cache, needle in ((mine, "not a dvsland training-data cache"), (junk, "not a readable")):
        before = _digest(cache)
        assert main(["train", *SNN_TINY, "--data-cache", str(cache), "--out", str(tmp_path / "o.pt")]) == 2
        err = _one_line_error(capsys)
        assert err.startswith(f"dvsland: error: --data-cache: {cache}") and needle in err, err
        assert _digest(cache) == before and not (tmp_path / "o.pt").exists()
    cache = tmp_path / "cache.pt"  # a real cache: written, then read back
    assert main(["train", *SNN_TINY, "--data-cache", str(cache), "--out", str(tmp_path / "a.pt")]) == 0
    assert main(["train", *SNN_TINY, "--data-cache", str(cache), "--out", str(tmp_path / "b.pt")]) == 0
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.parametrize("name, needle", [("", "empty"), ("nofolder/c.pt", "does not exist"), ("x" * 300, "")])
def test_data_cache_bad_paths_are_refused_before_any_data(tmp_path, capsys, no_data, name, needle):
    path = name if name == "" else str(tmp_path / name)
    assert main(["train", *SNN_TINY, "--data-cache", path, "--out", str(tmp_path / "o.pt")]) == 2
    err = _one_line_error(capsys)
    assert err.startswith("dvsland: error: --data-cache") and needle in err, err


@pytest.mark.parametrize("field, value", [("best_val", "x"), ("best_val", float("nan")), ("epoch", -1),
                                          ("bad_epochs", 1.5), ("seconds", float("nan")), ("history", None)])
def test_resume_refuses_damaged_counters(cnn_ckpt, tmp_path, capsys, field, value):
    """best_val = 'x' gave a TypeError traceback from the training loop."""
    def damage(ck):
        (ck["last"] if field == "seconds" else ck)[field] = value

    path = _damaged(cnn_ckpt, tmp_path / "c.pt", damage)
    assert main(["train", *RECIPE, "--data", data_of(cnn_ckpt), "--out", str(path), "--resume"]) == 2
    err = _one_line_error(capsys)
    assert f"--resume: {path}" in err and field in err, err


def test_snn_checkpoint_is_replaced_atomically(tmp_path, capsys, monkeypatch):
    """An interrupted write (SIGKILL, a full disk) left a truncated checkpoint in place of the one
    --overwrite was replacing; now the old file stays until the new one is complete."""
    import dvsland.estimators.snn as snn

    out = tmp_path / "mine.pt"
    out.write_bytes(DEFAULT_CHECKPOINT.read_bytes())

    def half_write(path, *a, **k):
        open(path, "wb").write(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(snn, "save_checkpoint", half_write)
    try:
        assert main(["train", *SNN_TINY, "--out", str(out), "--overwrite"]) != 0
    except OSError:
        pass
    capsys.readouterr()
    assert out.read_bytes() == DEFAULT_CHECKPOINT.read_bytes()
