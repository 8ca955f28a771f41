"""Regression tests of a second fault pass over the new doors (dataset build, campaign, the
gymnasium env and its stable-baselines3 adapter, loop-state files, the shared worker pool and
the command guard). Each test names the case it guards and failed before its fix."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys

import numpy as np
import pytest
import torch

from dvsland.cli.main import main
from dvsland.runs import RunDirError, guarded_run, lock_folder, make_run_dir

CONFIG = "montecarlo_efference"
SETS = ["render.threads=1", "simulation.torch_threads=1", "simulation.t_max_s=2"]
TINY = dict(n_seeds=1, sites="A", shard_size=1, overrides=SETS, quiet=True)


# ------------------------------------------------------------------ dataset build: its folder
def test_dataset_build_empty_out_is_refused_not_built_in_cwd(tmp_path, monkeypatch, capsys):
    """`dataset build --out ""` built the dataset into the current folder (Path("") is ".")."""
    monkeypatch.chdir(tmp_path)
    rc = main(["dataset", "build", CONFIG, "--n-seeds", "1", "--out", "", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "--out" in err and "must not be empty" in err and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("out", ["/proc/x/y", "LONG"])
def test_dataset_build_unwritable_out_is_one_error(tmp_path, capsys, out):
    """--out under /proc or with a 300-byte name: FileNotFoundError / OSError tracebacks."""
    out = str(tmp_path / ("x" * 300)) if out == "LONG" else out
    rc = main(["dataset", "build", CONFIG, "--n-seeds", "1", "--out", out, "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "--out" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def test_dataset_build_into_a_folder_another_build_writes_is_refused(tmp_path):
    """Two `dataset build` into one folder at once both flew and wrote the same shards and manifest."""
    from dvsland.data import build_dataset
    from dvsland.data.build import LOCK_FILE

    out = tmp_path / "ds"
    out.mkdir()
    held = lock_folder(out, LOCK_FILE, "dvsland dataset build")  # as a running build holds it
    try:
        with pytest.raises(RunDirError, match="another dvsland dataset build is running"):
            build_dataset(CONFIG, out=out, **TINY)
    finally:
        held.close()
    assert not (out / "shards").exists()


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from dvsland.data import build_dataset

    out = tmp_path_factory.mktemp("ds") / "tiny"
    assert build_dataset(CONFIG, out=out, **{**TINY, "n_seeds": 2}).status == "complete"
    return out


def _damaged_copy(built, tmp_path, edit):
    out = tmp_path / "ds"
    shutil.copytree(built, out)
    m = json.loads((out / "dataset.json").read_text())
    edit(m)
    (out / "dataset.json").write_text(json.dumps(m))
    return out


@pytest.mark.parametrize("damage", ["no_keys", "foreign_file"])
def test_resume_rebuilds_a_damaged_manifest_entry(built, tmp_path, capsys, damage):
    """A manifest entry without its file and sizes gave `KeyError: 'file'`; an entry naming a file
    outside the folder (../../etc/passwd) was kept in the manifest after the shard was rebuilt."""
    from dvsland.data import EventWindowDataset, build_dataset

    def edit(m):
        e = m["shards"][0]
        m["shards"][0] = ({"id": e["id"], "status": "complete"} if damage == "no_keys"
                          else {**e, "file": "../../../../etc/passwd"})

    out = _damaged_copy(built, tmp_path, edit)
    res = build_dataset(CONFIG, out=out, **{**TINY, "n_seeds": 2})
    assert res.status == "complete" and res.n_shards_built == 1
    m = json.loads((out / "dataset.json").read_text())
    assert [e["file"] for e in m["shards"]] == [f"shards/{e['id']}.h5" for e in m["shards"]]
    assert "rebuilding" in capsys.readouterr().err
    assert len(EventWindowDataset(out, split="all", valid_only=False)) > 0


def test_resume_rewrites_a_damaged_config_yaml(built, tmp_path):
    """A damaged config.yaml stayed damaged after a resume (the manifest holds the config)."""
    from dvsland.data import build_dataset

    out = tmp_path / "ds"
    shutil.copytree(built, out)
    (out / "config.yaml").write_text(":::: not yaml [")
    build_dataset(CONFIG, out=out, **{**TINY, "n_seeds": 2})
    assert "simulation:" in (out / "config.yaml").read_text()


# ------------------------------------------------------------------ campaign flags
def test_campaign_empty_resume_is_refused(capsys):
    """`campaign --resume ""` looked for a campaign in the current folder ('--resume .')."""
    assert main(["campaign", "--resume", ""]) == 2
    err = capsys.readouterr().err
    assert "--resume" in err and "empty" in err, err


def test_campaign_n_seeds_zero_names_the_flag(capsys):
    """`campaign --n-seeds 0`: "n_seeds and workers must be >= 1, got 0 and 1"."""
    with pytest.raises(SystemExit):
        main(["campaign", "paper", "--n-seeds", "0"])
    assert "--n-seeds must be from 1" in capsys.readouterr().err


# ------------------------------------------------------------------ the command guard
def test_command_that_returns_130_leaves_results_json(tmp_path):
    """A command that caught Ctrl-C and returned 130 (campaign, dataset build, simulate) before
    its own report left its run folder without results.json (a campaign interrupted right after
    planning)."""
    from dvsland.config import load_config

    def command():
        make_run_dir(load_config("paper"), tmp_path / "r")
        return 130

    assert guarded_run(command)() == 130
    saved = json.loads((tmp_path / "r" / "results.json").read_text())
    assert saved["status"] == "interrupted"


# ------------------------------------------------------------------ the shared worker pool
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="signal masks of spawned processes")
def test_pool_workers_leave_ctrl_c_to_their_driver():
    """A terminal's Ctrl-C reaches the whole process group: a worker still importing its modules
    printed a KeyboardInterrupt traceback (or an EOFError when the driver stopped mid-start).
    Workers now start with SIGINT blocked and then ignore it; the driver stops them."""
    from dvsland.campaign.executors import map_pool

    got = list(map_pool(signal.getsignal, [(signal.SIGINT,)], workers=1))
    assert got == [(0, signal.SIG_IGN)]
    # the driver's own mask is left as it was
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, set())


def test_pool_stops_and_reaps_its_workers_when_the_consumer_stops():
    """Closing the generator (Ctrl-C in the consumer, a failed write) kills and reaps the workers."""
    import time

    from dvsland.campaign.executors import map_pool

    it = map_pool(time.sleep, [(0.0,), (60.0,)], workers=2)
    assert next(it)[0] == 0
    t0 = time.monotonic()
    it.close()
    assert time.monotonic() - t0 < 10


# ------------------------------------------------------------------ the gymnasium env
ENV = dict(config="paper", sites="D", estimator="oracle", observation="oracle", overrides=["simulation.t_max_s=2"])


@pytest.mark.parametrize("kw, match", [
    (dict(sites=[1]), "sites must be None"),
    (dict(reward={"nosuch": 1.0}), "reward: unknown key"),
    (dict(reward="x"), "reward must be None, a RewardConfig or a mapping"),
    (dict(clip_actions="no"), "clip_actions must be True or False"),
    (dict(overrides={"simulation.t_max_s": 2}), "overrides must be 'section.key=value' strings"),
])
def test_env_constructor_names_the_bad_argument(kw, match):
    """A list of ints as sites (AttributeError from the layout), an unknown reward key or a string
    reward (TypeError from RewardConfig), clip_actions='no' (truthy: actions were clipped), a dict
    of overrides (iterated as --set strings)."""
    from dvsland.envs import LandingVectorEnv

    with pytest.raises(ValueError, match=match):
        LandingVectorEnv(num_envs=1, **{**ENV, **kw})


@pytest.fixture(scope="module")
def env2():
    from dvsland.envs import LandingVectorEnv

    env = LandingVectorEnv(num_envs=2, autoreset_mode="same_step", **ENV)
    yield env
    env.close()


def test_env_reset_options_not_a_dict(env2):
    """reset(options=5): "'int' object is not iterable"."""
    with pytest.raises(ValueError, match="options must be None or a dict"):
        env2.reset(options=5)


def test_sb3_adapter_checks_seed_and_indices(env2):
    """seed('x'): a str + int TypeError; get_attr(indices=[5]) answered for 2 envs; set_attr of
    some envs set the attribute of the whole batch silently."""
    pytest.importorskip("stable_baselines3")
    from dvsland.envs.sb3 import sb3_vec_env

    v = sb3_vec_env(env2)
    with pytest.raises(ValueError, match="seed must be None or an int >= 0"):
        v.seed("x")
    with pytest.raises(ValueError, match=r"indices must be env indices in \[0, 2\)"):
        v.get_attr("num_envs", indices=[5])
    assert v.get_attr("num_envs", indices=[1]) == [2]
    with pytest.raises(ValueError, match="one batch"):
        v.set_attr("foo", 1, indices=[0])
    assert v.seed(3) == [3, 4]


# ------------------------------------------------------------------ loop-state files
@pytest.fixture(scope="module")
def state():
    from dvsland.config import load_config
    from dvsland.sim import init_state
    from dvsland.stages import build_stages

    cfg = load_config("paper", ["simulation.sites=[{name: E, z0_m: 4000.0, v0_mps: -100.0}]",
                                "estimator.name=oracle", "render.threads=1"])
    return init_state(build_stages(cfg))


def test_save_state_to_a_folder_or_a_missing_folder(tmp_path, state):
    """A folder as the path: IsADirectoryError and a '.tmp' file left beside it; a missing
    folder: torch's RuntimeError; /proc: a RuntimeError that named no file."""
    from dvsland.sim.state import save_state

    with pytest.raises(ValueError, match="is a folder"):
        save_state(tmp_path, state)
    with pytest.raises(ValueError, match="does not exist"):
        save_state(tmp_path / "nope" / "s.pt", state)
    assert sorted(p.name for p in tmp_path.parent.iterdir() if p.name.startswith(tmp_path.name)) == [tmp_path.name]
    if os.path.isdir("/proc/self"):
        with pytest.raises(OSError, match="/proc/self/s.pt"):
            save_state("/proc/self/s.pt", state)


def test_load_state_checks_device_and_finite_fields(tmp_path, state):
    """device='gpu0': torch's "Invalid device string"; 'cuda' on a CPU build: an AssertionError;
    a state whose altitude is NaN loaded silently."""
    from dvsland.sim.state import STATE_FORMAT, load_state, save_state

    path = save_state(tmp_path / "s.pt", state)
    with pytest.raises(ValueError, match="device='gpu0'"):
        load_state(path, device="gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device='cuda'"):
            load_state(path, device="cuda")
    blob = torch.load(path, weights_only=False)
    blob["state"] = blob["state"]._replace(z_m=blob["state"].z_m * float("nan"))
    assert blob["format"] == STATE_FORMAT
    torch.save(blob, tmp_path / "nan.pt")
    with pytest.raises(ValueError, match="'z_m' is not a finite"):
        load_state(tmp_path / "nan.pt")
    assert np.isfinite(load_state(path).z_m.numpy()).all()


# ------------------------------------------------------------------ what an interrupt says
def test_campaign_interrupted_before_its_folder_says_nothing_was_written(tmp_path, monkeypatch, capsys):
    """Ctrl-C while the plan was built said "finished shards are kept: resume with --resume
    <folder>" when there was no folder; now it says nothing was written (and, once the folder
    exists, names it)."""
    import dvsland.campaign.runner as runner_mod

    def ctrl_c(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner_mod, "make_plan", ctrl_c)
    assert main(["campaign", "paper", "--n-seeds", "1", "--shard-seeds", "1", "--out", str(tmp_path / "c")]) == 130
    err = capsys.readouterr().err
    assert "before its folder was made; nothing was written" in err and "--resume" not in err, err
    assert not (tmp_path / "c").exists()


def test_dataset_build_interrupted_before_its_dataset_says_nothing_was_written(tmp_path, monkeypatch, capsys):
    import dvsland.campaign

    def ctrl_c(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(dvsland.campaign, "make_plan", ctrl_c)
    rc = main(["dataset", "build", CONFIG, "--n-seeds", "1", "--out", str(tmp_path / "d"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 130 and "nothing was written" in err and "resume" not in err, err


def test_ctrl_c_while_torch_imports_is_held_until_it_is_imported():
    """A signal in the first second of a command could land inside torch's import, where its C++
    calls back into Python: the KeyboardInterrupt aborted the process ("terminate called after
    throwing an instance of 'pybind11::error_already_set'", status -6; seen about once in 70 SIGTERMs
    at 0.2-1.6 s into `dvsland config show paper`). The CLI now holds the interrupt while torch
    imports and delivers it once torch is whole (and importable again)."""
    import subprocess

    code = ("import os, signal, sys, threading\n"
            "from dvsland.cli.main import _TorchImportGuard\n"
            "_TorchImportGuard().install()\n"
            "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
            "threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT)).start()\n"
            "try:\n"
            "    import torch\n"
            "    print('IMPORTED', flush=True)\n"
            "    threading.Event().wait(60)\n"
            "    print('NOT INTERRUPTED')\n"
            "except KeyboardInterrupt:\n"
            "    import torch\n"
            "    print('HELD', float(torch.ones(2).sum()))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=240,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr[-2000:]
    assert out.stdout.split() == ["IMPORTED", "HELD", "2.0"], out.stdout + out.stderr[-2000:]


@pytest.mark.parametrize("entry", [{"id": 0, "status": "complete"}, {"id": 0, "status": "complete", "file": "../x.h5"},
                                   {"id": 0, "status": "complete", "file": "/etc/passwd"}, 7])
def test_readers_refuse_a_damaged_manifest_entry(tmp_path, capsys, entry):
    """`dataset info` (and every reader) names the damaged entry instead of a KeyError traceback or
    reading a file outside the folder; the build reads without the check (it repairs on resume)."""
    import json as _json

    from dvsland.cli.main import main as cli_main
    from dvsland.data.manifest import load_manifest

    d = tmp_path / "ds"
    d.mkdir()
    (d / "dataset.json").write_text(_json.dumps({"format": "dvsland-event-windows", "shards": [entry]}))
    with pytest.raises(ValueError, match=r"shards\[0\]"):
        load_manifest(d)
    assert load_manifest(d, "out", check_entries=False)["shards"] == [entry]
    assert cli_main(["dataset", "info", str(d)]) == 2
    err = capsys.readouterr().err
    assert "shards[0]" in err and "Traceback" not in err


def test_bench_refuses_an_unknown_estimator_before_running(tmp_path, capsys):
    from dvsland.cli.main import main as cli_main
    from dvsland.estimators.registry import check_estimator_names

    check_estimator_names(["dpr[baseline_steps=5]", "fast=dpr", "cmax", "my.mod:Cls"])  # accepted
    assert cli_main(["bench", "throughput", "--quick", "--estimators", "nosuch", "--out", str(tmp_path / "b")]) == 2
    assert "--estimators: unknown estimator(s) ['nosuch']" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()
