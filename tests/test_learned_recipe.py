"""The training recipe (dvsland.learn) and `dvsland train --model` on a tiny dataset (one site, five
seeds = five terrain variants, so train, val and test all have samples; one second of flight)."""

from __future__ import annotations

import pytest
import torch

from dvsland.data import build_dataset, gather_batch, load_windows
from dvsland.estimators import get_estimator
from dvsland.estimators.learned import read_checkpoint
from dvsland.estimators.learned.estimator import ordered_ring
from dvsland.learn import RecipeSettings, score, train

SETS = ["render.threads=1", "simulation.torch_threads=1", "simulation.t_max_s=1.0"]


@pytest.fixture(scope="module")
def data(tiny_dataset):
    return tiny_dataset


FAST = dict(epochs=2, batch_size=4, val_max_samples=100, model_settings={"width": 4})


def test_windows_hold_every_event_of_the_split(data):
    from dvsland.data import EventWindowDataset

    w = load_windows(data, "val")
    ds = EventWindowDataset(data, representation="events", split="val")
    assert w.n_samples == len(ds) and int(w.offset[-1]) == int(sum(len(ds[i][0]) for i in range(len(ds))))
    b, x, y, frac, p, n = gather_batch(w, torch.tensor([1, 0]))
    assert n.tolist() == [len(ds[1][0]), len(ds[0][0])] and b.tolist() == sorted(b.tolist())
    assert ((frac >= 0) & (frac <= 1)).all() and set(p.unique().tolist()) <= {-1, 1}


def test_train_writes_a_checkpoint_with_history_provenance_and_calibration(data, tmp_path):
    ck = train(data, tmp_path / "m.pt", RecipeSettings(**FAST), progress=False, tb_dir=tmp_path / "tb",
               log=lambda *a: None)
    assert ck["epoch"] == 2 and len(ck["history"]) == 2
    assert ck["data"]["config_hash"] and ck["data"]["sensor_size"] == [128, 128] and ck["data"]["samples"]["train"] > 0
    for split in ("val", "test"):
        a = ck["final"][split]["all"]
        assert a["n"] > 0 and 0 <= a["within_1sigma"] <= a["within_2sigma"] <= 1 and a["median_rel_error"] >= 0
    assert "A" in ck["final"]["test"] and "craters" in ck["history"][0]["val"]
    assert any((tmp_path / "tb").iterdir())
    est = get_estimator("learned", 2, (128, 128), checkpoint=str(tmp_path / "m.pt"))
    assert est.meta["model"]["name"] == "cnn"


def test_training_is_seeded_and_resume_continues_exactly(data, tmp_path):
    quiet = dict(progress=False, log=lambda *a: None)
    full = train(data, tmp_path / "full.pt", RecipeSettings(**FAST), **quiet)
    train(data, tmp_path / "half.pt", RecipeSettings(**{**FAST, "epochs": 2, "max_minutes": 1e-6}), **quiet)
    half = read_checkpoint(tmp_path / "half.pt")
    assert half["epoch"] == 1 and len(half["history"]) == 1  # stopped after one batch of the first epoch
    part = train(data, tmp_path / "part.pt", RecipeSettings(**{**FAST, "epochs": 1}), **quiet)
    assert part["history"][0]["val_loss"] == pytest.approx(full["history"][0]["val_loss"], rel=1e-6)
    resumed = train(data, tmp_path / "part.pt", RecipeSettings(**FAST), resume=True, **quiet)
    assert resumed["epoch"] == 2
    assert resumed["history"][1]["val_loss"] == pytest.approx(full["history"][1]["val_loss"], rel=1e-4)
    with pytest.raises(ValueError, match="--resume.*other settings"):
        train(data, tmp_path / "part.pt", RecipeSettings(**{**FAST, "lr": 1e-4}), resume=True, **quiet)


def test_ema_ships_the_weight_average_and_resume_continues_it(data, tmp_path):
    quiet = dict(progress=False, log=lambda *a: None)
    ema = {**FAST, "ema": 0.9}
    full = train(data, tmp_path / "ema.pt", RecipeSettings(**ema), **quiet)
    avg = full["last"]["ema"]
    assert avg["n_averaged"] > 2 and full["train"]["ema"] == 0.9
    best = 0 if full["history"][0]["val"]["all"]["median_rel_error"] <= full["history"][1]["val"]["all"][
        "median_rel_error"] else 1
    if best == 1:  # the best epoch is the last: its average is the shipped state
        assert all(torch.equal(full["state_dict"][k], avg["state_dict"][k]) for k in avg["state_dict"])
    # the average is not the last weights: validated and shipped apart from them
    assert any(not torch.equal(full["last"]["state_dict"][k], avg["state_dict"][k]) for k in avg["state_dict"])
    plain = train(data, tmp_path / "plain.pt", RecipeSettings(**FAST), **quiet)
    assert all(torch.equal(plain["last"]["state_dict"][k], full["last"]["state_dict"][k])
               for k in avg["state_dict"])  # the average does not touch the training itself
    assert plain["history"][1]["val_loss"] != pytest.approx(full["history"][1]["val_loss"], rel=1e-9)
    train(data, tmp_path / "part.pt", RecipeSettings(**{**ema, "epochs": 1}), **quiet)
    resumed = train(data, tmp_path / "part.pt", RecipeSettings(**ema), resume=True, **quiet)
    assert resumed["last"]["ema"]["n_averaged"] == avg["n_averaged"]
    assert all(torch.allclose(resumed["last"]["ema"]["state_dict"][k], avg["state_dict"][k], rtol=1e-4, atol=1e-6)
               for k in avg["state_dict"])
    with pytest.raises(ValueError, match=r"ema must be in \[0.0, 0.99999\]"):
        RecipeSettings(ema=1.0).check()


def test_bad_settings_name_the_setting(data, tmp_path):
    with pytest.raises(ValueError, match="batch_size"):
        RecipeSettings(batch_size=0).check()
    with pytest.raises(ValueError, match="lr"):
        RecipeSettings(lr=0).check()
    with pytest.raises(ValueError, match="root="):
        train(tmp_path, tmp_path / "x.pt", RecipeSettings(**FAST), progress=False)


def test_score_groups_by_site_type_and_counts_calibration(data):
    w = load_windows(data, "val")
    d = w.d_true.abs().log()
    perfect = score(d, torch.zeros_like(d), w)
    assert perfect["all"]["median_rel_error"] == pytest.approx(0.0, abs=1e-6)
    assert perfect["all"]["within_1sigma"] == 1.0
    off = score(d + 3.0, torch.zeros_like(d), w)  # 3 sigma off: outside 1 and 2 sigma
    assert off["all"]["within_2sigma"] == 0.0 and off["craters"]["n"] == w.n_samples


def test_cli_train_model(data, tmp_path, capsys):
    from dvsland.cli.main import main

    out = tmp_path / "cli.pt"
    rc = main(["train", "montecarlo_efference", "--model", "cnn", "--data", str(data), "--epochs", "1",
               "--batch", "4", "--model-set", "width=4", "--out", str(out), "--quiet"])
    assert rc == 0 and out.is_file() and str(out) in capsys.readouterr().out
    assert main(["train", "--model", "cnn", "--data", str(data), "--model-set", "width",
                 "--out", str(tmp_path / "y.pt")]) != 0
    assert "--model-set 'width': expected KEY=VALUE" in capsys.readouterr().err


def test_several_datasets_are_one_split(data):
    from dvsland.data import concat_windows

    w = load_windows(data, "train")
    two = concat_windows([w, w])
    assert two.n_samples == 2 * w.n_samples and int(two.offset[-1]) == 2 * int(w.offset[-1])
    b, *_rest, n = gather_batch(two, torch.tensor([w.n_samples]))  # the second copy's first sample
    assert int(n[0]) == int(w.offset[1] - w.offset[0]) and torch.equal(_rest[0], w.x[: int(n[0])])
    assert len(set(two.descent.tolist())) == 2 * len(set(w.descent.tolist()))
    with pytest.raises(ValueError, match="data: the datasets are of different sensors"):
        concat_windows([w, w._replace(sensor_size=(346, 260))])


def test_time_scale_augmentation_moves_the_target_with_the_events(data):
    from dvsland.estimators.learned import InputSpec
    from dvsland.learn.batches import make_batch

    w = load_windows(data, "train")
    idx = torch.nonzero(w.next >= 0).squeeze(1)[:64]
    spec = InputSpec((128, 128), 4, 2)
    plain = make_batch(w, idx, spec)
    g = torch.Generator().manual_seed(3)
    aug = make_batch(w, idx, spec, g, max_drop=0.0, time_scale=(0.5, 0.4))
    f = torch.exp(aug.target - plain.target)
    assert ((f > 0.39) & (f < 2.01)).all() and (f > 1.01).any() and (f < 0.99).any()
    # a stretched window (f < 1, no merge) holds fewer events than the whole one
    assert (aug.log_count[f < 0.9] <= plain.log_count[f < 0.9] + 1e-6).all()
    assert (aug.log_count[f > 1.1] >= plain.log_count[f > 1.1] - 1e-6).all()


def test_estimator_ring_sees_what_training_sees(data, tmp_path):
    """With an input of K = 3 control steps, the estimator's ring of the last windows gives the
    same input, hence the same estimate, as the recipe's batch of that sample."""
    from dvsland.estimators.learned import InputSpec, build_model, coord_channels, save_checkpoint
    from dvsland.learn.batches import make_batch

    torch.manual_seed(0)
    net, cls = build_model("cnn", {"n_bins": 3, "width": 4})
    spec = InputSpec((128, 128), 3, 2, 64.0, 3)
    save_checkpoint(tmp_path / "k3.pt", {"model": {"name": "cnn", "class": cls, "settings": net.settings()},
                                         "input": {**spec._asdict(), "sensor_size": [128, 128]},
                                         "state_dict": net.state_dict()})
    w = load_windows(data, "val")
    i = int(torch.nonzero((w.prev >= 0) & (w.prev[w.prev.clamp_min(0)] >= 0)).squeeze(1)[5])
    chain = [int(w.prev[w.prev[i]]), int(w.prev[i]), i]
    est = get_estimator("learned", 1, (128, 128), checkpoint=str(tmp_path / "k3.pt"), min_events=1)
    est.update(_window(w, i, 1), 100_000)  # something in the ring, then a reset empties it
    est.reset()
    assert not est.state.ring.any()
    for k, r in enumerate(chain, start=1):
        d = est.update(_window(w, r, k), 100_000 * k)
    with torch.no_grad():
        bt = make_batch(w, torch.tensor([i]), spec)
        mu, _ = net.eval()(bt.vox, coord_channels(spec, (63.5, 63.5)), bt.log_count)
    assert torch.equal(ordered_ring(est.state, est.spec), bt.vox)
    assert float(d[0]) == pytest.approx(-float(torch.exp(mu[0])), rel=1e-5)


def _window(w, r: int, k: int):
    """Sample r's events as the k-th 0.1 s window of one descent (Events, B = 1)."""
    from dvsland.events import Events

    a, b = int(w.offset[r]), int(w.offset[r + 1])
    t = (100_000 * (k - 1) + (w.frac[a:b].double() * 100_000).round().long()).clamp_min(100_000 * (k - 1) + 1)
    order = torch.argsort(t, stable=True)
    return Events(b=torch.zeros(b - a, dtype=torch.long), x=w.x[a:b].long()[order], y=w.y[a:b].long()[order],
                  t=t[order], p=w.p[a:b][order])


@pytest.mark.slow
def test_mixed_cameras_train_on_one_canvas_and_resume_on_other_data_fine_tunes(data, tmp_path):
    """A dataset of another camera (96 x 80, principal point off the centre) joins the DVS128 one on
    the first folder's canvas; --resume of a checkpoint on other data fine-tunes it (fresh epochs
    and optimizer, old history kept, the old data recorded)."""
    from dvsland.learn.recipe import input_spec, load_split

    other = tmp_path / "oc"
    build_dataset("montecarlo_efference", out=other, n_seeds=2, sites="A", shard_size=2, quiet=True,
                  overrides=SETS + ["camera.width_px=96", "camera.height_px=80",
                                    "camera.principal_point_px=[40.5, 45.5]", "simulation.seed_offset=1"])
    both = f"{data},{other}"
    spec = input_spec(both, RecipeSettings(**FAST))
    assert spec.sensor_size == (128, 128)
    w, w0 = load_split(both, "train", spec), load_split(data, "train")
    assert w.n_samples > w0.n_samples and w.sensor_size == (128, 128)
    assert int(w.x.min()) >= 0 and int(w.x.max()) < 128 and int(w.y.max()) < 128
    assert torch.equal(w.x[:len(w0.x)], w0.x)  # the reference camera's events as they were
    quiet = dict(progress=False, log=lambda *a: None)
    base = train(data, tmp_path / "m.pt", RecipeSettings(**FAST), **quiet)
    ft = train(both, tmp_path / "m.pt", RecipeSettings(**{**FAST, "epochs": 1, "lr": 1e-3}), resume=True, **quiet)
    assert ft["epoch"] == 1 and len(ft["history"]) == 3
    assert ft["data"]["finetuned_from"]["config_hash"] == base["data"]["config_hash"]
    assert "+" in ft["data"]["config_hash"]
