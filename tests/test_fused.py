"""``fused``: the combination rules by hand, NaN and disagreement, the stage contract with two
oracles, the factory's members from their own sections, and its errors."""

from __future__ import annotations

import math

import pytest
import torch

from dvsland.config import ConfigError, load_config
from dvsland.estimators import Truth, get_estimator, make_estimator
from dvsland.estimators.fused import FusedEstimator, fuse_precision, fuse_priority, member_names

NAN = float("nan")
pytestmark = pytest.mark.usefixtures("one_thread")


def _rel_var(c: float) -> float:
    """sigma_rel^2 of confidence c (the filters' reading)."""
    return 0.01 * (1.0 / c - 1.0)


def _f32(*rows):
    return torch.tensor(rows, dtype=torch.float32)


class TestPrecision:
    def test_agreeing_members_give_their_inverse_variance_mean(self):
        d, c = _f32([-0.10], [-0.11]), _f32([0.5], [0.8])
        w1, w2 = 1 / _rel_var(0.5), 1 / _rel_var(0.8)
        mean = (w1 * -0.10 + w2 * -0.11) / (w1 + w2)
        chi2 = sum(w * ((x - mean) / abs(mean)) ** 2 for w, x in ((w1, -0.10), (w2, -0.11)))
        var = max(chi2, 1.0) / (w1 + w2)
        out_d, out_c = fuse_precision(d, c)
        assert out_d.dtype == torch.float32 and out_c.dtype == torch.float32 and out_d.shape == (1,)
        assert out_d.item() == pytest.approx(mean, rel=1e-6)
        assert out_c.item() == pytest.approx(1 / (1 + var / 0.01), rel=1e-5)
        assert out_c.item() > 0.8  # two consistent estimates: surer than either

    def test_contradicting_confident_members_give_a_low_confidence(self):
        out_d, out_c = fuse_precision(_f32([-0.10], [-0.30]), _f32([0.8], [0.8]))
        assert out_d.item() == pytest.approx(-0.20, rel=1e-6)
        assert out_c.item() < 0.1  # Birge ratio: they disagree by ~5 sigma each

    def test_one_member_without_an_estimate_passes_the_other(self):
        out_d, out_c = fuse_precision(_f32([NAN, -0.2], [-0.1, NAN]), _f32([0.0, 0.6], [0.7, 0.0]))
        assert out_d.tolist() == pytest.approx([-0.1, -0.2], rel=1e-6)
        assert out_c.tolist() == pytest.approx([0.7, 0.6], rel=1e-5)

    def test_no_estimate_anywhere_is_nan_at_confidence_zero(self):
        out_d, out_c = fuse_precision(_f32([NAN, -0.1], [NAN, -0.1]), _f32([0.0, 0.0], [0.0, 0.0]))
        assert math.isnan(out_d[0]) and math.isnan(out_d[1])  # confidence 0: no estimate
        assert out_c.tolist() == [0.0, 0.0]

    def test_a_sure_member_is_finite(self):
        out_d, out_c = fuse_precision(_f32([-0.1], [-0.2]), _f32([1.0], [1.0]))
        assert torch.isfinite(out_d).all() and 0.0 <= out_c.item() <= 1.0


class TestPriority:
    def test_the_first_member_over_the_bar_wins(self):
        d, c = _f32([-0.1, -0.1, NAN], [-0.2, -0.2, -0.2]), _f32([0.3, 0.1, 0.0], [0.9, 0.9, 0.05])
        out_d, out_c = fuse_priority(d, c, 0.15)
        assert out_d.tolist() == pytest.approx([-0.1, -0.2, -0.2])  # first over the bar; else the surest
        assert out_c.tolist() == pytest.approx([0.3, 0.9, 0.05])

    def test_no_estimate_is_nan(self):
        out_d, out_c = fuse_priority(_f32([NAN], [NAN]), _f32([0.0], [0.0]), 0.15)
        assert math.isnan(out_d.item()) and out_c.item() == 0.0


def _oracles(B=3, rule="precision"):
    members = [get_estimator("oracle", B, (128, 128), noise_rel=0.05, seed=1),
               get_estimator("oracle", B, (128, 128), noise_rel=0.1, delay_steps=1, seed=2)]
    return FusedEstimator(B, (128, 128), members=members, rule=rule)


class TestEstimator:
    def test_contract_with_two_oracles(self):
        est = _oracles()
        assert not est.needs_events and len(est.init_state().members) == 2
        truth = Truth(altitude_m=torch.full((3,), 1000.0, dtype=torch.float64),
                      velocity_mps=torch.full((3,), -50.0, dtype=torch.float64))
        st, out = est.step_state(est.init_state(), None, 100_000, truth)
        # the delayed oracle has nothing yet: the first one's estimate and confidence pass
        assert out.confidence.tolist() == pytest.approx([0.8] * 3, rel=1e-5)
        assert out.diagnostics["n_members"].tolist() == [1, 1, 1]
        assert "oracle.d_oracle" in out.diagnostics or any(k.endswith(".d_oracle") for k in out.diagnostics)
        st, out = est.step_state(st, None, 200_000, truth)
        assert out.diagnostics["n_members"].tolist() == [2, 2, 2]
        assert torch.isfinite(out.d_hat).all() and ((out.d_hat + 0.05).abs() < 0.02).all()
        st = est.reset_where(st, torch.tensor([True, False, False]))
        st, out = est.step_state(st, None, 300_000, truth)
        assert out.diagnostics["n_members"].tolist() == [1, 2, 2]  # the restarted descent's delayed oracle is empty

    def test_object_api_runs_the_contract(self):
        est = _oracles(rule="priority")
        truth = Truth(altitude_m=torch.full((3,), 500.0, dtype=torch.float64),
                      velocity_mps=torch.full((3,), -20.0, dtype=torch.float64))
        d = est.update(None, 100_000, truth)
        assert d.shape == (3,) and torch.isfinite(d).all() and est.confidence().shape == (3,)

    @pytest.mark.parametrize("members, match", [("cmax", "at least two"), ("cmax,fused", "own member"),
                                                ("", "at least two")])
    def test_bad_members_name_the_key(self, members, match):
        with pytest.raises(ValueError, match=f"estimator.fused.members.*{match}|{match}"):
            member_names(members)

    def test_bad_rule_and_bar_name_the_key(self):
        with pytest.raises(ValueError, match="estimator.fused.rule"):
            FusedEstimator(2, (128, 128), members=["oracle", "oracle"], rule="vote")
        with pytest.raises(ValueError, match=r"estimator.fused.min_confidence must be in \[0, 1\]"):
            FusedEstimator(2, (128, 128), members=["oracle", "oracle"], min_confidence=2.0)

    def test_members_for_another_batch_are_refused(self):
        with pytest.raises(ValueError, match="built for 4 descents"):
            FusedEstimator(2, (128, 128), members=[get_estimator("oracle", 4, (128, 128)), "oracle"])


class TestFromConfig:
    def test_members_come_from_their_own_sections(self):
        cfg = load_config("paper", overrides=["estimator.name=fused", "estimator.fused.members=oracle,dpr",
                                              "estimator.oracle.noise_rel=0.2", "estimator.dpr.n_max=7"])
        est = make_estimator(cfg, 4)
        oracle, dpr = est.members
        assert oracle.noise_rel == 0.2 and dpr.params.n_max == 7
        assert est.needs_events and est.member_labels == ("oracle", "dpr")

    def test_schema_checks_the_rule_and_the_bar(self):
        with pytest.raises(ConfigError, match="estimator.fused.rule"):
            load_config("paper", overrides=["estimator.fused.rule=vote"])
        with pytest.raises(ConfigError, match="estimator.fused.min_confidence"):
            load_config("paper", overrides=["estimator.fused.min_confidence=1.5"])

    def test_a_members_checkpoint_is_the_runs(self):
        cfg = load_config("paper", overrides=["estimator.name=fused", "estimator.fused.members=dpr,learned",
                                              "estimator.learned.checkpoint=cnn_both"])
        est = make_estimator(cfg, 2)
        assert est.checkpoint == est.members[1].checkpoint and str(est.checkpoint).endswith("learned_cnn_both.pt")

    def test_realistic_sensor_flies_it_with_the_cnn_of_its_own_flights(self):
        assert load_config("realistic_sensor", ["estimator.name=fused"]).estimator.learned.checkpoint == "cnn_dagger"
        assert load_config("realistic_sensor", ["estimator.name=learned"]).estimator.learned.checkpoint == ""
        over = ["estimator.name=fused", "estimator.learned.checkpoint=cnn_both"]  # a --set wins
        assert load_config("realistic_sensor", over).estimator.learned.checkpoint == "cnn_both"

    def test_realistic_sensor_lets_the_filter_read_fuseds_weak_estimates(self):
        # the filter's bar falls from the preset's 0.15 to 0.015 for fused only, and a --set wins
        assert load_config("realistic_sensor", ["estimator.name=fused"]).controller.efference.min_confidence == 0.015
        assert load_config("realistic_sensor", ["estimator.name=cmax"]).controller.efference.min_confidence == 0.15
        over = ["estimator.name=fused", "controller.efference.min_confidence=0.3"]
        assert load_config("realistic_sensor", over).controller.efference.min_confidence == 0.3


class TestCalibration:
    def test_tables_own_calibrates_fuseds_output_with_its_own_table(self):
        cfg = load_config("realistic_sensor", ["estimator.name=fused", "estimator.calibration=realistic",
                                               "estimator.fused.tables=own"])
        est = make_estimator(cfg, 2)
        assert est.calibration is not None and est.calibration.feature == "abs_d_hat"  # fused_realistic.json
        assert all(m.calibration is None for m in est.members)  # the table was fitted on the raw members

    def test_other_members_or_checkpoint_fly_the_members_tables(self):
        for over in (["estimator.learned.checkpoint=cnn_both"],  # fused_realistic was fitted on cnn_dagger
                     ["estimator.fused.members=learned,cmax"]):  # ... as cmax,learned
            cfg = load_config("realistic_sensor", ["estimator.name=fused", "estimator.calibration=realistic",
                                                   "estimator.fused.tables=own"] + over)
            est = make_estimator(cfg, 2)
            assert est.calibration is None and all(m.calibration is not None for m in est.members)

    def test_by_default_the_members_fly_their_own_tables(self):
        cfg = load_config("realistic_sensor", ["estimator.name=fused", "estimator.calibration=realistic"])
        est = make_estimator(cfg, 2)
        assert est.calibration is None and all(m.calibration is not None for m in est.members)
        with pytest.raises(ConfigError, match="estimator.fused.tables"):
            load_config("realistic_sensor", ["estimator.fused.tables=both"])

    def test_a_named_table_must_be_fuseds(self):
        cfg = load_config("realistic_sensor", ["estimator.name=fused", "estimator.calibration=fused_realistic"])
        assert make_estimator(cfg, 2).calibration is not None
        cfg = load_config("realistic_sensor", ["estimator.name=fused", "estimator.calibration=cmax_realistic"])
        with pytest.raises(ValueError, match="estimator.calibration: 'cmax_realistic' was fitted for estimator 'cmax'"):
            make_estimator(cfg, 2)

    def test_evaluate_checks_the_tables_before_running(self):
        from dvsland.cli.cmd_evaluate import _check_calibration_key

        cfg = load_config("realistic_sensor", ["estimator.name=fused", "estimator.calibration=realistic"])
        _check_calibration_key(cfg, ["fused"], False)  # both members' tables ship
        _check_calibration_key(cfg, ["both=fused"], False)  # under an alias too
        own = load_config("realistic_sensor", ["estimator.name=fused", "estimator.calibration=realistic",
                                               "estimator.fused.tables=own"])
        _check_calibration_key(own, ["fused"], False)  # fused's own table ships
        cfg = load_config("realistic_sensor", ["estimator.name=fused", "estimator.calibration=realistic",
                                               "estimator.fused.members=cmax,oracle"])
        msg = "estimator.calibration: no shipped 'realistic' calibration for estimator 'oracle'"
        with pytest.raises(ValueError, match=msg):
            _check_calibration_key(cfg, ["fused"], False)
