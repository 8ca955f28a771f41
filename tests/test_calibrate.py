"""Post-hoc confidence calibration (dvsland/estimators/calibrate.py): the pure map (shape, dtype,
monotone, identity bit for bit, abstentions kept, batched on any device), the fitter (a table fitted
on one synthetic sample brings a held-out one to 68 / 95 % coverage), the estimator wiring
(``estimator.calibration``: the step's confidence calibrated, D_hat untouched, errors naming the
key) and the shipped tables."""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from dvsland.config import load_config
from dvsland.estimators.calibrate import (CONFIG_KEY, RAW_KEY, SHIPPED_DIR, SHIPPED_SETS, CalibrationParams,
                                          apply_calibration_np, best_log10_scale, calibrate_confidence,
                                          calibrate_output, calibration_to_json, check_params, feature_values,
                                          fit_calibration, identity_params, load_calibration, params_to,
                                          resolve_calibration, shipped_calibrations)
from dvsland.estimators.factory import make_estimator
from dvsland.evaluate.calibration import coverage_table
from dvsland.events import Events


def _table(S, sigma_knots=(-2.0, -1.0), feature_knots=(0.0,), feature="none"):
    return CalibrationParams(torch.tensor(sigma_knots, dtype=torch.float32),
                             torch.tensor(feature_knots, dtype=torch.float32),
                             torch.tensor(S, dtype=torch.float32).reshape(len(feature_knots), len(sigma_knots)), feature)


CONF = torch.tensor([0.0, 1e-8, 0.01, 0.2, 0.5, 0.7, 0.93, 0.999, 1.0], dtype=torch.float32)


def test_shape_dtype_and_the_formula():
    p = _table([0.5, 0.5])  # a factor sqrt(10) on the sigma everywhere
    out = calibrate_confidence(CONF, p)
    assert out.shape == CONF.shape and out.dtype == torch.float32
    assert ((out >= 0) & (out <= 1)).all()
    # sigma_rel(c_cal) = sqrt(10) sigma_rel(c): c_cal = c / (c + 10 (1 - c))
    c = CONF.double()
    np.testing.assert_allclose(out.double().numpy()[1:-1], (c / (c + 10 * (1 - c))).numpy()[1:-1], rtol=1e-5)
    assert out[0] == 0 and out[-1] == 1
    # float64 input: a float32 answer; a batch of 2-D stays its shape
    assert calibrate_confidence(CONF.double(), p).dtype == torch.float32


def test_identity_table_changes_nothing_bit_for_bit():
    c = torch.rand(10_000, generator=torch.Generator().manual_seed(0))
    c[::7] = 0.0
    c[::11] = 1.0
    for p in (identity_params(), _table([0.0, 0.0, 0.0], (-3, -1, 0)),
              _table([[0.0], [0.0]], (-1.0,), (1.0, 3.0), "events")):
        f = torch.full_like(c, 2.5) if p.feature == "events" else None
        assert torch.equal(calibrate_confidence(c, p, f), c)


def test_map_is_monotone_in_the_raw_confidence():
    # a fitted-looking table: isotonic along sigma at each event knot (what the fitter guarantees)
    p = _table([[0.8, 0.4, 0.1, -0.2], [0.3, 0.2, 0.2, 0.0]], (-2.0, -1.5, -1.0, -0.5), (2.0, 3.5), "events")
    check_params(p)
    c = torch.linspace(0.0, 1.0, 5001)
    for n in (10.0, 300.0, 1000.0, 1e5):
        f = feature_values("events", n_events=torch.full_like(c, n))
        out = calibrate_confidence(c, p, f)
        assert (out[1:] >= out[:-1] * (1 - 1e-6)).all(), n


def test_fitter_makes_the_table_monotone_even_when_cells_disagree():
    rng = np.random.default_rng(3)
    n = 6000
    d = -rng.uniform(0.02, 0.3, n)
    claimed = 10 ** rng.uniform(-2, -0.5, n)
    true = np.where(claimed < 0.05, 5 * claimed, 0.2 * claimed)  # low claims 5x too low, high claims 5x too high
    d_hat = d + true * np.abs(d) * rng.standard_normal(n)
    c = 1 / (1 + (claimed / 0.1) ** 2)
    p, _ = fit_calibration(d, d_hat, c, "none", sigma_bins=8)
    y = p.sigma_knots + p.log10_scale[0]
    assert (y[1:] >= y[:-1] - 1e-6).all()
    out = calibrate_confidence(torch.linspace(0.01, 0.99, 999), p)
    assert (out[1:] >= out[:-1] * (1 - 1e-6)).all()  # non-decreasing up to float32 round-off (flat where pooled)
    assert out[-1] > out[0]


def test_abstentions_are_kept_and_d_hat_untouched():
    from dvsland.estimators.base import EstimateOut

    d = torch.tensor([-0.1, float("nan"), -0.2, -0.05])
    c = torch.tensor([0.5, 0.0, 0.0, 0.9])
    out = EstimateOut(d, c, {"confidence": c})
    p = _table([[1.0, 1.0], [-1.0, -1.0]], (-2.0, -1.0), (1.0, 3.0), "events")
    ev = Events(torch.tensor([0, 0, 3]), torch.tensor([1, 2, 3]), torch.tensor([1, 2, 3]),
                torch.tensor([1, 2, 3]), torch.tensor([1, 1, -1], dtype=torch.int8))
    got = calibrate_output(out, ev, 4, p)
    assert torch.equal(got.d_hat.nan_to_num(7.0), d.nan_to_num(7.0))
    assert got.confidence[1] == 0 and got.confidence[2] == 0  # NaN and c = 0 stay abstentions
    assert got.confidence[0] < c[0] and got.confidence[3] < c[3]  # few events: the +1 decade row
    assert torch.equal(got.diagnostics[RAW_KEY], c) and torch.equal(got.diagnostics["confidence"], got.confidence)
    assert calibrate_output(got, ev, 4, p) is got  # never twice
    assert calibrate_output(out, ev, 4, None) is out
    # NaN confidence (never returned by an estimator) stays NaN rather than becoming a claim
    assert torch.isnan(calibrate_confidence(torch.tensor([float("nan")]), _table([0.3, 0.3])))[0]


def test_batched_without_a_python_loop_on_every_device():
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    p = _table([[0.8, 0.4, 0.1], [0.3, 0.2, 0.0]], (-2.0, -1.5, -1.0), (2.0, 3.5), "events")
    c = torch.rand(4096, generator=torch.Generator().manual_seed(1))
    n = torch.randint(0, 20000, (4096,), generator=torch.Generator().manual_seed(2)).float()
    ref = calibrate_confidence(c, p, feature_values("events", n_events=n))
    for dev in devices:
        pd = params_to(p, dev)
        got = calibrate_confidence(c.to(dev), pd, feature_values("events", n_events=n.to(dev)))
        assert got.device.type == torch.device(dev).type
        torch.testing.assert_close(got.cpu(), ref)
    # element b depends on element b only (no mixing across the batch)
    one = calibrate_confidence(c[:1], p, feature_values("events", n_events=n[:1]))
    assert torch.equal(one, ref[:1])


def _synthetic(n, seed):
    """Steps with D in [-0.3, -0.02], an event count (10 to 10 000, log-uniform), a claimed relative
    sigma; the true error is 4x the claim at 10 events falling to 0.4x at 10 000 (log-linear):
    over-confident with few events, under-confident with many."""
    rng = np.random.default_rng(seed)
    d = -rng.uniform(0.02, 0.3, n)
    ne = np.round(10 ** rng.uniform(1, 4, n))
    claimed = 10 ** rng.uniform(-1.7, -0.7, n)
    true = claimed * 4.0 * 10 ** (-(np.log10(ne) - 1) / 3)
    d_hat = d + true * np.abs(d) * rng.standard_normal(n)
    c = 1 / (1 + (claimed / 0.1) ** 2)
    groups = np.where(ne < 300, "few", "many")
    return d, d_hat, c, ne, groups


def test_fitted_table_reaches_68_95_on_held_out_data():
    d, d_hat, c, ne, _ = _synthetic(20_000, seed=0)
    p, info = fit_calibration(d, d_hat, c, "events", ne, sigma_bins=6, feature_bins=6)
    assert info["n_estimates"] == 20_000
    d2, h2, c2, ne2, g2 = _synthetic(20_000, seed=1)  # held out
    before = coverage_table(d2, h2, c2, g2)
    assert before["few"]["cover_1sigma"] < 0.45 and before["many"]["cover_1sigma"] > 0.8
    after = coverage_table(d2, h2, apply_calibration_np(p, h2, c2, ne2), g2)
    for grp in ("few", "many", "all"):
        assert abs(after[grp]["cover_1sigma"] - 0.683) < 0.03, (grp, after[grp])
        assert abs(after[grp]["cover_2sigma"] - 0.954) < 0.03, (grp, after[grp])
    # without the feature one factor cannot serve both groups
    p0, _ = fit_calibration(d, d_hat, c, "none")
    no_f = coverage_table(d2, h2, apply_calibration_np(p0, h2, c2), g2)
    assert not no_f["few"]["within_5_points"] and not no_f["many"]["within_5_points"]


def test_best_scale_on_gaussian_errors():
    z = np.abs(np.random.default_rng(0).standard_normal(50_000)) * 3.0  # claimed sigma 3x too small
    s, gap = best_log10_scale(z)
    assert s == pytest.approx(np.log10(3.0), abs=0.01) and gap < 0.01


def _est_and_events(name, cfg):
    """An estimator of the config and 12 windows of an expanding random-dot scene (B = 2)."""
    g = torch.Generator().manual_seed(5)
    pts = (torch.rand(400, 2, generator=g) - 0.5) * 60
    wins = []
    for k in range(1, 13):
        bs, xs, ys, ts = [], [], [], []
        for j in range(20):
            t = (k - 1) * 100_000 + 5_000 * j + 1
            s = 1.0 + 0.02 * (k - 1 + j / 20)
            xy = pts * s + 63.5
            ok = (xy[:, 0] >= 0) & (xy[:, 0] < 128) & (xy[:, 1] >= 0) & (xy[:, 1] < 128)
            for b in range(2):
                n = int(ok.sum())
                bs.append(torch.full((n,), b))
                xs.append(xy[ok, 0].long())
                ys.append(xy[ok, 1].long())
                ts.append(torch.full((n,), t))
        N = sum(len(x) for x in bs)
        wins.append(Events(torch.cat(bs), torch.cat(xs), torch.cat(ys), torch.cat(ts),
                           torch.ones(N, dtype=torch.int8), sort=True))
    return make_estimator(cfg, 2, "cpu", name=name), wins


def _fly(est, wins):
    ds, cs = [], []
    for k, ev in enumerate(wins, 1):
        ds.append(est.update(ev, k * 100_000))
        cs.append(est.confidence())
    return torch.stack(ds), torch.stack(cs)


def _write_table(path, estimator, S=0.5):
    obj = calibration_to_json(_table([S, S]), estimator, {"configs": ["test"], "seeds": [9]})
    Path(path).write_text(json.dumps(obj))
    return str(path)


@pytest.mark.parametrize("name", ["cmax", "dpr"])
def test_estimator_calibration_from_the_config(tmp_path, name):
    base_est, wins = _est_and_events(name, load_config("paper"))
    d0, c0 = _fly(base_est, wins)
    path = _write_table(tmp_path / "t.json", name, S=0.5)
    est, _ = _est_and_events(name, load_config("paper", [f"estimator.calibration={path}"]))
    d1, c1 = _fly(est, wins)
    assert torch.equal(d0.nan_to_num(9.0), d1.nan_to_num(9.0))  # D_hat never changes
    assert (c0 > 0).any()
    expect = c0 / (c0 + 10 * (1 - c0))
    torch.testing.assert_close(c1, torch.where(c0 > 0, expect, c0))
    assert torch.equal(est._last.diagnostics[RAW_KEY], c0[-1])
    # the identity table flies exactly the uncalibrated estimator
    idp = _write_table(tmp_path / "id.json", name, S=0.0)
    est_id, _ = _est_and_events(name, load_config("paper", [f"estimator.calibration={idp}"]))
    d2, c2 = _fly(est_id, wins)
    assert torch.equal(c2, c0) and torch.equal(d2.nan_to_num(9.0), d0.nan_to_num(9.0))


def test_object_api_plugin_is_calibrated_too(tmp_path):
    from dvsland.estimators import DivergenceEstimator

    class Plain(DivergenceEstimator):
        abstain = None

        def reset(self, mask=None):
            pass

        def update(self, events, t_us, truth=None):
            self._d = torch.full((self.batch_size,), -0.1)
            return self._d.clone()

        def confidence(self):
            return torch.full((self.batch_size,), 0.5)

    est = Plain(2, (128, 128))
    est.update(None, 100_000)
    assert torch.equal(est.confidence(), torch.full((2,), 0.5))
    est.calibration = _table([0.5, 0.5])
    est.update(None, 200_000)
    torch.testing.assert_close(est.confidence(), torch.full((2,), 0.5 / (0.5 + 10 * 0.5)))


def test_bad_values_name_the_key(tmp_path):
    cfg = lambda v: load_config("paper", [f"estimator.calibration={v}"])  # noqa: E731
    bad = {"nonsense": "neither", str(tmp_path / "missing.json"): "no such calibration file",
           "ideal": None}
    (tmp_path / "broken.json").write_text("{not json")
    bad[str(tmp_path / "broken.json")] = "cannot read"
    (tmp_path / "other.json").write_text(json.dumps({"format": "something-else"}))
    bad[str(tmp_path / "other.json")] = "not a dvsland calibration table"
    wrong = _write_table(tmp_path / "for_dpr.json", "dpr")
    bad[wrong] = "fitted for estimator 'dpr', not 'cmax'"
    obj = json.loads(Path(wrong).read_text())
    obj["estimator"], obj["log10_scale"] = "cmax", [[0.1, 0.2, 0.3]]
    (tmp_path / "shape.json").write_text(json.dumps(obj))
    bad[str(tmp_path / "shape.json")] = "log10_scale must have shape"
    for value, what in bad.items():
        if value == "ideal":  # a shipped set the estimator has no table for
            with pytest.raises(ValueError, match=CONFIG_KEY) as ei:
                make_estimator(cfg(value), 2, "cpu", name="oracle")
            assert "no shipped 'ideal' calibration for estimator 'oracle'" in str(ei.value)
            continue
        with pytest.raises(ValueError, match=CONFIG_KEY) as ei:
            make_estimator(cfg(value), 2, "cpu", name="cmax")
        assert what in str(ei.value), (value, str(ei.value))
    assert resolve_calibration("none", "cmax") is None and resolve_calibration("", "cmax") is None


def test_cli_refuses_a_bad_calibration_before_the_run_folder(tmp_path, capsys):
    from dvsland.cli.main import main

    out = tmp_path / "run"
    rc = main(["evaluate", "--estimators", "cmax,learned", "--sites", "A", "--max-steps", "5", "--out", str(out),
               "--set", "estimator.calibration=cmax_ideal"])
    assert rc == 2
    assert "estimator.calibration: 'cmax_ideal' was fitted for estimator 'cmax', not 'learned'" in capsys.readouterr().err
    assert not out.exists()


PLUGIN = textwrap.dedent('''
    import torch
    from dvsland.estimators import DivergenceEstimator

    class Noisy(DivergenceEstimator):
        """The true D with 20 % relative noise, claiming 5 % (over-confident by 4x)."""
        needs_events = False

        def __init__(self, batch_size, sensor_size, device="cpu", seed=0, **kw):
            super().__init__(batch_size, sensor_size, device)
            self.g = torch.Generator().manual_seed(int(seed))

        def reset(self, mask=None):
            pass

        def update(self, events, t_us, truth=None):
            d = truth.divergence.to(torch.float32)
            self._d = d * (1 + 0.2 * torch.randn(d.shape, generator=self.g))
            return self._d.clone()

        def confidence(self):
            return torch.full((self.batch_size,), 0.8)
''')


def test_cli_fits_a_table_and_flies_it(tmp_path, capsys):
    """evaluate --calibration --fit-calibration on one seed; the table flown on another seed
    through estimator.calibration brings the plug-in to 68 / 95 %."""
    from dvsland.cli.main import main

    (tmp_path / "noisy.py").write_text(PLUGIN)
    spec = f"mine={tmp_path / 'noisy.py'}:Noisy"
    common = ["evaluate", "--estimators", spec, "--sites", "A,F", "--max-steps", "300", "--warmup-steps", "1",
              "--calibration", "--scenarios", "none", "--no-figures", "--quiet", "--set", "logging.tensorboard=false"]
    fit_dir = tmp_path / "fit"
    assert main(common + ["--fit-calibration", "--out", str(fit_dir), "--set", "simulation.seed=1"]) == 0
    table = fit_dir / "calibration_table_mine.json"
    obj = json.loads(table.read_text())
    assert obj["fit"]["seeds"] == [1] and obj["fit"]["configs"] == ["paper"]
    assert (fit_dir / "calibration_sample.npz").is_file()
    before = json.loads((fit_dir / "calibration.json").read_text())["estimators"]["mine"]["coverage"]["all"]
    assert before["cover_1sigma"] < 0.3
    judge = tmp_path / "judge"
    assert main(common + ["--out", str(judge), "--set", "simulation.seed=2",
                          "--set", f"estimator.calibration={table}"]) == 0
    after = json.loads((judge / "calibration.json").read_text())["estimators"]["mine"]["coverage"]["all"]
    assert abs(after["cover_1sigma"] - 0.683) < 0.06 and abs(after["cover_2sigma"] - 0.954) < 0.04, after
    # the script fits the same table from the run folder and judges the held-out one
    import runpy
    import sys

    out = tmp_path / "script.json"
    argv = sys.argv
    try:
        sys.argv = ["fit_calibration.py", str(fit_dir), "--estimator", "mine", "--out", str(out), "--judge", str(fit_dir)]
        with pytest.raises(SystemExit) as ei:
            runpy.run_path(str(Path(__file__).parents[1] / "scripts" / "fit_calibration.py"), run_name="__main__")
        assert ei.value.code == 0
    finally:
        sys.argv = argv
    assert json.loads(out.read_text())["log10_scale"] == obj["log10_scale"]
    # fitting a calibrated run is refused
    capsys.readouterr()
    assert main(common + ["--fit-calibration", "--out", str(tmp_path / "x"), "--set", f"estimator.calibration={table}"]) == 2
    assert "--fit-calibration fits raw confidences" in capsys.readouterr().err


def test_shipped_tables_load_and_are_valid():
    shipped = shipped_calibrations()
    for est in ("cmax", "learned"):
        for s in SHIPPED_SETS:
            assert f"{est}_{s}" in shipped, f"{est}_{s}.json is not shipped"
    for name, path in shipped.items():
        p, obj = load_calibration(path)
        check_params(p)
        owner, sensor = name.rsplit("_", 1)  # an estimator, or a shipped checkpoint's file stem
        est = obj["estimator"]
        assert sensor in SHIPPED_SETS and (owner == est or obj["fit"]["checkpoint"].startswith(f"{owner}.pt "))
        fit = obj["fit"]
        assert fit["seeds"] and 0 not in fit["seeds"], "shipped tables are fitted on seeds other than the evaluation's 0"
        assert fit["n_estimates"] > 5000
        assert resolve_calibration(sensor, est, fit.get("checkpoint"))[1]["fit"] == fit
        # monotone in the raw confidence at every feature knot
        y = p.sigma_knots[None, :] + p.log10_scale
        assert (y[:, 1:] >= y[:, :-1] - 1e-5).all(), name
    # a wheel carries them
    text = (Path(__file__).parents[1] / "pyproject.toml").read_text()
    assert '"calibration/*.json"' in text
    assert SHIPPED_DIR.name == "calibration"


@pytest.mark.parametrize("checkpoint,sensors", [("cnn_both", SHIPPED_SETS), ("spiking8", ("ideal",))])
def test_a_shipped_checkpoint_with_its_own_tables_gets_them(checkpoint, sensors):
    """``ideal`` / ``realistic`` pick ``<checkpoint stem>_<set>.json`` where it ships (cnn_both both,
    spiking8 ideal), else ``<estimator>_<set>.json`` (the shipped CNN's)."""
    for sensor in sensors:
        own = make_estimator(load_config("paper", [f"estimator.calibration={sensor}",
                                                   f"estimator.learned.checkpoint={checkpoint}"]), 2, "cpu",
                             name="learned")
        assert own.calibration is not None
        plain = make_estimator(load_config("paper", [f"estimator.calibration={sensor}"]), 2, "cpu", name="learned")
        assert not torch.equal(own.calibration.log10_scale, plain.calibration.log10_scale)
    with pytest.raises(ValueError, match="was fitted on the checkpoint learned_cnn_both.pt"):
        resolve_calibration("learned_cnn_both_realistic", "learned", "learned_cnn.pt sha256:4dade5de1845")


@pytest.mark.parametrize("checkpoint", ["spiking", "spiking8"])
def test_a_table_is_refused_for_another_checkpoint(checkpoint):
    """A checkpoint without a realistic table of its own is refused the shipped CNN's."""
    est = make_estimator(load_config("paper", ["estimator.calibration=realistic"]), 2, "cpu", name="learned")
    assert est.calibration is not None
    cfg = load_config("paper", ["estimator.calibration=realistic", f"estimator.learned.checkpoint={checkpoint}"])
    with pytest.raises(ValueError, match="estimator.calibration: 'realistic' was fitted on the checkpoint learned_cnn.pt"):
        make_estimator(cfg, 2, "cpu", name="learned")


def test_a_table_fitted_with_other_parameters_warns():
    cfg = load_config("paper", ["estimator.calibration=ideal"])
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        make_estimator(cfg, 2, "cpu", name="cmax")  # the parameters it was fitted with: silent
    cfg = load_config("paper", ["estimator.calibration=ideal", "estimator.cmax.n_grid=31"])
    with pytest.warns(RuntimeWarning, match=r"estimator.calibration: 'ideal' was fitted with n_grid=21; this cmax runs with n_grid=31"):
        make_estimator(cfg, 2, "cpu", name="cmax")


def test_no_host_sync():
    """The map reads nothing back to the host (counted on the CPU, dvsland.bench.syncs), alone and
    in the loop: a calibrated estimator syncs as often per step as the uncalibrated one."""
    from dvsland.bench.syncs import SyncCounter, loop_syncs
    from dvsland.estimators.base import EstimateOut

    p = _table([[0.8, 0.4, 0.1], [0.3, 0.2, 0.0]], (-2.0, -1.5, -1.0), (2.0, 3.5), "events")
    ev = Events(torch.tensor([0, 0, 2]), torch.tensor([1, 2, 3]), torch.tensor([1, 2, 3]),
                torch.tensor([1, 2, 3]), torch.tensor([1, 1, -1], dtype=torch.int8))
    out = EstimateOut(torch.tensor([-0.1, float("nan"), -0.2]), torch.tensor([0.5, 0.0, 0.9]), {})
    with SyncCounter() as c:
        calibrate_output(out, ev, 3, p)
    assert c.calls == {}
    raw = loop_syncs("learned", steps=3, sites="D")
    cal = loop_syncs("learned", steps=3, sites="D", overrides=["estimator.calibration=ideal"])
    assert cal["syncs_per_step"] == raw["syncs_per_step"] and cal["by_call"] == raw["by_call"]


def test_structure_feature_reads_the_diagnostic():
    """The ``structure`` feature is log10 of the estimator's ``structure`` diagnostic (floored at
    1e-3, 0 where NaN); a table reading it calibrates an EstimateOut by its diagnostics, and names
    what is missing without them."""
    from dvsland.estimators.base import EstimateOut

    st = torch.tensor([0.2, 1.0, float("nan"), 0.0])
    f = feature_values("structure", structure=st)
    assert torch.allclose(f, torch.tensor([math.log10(0.2), 0.0, 0.0, -3.0]))
    with pytest.raises(ValueError, match="'structure' calibration feature needs the estimator's 'structure'"):
        feature_values("structure")
    p = _table([[0.6, 0.6], [-0.4, -0.4]], (-2.0, -1.0), (-1.0, 0.0), "structure")
    d = torch.tensor([-0.1, -0.1, float("nan")])
    c = torch.tensor([0.5, 0.5, 0.0])
    out = EstimateOut(d, c, {"structure": torch.tensor([0.1, 1.0, float("nan")])})
    cal = calibrate_output(out, None, 3, p)
    # structure 0.1 -> feature -1: factor 10^0.6 (wider sigma, lower confidence); 1.0 -> 0: 10^-0.4
    assert cal.confidence[0] < 0.5 < cal.confidence[1] and cal.confidence[2] == 0.0
    assert torch.equal(cal.diagnostics["confidence_raw"], c) and torch.equal(cal.d_hat.nan_to_num(9), d.nan_to_num(9))
    with pytest.raises(ValueError, match="needs the estimator's 'structure' diagnostic"):
        calibrate_output(EstimateOut(d, c, {}), None, 3, p)


def test_structure_feature_fits_where_events_cannot():
    """Two kinds of steps with the same raw confidence and event count whose errors differ by 4x, told
    apart by their structure: a table on ``structure`` brings both near 68 / 95 %, one on ``events`` cannot."""
    g = np.random.default_rng(3)
    n = 8000
    c = np.full(n, 0.5)  # a claimed sigma of 10 %
    kind = g.random(n) < 0.5
    structure = np.where(kind, 0.3, 2.0) * np.exp(0.05 * g.standard_normal(n))
    rel = np.where(kind, 0.2, 0.05) * g.standard_normal(n)
    d_true = -np.full(n, 0.1)
    d_hat = d_true * (1 + rel)
    ne = np.full(n, 3000)
    groups = np.where(kind, "wide", "narrow")
    rows = {}
    for feat in ("structure", "events"):
        p, _ = fit_calibration(d_true, d_hat, c, feat, ne, structure=structure, sigma_bins=4, feature_bins=4)
        rows[feat] = coverage_table(d_true, d_hat, apply_calibration_np(p, d_hat, c, ne, structure), groups)
    assert all(rows["structure"][g]["within_5_points"] for g in ("wide", "narrow", "all"))
    assert not any(rows["events"][g]["within_5_points"] for g in ("wide", "narrow"))


def test_evaluation_sample_holds_cmax_structure(tmp_path):
    """``evaluate --calibration`` writes ``structure_i`` for an estimator whose diagnostics give it
    (cmax), not for one without (oracle), and a 'structure' table fits from it."""
    from dvsland.cli.main import main
    from dvsland.evaluate.calibration_report import fit_from_samples, read_calibration_sample

    run = tmp_path / "ev"
    assert main(["evaluate", "paper", "--estimators", "cmax,oracle", "--sites", "D", "--max-steps", "60",
                 "--scenarios", "none", "--calibration", "--threads", "1", "--no-figures", "--quiet",
                 "--set", "logging.tensorboard=false", "--out", str(run)]) == 0
    s = read_calibration_sample(run)
    labels = [str(x) for x in s["labels"].tolist()]
    i, j = labels.index("cmax"), labels.index("oracle")
    assert f"structure_{i}" in s and f"structure_{j}" not in s
    st = s[f"structure_{i}"]
    answered = np.isfinite(s[f"d_hat_{i}"]) & (s[f"confidence_{i}"] > 0)
    assert st.shape == s["d_true"].shape and np.isfinite(st[answered]).all() and answered.any()
    obj = fit_from_samples([s], "cmax", feature="structure", feature_bins=2, min_count=5)
    assert obj["feature"] == "structure"
    with pytest.raises(ValueError, match="holds no structure for 'oracle'"):
        fit_from_samples([s], "oracle", feature="structure")


def test_shipped_cmax_table_flies_on_its_structure():
    """The shipped ``cmax_ideal`` table reads cmax's ``structure`` diagnostic: in the loop the raw
    confidence is kept beside the calibrated one, abstentions stay 0, D_hat is unchanged, and the
    map costs no host sync."""
    from dvsland.bench.syncs import loop_syncs
    from dvsland.sim import init_state, loop_step
    from dvsland.stages import build_stages

    assert load_calibration(shipped_calibrations()["cmax_ideal"])[0].feature == "structure"
    outs = {}
    for cal in ("none", "ideal"):
        stages = build_stages(load_config("paper", ["estimator.name=cmax", "render.threads=1",
                                                    f"estimator.calibration={cal}"]), "D")
        st = init_state(stages)
        for _ in range(25):
            st, out = loop_step(stages, st)
        outs[cal] = out
    raw, cal = outs["none"], outs["ideal"]
    assert torch.equal(raw.d_est.nan_to_num(9), cal.d_est.nan_to_num(9)) and torch.isfinite(cal.d_est).any()
    assert torch.equal(cal.diagnostics()["confidence_raw"], raw.d_conf.to(torch.float32))
    assert not torch.equal(cal.d_conf, raw.d_conf) and (cal.d_conf[~torch.isfinite(cal.d_est)] == 0).all()
    a = loop_syncs("cmax", steps=2, sites="D")
    b = loop_syncs("cmax", steps=2, sites="D", overrides=["estimator.calibration=ideal"])
    assert a["syncs_per_step"] == b["syncs_per_step"]
