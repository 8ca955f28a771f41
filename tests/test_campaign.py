"""Campaigns: planning, atomic shard files, resume after an interruption equals an uninterrupted
run, the process pool and Ray executors, the report files and the CLI."""

from __future__ import annotations

import json

import pytest

import dvsland.campaign.runner as runner_mod
from dvsland.campaign import make_plan, parse_sweep, ray_available, run_campaign, velocity_at_altitude
from dvsland.cli.main import main
from dvsland.config import load_config

BASE = ["estimator.name=oracle", "estimator.oracle.noise_rel=0.1", "logging.figures=false",
        "simulation.sites=[{name: A, z0_m: 10000.0, v0_mps: -200.0}, {name: E, z0_m: 4000.0, v0_mps: -100.0}]",
        "dispersion.enabled=true", "dispersion.z0_scale.kind=uniform", "dispersion.z0_scale.low=0.8",
        "dispersion.z0_scale.high=1.2", "controller.thrust_max_n=1e5"]


def _cfg(extra=()):
    return load_config("realistic", BASE + list(extra))


def _key(res):
    return json.dumps(res.runs, sort_keys=True), json.dumps(res.groups, sort_keys=True)


class TestPlan:
    def test_grid_and_shards(self):
        plan = make_plan(_cfg(), ["controller.c2=0.4,0.5", "estimator.oracle.noise_rel=0,0.1"], n_seeds=5,
                         shard_seeds=2)
        assert len(plan.shards) == 4 * 3 and [s.n_seeds for s in plan.shards[:3]] == [2, 2, 1]
        assert len({s.id for s in plan.shards}) == 12
        assert plan.shards[0].sweep == {"controller.c2": "0.4", "estimator.oracle.noise_rel": "0"}

    def test_seed_offset_starts_the_seeds(self):
        """--set simulation.seed_offset=K flies seeds K .. K + n_seeds - 1 (it used to be ignored)."""
        cfg = _cfg()
        cfg.simulation.seed_offset = 30
        plan = make_plan(cfg, n_seeds=5, shard_seeds=2)
        assert [(s.seed_offset, s.n_seeds) for s in plan.shards] == [(30, 2), (32, 2), (34, 1)]
        assert plan.shard_config(plan.shards[1]).simulation.seed_offset == 32

    @pytest.mark.parametrize("sweep,match", [("controller.c2", "key=v1"), ("controller.c2=", "at least one"),
                                             ("controller.c2=2.0", "controller.c2"),
                                             ("simulation.n_seeds=1,2", "--n-seeds"),
                                             ("estimator.name=oracle,nosuch", "nosuch")])
    def test_bad_sweeps(self, sweep, match):
        with pytest.raises(ValueError, match=match):
            make_plan(_cfg(), [sweep], n_seeds=2)

    def test_parse_and_bad_args(self, tmp_path):
        assert parse_sweep("a.b=1, 2") == ("a.b", ["1", "2"])
        with pytest.raises(ValueError, match="executor"):
            run_campaign(_cfg(), executor="slurm", out=tmp_path / "x")
        with pytest.raises(ValueError, match="campaign.json"):
            run_campaign(resume=tmp_path)


def test_velocity_at_altitude():
    import numpy as np

    z = np.array([[100.0, 100.0], [60.0, 70.0], [40.0, 60.0]])
    v = np.array([[-10.0, -5.0], [-8.0, -4.0], [-6.0, -3.0]])
    out = velocity_at_altitude(z, v, 50.0)
    assert out[0] == pytest.approx(-7.0) and np.isnan(out[1])


def test_interrupted_campaign_resumes_to_the_same_result(tmp_path, monkeypatch):
    full = run_campaign(_cfg(), n_seeds=4, shard_seeds=1, out=tmp_path / "full", quiet=True)
    assert full.status == "complete" and full.n_shards == 4 and len(full.runs) == 2 * 2 * 4
    assert (tmp_path / "full" / "config.yaml").is_file()
    # outcome times spread across the seeds once a dispersion is on
    assert len({r["t_end_s"] for r in full.runs if r["site"] == "E"}) > 4

    # kill half-way: the third shard raises (as Ctrl-C would)
    real = runner_mod.run_local
    calls = {"n": 0}

    def flaky(config, shards, workers=1, keep=None, **kw):
        for res in real(config, shards, workers, keep, **kw):
            calls["n"] += 1
            if calls["n"] == 3:
                raise KeyboardInterrupt
            yield res

    monkeypatch.setattr(runner_mod, "run_local", flaky)
    with pytest.raises(KeyboardInterrupt):
        run_campaign(_cfg(), n_seeds=4, shard_seeds=1, out=tmp_path / "cut", quiet=True)
    monkeypatch.setattr(runner_mod, "run_local", real)
    cut = tmp_path / "cut"
    assert (cut / "config.yaml").is_file() and (cut / "campaign.json").is_file()
    assert len(list((cut / "shards").glob("*.json"))) == 2  # the finished shards are kept
    partial = json.loads((cut / "results.json").read_text())
    assert partial["status"] == "interrupted" and len(partial["missing_shards"]) == 2

    resumed = run_campaign(resume=cut, quiet=True)
    assert resumed.status == "complete" and resumed.n_shards_run == 2
    assert _key(resumed) == _key(full)
    again = run_campaign(resume=cut, quiet=True)  # nothing left to run
    assert again.n_shards_run == 0 and _key(again) == _key(full)


def test_max_shards_then_resume_and_report_files(tmp_path):
    res = run_campaign(_cfg(["logging.figures=true"]), sweeps=["controller.c2=0.4,0.5"], n_seeds=2, shard_seeds=1,
                       out=tmp_path / "c", quiet=True, max_shards=1)
    assert res.status == "incomplete" and res.n_shards == 4
    res = run_campaign(resume=tmp_path / "c", quiet=True)
    assert res.status == "complete" and len(res.groups) == 2 * 2 * 2  # sites x settings x c2
    assert res.group_by == ["site", "label", "estimator", "sweep.controller.c2"]
    d = tmp_path / "c"
    for name in ("results.json", "runs.csv", "groups.csv", "table.txt", "table.md", "figures/campaign.png"):
        assert (d / name).is_file(), name
    assert list((d / "tb").rglob("events.out.tfevents.*"))
    g = res.groups[0]
    assert g["n"] == 2 and 0 <= g["success_lo"] <= g["success_rate"] <= g["success_hi"] <= 1
    header = (d / "groups.csv").read_text().splitlines()[0]
    assert "success_lo" in header and "v50_mps_median" in header


@pytest.mark.slow
def test_process_pool_equals_sequential(tmp_path):
    seq = run_campaign(_cfg(), n_seeds=2, shard_seeds=1, out=tmp_path / "seq", quiet=True)
    pool = run_campaign(_cfg(), n_seeds=2, shard_seeds=1, out=tmp_path / "pool", quiet=True, workers=2)
    assert _key(seq) == _key(pool)


@pytest.mark.slow  # 15 s: starts a local Ray instance (the optional executor)
@pytest.mark.skipif(not ray_available(), reason="Ray is not installed (pip install 'dvsland[ray]'); "
                                                "the Ray executor is not tested")
def test_ray_executor_on_a_local_instance(tmp_path, monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    seq = run_campaign(_cfg(), n_seeds=2, shard_seeds=1, out=tmp_path / "seq", quiet=True)
    ray_res = run_campaign(_cfg(), n_seeds=2, shard_seeds=1, out=tmp_path / "ray", quiet=True, executor="ray",
                           workers=2)
    assert ray_res.status == "complete" and _key(ray_res) == _key(seq)


def test_cli_campaign(tmp_path, capsys):
    args = ["campaign", "realistic", "--n-seeds", "2", "--shard-seeds", "2", "--out", str(tmp_path / "cli"),
            "--sweep", "controller.thrust_max_n=8e4,1e5", "--quiet"] + sum((["--set", s] for s in BASE[:-1]), [])
    assert main(args) == 0
    out = json.loads((tmp_path / "cli" / "results.json").read_text())
    assert out["status"] == "complete" and len(out["runs"]) == 2 * 2 * 2 * 2
    assert capsys.readouterr().out == ""  # --quiet
    assert main(["campaign", "--resume", str(tmp_path / "cli"), "--quiet"]) == 0
    assert main(["campaign", "realistic", "--sweep", "controller.c2", "--quiet", "--out", str(tmp_path / "bad")]) == 2


def test_keep_runs_and_a_stale_shard_folder(tmp_path):
    res = run_campaign(_cfg(), n_seeds=2, shard_seeds=1, out=tmp_path / "k", quiet=True, keep_runs=True, max_shards=1)
    shards = tmp_path / "k" / "shards"
    first, second = sorted(p.name for p in shards.glob("*.json"))[0][:-5], "g000-s00001"
    assert (shards / first / "traces.npz").is_file()
    (shards / second).mkdir()
    (shards / second / "results.json").write_text("{}")  # a killed earlier try of the missing shard
    res = run_campaign(resume=tmp_path / "k", quiet=True, keep_runs=True)
    assert res.status == "complete" and (shards / second / "traces.npz").is_file()
