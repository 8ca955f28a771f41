"""Lander dynamics (paper Eq. 1): exact zero-order-hold step, sub-steps, burnout, closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dvsland.dynamics import (INTEGRATORS, LanderDynamics, LanderParams, closed_form_state, closed_form_thrust,
                              closed_form_time_to_altitude, loop_gain, step_euler, step_exact, step_substeps)

F64 = torch.float64
P = LanderParams()


def _t(*xs, device="cpu"):
    return torch.tensor(xs, dtype=F64, device=device)


class TestStepExact:
    def test_smoke_shapes(self, device):
        z, v, m, u = _t(1e4, 4e3, device=device), _t(-200.0, -100.0, device=device), \
            _t(1e4, 1e4, device=device), _t(0.0, 2e4, device=device)
        out = step_exact(z, v, m, u, 0.1, P)
        assert len(out) == 4
        for x in out:
            assert x.shape == (2,) and x.dtype == F64 and x.device.type == device.type

    def test_free_fall(self, device):
        z, v, m = _t(1000.0, device=device), _t(-10.0, device=device), _t(5000.0, device=device)
        z1, v1, m1, burn = step_exact(z, v, m, torch.zeros_like(z), 0.1, P)
        assert z1.item() == pytest.approx(1000.0 - 1.0 - 0.5 * 1.62 * 0.01, abs=1e-12)
        assert v1.item() == pytest.approx(-10.0 - 0.162, abs=1e-12)
        assert m1.item() == 5000.0 and burn.item() == 0.0

    def test_rocket_equation(self):
        ce = P.exhaust_velocity_mps
        u, m0, dt = 5e4, 1e4, 0.1
        z1, v1, m1, burn = step_exact(_t(1e4), _t(-200.0), _t(m0), _t(u), dt, P)
        assert m1.item() == pytest.approx(m0 - u * dt / ce, rel=1e-14)
        assert v1.item() == pytest.approx(-200.0 - 1.62 * dt + ce * math.log(m0 / m1.item()), rel=1e-12)
        assert burn.item() == pytest.approx(dt)

    def test_matches_fine_rk4(self, device):
        # 300 random cases in one batch, a tenth of them running dry inside the step
        g = torch.Generator().manual_seed(0)
        B, dt = 300, 0.1
        u = torch.rand(B, generator=g, dtype=F64) * 2e6
        u[:30] = 0.0
        m0 = P.dry_mass_kg + 1.0 + torch.rand(B, generator=g, dtype=F64) * 1e5
        m0[30:60] = P.dry_mass_kg + torch.rand(30, generator=g, dtype=F64) * 5.0
        v0 = -300.0 + torch.rand(B, generator=g, dtype=F64) * 350.0
        args = [x.to(device) for x in (torch.full((B,), 5e3, dtype=F64), v0, m0, u)]
        ze, ve, me, _ = step_exact(*args, dt, P)
        zs, vs, ms, _ = step_substeps(*args, dt, P, substeps=1000)
        dry = me <= P.dry_mass_kg
        assert 10 < int(dry.sum()) < 60
        assert torch.all(me >= P.dry_mass_kg)
        torch.testing.assert_close(ze[~dry], zs[~dry], rtol=0, atol=1e-8)
        torch.testing.assert_close(ve[~dry], vs[~dry], rtol=0, atol=1e-8)
        torch.testing.assert_close(me[~dry], ms[~dry], rtol=0, atol=1e-6)
        # RK4 resolves burnout to one sub-step only: error <= (u / m_dry) * h
        tol = (u.to(device)[dry] / P.dry_mass_kg) * (dt / 1000) * 1.5
        assert torch.all((ve[dry] - vs[dry]).abs() <= tol)
        assert torch.all((ze[dry] - zs[dry]).abs() <= tol * dt)

    @settings(max_examples=60, deadline=None)
    @given(u=st.floats(0.0, 5e6), m0=st.floats(1.0, 1e5), v0=st.floats(-300.0, 50.0), dt=st.floats(1e-3, 2.0))
    def test_invariants(self, u, m0, v0, dt):
        z1, v1, m1, burn = step_exact(_t(5e3), _t(v0), _t(m0), _t(u), dt, P)
        for x in (z1, v1, m1, burn):
            assert torch.isfinite(x).all()
        assert m1.item() <= m0 and m1.item() >= min(m0, P.dry_mass_kg)
        assert 0.0 <= burn.item() <= dt
        # thrust never makes the craft fall faster than free fall
        assert v1.item() >= v0 - 1.62 * dt - 1e-9

    def test_burnout_splits_step(self):
        ce, dry, dt = P.exhaust_velocity_mps, P.dry_mass_kg, 0.1
        u, m0 = 1e6, dry + 0.5  # 0.5 kg left, mdot = 170 kg/s: burns out after ~2.9 ms
        z1, v1, m1, burn = step_exact(_t(1e4), _t(-200.0), _t(m0), _t(u), dt, P)
        tb = 0.5 / (u / ce)
        assert m1.item() == dry
        assert burn.item() == pytest.approx(tb, rel=1e-12)
        vb = -200.0 - 1.62 * tb + ce * math.log(m0 / dry)
        assert v1.item() == pytest.approx(vb - 1.62 * (dt - tb), rel=1e-10)

    def test_empty_tank_no_thrust(self):
        z1, v1, m1, burn = step_exact(_t(1e4), _t(-200.0), _t(P.dry_mass_kg), _t(1e6), 0.1, P)
        assert m1.item() == P.dry_mass_kg and burn.item() == 0.0
        assert v1.item() == pytest.approx(-200.0 - 0.162)

    def test_negative_thrust_is_zero(self):
        a = step_exact(_t(1e4), _t(-200.0), _t(1e4), _t(-5e4), 0.1, P)
        b = step_exact(_t(1e4), _t(-200.0), _t(1e4), _t(0.0), 0.1, P)
        for x, y in zip(a, b):
            assert torch.equal(x, y)

    def test_bad_input(self):
        with pytest.raises(ValueError, match="dt_s"):
            step_exact(_t(1.0), _t(-1.0), _t(1e4), _t(0.0), 0.0, P)
        with pytest.raises(ValueError, match="shape"):
            step_exact(_t(1.0, 2.0), _t(-1.0), _t(1e4), _t(0.0), 0.1, P)
        with pytest.raises(ValueError, match="isp_s"):
            LanderParams(isp_s=0.0)
        with pytest.raises(ValueError, match="integrator"):
            LanderDynamics(P, integrator="rk45")  # euler is a valid choice now
        with pytest.raises(ValueError, match="substeps"):
            step_substeps(_t(1.0), _t(-1.0), _t(1e4), _t(0.0), 0.1, P, substeps=0)

    def test_module_matches_function(self):
        dyn = LanderDynamics(P, "exact")
        args = (_t(1e4), _t(-200.0), _t(1e4), _t(3e4), 0.1)
        for x, y in zip(dyn.step(*args), step_exact(*args, P)):
            assert torch.equal(x, y)


class TestClosedForm:
    def test_paper_times(self):
        assert closed_form_time_to_altitude(50.0, 1e4, -200.0, 0.5) == pytest.approx(92.93, abs=0.01)
        assert closed_form_time_to_altitude(50.0, 4e3, -100.0, 0.5) == pytest.approx(71.06, abs=0.01)

    def test_ttc_decreases_linearly(self):
        t = np.linspace(0, 80, 50)
        z, v = closed_form_state(t, 1e4, -200.0, 0.5)
        assert z[0] == 1e4 and v[0] == -200.0
        np.testing.assert_allclose(-z / v, 50.0 - 0.5 * t, rtol=1e-12)

    def test_open_loop_closed_form_thrust_tracks(self):
        # feeding the ideal thrust (sampled mid-step) through the exact dynamics follows the closed form
        dt, m = 0.1, torch.tensor([1e4], dtype=F64)
        z, v = _t(4e3), _t(-100.0)
        for k in range(600):
            u = closed_form_thrust((k + 0.5) * dt, 4e3, -100.0, m.item())
            z, v, m, _ = step_exact(z, v, m, _t(float(u)), dt, P)
        zc, vc = closed_form_state(600 * dt, 4e3, -100.0)
        assert z.item() == pytest.approx(float(zc), rel=0.01)
        assert v.item() == pytest.approx(float(vc), rel=0.01)

    def test_loop_gain_and_errors(self):
        assert loop_gain(5e6, 1e4, -200.0, 1e4) == pytest.approx(125.0)
        with pytest.raises(ValueError, match="v0_mps"):
            closed_form_state([0.0], 1e4, 10.0)
        with pytest.raises(ValueError, match="c2"):
            closed_form_state([0.0], 1e4, -10.0, c2=1.5)
        with pytest.raises(ValueError, match="z_m"):
            closed_form_time_to_altitude(2e4, 1e4, -200.0)


class TestIntegratorChoice:
    """exact / euler / substeps against the rocket equation's closed form under a held thrust."""

    @staticmethod
    def _closed_form(t, z0, v0, m0, u, p=P):
        ce = p.exhaust_velocity_mps
        x = u * t / (ce * m0)
        v = v0 - p.g_mps2 * t - ce * math.log1p(-x)
        z = z0 + v0 * t - 0.5 * p.g_mps2 * t * t + ce * t * ((1 - x) * math.log1p(-x) + x) / x
        return z, v, m0 - u * t / ce

    def _fly(self, integrator, dt, t_end=20.0, u=3e4):
        dyn = LanderDynamics(P, integrator, substeps=20)
        z, v, m = _t(4000.0), _t(-100.0), _t(1e4)
        for _ in range(int(round(t_end / dt))):
            z, v, m, _b = dyn.step(z, v, m, _t(u), dt)
        return z.item(), v.item(), m.item()

    def test_against_closed_form(self):
        z_cf, v_cf, m_cf = self._closed_form(20.0, 4000.0, -100.0, 1e4, 3e4)
        z, v, m = self._fly("exact", 0.1)
        assert z == pytest.approx(z_cf, abs=1e-6) and v == pytest.approx(v_cf, abs=1e-9) and m == pytest.approx(m_cf)
        z, v, m = self._fly("substeps", 0.1)
        assert z == pytest.approx(z_cf, abs=1e-6) and v == pytest.approx(v_cf, abs=1e-8)
        z, v, m = self._fly("euler", 0.1)
        assert m == pytest.approx(m_cf, abs=1e-9)  # the mass rate is constant: Euler is exact there
        err_z, err_v = abs(z - z_cf), abs(v - v_cf)
        assert 0.05 < err_z < 5.0 and 1e-4 < err_v < 0.1  # first order: visible, bounded

    def test_euler_is_first_order(self):
        z_cf, v_cf, _ = self._closed_form(20.0, 4000.0, -100.0, 1e4, 3e4)
        e1 = abs(self._fly("euler", 0.1)[0] - z_cf)
        e2 = abs(self._fly("euler", 0.05)[0] - z_cf)
        assert e1 / e2 == pytest.approx(2.0, rel=0.05)

    def test_euler_free_fall_by_hand(self):
        z1, v1, m1, burn = step_euler(_t(1000.0), _t(-10.0), _t(5000.0), _t(0.0), 0.1, P)
        assert z1.item() == pytest.approx(999.0) and v1.item() == pytest.approx(-10.162) and m1.item() == 5000.0
        assert burn.item() == 0.0

    def test_euler_burnout(self):
        p = LanderParams(dry_mass_kg=9999.0)
        ce = p.exhaust_velocity_mps
        z1, v1, m1, burn = step_euler(_t(1000.0), _t(-10.0), _t(1e4), _t(1e5), 0.1, p)
        t_burn = 1.0 * ce / 1e5  # 1 kg of fuel at 1e5 / ce kg/s
        assert burn.item() == pytest.approx(t_burn) and m1.item() == pytest.approx(9999.0)
        assert v1.item() == pytest.approx(-10.0 + 1e5 / 1e4 * t_burn - 1.62 * 0.1)

    def test_unknown_integrator(self):
        with pytest.raises(ValueError, match=r"integrator must be one of \['exact', 'euler', 'substeps'\]"):
            LanderDynamics(P, "rk45")
        assert INTEGRATORS == ("exact", "euler", "substeps")
