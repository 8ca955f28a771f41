"""The efference_fit filter's compiled round terms (dvsland.control.native_fit): the same bits as the
torch path over whole flights (NaN estimates, the confidence's noise, forgetting, finished descents,
a wild start), input checks, the mode switch, and the torch path wherever a gradient is wanted."""

import pytest
import torch

import dvsland.control.efference_fit as F
from dvsland.control import EfferenceFitFilter, native_fit
from dvsland.pytree import tree_equal

from test_efference_fit_compact import DT, _flight, _fly

F64 = torch.float64


@pytest.fixture(scope="module")
def kernels(native_kernels):
    return native_kernels(native_fit.LIBRARY, "the compiled fit terms")


def _both(make, steps, monkeypatch):
    monkeypatch.setattr(native_fit.LIBRARY, "chosen", True)
    native = _fly(make, steps)
    monkeypatch.setattr(native_fit.LIBRARY, "chosen", False)
    torch_path = _fly(make, steps)
    monkeypatch.setattr(native_fit.LIBRARY, "chosen", None)
    return native, torch_path


@pytest.mark.parametrize("options", [{}, {"forget_s": 0.5, "iterations": 4},
                                     {"meas_noise": "confidence", "min_confidence": 0.2},
                                     {"meas_noise": "confidence", "gate_sigma": 1.0, "cauchy_c": 0.5,
                                      "min_altitude_m": 4000.0, "prior_scale": 1.3}])
@pytest.mark.parametrize("compact", [True, False])
def test_native_terms_give_the_torch_paths_bits(kernels, options, compact, monkeypatch):
    """Every step's state and output of a flight, both paths; the last case gates most estimates out and
    clamps the altitude (a floor above the start), so every branch of the terms runs."""
    monkeypatch.setattr(F, "CPU_COMPACT", compact)
    z0, v0, steps = _flight(5)
    native, torch_path = _both(lambda idx: EfferenceFitFilter(z0, v0, DT, **options), steps, monkeypatch)
    for (s1, o1), (s2, o2) in zip(native, torch_path):
        assert tree_equal((s1, tuple(o1)), (s2, tuple(o2)))
    if options.get("gate_sigma") == 1.0:  # the gate rejected some: both weights' branches ran
        assert native[-1][0].n_rejected.sum() > 0


def test_native_terms_are_used_and_mode_off_runs_torch(kernels, monkeypatch, count_calls):
    z0, v0, steps = _flight(6)
    calls = count_calls(native_fit.Kernels, "terms")
    monkeypatch.setattr(native_fit.LIBRARY, "chosen", True)
    _fly(lambda idx: EfferenceFitFilter(z0, v0, DT, iterations=2), steps[:3])
    assert len(calls) == 6  # two rounds per step
    monkeypatch.setattr(native_fit.LIBRARY, "chosen", False)
    _fly(lambda idx: EfferenceFitFilter(z0, v0, DT, iterations=2), steps[:3])
    assert len(calls) == 6


def test_gradients_take_the_torch_path(kernels, monkeypatch, count_calls):
    """An estimate carrying a gradient (training through the loop) is fitted by torch, whose graph the
    compiled terms would cut; the gradient reaches it."""
    monkeypatch.setattr(native_fit.LIBRARY, "chosen", True)
    calls = count_calls(native_fit.Kernels, "terms")
    z0, v0, steps = _flight(7)
    f = EfferenceFitFilter(z0, v0, DT)
    st = f.init_state()
    d = steps[0][0].nan_to_num(-0.02).clone().requires_grad_(True)
    st, out = f.step_state(st, d)
    st, out = f.step_state(st, d * 1.01, accel_mps2=steps[0][2])
    out[0].sum().backward()
    assert not calls and d.grad is not None and torch.isfinite(d.grad).all() and d.grad.abs().sum() > 0


def test_kernel_checks_its_inputs(kernels):
    B, N = 2, 3
    hist = torch.zeros(5, B, N, dtype=F64)
    theta, pcov = torch.zeros(B, 2, dtype=F64), torch.ones(B, 3, dtype=F64)
    prod, w, r = kernels.terms(hist, False, None, theta, pcov, 1.0, 0.05, 0.001, 9.0, 4.0)
    assert prod.shape == (5, B, N) and w.shape == r.shape == (B,)
    with pytest.raises(RuntimeError, match="theta must hold 4 elements"):
        kernels.terms(hist, False, None, theta[:1], pcov, 1.0, 0.05, 0.001, 9.0, 4.0)
    with pytest.raises(RuntimeError, match="fade must hold 6 elements"):
        kernels.terms(hist, False, torch.ones(B, dtype=F64), theta, pcov, 1.0, 0.05, 0.001, 9.0, 4.0)
    with pytest.raises(RuntimeError, match="hist must be a contiguous torch.float64 CPU tensor"):
        kernels.terms(hist.float(), False, None, theta, pcov, 1.0, 0.05, 0.001, 9.0, 4.0)
    with pytest.raises(RuntimeError, match=r"hist must have shape \(5, B, N\), got \(4, 2, 3\)"):
        kernels.terms(hist[:4], False, None, theta, pcov, 1.0, 0.05, 0.001, 9.0, 4.0)
    with pytest.raises(RuntimeError, match="not contiguous"):
        kernels.terms(hist.transpose(1, 2).contiguous().transpose(1, 2), False, None, theta, pcov, 1.0, 0.05, 0.001,
                      9.0, 4.0)


def test_rows_without_estimates_or_with_infinite_values_weigh_nothing(kernels):
    """A row whose D_hat or sigma_c is NaN or infinite gets weight 0, as the torch path's isfinite tests."""
    B, N = 1, 4
    hist = torch.tensor([[3000.0] * N, [-80.0] * N, [0.1, 0.2, 0.3, 0.4], [-0.027, float("nan"), float("inf"), -0.027],
                         [0.0, 0.0, 0.0, float("inf")]], dtype=F64).view(5, B, N)
    theta, pcov = torch.zeros(B, 2, dtype=F64), torch.eye(2, dtype=F64)[[0, 0, 1], [0, 1, 1]].view(1, 3)
    prod, w, _ = kernels.terms(hist, True, None, theta, pcov, 1.0, 0.05, 0.001, 9.0, 4.0)
    assert (prod[:, 0, 0] != 0).all() and (prod[:, 0, 1:] == 0).all() and w[0] == 0


@pytest.mark.parametrize("options", [{}, {"meas_noise": "confidence", "forget_s": 2.0}])
def test_restarted_descents_leading_blank_rows_give_the_torch_paths_bits(kernels, options, monkeypatch):
    """Descents restarted mid-flight (a fleet's slots, an environment's autoreset) have blank rows
    before their restart: the same bits as the torch path."""
    z0, v0, steps = _flight(8)
    restart = torch.zeros(len(z0), dtype=torch.bool)
    restart[[0, 3, 5]] = True

    def fly():
        f = EfferenceFitFilter(z0, v0, DT, **options)
        st, out = f.init_state(), []
        for k, (d, conf, a, _) in enumerate(steps):
            if k in (20, 41):
                st = f.reset_where(st, restart if k == 20 else ~restart)
            st, o = f.step_state(st, d, None, None if k == 0 else steps[k - 1][2], None, conf)
            out.append((st, o))
        return out

    monkeypatch.setattr(native_fit.LIBRARY, "chosen", True)
    native = fly()
    monkeypatch.setattr(native_fit.LIBRARY, "chosen", False)
    torch_path = fly()
    hist = native[-1][0].rows_packed  # rows 0-19 (blank for all) dropped; 20-40 blank for those restarted at 41
    assert torch.isnan(hist[1, :21, 3]).all() and torch.isfinite(hist[0, :21, 0]).all()
    for (s1, o1), (s2, o2) in zip(native, torch_path):
        assert tree_equal((s1, tuple(o1)), (s2, tuple(o2)))
