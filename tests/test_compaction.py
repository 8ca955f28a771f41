"""Compaction: finished descents leave the hot path (simulation.compact) with the same outcomes."""

from __future__ import annotations

import pytest
import torch

from dvsland.config import load_config
from dvsland.events import Events
from dvsland.sim import init_state, loop_step
from dvsland.sim.step import active_events
from dvsland.stages import build_stages


@pytest.fixture(autouse=True)
def _rows_step_always(monkeypatch):
    """The emulator steps only the flying rows as soon as one descent has ended (the shipped shares,
    a quarter of the batch and a tenth with the compiled kernel, are never reached by these batches
    of 2-3)."""
    import dvsland.sim.step as step

    monkeypatch.setattr(step, "EMULATOR_ROWS_SHARE", 1.0)
    monkeypatch.setattr(step, "EMULATOR_ROWS_SHARE_COMPILED", 1.0)


def _stages(preset, est, sites, compact, extra=()):
    over = [f"estimator.name={est}", "render.threads=1", f"simulation.compact={str(compact).lower()}", *extra]
    if "montecarlo" in preset:
        over.append("simulation.n_seeds=1")
    return build_stages(load_config(preset, over), sites)


def _fly(stages, z_m, n_max):
    """Fly from altitudes ``z_m`` until every descent ended or ``n_max`` steps; (final state, outputs)."""
    state, outs = init_state(stages, z_m=z_m), []
    while not state.done and state.step < n_max:
        state, out = loop_step(stages, state)
        outs.append(out)
    return state, outs


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    return torch.equal(a.nan_to_num(-123.0), b.nan_to_num(-123.0))


# ------------------------------------------------------------------ the event filter
def test_active_events_keeps_only_active_rows_in_order():
    b = torch.tensor([0, 0, 1, 2, 2, 3])
    ev = Events(b, torch.arange(6), torch.arange(6), torch.tensor([1, 5, 2, 3, 9, 4]), torch.ones(6, dtype=torch.int8))
    out = active_events(ev, torch.tensor([True, False, True, False]))
    assert out.b.tolist() == [0, 0, 2, 2] and out.t.tolist() == [1, 5, 3, 9] and out.is_sorted()
    assert active_events(ev, torch.ones(4, dtype=torch.bool)) is ev
    assert active_events(None, torch.ones(4, dtype=torch.bool)) is None
    assert len(active_events(Events.empty(), torch.zeros(4, dtype=torch.bool))) == 0


# ------------------------------------------------------------------ same outcomes, on and off
def _both(preset, est, sites, z_m):
    ends, outs = {}, {}
    for compact in (False, True):
        st = _stages(preset, est, sites, compact)
        ends[compact], outs[compact] = _fly(st, z_m, 40)
    assert ends[True].step == ends[False].step and bool((~ends[True].active).any()), \
        "the case needs a descent that ends early"
    return ends, outs


# estimators whose estimate of one descent does not depend on the other descents of the batch
@pytest.mark.parametrize("preset,est,sites,z_m", [
    ("paper_eq2", "dpr", "D,E", None),  # Eq. 2 read literally: both ascend within 1.5 s
    ("montecarlo_efference", "dpr", "H,I", [52.0, 4000.0]),  # the first lands after a few steps
    ("paper", "snn", "F", [52.0, 4000.0]),  # two settings of one site
    ("montecarlo_efference", "oracle", "E,H", [52.0, 4000.0]),
])
def test_compaction_changes_no_flown_value(preset, est, sites, z_m):
    ends, outs = _both(preset, est, sites, z_m)
    on, off = ends[True], ends[False]
    for name in ("z_m", "v_mps", "m_kg", "outcome", "t_end_s", "lowest_m", "max_thrust_n", "n_held", "n_missing",
                 "n_sanitised", "n_positive"):
        assert _same(getattr(on, name), getattr(off, name)), name
    finished_early = 0
    for a, b in zip(outs[True], outs[False]):
        act = b.active
        assert torch.equal(a.active, act)
        for name in ("d_est", "d_conf", "d_filtered", "thrust_n", "z_m", "v_mps", "n_used"):
            assert _same(getattr(a, name)[act], getattr(b, name)[act]), (name, a.step)
        assert _same(a.thrust_n, b.thrust_n) and _same(a.d_filtered, b.d_filtered)
        if a.events is not None and len(a.events):
            assert bool(act[a.events.b].all())  # the estimator saw only flying descents' events
        finished_early += int((~act).sum())
    assert finished_early > 0


def test_finished_descents_events_reach_the_estimator_only_without_compaction():
    """montecarlo_efference's sensors fire background events: a landed descent keeps emitting them."""
    seen = {}
    for compact in (False, True):
        _, outs = _fly(_stages("montecarlo_efference", "dpr", "H,I", compact), [52.0, 4000.0], 30)
        seen[compact] = sum(int((~o.active[o.events.b]).sum()) for o in outs if o.events is not None)
    assert seen[False] > 0 and seen[True] == 0


def test_compact_setting_is_read_from_the_config():
    assert _stages("paper", "oracle", "D", True).settings.compact is True
    assert _stages("paper", "oracle", "D", False).settings.compact is False


def test_compaction_cmax_flies_bit_identically():
    """cmax's canvas margin is a constant (it was the widest the batch needed, which tied each
    descent's estimate to the others' in the 5th digit): with compaction on or off the flown
    descents' estimates and states are identical, and only the finished ones get NaN."""
    for sites, z_m in (("H,I", [52.0, 4000.0]), ("A,D,G", [60.0, 3000.0, 55.0])):
        ends, outs = _both("montecarlo_efference", "cmax", sites, z_m)
        assert torch.equal(ends[True].outcome, ends[False].outcome)
        for a, b in zip(outs[True], outs[False]):
            assert _same(a.d_est[b.active], b.d_est[b.active])
            assert torch.equal(a.z_m, b.z_m) and torch.equal(a.v_mps, b.v_mps)