"""TensorBoard through SummaryWriter: flight time on the step axis (ms) and on the relative axis,
HParams (experiment on top, one session per descent with its outcome metrics), error histograms,
one event file per run folder, a fresh folder when --out is reused; events and evaluate too."""

from __future__ import annotations

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from dvsland.report.tensorboard import OUTCOME_METRICS, flight_step, fresh_log_dir
from dvsland.sim import simulate

SIM = ["simulation.t_max_s=3", "logging.figures=false", "logging.scalar_every_s=0.5"]


def _acc(path):
    return EventAccumulator(str(path), size_guidance={"scalars": 0, "histograms": 0, "tensors": 0}).Reload()


def _raw(path) -> dict:
    """{tag: [Summary.Value]} of the one event file in ``path`` (the HParams summaries carry only
    metadata, which EventAccumulator leaves out)."""
    from tensorboard.backend.event_processing.event_file_loader import LegacyEventFileLoader

    (f,) = [p for p in path.iterdir() if p.name.startswith("events.out.tfevents")]
    out = {}
    for ev in LegacyEventFileLoader(str(f)).Load():
        for v in ev.summary.value:
            out.setdefault(v.tag, []).append(v)
    return out


def _plugin(value):
    from tensorboard.plugins.hparams import plugin_data_pb2

    return plugin_data_pb2.HParamsPluginData.FromString(value.metadata.plugin_data.content)


def _event_files(path):
    return sorted(p.name for p in path.iterdir() if p.name.startswith("events.out.tfevents"))


@pytest.fixture(scope="module")
def oracle_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("tb") / "run"
    r = simulate(None, estimator="oracle", sites="D", out=out, quiet=True,
                 overrides=SIM + ["estimator.oracle.noise_rel=0.1"])
    return r


def test_flight_step():
    assert flight_step(0.0) == 0 and flight_step(93.1) == 93100 and flight_step(0.1 * 3) == 300


def test_scalars_against_flight_time(oracle_run):
    acc = _acc(oracle_run.run_dir / "tb" / "D_Kp5e6-n5")
    alt = acc.Scalars("altitude_m")
    steps = [e.step for e in alt]
    assert steps[:4] == [0, 500, 1000, 1500]  # ms of flight, every scalar_every_s = 0.5 s
    assert alt[0].value == pytest.approx(4000.0)
    # relative time (wall - first wall) is flight time too
    rel = np.array([e.wall_time - alt[0].wall_time for e in alt])
    np.testing.assert_allclose(rel, np.array(steps) / 1000.0, atol=1e-3)
    tr = oracle_run.traces
    np.testing.assert_allclose([e.value for e in alt], tr["z_m"][[s // 100 for s in steps], 0], rtol=1e-6)


def test_error_histograms_and_one_event_file_per_run(oracle_run):
    tb = oracle_run.run_dir / "tb"
    for run in ("D_Kp5e6-n5", "D_Kp4e6-n10"):
        assert len(_event_files(tb / run)) == 1
        h = _acc(tb / run).Histograms("divergence/rel_error")
        assert h and all(e.histogram_value.num > 0 for e in h)
        # oracle with 10 % relative noise: the spread of the relative error is about 0.1
        tot = sum(e.histogram_value.num for e in h)
        sq = sum(e.histogram_value.sum_squares for e in h)
        assert 0.05 < (sq / tot) ** 0.5 < 0.2
    assert len(_event_files(tb)) == 1


def test_hparams_one_session_per_descent(oracle_run):
    tb = oracle_run.run_dir / "tb"
    top = _raw(tb)
    exp = _plugin(top["_hparams_/experiment"][0]).experiment
    names = {h.name for h in exp.hparam_infos}
    assert {"site", "setting", "kp_n_per_s", "n_bin", "seed_index", "estimator"} <= names
    assert {m.name.tag for m in exp.metric_infos} == set(OUTCOME_METRICS)
    for run in oracle_run.runs:
        folder = tb / run["run"].replace("/", "_")
        ssi = _plugin(_raw(folder)["_hparams_/session_start_info"][0]).session_start_info
        assert ssi.hparams["setting"].string_value == run["label"]
        assert ssi.hparams["kp_n_per_s"].number_value == run["kp"]
        assert ssi.hparams["estimator"].string_value == "oracle"
        acc = _acc(folder)
        t_end = acc.Scalars("outcome/t_end_s")[0]
        assert t_end.value == pytest.approx(run["t_end_s"]) and t_end.step == flight_step(run["t_end_s"])
        assert acc.Scalars("outcome/success")[0].value == float(run["outcome"] == "success")
        assert 0.0 < acc.Scalars("outcome/median_abs_rel_err")[0].value < 0.2


def test_custom_scalars_layout_and_text(oracle_run):
    top = _acc(oracle_run.run_dir / "tb")
    tags = set(top.Tags()["tensors"])
    assert {"config/text_summary", "results/text_summary", "custom_scalars__config__"} <= tags


def test_reused_out_is_refused_and_tensorboard_never_appends(tmp_path):
    from dvsland.report.tensorboard import TensorBoardLogger
    from dvsland.runs import RunDirError

    out = tmp_path / "again"
    simulate(None, estimator="oracle", sites="D", out=out, quiet=True, overrides=SIM[:2])
    with pytest.raises(RunDirError, match="already holds a run"):
        simulate(None, estimator="oracle", sites="D", out=out, quiet=True, overrides=SIM[:2])
    # a folder reused anyway (make_run_dir(..., overwrite=True)): the logger takes a fresh tb-2/
    tb = TensorBoardLogger(out / "tb", ["D/Kp5e6-n5"], 0.1)
    tb.close()
    assert tb.log_dir == out / "tb-2" and len(_event_files(out / "tb-2" / "D_Kp5e6-n5")) == 1
    assert len(_event_files(out / "tb" / "D_Kp5e6-n5")) == 1
    assert fresh_log_dir(out / "tb") == out / "tb-3"
    assert fresh_log_dir(tmp_path / "new") == tmp_path / "new"


def test_events_and_evaluate_write_tensorboard(tmp_path):
    from dvsland.cli.main import main

    small = ["--set", "camera.width_px=32", "--set", "camera.height_px=32", "--quiet"]
    assert main(["events", "--site", "D", "--from-m", "1000", "--to-m", "990", "--out", str(tmp_path / "ev"),
                 *small]) == 0
    acc = EventAccumulator(str(tmp_path / "ev" / "tb"), size_guidance={"images": 0, "scalars": 0}).Reload()
    assert {"altitude_m", "events/per_step"} <= set(acc.Tags()["scalars"])
    assert {"events/frame", "frames/last"} <= set(acc.Tags()["images"])
    alt = acc.Scalars("altitude_m")
    assert alt[0].value == pytest.approx(1000.0, abs=0.5) and alt[-1].value <= 990.0
    assert all(b.step > a.step for a, b in zip(alt, alt[1:]))  # flight time, increasing

    assert main(["evaluate", "--estimators", "oracle", "--sites", "D", "--max-steps", "4", "--warmup-steps", "0",
                 "--no-figures", "--out", str(tmp_path / "eval"), *small]) == 0
    tb = tmp_path / "eval" / "tb"
    assert sorted(p.name for p in tb.iterdir() if p.is_dir()) == ["oracle", "truth"]
    truth = _acc(tb / "truth").Scalars("divergence/site_D")
    est = _acc(tb / "oracle").Scalars("divergence/site_D")
    assert [e.step for e in truth] == [0, 100, 200, 300, 400]
    np.testing.assert_allclose([e.value for e in est], [e.value for e in truth[-len(est):]], rtol=1e-5)
    ora = _acc(tb / "oracle")
    assert ora.Scalars("eval/median_abs_rel_err")[0].value == pytest.approx(0.0, abs=1e-6)
    assert _plugin(_raw(tb / "oracle")["_hparams_/session_start_info"][0]).session_start_info.hparams[
        "estimator"].string_value == "oracle"
    assert "_hparams_/experiment" in _raw(tb)
