"""efference_fit's fit of the descents in flight only (``CPU_COMPACT``): the same bits as fitting
every descent, and each descent's fit independent of the rest of the batch."""

import pytest
import torch

import dvsland.control.efference_fit as F
from dvsland.control import EfferenceFitFilter
from dvsland.pytree import tree_equal

F64 = torch.float64
B, K, DT = 7, 60, 0.1


def _flight(seed: int):
    """(z0 (B,), v0 (B,), per step: d_hat (B,), confidence (B,), accel (B,), active (B,) bool);
    descent i flies until step ``ends[i]`` (one never ends), some estimates NaN."""
    g = torch.Generator().manual_seed(seed)
    z0 = 3000.0 + 2000.0 * torch.rand(B, generator=g, dtype=F64)
    v0 = -(60.0 + 60.0 * torch.rand(B, generator=g, dtype=F64))
    ends = torch.tensor([K, 11, 25, 40, 3, 59, 33])
    z, v, steps = z0 * 1.07, v0 * 0.95, []
    for k in range(K):
        a = 0.5 * torch.randn(B, generator=g, dtype=F64)
        d = v / z * (1.0 + 0.1 * torch.randn(B, generator=g, dtype=F64))
        d = torch.where(torch.rand(B, generator=g) < 0.1, float("nan"), d)
        conf = torch.rand(B, generator=g, dtype=F64)
        steps.append((d, conf, a, ends > k))
        z, v = z + v * DT + 0.5 * a * DT * DT, v + a * DT
    return z0, v0, steps


def _fly(make, steps, idx=None):
    """Every step's (state, output) of the filter ``make()`` over ``steps`` (rows ``idx`` only)."""
    sel = (lambda x: x) if idx is None else (lambda x: x[idx])
    f = make(idx)
    st, out = f.init_state(), []
    for k, (d, conf, a, act) in enumerate(steps):
        st, o = f.step_state(st, sel(d), sel(act), None if k == 0 else sel(steps[k - 1][2]), None, sel(conf))
        out.append((st, o))
    return out


@pytest.mark.parametrize("options", [{}, {"forget_s": 0.5, "iterations": 4},
                                     {"meas_noise": "confidence", "min_confidence": 0.2}])
def test_compacted_fit_is_bit_identical(options, monkeypatch):
    z0, v0, steps = _flight(1)

    def make(idx):
        return EfferenceFitFilter(z0, v0, DT, **options)

    monkeypatch.setattr(F, "CPU_COMPACT", True)
    compact = _fly(make, steps)
    monkeypatch.setattr(F, "CPU_COMPACT", False)
    full = _fly(make, steps)
    for (s1, o1), (s2, o2) in zip(compact, full):
        assert tree_equal((s1, tuple(o1)), (s2, tuple(o2)))


def test_each_descents_fit_ignores_the_others(monkeypatch):
    """Flown alone or in the batch, a descent's outputs are the same bits (all in flight: no compaction)."""
    monkeypatch.setattr(F, "CPU_COMPACT", False)
    z0, v0, steps = _flight(2)
    steps = [(d, c, a, torch.ones(B, dtype=torch.bool)) for d, c, a, _ in steps]

    def make(idx):
        return EfferenceFitFilter(z0 if idx is None else z0[idx], v0 if idx is None else v0[idx], DT)

    idx = torch.tensor([1, 4])
    whole, part = _fly(make, steps), _fly(make, steps, idx)
    for (_, o1), (_, o2) in zip(whole, part):
        assert tree_equal(tuple(x[idx] for x in o1), tuple(o2))


def test_finished_descents_keep_their_fit():
    z0, v0, steps = _flight(3)
    out = _fly(lambda idx: EfferenceFitFilter(z0, v0, DT), steps)
    st_end, o_end = out[4]  # descent 4 ended at step 3
    st_last, o_last = out[-1]
    assert torch.equal(st_last.theta[4], st_end.theta[4]) and torch.equal(o_last[2][4], o_end[2][4])
    assert int(o_last[1][4]) == 0
