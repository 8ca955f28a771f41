"""TTC target, NaN-aware moving-average filter, and the Eq. 2 controller."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dvsland.control import MovingAverageFilter, TauPController, initial_ttc, nan_moving_average, tau_target

F64 = torch.float64
NAN = float("nan")


def test_tau_target():
    tau0 = initial_ttc(torch.tensor([1e4, 4e3], dtype=F64), torch.tensor([-200.0, -100.0], dtype=F64))
    assert tau0.tolist() == [50.0, 40.0]
    assert tau_target(10.0, tau0, 0.5).tolist() == [45.0, 35.0]
    with pytest.raises(ValueError, match="c2"):
        tau_target(0.0, tau0, 1.0)
    with pytest.raises(ValueError, match="v0_mps"):
        initial_ttc(torch.tensor([1.0], dtype=F64), torch.tensor([0.0], dtype=F64))


class TestFilter:
    def test_per_element_window_and_nan(self):
        f = MovingAverageFilter([1, 3])
        outs = []
        for d in ([1.0, 1.0], [2.0, NAN], [3.0, 3.0], [NAN, 5.0]):
            outs.append(f.update(torch.tensor(d, dtype=F64)))
        mean, n = outs[-1]
        assert torch.isnan(mean[0]) and n[0] == 0  # window 1, newest missing
        assert mean[1].item() == pytest.approx(4.0) and n[1] == 2  # (5 + 3) / 2, NaN skipped
        assert outs[2][0].tolist() == [3.0, 2.0]

    def test_mask_freezes_history(self):
        f = MovingAverageFilter([2, 2])
        f.update(torch.tensor([1.0, 1.0], dtype=F64))
        mean, _ = f.update(torch.tensor([3.0, 3.0], dtype=F64), mask=torch.tensor([True, False]))
        assert mean.tolist() == [2.0, 1.0]

    def test_reset(self):
        f = MovingAverageFilter([2, 2])
        f.update(torch.tensor([1.0, 1.0], dtype=F64))
        f.reset(torch.tensor([True, False]))
        mean, n = f.update(torch.tensor([NAN, NAN], dtype=F64))
        assert torch.isnan(mean[0]) and mean[1].item() == 1.0 and n.tolist() == [0, 1]

    def test_bad_input(self):
        with pytest.raises(ValueError, match="n_bin"):
            MovingAverageFilter([0, 3])
        with pytest.raises(ValueError, match="d_hat"):
            MovingAverageFilter([1, 3]).update(torch.zeros(3, dtype=F64))

    @settings(max_examples=50, deadline=None)
    @given(data=st.lists(st.lists(st.one_of(st.floats(-5, 5), st.just(NAN)), min_size=3, max_size=3),
                         min_size=1, max_size=15),
           n_bin=st.lists(st.integers(1, 6), min_size=3, max_size=3))
    def test_against_numpy(self, data, n_bin):
        f = MovingAverageFilter(n_bin)
        for row in data:
            mean, n = f.update(torch.tensor(row, dtype=F64))
        arr = np.asarray(data, dtype=np.float64)
        for b, nb in enumerate(n_bin):
            win = arr[-nb:, b]
            fin = win[np.isfinite(win)]
            assert int(n[b]) == fin.size
            if fin.size:
                assert mean[b].item() == pytest.approx(fin.mean(), abs=1e-12)
            else:
                assert np.isnan(mean[b].item())

    def test_functional(self):
        hist = torch.tensor([[1.0, NAN], [3.0, 2.0]], dtype=F64)
        mean, n = nan_moving_average(hist, torch.tensor([2, 1]))
        assert mean[0].item() == 2.0 and torch.isnan(mean[1]) and n.tolist() == [2, 0]


def _ctl(**kw):
    args = dict(kp=torch.tensor([5e6, 4e6], dtype=F64), tau0_s=torch.tensor([50.0, 40.0], dtype=F64),
                c2=0.5, g_mps2=1.62)
    args.update(kw)
    return TauPController(**args)


class TestTauP:
    def test_law(self):
        ctl = _ctl()
        m = torch.tensor([1e4, 1e4], dtype=F64)
        out = ctl(10.0, torch.tensor([-1 / 44.0, -1 / 36.0], dtype=F64), m)
        # tau* = 45, 35; tau_hat = 44, 36
        assert out.thrust_n.tolist() == pytest.approx([5e6 * 1 + 16200.0, 0.0])
        assert out.tau_target_s.tolist() == [45.0, 35.0]
        assert not out.held.any()

    def test_on_target_is_hover(self):
        out = _ctl()(0.0, torch.tensor([-1 / 50.0, -1 / 40.0], dtype=F64), torch.full((2,), 1e4, dtype=F64))
        assert out.thrust_n.tolist() == pytest.approx([16200.0, 16200.0])

    def test_missing_and_wrong_sign_hold_last(self):
        ctl = _ctl()
        m = torch.full((2,), 1e4, dtype=F64)
        first = ctl(10.0, torch.tensor([-1 / 44.0, -1 / 44.0], dtype=F64), m).thrust_n
        out = ctl(10.1, torch.tensor([NAN, 0.3], dtype=F64), m)
        assert torch.equal(out.thrust_n, first) and out.held.all()
        assert torch.isnan(out.tau_hat_s).all()

    def test_first_missing_is_hover_and_hover_policy(self):
        m = torch.full((2,), 1e4, dtype=F64)
        assert _ctl()(0.0, torch.tensor([NAN, NAN], dtype=F64), m).thrust_n.tolist() == pytest.approx([16200.0, 16200.0])
        ctl = _ctl(missing_policy="hover")
        ctl(10.0, torch.tensor([-1 / 30.0, -1 / 30.0], dtype=F64), m)
        assert ctl(10.1, torch.tensor([NAN, 0.0], dtype=F64), m).thrust_n.tolist() == pytest.approx([16200.0, 16200.0])

    def test_clamps(self):
        ctl = _ctl(thrust_min_n=1000.0, thrust_max_n=1e5)
        out = ctl(10.0, torch.tensor([-1 / 30.0, -1 / 60.0], dtype=F64), torch.full((2,), 1e4, dtype=F64))
        assert out.thrust_n.tolist() == [1e5, 1000.0]

    def test_never_inf_or_nan(self):
        ctl = _ctl()
        m = torch.full((6,), 1e4, dtype=F64)
        ctl = TauPController(torch.full((6,), 5e6, dtype=F64), torch.full((6,), 50.0, dtype=F64), 0.5, 1.62)
        d = torch.tensor([-1e-320, -0.0, 0.0, float("inf"), float("-inf"), NAN], dtype=F64)
        for t in (0.0, 1e6):
            u = ctl(t, d, m).thrust_n
            assert torch.isfinite(u).all() and (u >= 0).all()

    def test_active_mask_keeps_last(self):
        ctl = _ctl()
        m = torch.full((2,), 1e4, dtype=F64)
        first = ctl(10.0, torch.tensor([-1 / 44.0, -1 / 44.0], dtype=F64), m).thrust_n
        out = ctl(20.0, torch.tensor([-1 / 10.0, -1 / 10.0], dtype=F64), m, active=torch.tensor([True, False]))
        assert out.thrust_n[1] == first[1] and out.thrust_n[0] != first[0]

    def test_bad_input(self):
        with pytest.raises(ValueError, match="missing_policy"):
            _ctl(missing_policy="zero")
        with pytest.raises(ValueError, match="thrust_max_n"):
            _ctl(thrust_min_n=10.0, thrust_max_n=1.0)
        with pytest.raises(ValueError, match="kp"):
            _ctl(kp=torch.tensor([0.0, 1.0], dtype=F64))
