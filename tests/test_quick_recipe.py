"""The ``quick`` recipe (``dvsland train --recipe quick``): it resolves to the settings it names,
options given beside it win, its CPU-time cap and per-batch schedule work, and a tiny run of it (one
site, one second of flight, a CPU cap of about a second) writes a checkpoint the learned estimator
flies."""

from __future__ import annotations

import math

import pytest
import torch

from dvsland.cli.main import build_parser, main
from dvsland.learn import RECIPES, RecipeSettings, recipe
from dvsland.learn.recipe import Clock, _lr


@pytest.fixture(scope="module")
def data(tiny_dataset):
    return tiny_dataset


def test_quick_resolves_to_its_settings():
    s = recipe("quick")
    assert (s.model, s.model_settings, s.n_bins, s.n_windows, s.pool_px) == ("cnn", {"width": 16}, 8, 8, 4)
    assert s.schedule == "budget" and s.max_cpu_minutes == 9.0 and s.echo == 2 and s.max_minutes is None
    assert s.batch_size == 64 and s.lr == 3e-3 and s.patience >= s.epochs  # the budget, not patience, ends it
    assert recipe("quick", lr=1e-3).lr == 1e-3 and RECIPES["quick"]["lr"] == 3e-3  # the table is not changed
    with pytest.raises(ValueError, match="--recipe 'quik'.*quick"):
        recipe("quik")


def _cli_settings(argv):
    from dvsland.cli.train_recipe import recipe_settings
    from dvsland.config import load_config

    args = build_parser().parse_args(["train", *argv])
    return recipe_settings(args, load_config("montecarlo_efference"))


def test_cli_recipe_quick_is_the_named_recipe_and_options_win():
    assert _cli_settings(["--recipe", "quick", "--data", "x"]) == recipe("quick")
    s = _cli_settings(["--recipe", "quick", "--data", "x", "--lr", "1e-3", "--max-cpu-minutes", "5",
                       "--n-windows", "4", "--model-set", "width=8"])
    assert (s.lr, s.max_cpu_minutes, s.n_windows, s.model_settings) == (1e-3, 5.0, 4, {"width": 8})
    plain = _cli_settings(["--data", "x"])  # no recipe: the defaults as before
    assert (plain.n_bins, plain.pool_px, plain.n_windows, plain.schedule, plain.patience) == (4, 2, 1, "cosine", 6)
    assert plain.max_cpu_minutes is None and plain.ema == 0.0
    assert _cli_settings(["--data", "x", "--ema", "0.999"]).ema == 0.999


def test_unknown_recipe_is_refused_naming_the_option(tmp_path, capsys, data):
    assert main(["train", "--recipe", "quik", "--data", str(data), "--out", str(tmp_path / "x.pt")]) == 2
    assert "--recipe 'quik'" in capsys.readouterr().err and not (tmp_path / "x.pt").exists()


def test_recipe_options_outside_the_recipe_are_refused(tmp_path, capsys):
    assert main(["train", "--max-cpu-minutes", "1", "--out", str(tmp_path / "x.pt")]) == 2
    assert "--max-cpu-minutes is an option of the recipe" in capsys.readouterr().err
    assert main(["train", "--ema", "0.99", "--out", str(tmp_path / "x.pt")]) == 2
    assert "--ema is an option of the recipe" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # argparse's range check, before anything runs
        main(["train", "--model", "cnn", "--data", "x", "--ema", "1.5", "--out", str(tmp_path / "x.pt")])
    assert exc.value.code == 2 and not (tmp_path / "x.pt").exists()
    assert "--ema must be from 0.0 to 0.99999, got '1.5'" in capsys.readouterr().err


def test_budget_schedule_warms_up_and_decays_and_cosine_is_per_epoch():
    s = RecipeSettings(schedule="budget", lr=1e-2)
    lrs = [_lr(s, 0, p) for p in (0.0, 0.03, 0.5, 1.0)]
    assert lrs[0] == pytest.approx(1e-3) and lrs[1] == pytest.approx(1e-2, rel=0.01)
    assert lrs[2] == pytest.approx(1e-2 * (0.05 + 0.95 * 0.5)) and lrs[3] == pytest.approx(5e-4)
    c = RecipeSettings(lr=1e-2, epochs=4)
    assert _lr(c, 2, 0.99) == _lr(c, 2) == pytest.approx(1e-2 * (0.05 + 0.95 * 0.5))


def test_clock_counts_cpu_time_against_its_cap():
    clock = Clock(RecipeSettings(max_cpu_minutes=0.5 / 60), cpu0=0.25)
    assert 0.5 <= clock.share() < 1 and not clock.up()
    t = torch.randn(200, 200)
    while not clock.up():
        t = t @ t.T / 200
    assert clock.cpu() >= 0.5 and clock.share() >= 1
    assert Clock(RecipeSettings()).share() == 0.0


def test_quick_smoke_run_writes_a_checkpoint_the_estimator_flies(data, tmp_path, capsys):
    from dvsland.estimators import get_estimator
    from dvsland.estimators.learned import read_checkpoint

    out = tmp_path / "quick.pt"
    assert main(["train", "montecarlo_efference", "--recipe", "quick", "--data", str(data), "--max-cpu-minutes",
                 "0.02", "--batch", "4", "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    ck = read_checkpoint(out)
    assert ck["train"]["schedule"] == "budget" and ck["train"]["max_cpu_minutes"] == 0.02
    assert ck["input"]["n_windows"] == 8 and ck["input"]["pool_px"] == 4 and ck["epoch"] >= 1
    # a run stopped before its epochs ran out was stopped by the cap (0.02 CPU-minutes) and recorded at least
    # the cap. (A run that ran every epoch may still end just past the cap: its last epoch started before it,
    # as on a fast CPU where the 30 epochs take about 1.2 s.)
    assert ck["epoch"] == ck["train"]["epochs"] or ck["final"]["train_cpu_seconds"] >= 1.2
    assert math.isfinite(ck["final"]["val"]["all"]["median_rel_error"])
    est = get_estimator("learned", 2, (128, 128), checkpoint=str(out))
    assert est.meta["model"]["settings"]["width"] == 16


def test_echoes_mirror_the_grid_as_the_events_would_be(data):
    """An echo's grid (:func:`_mirrored`) is the grid of the same events mirrored or transposed."""
    from dvsland.data import gather_batch
    from dvsland.estimators.learned.inputs import voxel_grid
    from dvsland.learn.recipe import _mirrored, input_spec, load_split

    spec = input_spec(data, recipe("quick"))
    w = load_split(data, "train", spec)
    b, x, y, frac, p, _ = gather_batch(w, torch.arange(4))
    vox = voxel_grid(b, x, y, frac, p, 4, spec)
    W, H = spec.sensor_size
    assert vox.abs().sum() > 0
    assert torch.equal(voxel_grid(b, W - 1 - x, y, frac, p, 4, spec), vox.flip(3))
    assert torch.equal(voxel_grid(b, x, H - 1 - y, frac, p, 4, spec), vox.flip(2))
    assert torch.equal(voxel_grid(b, y, x, frac, p, 4, spec), vox.transpose(2, 3))
    out = _mirrored(vox, spec, torch.Generator().manual_seed(1))
    views = lambda v: [t for u in (v, v.transpose(1, 2)) for t in (u, u.flip(2), u.flip(1), u.flip(1).flip(2))]
    assert all(any(torch.equal(o, t) for t in views(v)) for o, v in zip(out, vox))
    odd = spec._replace(pool_px=3)  # cells that do not tile the sensor symmetrically: no mirror
    assert _mirrored(vox, odd, torch.Generator()) is vox
