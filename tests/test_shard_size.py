"""A campaign's shard size chosen from the memory estimate (dvsland campaign --shard-seeds 0)."""

from __future__ import annotations

import math

import pytest

from dvsland.campaign.plan import auto_shard_seeds, shard_bytes
from dvsland.config import load_config


def _cfg(gb):
    return load_config("montecarlo_efference", ["estimator.name=cmax", f"simulation.max_memory_gb={gb}"])


@pytest.mark.parametrize("gb,workers", [(4.0, 1), (12.0, 1), (12.0, 2), (1e4, 2)])
def test_auto_shard_fits_the_budget_and_is_the_largest_that_does(gb, workers):
    cfg, n = _cfg(gb), 50
    s = auto_shard_seeds(cfg, n, workers)
    assert 1 <= s <= math.ceil(n / workers)
    budget = gb * 2 ** 30 / workers
    if s > 1:
        assert shard_bytes(cfg, s) <= budget
    if s < math.ceil(n / workers):
        assert shard_bytes(cfg, s + 1) > budget


def test_auto_shard_gives_every_worker_a_shard_when_memory_is_plenty():
    assert auto_shard_seeds(_cfg(1e4), 50, 2) == 25
    assert auto_shard_seeds(_cfg(1e4), 7, 1) == 7


def test_auto_shard_shrinks_with_the_budget():
    assert auto_shard_seeds(_cfg(3.0), 50, 1) < auto_shard_seeds(_cfg(12.0), 50, 1) <= auto_shard_seeds(_cfg(48.0), 50, 1)


def test_auto_shard_bad_input():
    with pytest.raises(ValueError, match="n_seeds and workers"):
        auto_shard_seeds(_cfg(4.0), 0, 1)
    with pytest.raises(ValueError, match="n_seeds and workers"):
        auto_shard_seeds(_cfg(4.0), 5, 0)


def test_campaign_without_shard_seeds_plans_the_estimated_size(tmp_path):
    from dvsland.campaign import run_campaign
    from dvsland.campaign.plan import CampaignPlan

    cfg = _cfg(1e4)
    res = run_campaign(cfg, n_seeds=3, shard_seeds=0, out=tmp_path / "c", quiet=True, max_shards=0)
    plan = CampaignPlan.load(tmp_path / "c")
    assert plan.shard_seeds == 3 == auto_shard_seeds(cfg, 3, 1) and len(plan.shards) == 1
    assert res.status != "complete"  # no shard was flown (max_shards=0)


def test_auto_shard_default_budget_is_what_is_free_now(monkeypatch):
    """max_memory_gb = 0: the budget follows the memory available now, not the machine's total
    (other jobs on a shared machine); an explicit max_memory_gb is taken as given."""
    import dvsland.campaign.plan as plan_mod

    cfg = load_config("montecarlo_efference", ["estimator.name=cmax"])
    monkeypatch.setattr(plan_mod, "available_memory_bytes", lambda: 1e15)
    roomy = auto_shard_seeds(cfg, 50, 2)
    monkeypatch.setattr(plan_mod, "available_memory_bytes", lambda: 5.0 * 2 ** 30)
    tight = auto_shard_seeds(cfg, 50, 2)
    assert tight < roomy and shard_bytes(cfg, tight) <= 0.8 * 5.0 * 2 ** 30 / 2 < shard_bytes(cfg, tight + 1)
    assert auto_shard_seeds(_cfg(1e4), 50, 2) == 25  # explicit: not capped by what is free


def test_available_memory_is_positive():
    from dvsland.campaign.plan import available_memory_bytes

    assert available_memory_bytes() > 0
