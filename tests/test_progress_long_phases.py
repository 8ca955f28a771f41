"""Progress inside the long phases: a one-shard ``dataset build`` or ``campaign`` showed a bar at
``0/1`` for minutes. Now the bar counts the loop steps inside the shards (here and in pool
workers), shows an ETA, ends at 100 % and is silenced by ``quiet``."""

from __future__ import annotations

import re

import pytest

from dvsland.campaign import run_campaign
from dvsland.campaign.progress import StepBar, report
from dvsland.config import load_config
from dvsland.data import build_dataset

SETS = ["render.threads=1", "simulation.torch_threads=1", "simulation.t_max_s=3"]
# a campaign descent that stays in the air for the whole t_max (oracle, 4 km up)
CAMPAIGN = ["estimator.name=oracle", "logging.figures=false", "logging.tensorboard=false", "simulation.t_max_s=3",
            "render.threads=1", "simulation.sites=[{name: E, z0_m: 4000.0, v0_mps: -100.0}]",
            "controller.settings=[{kp: 5e6, n_bin: 5}]"]


def _percents(err: str, desc: str) -> list:
    """The percentages the bar labelled ``desc`` printed, in order."""
    return [int(m) for m in re.findall(rf"{desc}:\s+(\d+)%\|", err)]


@pytest.fixture
def seen(monkeypatch):
    """The (steps, total) of every bar update (tqdm prints at most every 0.1 s: a fast flight
    may print only its ends, so the bar's own counts are checked as well as its text)."""
    got = []
    real = StepBar.refresh

    def spy(self, slot=None):
        real(self, slot)
        got.append((self.bar.n, self.bar.total))

    monkeypatch.setattr(StepBar, "refresh", spy)
    return got


def _check_moves_and_ends(err: str, desc: str, seen: list) -> None:
    pct = _percents(err, desc)
    assert pct and pct[-1] == 100 and pct == sorted(pct), err[-2000:]
    assert re.search(r"<\d\d:\d\d", err), "no ETA"
    assert "step" in err
    inside = {n for n, total in seen if 0 < n < total}
    assert len(inside) >= 3, f"no progress inside the shard: {seen}"  # a shard bar goes 0 -> 1
    assert seen[-1][0] == seen[-1][1]


def test_one_shard_dataset_build_shows_steps_and_ends_full(tmp_path, capsys, seen):
    res = build_dataset("montecarlo_efference", out=tmp_path / "d", n_seeds=1, sites="A", shard_size=1,
                        overrides=SETS, quiet=False)
    assert res.status == "complete" and res.n_shards == 1
    _check_moves_and_ends(capsys.readouterr().err, "dataset", seen)


def test_quiet_dataset_build_prints_no_bar(tmp_path, capsys):
    build_dataset("montecarlo_efference", out=tmp_path / "d", n_seeds=1, sites="A", shard_size=1, overrides=SETS,
                  quiet=True)
    err = capsys.readouterr().err
    assert "%|" not in err and "step" not in err, err


def test_one_shard_campaign_shows_steps_and_ends_full(tmp_path, capsys, seen):
    res = run_campaign(load_config("paper", CAMPAIGN), n_seeds=1, shard_seeds=1, out=tmp_path / "c", quiet=False)
    assert res.status == "complete" and res.n_shards == 1
    _check_moves_and_ends(capsys.readouterr().err, "campaign", seen)


def test_quiet_campaign_prints_no_bar(tmp_path, capsys):
    run_campaign(load_config("paper", CAMPAIGN), n_seeds=1, shard_seeds=1, out=tmp_path / "c", quiet=True)
    assert "%|" not in capsys.readouterr().err


@pytest.mark.slow
def test_pool_workers_report_their_steps(tmp_path, capsys, seen):
    """--workers 2: the workers write their steps into shared slots; the driver's bar moves
    between the shard ends (not only 0, 50 and 100 %)."""
    sets = SETS[:-1] + ["simulation.t_max_s=20"]  # long enough for several of the driver's 0.25 s polls
    res = build_dataset("montecarlo_efference", out=tmp_path / "d", n_seeds=2, sites="A", shard_size=1,
                        overrides=sets, quiet=False, workers=2)
    assert res.status == "complete" and res.n_shards_built == 2
    _check_moves_and_ends(capsys.readouterr().err, "dataset", seen)
    # the workers' steps, not only the shard ends (0, half, all)
    assert {n for n, total in seen} - {0, seen[-1][1] // 2, seen[-1][1]}, seen


def test_step_bar_counts_slots_and_finished_shards(capsys):
    """The bar's arithmetic: steps from the slots, a shard in flight one step short, a finished
    shard as all its steps (its descents ended before t_max), shards done before as the start."""
    from dvsland.campaign import progress

    bar = StepBar([10, 20], "unit", shards_total=3, shards_before=1, steps_before=5)
    progress.install(bar.slots, bar.refresh)  # flown here: one shard at a time
    try:
        report(0, 4)
        assert bar.bar.n == 5 + 4
        bar.shard_done(0)  # ended early at 4 steps: counted whole
        assert bar.bar.n == 5 + 10 and bar.shards_done == 2
        report(1, 25)  # more than its maximum: one short of it until it is finished
        assert bar.bar.n == 5 + 10 + 19
        bar.shard_done(1)
        assert bar.bar.n == bar.bar.total == 35
        report(None, 3)  # no slot: nothing
    finally:
        progress.install(None)
        bar.close()
    pool = StepBar([10, 20, 30], "pool", shards_total=3, shared=True)  # workers fill shared slots
    pool.slots[0], pool.slots[2] = 3, 7  # two shards in flight at once
    pool.refresh()
    assert pool.bar.n == 10
    pool.shard_done(2)
    assert pool.bar.n == 3 + 30
    pool.close()
    assert "100%" in capsys.readouterr().err
