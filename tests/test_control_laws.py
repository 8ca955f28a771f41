"""The thrust laws by name: div_p and div_gs against hand computations, the registry, the gain maths."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dvsland.config import ConfigError, load_config
from dvsland.control import (ControlOutput, Controller, DescentParams, DivGSController, DivPController,
                             TauPController, available_controllers, critical_step_gain, div_loop_gain,
                             gain_limit_altitude_m, get_controller, divergence_target, register_controller,
                             tau_loop_gain)
from dvsland.control.gain import loop_gain_fields
from dvsland.control.registry import _ENTRY_POINT_GROUP, _REGISTRY
from dvsland.stages import check_names

F64 = torch.float64
NAN = float("nan")


def _t(*x):
    return torch.tensor(x, dtype=F64)


class TestDivP:
    def _ctl(self, **kw):
        args = dict(kp=_t(5e6, 4e6), tau0_s=_t(40.0, 40.0), c2=0.25, g_mps2=1.623)
        args.update(kw)
        return DivPController(**args)

    def test_law_by_hand(self):
        # t = 10 s: tau* = 40 - 0.25 * 10 = 37.5 s, D* = -1/37.5; e = D* - D_f; u = Kp e, negative -> 0
        out = self._ctl()(10.0, _t(-0.03, -0.02), _t(1e4, 1e4))
        e0 = -1 / 37.5 + 0.03
        assert out.thrust_n.tolist() == pytest.approx([5e6 * e0, 0.0])
        assert out.tau_target_s.tolist() == [37.5, 37.5]
        assert out.tau_hat_s.tolist() == pytest.approx([1 / 0.03, 50.0])
        assert not out.held.any()

    def test_feedforward_and_cap(self):
        out = self._ctl(feedforward_mg=True, thrust_max_n=2e4)(10.0, _t(-0.03, -0.02), _t(1e4, 1e4))
        e = np.array([-1 / 37.5 + 0.03, -1 / 37.5 + 0.02])
        assert out.thrust_n.tolist() == pytest.approx(list(np.clip(np.array([5e6, 4e6]) * e + 16230.0, 0.0, 2e4)))

    def test_positive_divergence_cuts_thrust_not_held(self):
        out = self._ctl()(0.0, _t(0.1, 0.0), _t(1e4, 1e4))
        assert out.thrust_n.tolist() == [0.0, 0.0] and not out.held.any()

    def test_missing_holds_then_hover_policy(self):
        ctl = self._ctl()
        m = _t(1e4, 1e4)
        assert ctl(0.0, _t(NAN, NAN), m).thrust_n.tolist() == pytest.approx([16230.0, 16230.0])  # hover first
        first = ctl(10.0, _t(-0.03, -0.03), m).thrust_n
        out = ctl(10.1, _t(NAN, -0.03), m)
        assert out.thrust_n[0] == first[0] and out.held.tolist() == [True, False]
        hov = self._ctl(missing_policy="hover")
        hov(10.0, _t(-0.03, -0.03), m)
        assert hov(10.1, _t(NAN, NAN), m).thrust_n.tolist() == pytest.approx([16230.0, 16230.0])

    def test_gain_fields(self):
        ctl = self._ctl(n_bin=torch.tensor([1, 5]), dt_s=0.1)
        f = ctl.loop_gain_fields(_t(1e4, 1e4), _t(100.0, 100.0))
        assert f["loop_gain"].tolist() == pytest.approx([5.0, 4.0]) and f["loop_gain_kind"] == "div"
        # n_bin 1: g_crit = 2 -> z = Kp dt / (m 2) = 25 m
        assert f["gain_limit_altitude_m"][0].item() == pytest.approx(25.0)

    def test_bad_input(self):
        with pytest.raises(ValueError, match="kp"):
            self._ctl(kp=_t(0.0, 1.0))
        with pytest.raises(ValueError, match="c2"):
            self._ctl(c2=1.0)
        with pytest.raises(ValueError, match="thrust_max_n"):
            self._ctl(thrust_min_n=5.0, thrust_max_n=1.0)


class TestDivGS:
    def test_target_by_hand(self):
        tau0 = _t(40.0, 40.0, 40.0)
        # t = 0: D* = -1/40 (TTC part, coef 1 - c2); t = 60: tau* = 10 -> 1/10 > 0.03: final part (coef 1)
        d_star, coef = divergence_target(_t(0.0, 60.0, 200.0), tau0, 0.5, 0.03)
        assert d_star.tolist() == pytest.approx([-1 / 40.0, -0.03, -0.03]) and coef.tolist() == [0.5, 1.0, 1.0]
        # the switch: 1/tau* = 0.03 at tau* = 33.3 s, t = (40 - 33.3) / 0.5 = 13.3 s
        d_star, _ = divergence_target(_t(13.0, 13.7, 13.7), tau0, 0.5, 0.03)
        assert d_star[0].item() == pytest.approx(-1 / 33.5) and d_star[1].item() == -0.03

    def test_law_by_hand(self):
        ctl = DivGSController(_t(40.0), 0.5, 1.62, lambda_per_s=0.5, d_final_per_s=0.03)
        z, m = _t(70.0), _t(9000.0)
        d_f = _t(-0.04)  # approaching faster than the final 0.03 1/s
        out = ctl(100.0, d_f, m, altitude_m=z)
        expect = 9000 * (1.62 + 0.03 ** 2 * 70) + 0.5 * 9000 * 70 * (-0.03 + 0.04)
        assert out.thrust_n.item() == pytest.approx(expect)
        assert out.tau_target_s.item() == pytest.approx(1 / 0.03)
        f = ctl.loop_gain_fields(m, z)
        assert f["loop_gain"].item() == 0.5 and f["loop_gain_kind"] == "div"

    def test_sink_rate_floor_by_hand(self):
        """v_min_mps: below z_hat = v_min / d_final the target is the constant velocity -v_min (a_ref = 0);
        above it, and on the TTC part, the law is unchanged."""
        ctl = DivGSController(_t(40.0, 40.0, 40.0), 0.5, 1.62, lambda_per_s=0.5, d_final_per_s=0.03, v_min_mps=2.0)
        plain = DivGSController(_t(40.0, 40.0, 40.0), 0.5, 1.62, lambda_per_s=0.5, d_final_per_s=0.03)
        z, m, d_f = _t(20.0, 200.0, 20.0), _t(9000.0, 9000.0, 9000.0), _t(-0.04, -0.04, -0.04)
        t = _t(100.0, 100.0, 0.0)  # final part, final part above the floor, TTC part
        out, ref = ctl(t, d_f, m, altitude_m=z), plain(t, d_f, m, altitude_m=z)
        expect = 9000 * 1.62 + 0.5 * 9000 * 20 * (-2.0 / 20 + 0.04)
        assert out.thrust_n[0].item() == pytest.approx(expect)
        assert out.tau_target_s[0].item() == pytest.approx(10.0)
        assert out.thrust_n[1:].tolist() == pytest.approx(ref.thrust_n[1:].tolist())
        with pytest.raises(ValueError, match="v_min_mps"):
            DivGSController(_t(40.0), 0.5, 1.62, v_min_mps=-1.0)

    def test_needs_altitude(self):
        ctl = DivGSController(_t(40.0), 0.5, 1.62)
        assert ctl.needs_altitude
        with pytest.raises(ValueError, match="altitude_m"):
            ctl(0.0, _t(-0.025), _t(1e4))
        with pytest.raises(ValueError, match="lambda_per_s"):
            DivGSController(_t(40.0), 0.5, 1.62, lambda_per_s=0.0)
        with pytest.raises(ValueError, match="d_final_per_s"):
            DivGSController(_t(40.0), 0.5, 1.62, d_final_per_s=-1.0)


class TestRegistry:
    def test_builtins_and_unknown(self):
        assert {"tau_p", "div_p", "div_gs"} <= set(available_controllers())
        with pytest.raises(ValueError, match=r"unknown controller 'nope'.*div_p.*tau_p"):
            get_controller("nope", DescentParams.simple(5e6, 5, 4000.0, -100.0))
        assert _ENTRY_POINT_GROUP == "dvsland.controllers"

    def test_get_builtins_from_params(self):
        p = DescentParams.simple([5e6, 4e6], [5, 10], 4000.0, -100.0, c2=0.25, dt_s=0.1)
        assert isinstance(get_controller("tau_p", p), TauPController)
        d = get_controller("div_p", p, feedforward_mg=True)
        assert isinstance(d, DivPController) and d.feedforward_mg and d.n_bin.tolist() == [5, 10]
        assert isinstance(get_controller("div_gs", p, lambda_per_s=2.0), DivGSController)
        with pytest.raises(TypeError):
            get_controller("div_p", p, bogus=1)

    def test_register_custom_and_config(self):
        @register_controller("test_const")
        class Const(Controller):
            def __init__(self, u):
                self.u = u

            @classmethod
            def from_params(cls, p, thrust_n=1.0):
                return cls(torch.full_like(p.kp, thrust_n))

            def reset(self, mask=None):
                pass

            def __call__(self, t_s, d_filtered, mass_kg, active=None):
                nan = torch.full_like(mass_kg, NAN)
                return ControlOutput(self.u, nan, nan, torch.zeros_like(mass_kg, dtype=torch.bool))

        try:
            assert "test_const" in available_controllers()
            c = get_controller("test_const", DescentParams.simple(1.0, 1, 100.0, -1.0), thrust_n=7.0)
            assert c.u.tolist() == [7.0]
            cfg = load_config(None, ["controller.name=test_const"])
            check_names(cfg)  # names are checked where stages are built
        finally:
            _REGISTRY.pop("test_const", None)
        with pytest.raises(ConfigError, match=r"controller\.name.*unknown controller 'test_const'.*known"):
            check_names(cfg)

    def test_register_needs_from_params(self):
        with pytest.raises(TypeError, match="from_params"):
            register_controller("bad")(type("Bad", (), {}))
        with pytest.raises(ValueError, match="non-empty"):
            register_controller("")


class TestGainMaths:
    def test_critical_gain_closed_forms(self):
        assert critical_step_gain(1, 0) == pytest.approx(2.0, abs=1e-9)  # D[k+1] = (1 - g) D[k]
        assert critical_step_gain(1, 1) == pytest.approx(1.0, abs=1e-9)  # z^2 - z + g: |z|^2 = g
        assert critical_step_gain(1, 2) == pytest.approx((math.sqrt(5) - 1) / 2, abs=1e-9)  # golden ratio
        assert critical_step_gain(2, 0) == pytest.approx(2.0, abs=1e-9)  # z^2 + (g/2 - 1) z + g/2
        assert critical_step_gain(10) < critical_step_gain(5) < critical_step_gain(1)

    @pytest.mark.parametrize("n_bin,delay", [(1, 0), (5, 0), (10, 0), (5, 1)])
    def test_critical_gain_against_recurrence(self, n_bin, delay):
        gc = critical_step_gain(n_bin, delay)

        def final_amplitude(g):
            hist = [1.0] * (n_bin + delay)  # newest last
            for _ in range(4000):
                window = hist[len(hist) - delay - n_bin: len(hist) - delay]
                hist.append(hist[-1] - g * sum(window) / n_bin)
            return max(abs(x) for x in hist[-200:])

        assert final_amplitude(0.97 * gc) < 1e-2
        assert final_amplitude(1.03 * gc) > 1e2

    @pytest.mark.parametrize("n_bin,delay", [(50, 0), (50, 2), (64, 3), (100, 2)])
    def test_long_average_limit_against_exact_roots(self, n_bin, delay):
        """Above EXACT_MAX_N_BIN the closed-form limit stands in for the roots (which cost minutes
        at n_bin = 400 and made n_bin = 10 000 a simulate that Ctrl-C could not stop)."""
        from dvsland.control.gain import _spectral_radius, long_average_step_gain

        g = long_average_step_gain(n_bin, delay)
        assert _spectral_radius(0.995 * g, n_bin, delay) < 1.0 < _spectral_radius(1.005 * g, n_bin, delay)

    def test_huge_n_bin_finds_no_roots(self, monkeypatch):
        """n_bin at its upper bound (10 000) must not solve a degree-10 000 polynomial."""
        import dvsland.control.gain as gain

        real_roots = np.roots

        def no_big_roots(coeffs):
            assert len(coeffs) <= gain.EXACT_MAX_N_BIN + 20, f"np.roots of degree {len(coeffs) - 1}"
            return real_roots(coeffs)

        monkeypatch.setattr(gain.np, "roots", no_big_roots)
        g = gain.critical_step_gain.__wrapped__(10_000, 2)
        assert g * 10_000 == pytest.approx(math.pi ** 2 / 2, rel=2e-3)

    def test_limit_altitude_and_gains(self):
        assert gain_limit_altitude_m(5e6, 1e4, 0.1, 1) == pytest.approx(25.0)
        z = gain_limit_altitude_m(_t(5e6, 4e6), _t(9e3, 9e3), 0.1, torch.tensor([5, 10]))
        assert z.tolist() == pytest.approx([5e6 * 0.1 / (9e3 * critical_step_gain(5)),
                                            4e6 * 0.1 / (9e3 * critical_step_gain(10))])
        # at that altitude the loop gain times dt is exactly g_crit
        assert (div_loop_gain(5e6, 9e3, z[0].item()) * 0.1) == pytest.approx(critical_step_gain(5))
        assert tau_loop_gain(5e6, 1e4, -200.0, 1e4) == pytest.approx(125.0)
        with pytest.raises(ValueError, match="n_bin"):
            critical_step_gain(0)

    def test_loop_gain_fields_dispatch(self):
        p = DescentParams.simple([5e6], [5], 1e4, -200.0)
        tau = loop_gain_fields(get_controller("tau_p", p), _t(9e3), _t(50.0))
        assert tau["loop_gain_kind"] == "tau" and tau["loop_gain"].item() == pytest.approx(125.0)
        assert tau["gain_limit_altitude_m"] is None  # the tau-space lambda only
        div = loop_gain_fields(get_controller("div_p", p), _t(9e3), _t(50.0))
        assert div["loop_gain"].item() == pytest.approx(5e6 / (9e3 * 50.0))
        assert loop_gain_fields(object(), _t(1.0), _t(1.0)) == {"loop_gain": None, "loop_gain_kind": None,
                                                                 "gain_limit_altitude_m": None}


def test_custom_controller_script_flies(tmp_path, capsys):
    """scripts/custom_controller.py registers 'div_backoff' and flies it in the closed loop (oracle, D)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "custom_controller.py"
    spec = importlib.util.spec_from_file_location("custom_controller", path)
    mod = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(mod)
        assert "div_backoff" in available_controllers()
        assert mod.main(["--sites", "D", "--quiet", "--out", str(tmp_path / "cc")]) == 0
    finally:
        _REGISTRY.pop("div_backoff", None)
    out = capsys.readouterr().out
    assert out.count("D/") == 2 and "success" in out
    import json

    runs = json.loads((tmp_path / "cc" / "results.json").read_text())["runs"]
    assert all(r["controller"] == "div_backoff" and r["outcome"] == "success" for r in runs)


def test_cli_controller_flag(tmp_path, capsys):
    from dvsland.cli.main import main

    assert main(["simulate", "--controller", "nope", "--estimator", "oracle", "--sites", "D", "--quiet",
                 "--out", str(tmp_path / "bad")]) == 2
    assert "unknown controller 'nope'" in capsys.readouterr().err
    assert main(["simulate", "paper_eq2", "--controller", "div_p", "--estimator", "oracle", "--sites", "D", "--quiet",
                 "--set", "logging.figures=false", "--set", "logging.tensorboard=false",
                 "--out", str(tmp_path / "ok")]) == 0
    import json

    res = json.loads((tmp_path / "ok" / "results.json").read_text())
    assert {r["controller"] for r in res["runs"]} == {"div_p"}
    assert {r["outcome"] for r in res["runs"]} == {"success"}
    assert "controller:\n  name: div_p" in (tmp_path / "ok" / "config.yaml").read_text()
