"""The sink-rate floor that grows with the filter's velocity uncertainty (``controller.div_gs.v_min_sigma``):
the filters' posterior velocity standard deviation, the law by hand, its errors, and a closed loop
without a single estimate."""

from __future__ import annotations

import pytest
import torch

from dvsland.config import ConfigError, load_config
from dvsland.control import DivGSController, EfferenceFilter, EfferenceFitFilter

F64 = torch.float64
NAN = float("nan")


def _t(*x):
    return torch.tensor(x, dtype=F64)


class TestVelocitySigma:
    def test_fit_starts_at_the_prior_and_is_the_inverse_of_its_information(self):
        f = EfferenceFitFilter(_t(4000.0, 2000.0), _t(-100.0, -50.0), 0.1, prior_rel_sigma=0.06, prior_rel_sigma_v=0.03)
        out = f.step_state(f.init_state(), _t(NAN, NAN))[1]
        assert out.velocity_sigma_mps.dtype == F64 and out.velocity_sigma_mps.shape == (2,)
        assert out.velocity_sigma_mps.tolist() == pytest.approx([3.0, 1.5])
        st, a = f.init_state(), torch.full((2,), 0.5, dtype=F64)
        z, v = _t(4000.0, 2000.0), _t(-100.0, -50.0)
        for k in range(60):  # consistent estimates: the velocity becomes known
            if k:
                z, v = z + v * 0.1 + 0.5 * a * 0.01, v + a * 0.1
            st, out = f.step_state(st, v / z, accel_mps2=None if k == 0 else a)
        cov = torch.linalg.inv(torch.stack([torch.stack([st.info[:, 0], st.info[:, 1]], 1),
                                            torch.stack([st.info[:, 1], st.info[:, 2]], 1)], 1))
        assert out.velocity_sigma_mps.tolist() == pytest.approx(cov[:, 1, 1].sqrt().tolist(), rel=1e-9)
        assert (out.velocity_sigma_mps < _t(3.0, 1.5)).all()

    def test_ekf_gives_the_root_of_its_velocity_variance(self):
        f = EfferenceFilter(_t(4000.0), _t(-100.0), 0.1, prior_rel_sigma=0.05)
        st, out = f.step_state(f.init_state(), _t(-0.025))
        assert out.velocity_sigma_mps.item() == pytest.approx(st.pvv.sqrt().item())
        assert EfferenceFilter.provides_velocity_sigma and EfferenceFitFilter.provides_velocity_sigma


class TestLaw:
    def _pair(self, k):
        kw = dict(lambda_per_s=0.5, d_final_per_s=0.03, v_min_mps=2.0)
        tau0 = _t(40.0, 40.0, 40.0)
        return DivGSController(tau0, 0.5, 1.62, v_min_sigma=k, **kw), DivGSController(tau0, 0.5, 1.62, **kw)

    def test_floor_by_hand(self):
        """v_min + k sigma_v: the target is -(2 + 2 x 1.5) / z below z = 5 / 0.03; a NaN sigma counts as 0."""
        ctl, plain = self._pair(2.0)
        assert ctl.needs_velocity_sigma and not plain.needs_velocity_sigma
        z, m, d_f, t = _t(20.0, 100.0, 20.0), _t(9000.0, 9000.0, 9000.0), _t(-0.3, -0.04, -0.04), 100.0
        sig = _t(1.5, 1.5, NAN)
        out = ctl(t, d_f, m, altitude_m=z, velocity_sigma_mps=sig)
        expect = 9000 * 1.62 + 0.5 * 9000 * 20 * (-5.0 / 20 + 0.3)
        assert out.thrust_n[0].item() == pytest.approx(expect)
        assert out.tau_target_s[0].item() == pytest.approx(4.0)  # z / v_floor = 20 / 5
        assert out.tau_target_s[1].item() == pytest.approx(20.0)  # 100 m: the floor 5 m/s binds (d_final z = 3)
        ref = plain(t, d_f, m, altitude_m=z)
        assert out.thrust_n[2].item() == ref.thrust_n[2].item()  # NaN sigma: the plain floor

    def test_off_reads_no_sigma_and_keeps_the_bits(self):
        ctl, plain = self._pair(0.0)
        z, m, d_f = _t(20.0, 300.0, 20.0), _t(9000.0, 9000.0, 9000.0), _t(-0.04, -0.02, NAN)
        t = _t(100.0, 10.0, 100.0)
        a = ctl(t, d_f, m, altitude_m=z, velocity_sigma_mps=_t(5.0, 5.0, 5.0))
        b = plain(t, d_f, m, altitude_m=z)
        assert torch.equal(a.thrust_n, b.thrust_n)

    def test_errors_name_the_option(self):
        ctl, _ = self._pair(1.0)
        with pytest.raises(ValueError, match="v_min_sigma"):
            ctl(100.0, _t(-0.04, -0.04, -0.04), _t(9e3, 9e3, 9e3), altitude_m=_t(20.0, 20.0, 20.0))
        with pytest.raises(ValueError, match="controller.div_gs.v_min_sigma"):
            DivGSController(_t(40.0), 0.5, 1.62, v_min_sigma=-1.0)
        with pytest.raises(ConfigError, match="v_min_sigma"):
            load_config("montecarlo_efference", overrides=["controller.div_gs.v_min_sigma=-0.5"])
        with pytest.raises(ConfigError, match="v_min_sigma"):
            load_config("montecarlo_efference", overrides=["controller.div_gs.v_min_sigma=11"])

    def test_a_residual_policy_on_div_gs_asks_for_the_sigma(self):
        from dvsland.control.policy import PolicyController

        tau0 = _t(40.0, 40.0)
        pol = PolicyController(tau0, 0.5, 1.62, 9000.0, base="div_gs",
                               base_options={"v_min_mps": 2.0, "v_min_sigma": 2.0})
        assert pol.needs_velocity_sigma and pol.needs_altitude
        out = pol(100.0, _t(-0.04, -0.04), _t(9e3, 9e3), altitude_m=_t(20.0, 20.0), velocity_sigma_mps=_t(1.0, 1.0))
        assert torch.isfinite(out.thrust_n).all()
        assert not PolicyController(tau0, 0.5, 1.62, 9000.0, base="div_gs").needs_velocity_sigma


def test_without_any_estimate_the_grown_floor_lands_where_the_plain_one_stops_high(tmp_path, blind_estimator):
    """montecarlo_efference's dispersed starts, no estimate at all: the filter flies its prior, whose
    velocity is up to 5 % off (sigma_v 3 m/s). A 2 m/s floor lets the true velocity reach 0 high up
    (4 of these 5 climb away); with the floor grown by 2 sigma_v every descent lands."""
    from dvsland.sim import simulate

    over = ["logging.tensorboard=false", "logging.figures=false", "simulation.n_seeds=5"]
    plain = simulate("montecarlo_efference", estimator=blind_estimator(5), sites="I", quiet=True,
                     out=tmp_path / "plain", overrides=over)
    grown = simulate("montecarlo_efference", estimator=blind_estimator(5), sites="I", quiet=True,
                     out=tmp_path / "grown", overrides=over + ["controller.div_gs.v_min_sigma=2"])
    assert sum(r["outcome"] != "success" for r in plain.runs) >= 3, plain.runs
    assert [r["outcome"] for r in grown.runs] == ["success"] * 5, grown.runs
    assert all(abs(r["v_end_mps"]) < 25.0 for r in grown.runs)
