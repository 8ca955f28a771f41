"""Regression tests of faults found by feeding bad input to every entry point: each value here was
accepted and then crashed, hung, or lost data. Each test names the case it guards."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import torch

import dvsland
from dvsland.cli.main import main
from dvsland.config import Config, ConfigError, ControllerSetting, load_config, validate_config
from dvsland.events import EventDataError, EventEmulator, Events, load_events, save_events
from dvsland.estimators import get_estimator
from dvsland.report import read_results_json
from dvsland.runs import RunDirError, make_run_dir

QUIET = ["logging.figures=false", "logging.quiet=true"]


def _cfg(*overrides, root=None) -> Config:
    extra = [f"logging.root={root}"] if root is not None else []
    return load_config(None, [*QUIET, *extra, *overrides])


def _events(n, W=64, H=64, B=1, seed=0, t0=0, t1=100_000) -> Events:
    """n random events of B cameras W x H, t in [t0, t1), sorted."""
    g = torch.Generator().manual_seed(seed)
    return Events(b=torch.randint(0, B, (n,), generator=g), x=torch.randint(0, W, (n,), generator=g),
                  y=torch.randint(0, H, (n,), generator=g), t=torch.randint(t0, t1, (n,), generator=g),
                  p=(torch.randint(0, 2, (n,), generator=g) * 2 - 1).to(torch.int8), sort=True)


# ------------------------------------------------------------------ 1. cmax canvas bound
@pytest.mark.parametrize("d_min", [-100.0, -10.0])
def test_cmax_extreme_d_min_has_bounded_canvas(d_min):
    """cmax d_min=-100 raised OverflowError, d_min=-10 tried to allocate ~60 GB (canvas padding
    exp(|d| window / 2) unbounded)."""
    est = get_estimator("cmax", 1, (32, 32), d_min=d_min, window_ms=1000.0, min_events=5, n_grid=5,
                        n_refine=0, max_events=200)
    assert est.pad_px <= 32
    for k in range(6):  # the window is half full after 5 updates: the search runs
        d = est.update(_events(150, 32, 32, seed=k, t0=k * 100_000, t1=(k + 1) * 100_000), (k + 1) * 100_000)
    assert d.shape == (1,) and not torch.isinf(d).any()


# ------------------------------------------------------------------ 2. narrow field of view
def test_stamp_feature_larger_than_patch_ladder():
    """camera.fov_deg=1 or 2 gave IndexError in terrain/stamp.py: a crater wider than the largest
    patch on the ladder (1.25^63 texels) on a very fine grid."""
    from dvsland.terrain.grid import Grid
    from dvsland.terrain.stamp import stamp

    grid = Grid(0.0, 0.0, 0.0, 16, 16, 1e-3)  # 1 mm texels
    out = torch.zeros(16 * 16, dtype=torch.float64)
    one = torch.ones(1, dtype=torch.float64)
    stamp([out], grid, 0 * one, 0 * one, 5000.0 * one, one, one, 1.5,
          lambda r, d, f: (torch.ones_like(r),))
    assert out.sum() == 16 * 16  # the whole grid lies inside the crater: every texel once


@pytest.mark.slow
@pytest.mark.parametrize("fov", [1.0, 2.0])
def test_render_narrow_fov(fov):
    from dvsland.render import get_renderer

    cfg = _cfg(f"camera.fov_deg={fov}")
    r = get_renderer("fast", ["A"], cfg.camera, cfg.render, "cpu")
    f = r.render(torch.tensor([1000.0, 50.0]), torch.tensor([0, 0]))
    assert f.shape == (2, 128, 128) and torch.isfinite(f).all()


# ------------------------------------------------------------------ 3. memory bounds
def test_emulator_caps_events_per_step():
    """emulator.threshold=1e-6 allocated 714 MB per step; 1e-9 asked for terabytes."""
    frames0 = torch.full((2, 16, 16), 0.1)
    frames1 = torch.full((2, 16, 16), 0.5)
    emu = EventEmulator(threshold=1e-9, refractory_us=0.0, max_events_per_step=10_000)
    emu.reset(frames0, 0)
    with pytest.raises(ValueError, match="max_events_per_step"):
        emu.step(frames1, 100_000)
    # below the cap nothing changes
    emu = EventEmulator(threshold=0.1, max_events_per_step=10_000)
    emu.reset(frames0, 0)
    assert len(emu.step(frames1, 100_000)) == 2 * 16 * 16 * 16  # log(5)/0.1 = 16.09 crossings


def test_event_cap_grows_with_the_batch():
    """A large batch's step may emit max_events_per_descent x B events: the 20 M cap of one step
    stopped an 8,192-descent fleet near the ground (20.2 M events) on a card with 139 GiB free."""
    from dvsland.config.validate import check_event_rates, event_cap_of, memory_parts

    frames0, frames1 = torch.full((2, 16, 16), 0.1), torch.full((2, 16, 16), 0.5)  # 8,192 events per step
    for per_descent, ok in ((0, False), (4_000, False), (4_096, True)):
        emu = EventEmulator(threshold=0.1, max_events_per_step=1_000, max_events_per_descent=per_descent)
        emu.reset(frames0, 0)
        if ok:
            assert len(emu.step(frames1, 100_000)) == 2 * 16 * 16 * 16
        else:
            with pytest.raises(ValueError, match=f"max_events_per_descent = {per_descent} x 2 descents"):
                emu.step(frames1, 100_000)
    cfg = _cfg()
    assert cfg.emulator.max_events_per_descent == 10_000 and EventEmulator.from_config(cfg.emulator) \
        .params.max_events_per_descent == 10_000
    assert event_cap_of(cfg, 576) == 20_000_000 and event_cap_of(cfg, 8192) == 81_920_000
    assert memory_parts(cfg, batch_size=8192)["events"] == 81_920_000 * 48
    check_event_rates(_cfg("emulator.background_rate_hz=4"), batch_size=8192)  # 55 M events: under the cap
    with pytest.raises(ConfigError, match="max_events_per_descent = 0 x B"):
        check_event_rates(_cfg("emulator.background_rate_hz=4", "emulator.max_events_per_descent=0"), batch_size=8192)


def test_config_caps_flow_into_emulator():
    cfg = _cfg("emulator.max_events_per_step=123")
    assert EventEmulator.from_config(cfg.emulator).max_events_per_step == 123


def test_memory_estimate_refuses_huge_camera(tmp_path):
    """A 4096x4096 camera asked for 7.9 GB at set-up before anything checked."""
    cfg = _cfg("camera.width_px=4096", "camera.height_px=4096", "simulation.max_memory_gb=4", root=tmp_path / "logs")
    with pytest.raises(ConfigError, match="max_memory_gb"):
        dvsland.simulate(cfg, estimator="dpr", sites="D")
    assert not (tmp_path / "logs").exists()  # refused before the run folder and the renderer
    from dvsland.config.validate import check_memory

    check_memory(_cfg("simulation.max_memory_gb=4"))  # the paper experiment fits


# ------------------------------------------------------------------ 4. one validation path
@pytest.mark.parametrize("field, value, name", [
    ("simulation.sites[0].z0_m", float("nan"), "z0_m"),
    ("controller.thrust_max_n", float("nan"), "thrust_max_n"),
    ("controller.settings[0].kp", float("nan"), "kp"),
    ("camera.frame_rate_hz", 0.0, "frame_rate_hz"),
    ("simulation.n_seeds", 0, "n_seeds"),
    ("simulation.t_max_s", float("nan"), "t_max_s"),
    ("simulation.t_max_s", float("inf"), "t_max_s"),
])
def test_simulate_validates_config_objects(tmp_path, field, value, name):
    """dvsland.simulate(Config) skipped validation: NaN z0_m flew 'complete' with NaN traces."""
    cfg = Config()
    cfg.logging.root = str(tmp_path / "logs")
    obj = cfg
    parts = field.replace("[0]", ".0").split(".")
    for p in parts[:-1]:
        obj = obj[int(p)] if p.isdigit() else getattr(obj, p)
    setattr(obj, parts[-1], value)
    with pytest.raises(ConfigError, match=name):
        dvsland.simulate(cfg, estimator="oracle", quiet=True)
    assert not (tmp_path / "logs").exists()  # refused before any output


@pytest.mark.parametrize("overrides, name", [
    (["estimator.dpr.nms_px=4"], "nms_px"),
    (["estimator.cmax.d_min=0", "estimator.cmax.d_max=0"], "d_min"),
    (["simulation.device=mps"], "simulation.device"),
    (["estimator.cmax.refine_points=4"], "refine_points"),
])
def test_config_show_rejects_what_simulate_rejects(capsys, overrides, name):
    """config show accepted nms_px=4, d_min=d_max=0 and device=mps, which simulate rejected."""
    argv = ["config", "show"]
    for o in overrides:
        argv += ["--set", o]
    assert main(argv) == 2
    assert name in capsys.readouterr().err
    cfg = Config()  # the same from Python
    for o in overrides:
        key, raw = o.split("=")
        sec, *rest = key.split(".")
        obj = getattr(cfg, sec)
        for p in rest[:-1]:
            obj = getattr(obj, p)
        setattr(obj, rest[-1], raw if not raw.lstrip("-").isdigit() else int(raw))
    with pytest.raises(ConfigError, match=name):
        validate_config(cfg)


# ------------------------------------------------------------------ 5. t_max_s below one step
def test_t_max_shorter_than_one_step():
    """t_max_s=1e-12 ended 'complete' with 0 steps and outcomes 'running'."""
    with pytest.raises(ConfigError, match=r"simulation.t_max_s.*one control step"):
        _cfg("simulation.t_max_s=1e-12")
    assert _cfg("simulation.t_max_s=0.1").simulation.t_max_s == 0.1  # exactly one step is fine


# ------------------------------------------------------------------ 6. duplicate labels
@pytest.mark.parametrize("labels", [("x", "x"), ("a/b", "a_b"), ("", "Kp5e6-n5")])
def test_duplicate_run_labels_rejected(labels):
    cfg = Config()
    cfg.controller.settings = [ControllerSetting(kp=5e6, n_bin=5, label=labels[0]),
                               ControllerSetting(kp=4e6, n_bin=10, label=labels[1])]
    with pytest.raises(ConfigError, match="label"):
        validate_config(cfg)


# ------------------------------------------------------------------ 7. interruption
def test_sigterm_is_handled_like_ctrl_c(tmp_path):
    """SIGTERM left results.json at 'running' with no traces."""
    def on_step(lp, out):
        if lp.step_index == 3:
            os.kill(os.getpid(), signal.SIGTERM)

    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        dvsland.simulate(_cfg(), estimator="oracle", sites="D", out=out, on_step=on_step, quiet=True)
    res = read_results_json(out / "results.json")
    assert res["status"] == "interrupted" and "SIGTERM" in res["error"]
    assert np.load(out / "traces.npz")["z_m"].shape[0] >= 3
    assert any((out / "tb").rglob("events.out.tfevents*"))
    assert signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, signal.default_int_handler) or callable(
        signal.getsignal(signal.SIGTERM))


def test_interrupt_during_setup_leaves_results(tmp_path, monkeypatch):
    """Ctrl-C during set-up left only config.yaml."""
    import dvsland.sim.api as api

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(api, "build_stages", boom)
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        dvsland.simulate(_cfg(), estimator="oracle", sites="D", out=out, quiet=True)
    res = read_results_json(out / "results.json")
    assert res["status"] == "interrupted" and res["phase"] == "setup"
    assert (out / "config.yaml").is_file()


def test_sigterm_handler_restored(tmp_path):
    before = signal.getsignal(signal.SIGTERM)
    dvsland.simulate(_cfg("simulation.t_max_s=0.5"), estimator="oracle", sites="D", out=tmp_path / "r", quiet=True)
    assert signal.getsignal(signal.SIGTERM) is before


# ------------------------------------------------------------------ 8. output folder guard
def test_out_dir_guard(tmp_path):
    cfg = _cfg(root=tmp_path / "logs")
    with pytest.raises(RunDirError, match="must not be empty"):
        make_run_dir(cfg, "")
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(RunDirError, match="not a folder"):
        make_run_dir(cfg, f)
    with pytest.raises(RunDirError, match="cannot write"):
        make_run_dir(cfg, "/proc/dvsland-test/x")
    d = make_run_dir(cfg, tmp_path / "run")
    with pytest.raises(RunDirError, match="already holds a run"):
        make_run_dir(cfg, d)
    assert make_run_dir(cfg, d, overwrite=True) == d
    empty = tmp_path / "empty"
    empty.mkdir()
    assert make_run_dir(cfg, empty) == empty  # an empty folder is fine


@pytest.mark.parametrize("name", ["../../x", "a/b", "..", ""])
def test_run_name_cannot_escape_root(tmp_path, name):
    with pytest.raises(ConfigError, match="name"):
        _cfg(f"name={name}", root=tmp_path / "logs")
    cfg = _cfg(root=tmp_path / "logs")
    cfg.name = name
    with pytest.raises(ValueError, match="name"):
        make_run_dir(cfg)
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("out", ["", "FILE", "/proc/dvsland-test/x"])
def test_cli_out_guard(tmp_path, capsys, out):
    if out == "FILE":
        out = str(tmp_path / "f")
        Path(out).write_text("x")
    rc = main(["simulate", "--estimator", "oracle", "--sites", "D", "--out", out, "--quiet",
               "--set", "logging.root=" + str(tmp_path / "logs")])
    assert rc == 2
    assert "Traceback" not in capsys.readouterr().err


def test_cli_refuses_reused_out(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["simulate", "--estimator", "oracle", "--sites", "D", "--out", str(out), "--quiet",
            "--set", "simulation.t_max_s=0.5", "--set", "logging.figures=false"]
    assert main(args) == 0
    n_tb = len(list((out / "tb").rglob("*")))
    assert main(args) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert len(list((out / "tb").rglob("*"))) == n_tb  # nothing mixed in


# ------------------------------------------------------------------ 9. --set list index
def test_set_list_index_out_of_range():
    with pytest.raises(ConfigError, match=r"simulation.sites has 9 items"):
        _cfg("simulation.sites.9=A")
    with pytest.raises(ConfigError, match=r"simulation.sites has 9 items"):
        _cfg("simulation.sites.12.z0_m=5")
    assert _cfg("simulation.sites.8.z0_m=3000").simulation.sites[8].z0_m == 3000


# ------------------------------------------------------------------ 10. events on the way in
def _npz(path, **fields):
    base = dict(b=np.zeros(3, np.int64), x=np.array([1, 2, 3], np.int16), y=np.array([1, 2, 3], np.int16),
                t=np.array([1, 2, 3], np.int64), p=np.array([1, -1, 1], np.int8),
                meta_sensor_size=np.array([8, 8, 2]), meta_batch_size=np.int64(1))
    base.update(fields)
    with open(path, "wb") as fh:
        np.savez(fh, **base)
    return path


@pytest.mark.parametrize("fields, match", [
    (dict(t=np.array([1.0, np.nan, 3.0])), "'t' contains nan"),
    (dict(p=np.array([1, 5, 1], np.int8)), r"polarity p \(field 'p'\) must be in \{-1, 1\}"),
    (dict(x=np.array([1, 2, 9], np.int16)), r"'x' must be in \[0, 8\)"),
    (dict(t=np.array([3, 2, 1], np.int64)), "sorted"),
    (dict(t=np.array([1.5, 2, 3])), "non-integer"),
    (dict(b=np.array([0, 0, 1])), r"'b' must be in \[0, 1\)"),
])
def test_event_file_values_checked(tmp_path, fields, match):
    with pytest.raises(EventDataError, match=match):
        load_events(_npz(tmp_path / "e.npz", **fields))


def test_truncated_npz(tmp_path):
    path = save_events(tmp_path / "e.npz", _events(500))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(EventDataError, match=f"truncated or corrupt event file {path}"):
        load_events(path)


def test_h5_values_checked(tmp_path):
    h5py = pytest.importorskip("h5py")
    path = save_events(tmp_path / "e.h5", _events(50), sensor_size=(64, 64), batch_size=1)
    with h5py.File(path, "r+") as h5:
        h5["events/p"][5] = 3
    with pytest.raises(EventDataError, match="'p'"):
        load_events(path)
    path = save_events(tmp_path / "f.h5", _events(50), sensor_size=(64, 64), batch_size=1)
    with h5py.File(path, "r+") as h5:
        h5["events/y"][5] = 100
    with pytest.raises(EventDataError, match="'y'"):
        load_events(path)


def test_is_sorted_no_overflow():
    big = 2 ** 62
    z = torch.zeros(2, dtype=torch.int64)
    ev = Events(z, z, z, torch.tensor([-big, big]), torch.ones(2, dtype=torch.int8))
    assert ev.is_sorted()
    ev = Events(z, z, z, torch.tensor([big, -big]), torch.ones(2, dtype=torch.int8))
    assert not ev.is_sorted()


def test_snn_rejects_x_beyond_sensor():
    est = get_estimator("snn", 1, (128, 128))
    bad = Events(torch.zeros(3, dtype=torch.int64), torch.tensor([0, 128, 5000]), torch.zeros(3, dtype=torch.int64),
                 torch.tensor([1, 2, 3]), torch.ones(3, dtype=torch.int8))
    with pytest.raises(EventDataError, match=r"'x' must be in \[0, 128\)"):
        est.update(bad, 100_000)


def test_cmax_same_answer_on_unsorted_events():
    kw = dict(window_ms=200.0, min_events=5, n_grid=7, n_refine=1, max_events=100)  # thinned, dithered
    a, b = get_estimator("cmax", 2, (32, 32), **kw), get_estimator("cmax", 2, (32, 32), **kw)
    for k in range(3):
        ev = _events(400, 32, 32, B=2, seed=k, t0=k * 100_000, t1=(k + 1) * 100_000)
        perm = torch.randperm(len(ev), generator=torch.Generator().manual_seed(k))
        da = a.update(ev, (k + 1) * 100_000)
        db = b.update(ev[perm], (k + 1) * 100_000)
    torch.testing.assert_close(da, db, equal_nan=True)


# ------------------------------------------------------------------ JSON, estimator names and parameters
def test_evaluation_json_is_strict(tmp_path):
    from types import SimpleNamespace

    from dvsland.evaluate.report import write_outputs

    desc = SimpleNamespace(t_s=np.zeros(2), altitude_m=np.ones((1, 2)), divergence=np.zeros((1, 2)), sites=["A"])
    res = SimpleNamespace(summary={"estimators": {"x": {"median": float("nan"), "rmse": float("inf")}}},
                          descents=desc, scored=np.zeros((1, 2), bool), n_events=np.zeros((1, 2), np.int64),
                          d_hat={"x": np.full((1, 2), np.nan)})
    import dvsland.evaluate.report as rep

    orig = rep.format_table
    rep.format_table = lambda s: "table"
    try:
        paths = write_outputs(res, tmp_path, figures=False)
    finally:
        rep.format_table = orig

    def no_const(c):
        raise AssertionError(f"invalid JSON constant {c}")

    data = json.loads(paths["json"].read_text(), parse_constant=no_const)
    assert data["estimators"]["x"]["median"] is None


def test_empty_estimator_flag_is_an_error(tmp_path, capsys):
    """--estimator '' silently ran dpr."""
    assert main(["simulate", "--estimator", "", "--quiet", "--out", str(tmp_path / "r")]) == 2
    assert "unknown estimator ''" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_unknown_estimator_parameters_rejected():
    with pytest.raises(ValueError, match=r"bogus.*d_max"):
        get_estimator("cmax", 1, (32, 32), bogus=1)
    with pytest.raises(ValueError, match="warmup_steps"):
        get_estimator("snn", 1, (128, 128), bogus=1)
    with pytest.raises(ValueError, match="nan"):
        get_estimator("cmax", 1, (32, 32), d_min=float("nan"))


def test_evaluate_rejects_unknown_override_key():
    from dvsland.evaluate import evaluate

    cfg = _cfg("simulation.sites.0.z0_m=60")
    frames = lambda alt, idx: torch.ones(len(alt), 128, 128)  # noqa: E731
    with pytest.raises(ValueError, match="bogus"):
        evaluate(cfg, ["cmax[bogus=1]"], ["A"], max_steps=3, frame_source=frames, progress=False)


def test_corrupt_snn_checkpoint(tmp_path):
    bad = tmp_path / "ck.pt"
    bad.write_bytes(b"PK\x03\x04 this is not a checkpoint" * 10)
    with pytest.raises(ValueError, match="not a readable dvsland snn checkpoint"):
        get_estimator("snn", 1, (128, 128), checkpoint=str(bad))
    torch.save({"format": 1, "hello": 2}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a readable dvsland snn checkpoint"):
        get_estimator("snn", 1, (128, 128), checkpoint=str(tmp_path / "other.pt"))


def test_snn_nan_after_empty_windows():
    est = get_estimator("snn", 1, (128, 128), warmup_steps=0)
    for k in range(12):
        d = est.update(Events.empty(), (k + 1) * 100_000)
    assert torch.isnan(d).all()


@pytest.mark.slow  # ~30 s on a loaded 2-core machine; test_sigterm_is_handled_like_ctrl_c covers it in-process
def test_sigterm_from_outside_cli(tmp_path):
    """`kill <pid>` of a running `dvsland simulate`: exit code 130, results.json 'interrupted',
    traces and TensorBoard files written."""
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "dvsland.cli.main", "simulate", "realistic", "--estimator", "dpr",
                             "--sites", "D", "--out", str(out), "--quiet", "--set", "logging.figures=false",
                             "--set", "controller.settings=[{kp: 5e6, n_bin: 5}]"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if (out / "results.json").is_file() and read_results_json(out / "results.json")["status"] == "running":
            break
        time.sleep(0.02)
    time.sleep(0.5)  # inside the loop
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    res = read_results_json(out / "results.json")
    assert res["status"] == "interrupted" and "SIGTERM" in res["error"]
    assert (out / "traces.npz").is_file()
    assert any((out / "tb").rglob("events.out.tfevents*"))
