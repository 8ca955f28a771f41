"""The efference-copy fusion filter: carries D through gaps, converges to the truth, batch semantics."""

from __future__ import annotations

import pytest
import torch

from dvsland.config import load_config
from dvsland.control import DescentParams, EfferenceFilter, MovingAverageFilter, filter_name, make_filter
from dvsland.control.factory import make_controller

F64 = torch.float64
NAN = float("nan")


def _truth(z0, v0, accel, dt, n):
    """Exact (z, v) under a piecewise-constant acceleration sequence ``accel`` (n,) per element."""
    zs, vs = [z0], [v0]
    z, v = z0, v0
    for k in range(n):
        a = accel[k]
        z = z + v * dt + 0.5 * a * dt * dt
        v = v + a * dt
        zs.append(z)
        vs.append(v)
    return torch.stack(zs), torch.stack(vs)


def _run(filt, zs, vs, accel, d_meas):
    outs = []
    for k in range(zs.shape[0]):
        d_f, used = filt.update(d_meas[k], accel_mps2=None if k == 0 else accel[k - 1])
        outs.append((d_f.clone(), filt.altitude_m.clone(), used.clone()))
    return outs


def test_converges_to_truth_with_oracle_input_from_a_wrong_prior():
    dt, n = 0.1, 400
    z0, v0 = torch.tensor([4000.0, 10000.0], dtype=F64), torch.tensor([-100.0, -200.0], dtype=F64)
    # a braking descent: 1.0 and 1.8 m/s^2 up, with a wobble so the acceleration varies
    k = torch.arange(n, dtype=F64).unsqueeze(1)
    accel = torch.tensor([1.0, 1.8], dtype=F64) + 0.3 * torch.sin(k * 0.05)
    zs, vs = _truth(z0, v0, accel, dt, n)
    # starts 30 % off; the oracle's D is exact, so the filter is told the estimates are good (5 %)
    filt = EfferenceFilter(z0, v0, dt, prior_scale=1.3, prior_rel_sigma=0.5, meas_sigma_rel=0.05, meas_sigma_abs=1e-4)
    outs = _run(filt, zs, vs, accel, vs / zs)
    rel = [(outs[i][1] / zs[i] - 1).abs() for i in (0, 200, n)]
    assert (rel[0] > 0.25).all() and (rel[1] < 0.02).all() and (rel[2] < 0.005).all(), rel
    d_err = (outs[-1][0] / (vs[-1] / zs[-1]) - 1).abs()
    assert (d_err < 0.005).all()


def test_carries_divergence_through_a_gap():
    dt, n = 0.1, 300
    z0, v0 = torch.tensor([4000.0], dtype=F64), torch.tensor([-100.0], dtype=F64)
    accel = torch.full((n, 1), 1.2, dtype=F64)
    zs, vs = _truth(z0, v0, accel, dt, n)
    d = (vs / zs).clone()
    d[150:250] = NAN  # 10 s without any estimate
    filt = EfferenceFilter(z0, v0, dt)
    ma = MovingAverageFilter([5])
    outs = _run(filt, zs, vs, accel, d)
    for k in range(150, 250):
        d_f, z_hat, used = outs[k]
        assert used.item() == 0 and torch.isfinite(d_f).all()
        assert d_f.item() == pytest.approx((vs[k] / zs[k]).item(), rel=0.02)  # predicted by the known thrust
    assert torch.isnan(torch.stack([ma.update(d[k])[0] for k in range(250)])[-1]).all()  # the average has nothing


def test_rejects_outliers_and_counts_them():
    dt = 0.1
    filt = EfferenceFilter(torch.tensor([4000.0], dtype=F64), torch.tensor([-100.0], dtype=F64), dt)
    for _ in range(20):
        filt.update(torch.tensor([-0.025], dtype=F64), accel_mps2=torch.tensor([0.0], dtype=F64))
    z_before = filt.altitude_m.clone()
    d_f, used = filt.update(torch.tensor([-5.0], dtype=F64), accel_mps2=torch.tensor([0.0], dtype=F64))
    assert used.item() == 0 and filt.n_rejected.item() == 1
    assert filt.altitude_m.item() == pytest.approx(z_before.item() - 10.0, rel=1e-3)  # prediction only


def test_mask_reset_and_shapes():
    f = EfferenceFilter(torch.tensor([4000.0, 4000.0], dtype=F64), torch.tensor([-100.0, -100.0], dtype=F64), 0.1)
    a = torch.zeros(2, dtype=F64)
    d_f, used = f.update(torch.tensor([-0.025, -0.025], dtype=F64), accel_mps2=a, mask=torch.tensor([True, False]))
    assert d_f.shape == (2,) and d_f.dtype == F64 and used.dtype == torch.int64
    assert f.altitude_m[1].item() == 4000.0 and f.altitude_m[0].item() < 4000.0  # frozen element did not move
    f.reset(torch.tensor([True, False]))
    assert f.altitude_m[0].item() == 4000.0
    with pytest.raises(ValueError, match="d_hat"):
        f.update(torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="prior_scale"):
        EfferenceFilter(torch.tensor([1.0], dtype=F64), torch.tensor([-1.0], dtype=F64), 0.1, prior_scale=0.0)
    with pytest.raises(ValueError, match="z0_m"):
        EfferenceFilter(torch.tensor([0.0], dtype=F64), torch.tensor([-1.0], dtype=F64), 0.1)


def test_config_selection():
    p = DescentParams.simple([5e6, 4e6], [5, 10], 4000.0, -100.0)
    cfg = load_config(None)
    assert cfg.controller.filter == "auto"
    assert isinstance(make_filter(cfg, p, make_controller(cfg, p)), MovingAverageFilter)  # outcomes unchanged
    cfg = load_config(None, ["controller.filter=efference", "controller.efference.prior_scale=1.2"])
    f = make_filter(cfg, p, make_controller(cfg, p))
    assert isinstance(f, EfferenceFilter) and f.prior_scale == 1.2
    cfg = load_config(None, ["controller.name=div_gs"])
    assert filter_name(cfg, make_controller(cfg, p)) == "efference"
    cfg = load_config(None, ["controller.name=div_gs", "controller.filter=moving_average"])
    with pytest.raises(ValueError, match="needs an altitude estimate"):
        make_filter(cfg, p, make_controller(cfg, p))
