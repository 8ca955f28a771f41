"""The loop as a typed state and one step: LoopState, loop_step, clone/save/load, resume, bad input."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch

from dvsland.config import load_config
from dvsland.pytree import tree_clone, tree_equal
from dvsland.sim import fly_steps, LoopState, StepOutput, clone_state, init_state, load_state, loop_step, reset_where, save_state
from dvsland.sim.termination import OUTCOMES
from dvsland.stages import build_stages

ROOT = Path(__file__).resolve().parents[1]


def _stages(preset="paper", est="oracle", sites="D", extra=()):
    over = [f"estimator.name={est}", "render.threads=1", *extra]
    if "montecarlo" in preset:
        over.append("simulation.n_seeds=1")
    return build_stages(load_config(preset, over), sites)


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    return torch.equal(a.nan_to_num(-123.0), b.nan_to_num(-123.0))


# ------------------------------------------------------------------ smoke and shapes
def test_step_output_shapes_and_types():
    st = _stages("paper", "dpr", "A,D")
    s0 = init_state(st)
    assert isinstance(s0, LoopState) and s0.step == 0 and s0.batch_size == 4
    s1, out = loop_step(st, s0)
    assert isinstance(out, StepOutput) and out.step == 0 and s1.step == 1
    assert out.frames.shape == (4, 128, 128) and out.frames.dtype == torch.float32
    assert out.events is None  # the first frame only starts the emulator
    for name in ("z_m", "v_mps", "m_kg", "d_true", "d_est", "d_conf", "d_filtered", "thrust_n"):
        t = getattr(out, name)
        assert t.shape == (4,) and t.dtype == torch.float64, name
    s2, out = loop_step(st, s1)
    assert out.events is not None and len(out.events) > 0
    assert torch.all(s2.z_m < s0.z_m)


def test_oracle_needs_no_frames():
    st = _stages("paper", "oracle", "D")
    s, out = loop_step(st, init_state(st))
    assert out.frames is None and out.events is None and st.events is None
    assert torch.isfinite(out.d_est).all()


# ------------------------------------------------------------------ clone, save, load, resume
@pytest.mark.parametrize("preset,est,sites", [("paper", "dpr", "C,D"), ("paper", "cmax", "D"),
                                              ("montecarlo_efference", "cmax", "H"), ("paper", "snn", "F")])
def test_resume_mid_descent_is_bit_identical(tmp_path, preset, est, sites):
    st = _stages(preset, est, sites)
    s, _ = fly_steps(st, init_state(st), 8)
    save_state(tmp_path / "k8.pt", s)
    kept = clone_state(s)
    end, ref = fly_steps(st, s, 7)
    for resumed in (load_state(tmp_path / "k8.pt"), kept, kept):  # a clone can be stepped from twice
        e2, outs = fly_steps(st, resumed, 7)
        assert all(_same(a.d_est, b.d_est) and _same(a.thrust_n, b.thrust_n) for a, b in zip(ref, outs))
        assert torch.equal(e2.z_m, end.z_m) and torch.equal(e2.v_mps, end.v_mps) and torch.equal(e2.m_kg, end.m_kg)


def test_a_state_can_be_stepped_from_twice():
    """The step is pure: the state it starts from is unchanged and gives the same step again."""
    st = _stages("paper", "dpr", "D")
    s0, _ = fly_steps(st, init_state(st), 3)
    copy0 = tree_clone(s0)
    s1, o1 = loop_step(st, s0)
    assert tree_equal(s0, copy0)
    s1b, o1b = loop_step(st, s0)
    assert tree_equal(s1, s1b) and _same(o1.d_est, o1b.d_est) and torch.equal(o1.thrust_n, o1b.thrust_n)


def test_load_state_rejects_other_files(tmp_path):
    bad = tmp_path / "x.pt"
    bad.write_bytes(b"not a state")
    with pytest.raises(ValueError, match=r"state file .*x\.pt.*not a readable loop state"):
        load_state(bad)
    torch.save({"format": 99}, bad)
    with pytest.raises(ValueError, match="not a dvsland loop state"):
        load_state(bad)


# ------------------------------------------------------------------ start anywhere, thrust given
def test_start_from_any_state_per_element():
    st = _stages("paper", "oracle", "A,D")
    s = init_state(st, z_m=torch.tensor([3000.0, 2000.0, 1500.0, 800.0]), v_mps=-50.0, m_kg=9000.0)
    assert s.z_m.tolist() == [3000.0, 2000.0, 1500.0, 800.0] and s.m_kg.tolist() == [9000.0] * 4
    s1, out = loop_step(st, s)
    assert torch.allclose(out.d_true, torch.tensor([-50 / 3000, -50 / 2000, -50 / 1500, -50 / 800], dtype=torch.float64))
    assert s1.lowest_m.tolist() == s1.z_m.tolist()


@pytest.mark.parametrize("kw,msg", [(dict(z_m=[1.0, 2.0]), r"z_m must be a scalar or of shape \(2,\)"),
                                    (dict(z_m=-5.0), "z_m must be finite and > 0"),
                                    (dict(m_kg=float("nan")), "m_kg must be finite"),
                                    (dict(v_mps=float("inf")), "v_mps must be finite")])
def test_bad_start_values(kw, msg):
    st = _stages("paper", "oracle", "D")
    kw = {k: (v if not isinstance(v, list) else v + [3.0]) for k, v in kw.items()}
    with pytest.raises(ValueError, match=msg):
        init_state(st, **kw)


def test_given_thrust_flies_and_is_checked():
    st = _stages("paper", "oracle", "D")
    s = init_state(st)
    hover = s.m_kg * st.settings.g_mps2
    s1, out = loop_step(st, s, thrust=hover)
    assert torch.equal(out.thrust_n, hover)
    assert torch.allclose(s1.v_mps, s.v_mps, atol=1e-3)  # hovering thrust: the velocity barely changes
    for bad in (torch.full((2,), float("nan"), dtype=torch.float64), -hover, torch.zeros(3)):
        with pytest.raises(ValueError, match="thrust must be"):
            loop_step(st, s1, thrust=bad)


def test_finished_descents_stay_frozen():
    st = _stages("paper", "oracle", "D,H")
    s = init_state(st, z_m=torch.tensor([60.0, 60.0, 3000.0, 3000.0]), v_mps=-10.0)
    while bool(s.active[:2].any()):
        s, _ = loop_step(st, s)
    frozen = (s.z_m[:2].clone(), s.outcome[:2].clone(), s.t_end_s[:2].clone())
    s, out = fly_steps(st, s, 5)[0], None
    assert torch.equal(s.z_m[:2], frozen[0]) and torch.equal(s.outcome[:2], frozen[1])
    assert torch.equal(s.t_end_s[:2], frozen[2]) and OUTCOMES[int(frozen[1][0])] != "running"


# ------------------------------------------------------------------ behaviour unchanged
def test_every_shipped_preset_flies_as_recorded():
    """Short flights of every shipped preset (scripts/loop_reference.py) reproduce the stored
    traces and summaries bit for bit."""
    spec = importlib.util.spec_from_file_location("loop_reference", ROOT / "scripts" / "loop_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main([]) == 0


def test_sense_then_act_is_loop_step():
    from dvsland.sim import act_step, sense_step

    a, b = _stages("paper", "dpr", "D"), _stages("paper", "dpr", "D")
    sa, sb = init_state(a), init_state(b)
    for k in range(6):
        sensed = sense_step(a, sa)
        u = sensed.out.thrust_n * (1.0 + 0.01 * k)  # an agent's thrust, chosen after seeing the estimate
        sa, oa = act_step(a, sensed, thrust=u)
        sb, ob = loop_step(b, sb, thrust=u)
        assert _same(oa.d_est, ob.d_est) and torch.equal(sa.z_m, sb.z_m) and torch.equal(oa.ended, ob.ended)
    again, _ = act_step(a, sensed, thrust=u)  # plain data: acting twice gives the same state
    assert tree_equal(again, sa)
