"""The calibration report: predicted sigma from the confidence (the filters' mapping), coverage per
site type with abstentions apart, reliability bins, the risk-coverage curve, and
``dvsland evaluate --calibration`` end to end with a plug-in estimator."""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest
import torch

from dvsland.control.efference import confidence_rel_sigma
from dvsland.estimators.base import confidence_from_rel_std
from dvsland.evaluate.calibration import (calibration_summary, coverage_table, predicted_sigma, rel_sigma,
                                          reliability_bins, risk_coverage, site_type)


def _sample(n, true_rel, claimed_rel, seed=0):
    """n steps at D in [-0.3, -0.02]: errors N(0, true_rel |D|), confidence claiming claimed_rel."""
    rng = np.random.default_rng(seed)
    d = -rng.uniform(0.02, 0.3, n)
    d_hat = d + true_rel * np.abs(d) * rng.standard_normal(n)
    c = 1.0 / (1.0 + (claimed_rel / 0.1) ** 2)
    return d, d_hat, np.full(n, c)


def test_sigma_is_the_filters_mapping_and_inverts_the_estimators():
    c = np.array([1.0, 0.5, 0.2, 0.0, np.nan])
    rs = rel_sigma(c)
    assert rs[0] == 0.0 and rs[1] == pytest.approx(0.1) and rs[2] == pytest.approx(0.2)
    assert np.isinf(rs[3]) and np.isinf(rs[4])
    np.testing.assert_allclose(rs, confidence_rel_sigma(torch.tensor(c)).numpy())
    back = confidence_from_rel_std(torch.tensor([0.05, 0.3]), torch.tensor([-0.1, -0.1])).double().numpy()
    np.testing.assert_allclose(rel_sigma(back), [0.05, 0.3], rtol=1e-5)
    # scale: max(|D_hat|, |D|)
    np.testing.assert_allclose(predicted_sigma([0.5, 0.5], [-0.2, -0.05], [-0.1, -0.1]), [0.02, 0.01])


def test_hand_computed_coverage_and_abstentions():
    # c = 0.5: sigma_rel 0.1, D = -0.1 -> sigma 0.01 (scale max(|D_hat|, |D|))
    d = np.full(6, -0.1)
    d_hat = np.array([-0.105, -0.1, -0.115, -0.06, np.nan, -0.1])
    c = np.array([0.5, 0.5, 0.5, 0.5, 0.0, 0.0])
    # errs / sigma: 0.005/0.0105 <= 1; 0; 0.015/0.0115 in (1, 2]; 0.04/0.01 > 2; NaN; c = 0
    row = coverage_table(d, d_hat, c)["all"]
    assert (row["n_steps"], row["n_estimates"], row["n_nan"], row["n_zero_confidence"]) == (6, 4, 1, 1)
    assert row["cover_1sigma"] == pytest.approx(2 / 4) and row["cover_2sigma"] == pytest.approx(3 / 4)
    assert row["abstain_share"] == pytest.approx(2 / 6) and row["within_5_points"] is False
    # confidence 1 claims sigma 0: covered only when exact
    r1 = coverage_table([-0.1, -0.1], [-0.1, -0.1001], [1.0, 1.0])["all"]
    assert r1["cover_1sigma"] == pytest.approx(0.5)
    # nothing answered: coverage None, all abstained
    r0 = coverage_table([-0.1], [np.nan], [0.0])["all"]
    assert r0["cover_1sigma"] is None and r0["abstain_share"] == 1.0


def test_calibrated_sample_covers_68_95_and_overconfident_less():
    d, d_hat, c = _sample(20000, 0.1, 0.1)
    row = coverage_table(d, d_hat, c)["all"]
    # the scale max(|D_hat|, |D|) >= |D| makes it a little wider than the Gaussian's
    assert abs(row["cover_1sigma"] - 0.683) < 0.03 and abs(row["cover_2sigma"] - 0.954) < 0.02
    assert row["within_5_points"]
    d, d_hat, c = _sample(20000, 0.2, 0.1)  # claims half its real error
    over = coverage_table(d, d_hat, c)["all"]
    assert over["cover_1sigma"] < 0.45 and over["cover_2sigma"] < 0.75 and not over["within_5_points"]


def test_coverage_per_group_and_site_types():
    d1, h1, c1 = _sample(4000, 0.1, 0.1, seed=1)
    d2, h2, c2 = _sample(4000, 0.3, 0.1, seed=2)
    g = np.array(["craters"] * 4000 + ["rocky"] * 4000)
    tab = coverage_table(np.r_[d1, d2], np.r_[h1, h2], np.r_[c1, c2], g)
    assert list(tab) == ["craters", "rocky", "all"]
    assert tab["craters"]["cover_1sigma"] > 0.6 > 0.35 > tab["rocky"]["cover_1sigma"]
    assert tab["all"]["n_estimates"] == 8000
    assert [site_type(s) for s in ("A", "D", "G", "H", "F~2", "X")] == [
        "craters", "craters_rocks", "rocky", "featureless", "rocky", "other"]
    with pytest.raises(ValueError, match="groups"):
        coverage_table(d1, h1, c1, g)


def test_reliability_bins_follow_the_diagonal_only_when_calibrated():
    rng = np.random.default_rng(3)
    n = 30000
    d = -rng.uniform(0.05, 0.3, n)
    rel = rng.choice([0.03, 0.15, 0.4], n)
    c = 1.0 / (1.0 + (rel / 0.1) ** 2)
    good = d + rel * np.abs(d) * rng.standard_normal(n)
    bins = reliability_bins(d, good, c)
    assert [b["n"] > 0 for b in bins] == [True] * 3 and sum(b["n"] for b in bins) == n
    for b in bins:  # observed RMS / predicted RMS ~ 1 (a bit below: the scale includes |D_hat|)
        assert 0.75 < b["obs_rms_rel_err"] / b["pred_rms_rel_sigma"] < 1.1, b
    bad = d + 3 * rel * np.abs(d) * rng.standard_normal(n)
    for b in reliability_bins(d, bad, c):
        assert b["obs_rms_rel_err"] / b["pred_rms_rel_sigma"] > 1.5, b
    with pytest.raises(ValueError, match="edges"):
        reliability_bins(d, good, c, edges=[0.1, 0.05])


def test_risk_coverage_rises_when_confidence_ranks_errors():
    rng = np.random.default_rng(4)
    n = 1000
    d = np.full(n, -0.1)
    rel = np.linspace(0.01, 0.5, n)
    d_hat = d * (1 + rel * rng.choice([-1, 1], n))
    c = 1.0 / (1.0 + (rel / 0.1) ** 2)
    d_hat[:100] = np.nan  # abstentions: never kept
    rc = risk_coverage(d, d_hat, c, grid=[0.1, 0.5, 0.9, 1.0])
    m = rc["median_abs_rel_err"]
    assert rc["answered_share"] == pytest.approx(0.9)
    assert m[0] < m[1] < m[2] and m[3] is None
    assert m[0] == pytest.approx(np.median(rel[100:200]), rel=1e-9)
    assert rc["min_confidence"][0] == pytest.approx(c[199])
    shuffled = risk_coverage(d, d_hat, rng.permutation(c), grid=[0.1, 0.9])["median_abs_rel_err"]
    assert shuffled[0] > m[0]


def test_summary_over_a_batch_uses_scored_steps_only():
    d = np.full((2, 4), -0.1)
    d_hat = {"x": np.array([[-0.1, -0.1, -0.1, np.nan], [-0.2, -0.2, -0.2, -0.2]])}
    conf = {"x": np.array([[0.5, 0.5, 0.5, 0.0], [0.5, 0.5, 0.5, 0.5]])}
    scored = np.array([[False, True, True, True], [True, True, False, False]])
    s = calibration_summary(d, d_hat, conf, scored, ["A", "F"])
    cov = s["estimators"]["x"]["coverage"]
    assert cov["craters"]["n_steps"] == 3 and cov["craters"]["n_nan"] == 1
    assert cov["craters"]["cover_1sigma"] == 1.0 and cov["rocky"]["cover_1sigma"] == 0.0
    assert s["site_types"] == {"A": "craters", "F": "rocky"}
    with pytest.raises(ValueError, match="no confidence"):
        calibration_summary(d, d_hat, {}, scored, ["A", "F"])


PLUGIN = textwrap.dedent('''
    import torch

    class Noisy:
        """Truth times (1 + 0.1 N(0, 1)) at confidence 0.5 (claims a 10 % error), no events needed."""
        needs_events = False
        def __init__(self, batch_size, sensor_size=None, device="cpu", **kw):
            self.batch_size, self.device = batch_size, torch.device(device)
            self.gen = torch.Generator().manual_seed(0)
        def reset(self, mask=None):
            pass
        def update(self, events, t_us, truth=None):
            d = truth.divergence
            return (d * (1 + 0.1 * torch.randn(d.shape, generator=self.gen, dtype=d.dtype))).float()
        def confidence(self):
            return torch.full((self.batch_size,), 0.5)
''')


def test_cli_calibration_with_a_plugin(tmp_path, capsys):
    from dvsland.cli.main import main

    (tmp_path / "calplug.py").write_text(PLUGIN)
    out = tmp_path / "run"
    rc = main(["evaluate", "--estimators", f"mine={tmp_path / 'calplug.py'}:Noisy,oracle", "--sites", "A,F",
               "--max-steps", "120", "--warmup-steps", "1", "--calibration", "--scenarios", "none",
               "--out", str(out), "--set", "logging.tensorboard=false"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "Calibration" in printed and "mine" in printed
    cal = json.loads((out / "calibration.json").read_text())
    mine = cal["estimators"]["mine"]["coverage"]
    assert set(mine) == {"craters", "rocky", "all"}
    assert mine["all"]["n_estimates"] == mine["all"]["n_steps"] > 150
    assert 0.55 < mine["all"]["cover_1sigma"] < 0.85 and mine["all"]["cover_2sigma"] > 0.85
    assert (out / "calibration.txt").read_text().startswith("Calibration")
    assert (out / "calibration.png").stat().st_size > 10_000
    assert cal["estimators"]["mine"]["risk_coverage"]["answered_share"] == 1.0


def test_cli_calibration_of_a_recording(tmp_path, capsys):
    """A recording's evaluation records each estimate's confidence, so its calibration report is written."""
    import json
    from pathlib import Path

    from dvsland.cli.main import main

    data = Path(__file__).parent / "data"
    out = tmp_path / "r"
    rc = main(["evaluate", "paper", "--recording", str(data / "descent_A.npz"), "--estimators", "oracle,dpr,cmax",
               "--max-steps", "25", "--calibration", "--no-figures", "--quiet", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    cal = json.loads((out / "calibration.json").read_text())
    cov = cal["estimators"]["dpr"]["coverage"]["all"]
    assert cov["n_steps"] > 0 and cov["n_estimates"] + cov["n_nan"] + cov["n_zero_confidence"] == cov["n_steps"]
    # its sample holds cmax's structure diagnostic (the 'structure' calibration feature), not dpr's
    from dvsland.evaluate.calibration_report import read_calibration_sample

    s = read_calibration_sample(out)
    labels = [str(x) for x in s["labels"].tolist()]
    assert f"structure_{labels.index('cmax')}" in s and f"structure_{labels.index('dpr')}" not in s
    assert s[f"structure_{labels.index('cmax')}"].shape == s["d_true"].shape
