"""Per-descent reset of the loop (reset_where): the restarted descents start over, the others fly
on bit for bit; bad masks and start values are refused by name."""

from __future__ import annotations

import pytest
import torch

from dvsland.config import load_config
from dvsland.pytree import tree_equal
from dvsland.sim import fly_steps, init_state, loop_step, reset_where, restart_finished
from dvsland.sim.termination import RUNNING
from dvsland.stages import build_stages


def _stages(est="oracle", sites="D", extra=()):
    return build_stages(load_config("paper", [f"estimator.name={est}", "render.threads=1", *extra]), sites)


def _same(a, b):
    return torch.equal(a.nan_to_num(-123.0), b.nan_to_num(-123.0))


@pytest.mark.parametrize("est", ["oracle", "dpr"])
def test_reset_leaves_other_descents_bit_identical(est):
    st = _stages(est, "A,D")
    s, _ = fly_steps(st, init_state(st), 4)
    ref, ref_outs = fly_steps(st, s, 4)
    mask = torch.tensor([False, True, False, False])
    r = reset_where(st, s, mask)
    got, outs = fly_steps(st, r, 4)
    keep = ~mask
    for a, b in zip(ref_outs, outs):
        assert _same(a.d_est[keep], b.d_est[keep]) and torch.equal(a.thrust_n[keep], b.thrust_n[keep])
    assert torch.equal(got.z_m[keep], ref.z_m[keep]) and torch.equal(got.v_mps[keep], ref.v_mps[keep])
    # the restarted descent flew 4 steps from its start: as a fresh batch's element 1 does
    fresh, fresh_outs = fly_steps(st, init_state(st), 4)
    assert torch.equal(got.z_m[1], fresh.z_m[1]) and got.flight_step[1] == 4 and got.step == 8
    if est == "oracle":  # no events: the restarted descent flies exactly as a fresh one
        assert torch.equal(outs[-1].thrust_n[1], fresh_outs[-1].thrust_n[1])


def test_restarted_descent_estimates_from_the_same_flight_step_as_a_new_one():
    """A descent restarted while its batch-mate flies on gets its first estimate at the flight step a
    new descent gets its first (cmax needs a full window: its estimator state restarts with the
    emulator, not one step before it)."""
    st = _stages("cmax", "A,D")
    _, fresh_outs = fly_steps(st, init_state(st), 8)
    s, _ = fly_steps(st, init_state(st), 3)
    _, outs = fly_steps(st, reset_where(st, s, torch.tensor([True, False, False, False])), 8)
    first = [next(i for i, o in enumerate(seq) if not torch.isnan(o.d_est[0])) for seq in (fresh_outs, outs)]
    assert first[0] == first[1]


def test_restarted_descent_gets_new_start_and_clean_bookkeeping():
    st = _stages("oracle", "D")
    s = init_state(st, z_m=torch.tensor([60.0, 3000.0]), v_mps=-10.0)
    while bool(s.active[0]):
        s, _ = loop_step(st, s)
    assert int(s.outcome[0]) != RUNNING
    r = restart_finished(st, s, z_m=2500.0, v_mps=-60.0)
    assert bool(r.active.all()) and int(r.outcome[0]) == RUNNING and r.z_m[0] == 2500.0 and r.v_mps[0] == -60.0
    assert r.flight_step[0] == 0 and r.t_end_s[0] == 0 and r.lowest_m[0] == 2500.0 and r.n_held[0] == 0
    assert torch.equal(r.z_m[1], s.z_m[1]) and r.flight_step[1] == s.flight_step[1]
    assert restart_finished(st, r) is r  # nothing finished: no copy
    r2, out = loop_step(st, r)
    assert out.t_flight_s[0] == 0.0 and out.t_flight_s[1] > 0


@pytest.mark.parametrize("kw,msg", [(dict(mask=torch.tensor([True])), r"reset mask must be a \(2,\) bool"),
                                    (dict(mask=torch.tensor([1, 0])), "reset mask must be"),
                                    (dict(z_m=float("nan")), "z_m must be finite"),
                                    (dict(m_kg=-1.0), "m_kg must be finite and > 0"),
                                    (dict(seed=1.5), "seed must be an integer"),
                                    (dict(scene_idx=7), r"scene_idx must lie in \[0, 0\]")])
def test_bad_reset_input_is_named(kw, msg):
    st = _stages("oracle", "D")
    s = init_state(st)
    kw.setdefault("mask", torch.tensor([True, False]))
    with pytest.raises(ValueError, match=msg):
        reset_where(st, s, **kw)


def test_reset_does_not_change_its_input():
    st = _stages("dpr", "D")
    s, _ = fly_steps(st, init_state(st), 3)
    from dvsland.pytree import tree_clone
    before = tree_clone(s)
    reset_where(st, s, torch.tensor([True, False]))
    assert tree_equal(s, before)


def test_a_state_that_does_not_fit_the_stages_is_named():
    st = _stages("oracle", "D")
    s = init_state(st)
    with pytest.raises(ValueError, match=r"LoopState: field 'z_m' must be a \(2,\) torch.float64 tensor"):
        loop_step(st, s._replace(z_m=s.z_m.float()))
    est = s.stage_state.estimator
    bad = s._replace(stage_state=s.stage_state._replace(estimator=est._replace(ring=est.ring[:, :0])))
    with pytest.raises(ValueError, match=r"estimator: state field 'ring' must have shape \(2, 1\), got \(2, 0\)"):
        loop_step(st, bad)
    other = _stages("oracle", "A,D")
    with pytest.raises(ValueError, match=r"LoopState: field 'flight_step' must be a \(4,\)"):
        loop_step(other, s)
