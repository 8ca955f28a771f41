"""Pieces that exist once: the closed-form descent, the paper's initial conditions, the renderer
registry, the loop gain."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from dvsland.config import PAPER_INITIAL_CONDITIONS, SITE_NAMES, load_config
from dvsland.dynamics import closed_form_descent, closed_form_state, closed_form_time_to_altitude, loop_gain


def test_closed_form_descent_frame_clock():
    t, z, v = closed_form_descent(10000.0, -200.0, 0.5, from_m=1000.0, to_m=800.0, dt_s=0.1)
    assert t[0] == pytest.approx(closed_form_time_to_altitude(1000.0, 10000.0, -200.0, 0.5))
    assert np.allclose(np.diff(t), 0.1)
    assert z[0] == pytest.approx(1000.0) and z[-1] <= 800.0 < z[-2]
    zz, vv = closed_form_state(t, 10000.0, -200.0, 0.5)
    assert np.array_equal(z, zz) and np.array_equal(v, vv)


def test_closed_form_descent_uniform_samples():
    t, z, _ = closed_form_descent(4000.0, -100.0, 0.5, to_m=50.0, n=5)
    assert len(t) == 5 and t[0] == 0.0 and z[0] == pytest.approx(4000.0) and z[-1] == pytest.approx(50.0)
    assert t[-1] == pytest.approx(71.06, abs=0.01)  # D-I reach 50 m at ~71.1 s


@pytest.mark.parametrize("kw,needle", [
    (dict(to_m=900.0, from_m=800.0, dt_s=0.1), "from_m > to_m"),
    (dict(to_m=50.0, from_m=20000.0, n=3), "z0_m >= from_m"),
    (dict(to_m=50.0), "exactly one of dt_s"),
    (dict(to_m=50.0, dt_s=0.1, n=3), "exactly one of dt_s"),
    (dict(to_m=50.0, dt_s=0.0), "dt_s must be > 0"),
    (dict(to_m=50.0, n=1), "n must be >= 2"),
])
def test_closed_form_descent_errors(kw, needle):
    with pytest.raises(ValueError, match=needle):
        closed_form_descent(10000.0, -200.0, 0.5, **kw)


def test_paper_initial_conditions_written_once():
    cfg = load_config("paper")
    assert {s.name: (s.z0_m, s.v0_mps) for s in cfg.simulation.sites} == PAPER_INITIAL_CONDITIONS
    assert set(PAPER_INITIAL_CONDITIONS) == set(SITE_NAMES)
    one = load_config("paper", ["simulation.sites=[{name: D, z0_m: 3000, v0_mps: -80}]"])
    assert one.initial_conditions("D") == (3000.0, -80.0)
    assert one.initial_conditions("A") == (10000.0, -200.0)  # not configured: the paper's
    assert one.initial_conditions("E~2") == (4000.0, -100.0)  # a variant takes its site's
    with pytest.raises(ValueError, match="unknown site 'Z'"):
        one.initial_conditions("Z")


def test_loop_gain_in_results_is_the_dynamics_one(tmp_path):
    from dvsland.sim import simulate

    # Eq. 2 (tau_p) reports the tau-space lambda of dynamics.loop_gain; configs/paper.yaml flies div_p,
    # whose gain (Kp / (m z) at the end) comes from dvsland.control.gain
    r = simulate("paper_eq2", estimator="oracle", sites="D", quiet=True, out=tmp_path / "g",
                 overrides=["logging.tensorboard=false", "logging.figures=false", "simulation.t_max_s=0.2"])
    run = r.runs[0]
    assert run["loop_gain_kind"] == "tau"
    assert run["loop_gain"] == loop_gain(run["kp"], run["z0_m"], run["v0_mps"], 10000.0)


@pytest.mark.parametrize("argv", [
    ["simulate", "--renderer", "raytracer", "--sites", "D", "--quiet"],
    ["render", "--renderer", "raytracer", "--sites", "D", "--quiet"],
    ["config", "show", "--set", "render.renderer=raytracer"],
])
def test_renderer_names_come_from_the_registry(argv, capsys, tmp_path):
    from dvsland.cli.main import main

    if argv[0] != "config":
        argv = argv + ["--out", str(tmp_path / "r")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "raytracer" in err and "'fast', 'pyrender'" in err


@pytest.mark.parametrize("module", ["dvsland.estimators._counts"])
def test_dead_modules_are_gone(module):
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(module)
    import dvsland.evaluate.trajectory as traj

    assert not hasattr(traj, "truth_tensors")
