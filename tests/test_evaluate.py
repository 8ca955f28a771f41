"""Open-loop evaluation: trajectory, schedule, metrics, a tiny run, outputs and the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dvsland.config import load_config
from dvsland.evaluate import (BANDS, ZoomTextureFrames, band_metrics, closed_form_descents, divergence_metrics,
                              evaluate, format_table, segment_schedule, write_outputs)
from dvsland.evaluate.run import parse_estimator_spec


@pytest.fixture(scope="module")
def cfg(paper_yaml_module):
    # the text's c^2 = 0.5 descents (configs/paper.yaml flies the released code's c*c = 0.25)
    return load_config(paper_yaml_module.parent / "paper_eq2.yaml")


@pytest.fixture(scope="module")
def paper_yaml_module():
    from pathlib import Path

    return Path(__file__).resolve().parents[1] / "configs" / "paper.yaml"




def test_closed_form_descents_paper_times(cfg):
    d = closed_form_descents(cfg)
    assert d.sites == list("ABCDEFGHI")
    # closed form: A-C reach 50 m at ~92.9 s, D-I at ~71.1 s
    last_a = d.t_s[d.valid[0]][-1]
    last_d = d.t_s[d.valid[3]][-1]
    assert 92.7 <= last_a <= 93.0 and 70.9 <= last_d <= 71.2
    assert d.altitude_m[0, 0] == 10000.0 and d.divergence[0, 0] == pytest.approx(-0.02)
    assert (d.divergence[d.valid] < 0).all()
    short = closed_form_descents(cfg, ["B", "E"], max_steps=7)
    assert short.n_steps == 7 and short.altitude_m.shape == (2, 8)
    with pytest.raises(ValueError, match="site"):
        closed_form_descents(cfg, ["Z"])


def test_segment_schedule():
    assert segment_schedule(10) == [range(1, 11)]
    assert segment_schedule(10, 3, 2) == [range(1, 4), range(7, 10)]
    assert segment_schedule(10, 4, 1) == [range(1, 11)]
    with pytest.raises(ValueError, match="stride"):
        segment_schedule(10, 3, 0)


def test_metrics_against_hand_values():
    d_true = np.array([-0.1, -0.1, -0.2, -0.2, -0.1])
    d_hat = np.array([-0.1, -0.105, -0.26, np.nan, -0.05])
    m = divergence_metrics(d_hat, d_true)
    assert m["n_steps"] == 5 and m["coverage"] == pytest.approx(0.8)
    # |rel| = 0, 0.05, 0.3, 0.5 -> median 0.175
    assert m["median_abs_rel_err"] == pytest.approx(0.175)
    assert m["rmse"] == pytest.approx(math.sqrt((0 + 0.005 ** 2 + 0.06 ** 2 + 0.05 ** 2) / 4))
    assert m["within_10"] == pytest.approx(2 / 5) and m["within_20"] == pytest.approx(2 / 5)
    empty = divergence_metrics(np.array([]), np.array([]))
    assert empty["n_steps"] == 0 and math.isnan(empty["coverage"])
    none = divergence_metrics(np.array([np.nan]), np.array([-0.1]))
    assert none["coverage"] == 0 and math.isnan(none["median_abs_rel_err"]) and none["within_10"] == 0
    b = band_metrics(d_hat, d_true, np.array([3000.0, 1000.0, 100.0, 100.0, 2500.0]))
    assert [k for k, _, _ in BANDS] == list(b)
    assert b["> 2 km"]["n_steps"] == 2 and b["< 500 m"]["coverage"] == pytest.approx(0.5)


def test_target_label_names_the_sites_run():
    from dvsland.evaluate.run import target_label

    assert target_label(list("ABCDEFG")) == "A-G"
    assert target_label(list("ABCDEFGHI")) == "A-G"
    assert target_label(["D", "A"]) == "A,D"
    assert target_label(["A", "D", "H"]) == "A,D"
    assert target_label(["H", "I"]) == "none"


def test_speed_figure_axis_names_the_sites_run(tmp_path, monkeypatch):
    from dvsland.evaluate.report import plot_speed_vs_error
    from dvsland.report import style

    seen = {}
    orig = style.save

    def keep(fig, path, **kw):
        seen["ylabel"] = fig.axes[0].get_ylabel()
        return orig(fig, path, **kw)

    monkeypatch.setattr(style, "save", keep)
    summary = {"sites": ["A", "D"], "target_label": "A,D", "device": "cpu",
               "estimators": {"dpr": {"ms_per_step_median": 2.0, "sites_A_G": {"median_abs_rel_err": 0.05}}}}
    plot_speed_vs_error(summary, tmp_path / "s.png")
    assert "sites A,D" in seen["ylabel"] and "A-G" not in seen["ylabel"]


def test_parse_estimator_spec():
    assert parse_estimator_spec("dpr") == ("dpr", "dpr", {})
    label, name, over = parse_estimator_spec("cmax[window_ms=300;n_grid=21;dither=false]")
    assert name == "cmax" and over == {"window_ms": 300, "n_grid": 21, "dither": False}
    with pytest.raises(ValueError, match="key=value"):
        parse_estimator_spec("cmax[window_ms]")


def test_evaluate_small_run_and_outputs(cfg, tmp_path, one_thread):
    frames = ZoomTextureFrames(2, (128, 128), cfg.camera.fov_deg, texture_px=512, seed=3)
    res = evaluate(cfg, ["oracle", "dpr", "cmax[window_ms=300;n_grid=7;n_refine=1;max_events=1000]"],
                   sites=["A", "D"], max_steps=10, warmup_steps=2, frame_source=frames, progress=False)
    s = res.summary
    assert s["sites"] == ["A", "D"] and s["trajectory"] == "closed_form"
    assert res.scored.sum() == 2 * 8
    o = s["estimators"]["oracle"]["all_sites"]
    assert o["median_abs_rel_err"] < 1e-6 and o["within_10"] == 1 and o["coverage"] == 1
    for name in res.d_hat:
        assert len(res.ms_per_step[name]) == 10
        assert not np.isinf(res.d_hat[name]).any()
    assert (res.n_events[:, 1:] > 0).all()
    table = format_table(s)
    assert "dpr" in table and "> 2 km" in table
    # only A and D ran: the aggregate row and the band heading name them, never "A-G"
    assert s["target_label"] == "A,D"
    assert "A-G" not in table and "(sites A,D)" in table
    assert any(line.startswith("oracle") and " A,D " in line for line in table.splitlines())
    paths = write_outputs(res, tmp_path)
    data = json.loads(paths["json"].read_text())
    assert set(data["estimators"]) == set(res.d_hat)
    assert paths["speed_vs_error"].stat().st_size > 1000 and paths["traces_png"].exists()
    npz = np.load(paths["traces"])
    assert npz["d_hat_dpr"].shape == (2, 11)


@pytest.mark.parametrize("integrator", ["exact", "euler"])
def test_evaluation_flies_the_closed_form_on_loop_step(cfg, integrator, one_thread):
    """The evaluation descents fly on loop_step with the tracking thrust: the altitudes are the closed
    form's (to rounding), the truth is the loop's v / z (Euler's velocity is the forward difference),
    and the oracle, reading that truth, scores zero."""
    import copy

    c = copy.deepcopy(cfg)
    c.dynamics.integrator = integrator
    res = evaluate(c, ["oracle"], sites=["A", "D"], max_steps=300, warmup_steps=2, progress=False)
    s = res.summary
    assert s["flight"].startswith("loop_step") and s["integrator"] == integrator
    assert s["trajectory_max_rel_dz"] < 1e-12
    ref = closed_form_descents(c, ["A", "D"], max_steps=300)
    sc = res.scored
    assert sc.sum() == 2 * (300 - 2)
    rel = np.abs(res.descents.divergence[sc] / ref.divergence[sc] - 1.0)
    assert rel.max() < (1e-4 if integrator == "exact" else 3e-3)  # Euler: D of the next step's motion
    assert s["estimators"]["oracle"]["all_sites"]["median_abs_rel_err"] < 1e-6
    assert (res.n_events[:, 1:] == 0).all()  # the oracle needs no events: none were made


def test_tracking_thrust_lands_on_the_profile():
    """One loop step with tracking_thrust reaches the profile's next altitude (exact) or, with the
    Euler step, the velocity that reaches the one after (and start_velocity the first)."""
    import torch

    from dvsland.config import load_config
    from dvsland.evaluate.reference import start_velocity, tracking_thrust
    from dvsland.sim import init_state, loop_step
    from dvsland.stages import build_stages

    for integrator in ("exact", "euler", "substeps"):
        c = load_config(None, ["estimator.name=oracle", f"dynamics.integrator={integrator}", "dynamics.substeps=4"])
        stages = build_stages(c, "A,D")  # B = 4: two sites x two settings
        dt = stages.settings.dt_s
        t = torch.arange(6, dtype=torch.float64) * dt
        z0 = torch.tensor([[5000.0], [5000.0], [900.0], [40.0]], dtype=torch.float64)
        rate = torch.tensor([[-0.03], [-0.3], [0.05], [0.5]], dtype=torch.float64)  # descents and climbs
        z = z0 * torch.exp(rate * t)  # constant D
        m = torch.full((4,), 1e4, dtype=torch.float64)
        v0 = start_velocity(stages.dynamics, z[:, 0], rate[:, 0] * z[:, 0], z[:, 1], m, dt)
        state = init_state(stages, z_m=z[:, 0], v_mps=v0, m_kg=m)
        for k in range(3):
            u = tracking_thrust(stages, state, z[:, k + 1], z[:, k + 2])
            assert (u > 0).all()
            state, out = loop_step(stages, state, thrust=u)
            state = state._replace(active=torch.ones_like(state.active))  # a climb reads as an ascent
            assert torch.allclose(state.z_m, z[:, k + 1], rtol=1e-12, atol=0), (integrator, k)


def test_evaluate_bad_args(cfg):
    with pytest.raises(ValueError, match="estimators"):
        evaluate(cfg, [], frame_source=lambda a, s: None)
    with pytest.raises(ValueError, match="unknown estimator"):
        evaluate(cfg, ["nope"], sites=["A"], max_steps=2, frame_source=ZoomTextureFrames(1, texture_px=64),
                 progress=False)


def test_cli_evaluate_quick(tmp_path, monkeypatch, capsys):
    from dvsland.cli.main import main
    import dvsland.evaluate.run as run_mod

    # no terrain renderer in the default suite: swap in the synthetic frames
    orig = run_mod.evaluate

    def fake(cfg, estimators, sites=None, **kw):
        kw["frame_source"] = ZoomTextureFrames(len(sites or cfg.simulation.sites), texture_px=256)
        return orig(cfg, estimators, sites, **kw)

    monkeypatch.setattr("dvsland.evaluate.evaluate", fake)
    rc = main(["evaluate", "--estimators", "oracle,dpr", "--sites", "A", "--max-steps", "4", "--warmup-steps", "1",
               "--out", str(tmp_path / "run"), "--no-figures"])
    assert rc == 0
    assert (tmp_path / "run" / "evaluation.json").exists() and (tmp_path / "run" / "config.yaml").exists()
    assert "oracle" in capsys.readouterr().out


def test_cli_evaluate_scenarios(tmp_path, monkeypatch, capsys):
    """--scenarios flies the named hard scenarios after the descents: their table is printed and in
    table.txt, their metrics in evaluation.json and their traces in traces.npz."""
    from dvsland.cli.main import main
    import dvsland.evaluate.run as run_mod

    orig = run_mod.evaluate

    def fake(cfg, estimators, sites=None, **kw):
        kw["frame_source"] = ZoomTextureFrames(2, texture_px=256)
        return orig(cfg, estimators, sites, **kw)

    monkeypatch.setattr("dvsland.evaluate.evaluate", fake)
    rc = main(["evaluate", "--estimators", "oracle", "--sites", "A", "--max-steps", "3", "--warmup-steps", "1",
               "--scenarios", "hover_start", "--out", str(tmp_path / "run"), "--no-figures"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "hover_start" in out and "speeding up 1-4 s" in out
    assert "hover_start" in (tmp_path / "run" / "table.txt").read_text()
    js = json.loads((tmp_path / "run" / "evaluation.json").read_text())
    assert js["scenarios"]["metrics"]["oracle"]["hover_start"]["after 1 s"]["n_steps"] == 80
    npz = np.load(tmp_path / "run" / "traces.npz")
    assert npz["scenario_d_hat_oracle_hover_start"].shape == npz["scenario_t_s"].shape
    assert main(["evaluate", "--scenarios", "nope", "--max-steps", "2", "--out", str(tmp_path / "r2")]) != 0
    assert "unknown scenario 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "r2").exists()
