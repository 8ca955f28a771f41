"""Reports that agree with themselves: one time base (CPU ms, wall beside) in the evaluation, the
checkpoint (file name and content hash) of a trained estimator in every table, figure title and
JSON of an evaluation, a recording's table that names its estimators, the descent figure's D panel
that clips nothing silently and shows the filtered D."""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from dvsland.config import load_config
from dvsland.evaluate import ZoomTextureFrames, evaluate, evaluate_recording, format_table, write_outputs

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "tests" / "data"
SHIPPED_CNN = REPO / "dvsland" / "estimators" / "learned" / "learned_cnn.pt"


@pytest.fixture(scope="module")
def cfg():
    return load_config(REPO / "configs" / "paper_eq2.yaml")


def test_checkpoint_identity_is_the_files_sha256(tmp_path):
    from dvsland.report.checkpoint import checkpoint_identity, checkpoint_text, estimator_checkpoint

    a, b = tmp_path / "a.pt", tmp_path / "b.pt"
    a.write_bytes(b"weights one")
    b.write_bytes(b"weights two")
    ia, ib = checkpoint_identity(a), checkpoint_identity(b)
    assert ia["file"] == "a.pt" and ia["sha256"] == hashlib.sha256(b"weights one").hexdigest()[:12]
    assert ia["sha256"] != ib["sha256"]
    assert checkpoint_text(ia) == f"a.pt sha256:{ia['sha256']}" and checkpoint_text(None) == ""
    a.write_bytes(b"weights one, retrained")  # new content: a new hash (the cache keys on size and time)
    assert checkpoint_identity(a)["sha256"] == hashlib.sha256(b"weights one, retrained").hexdigest()[:12]
    cfg = load_config("paper")
    assert estimator_checkpoint(cfg, "dpr") is None and estimator_checkpoint(cfg, "cmax") is None
    shipped = estimator_checkpoint(cfg, "learned")
    assert shipped["file"] == "learned_cnn.pt"
    assert shipped["sha256"] == hashlib.sha256(SHIPPED_CNN.read_bytes()).hexdigest()[:12]
    cfg.estimator.learned.checkpoint = str(b)
    assert estimator_checkpoint(cfg, "learned")["sha256"] == ib["sha256"]


@pytest.fixture(scope="module")
def learned_run(cfg, tmp_path_factory):
    """A short evaluation of dpr and the learned CNN (from a copy named mine.pt) on site A."""
    import torch

    torch.set_num_threads(1)
    tmp = tmp_path_factory.mktemp("learned")
    mine = tmp / "mine.pt"
    shutil.copyfile(SHIPPED_CNN, mine)
    c = copy.deepcopy(cfg)
    c.estimator.learned.checkpoint = str(mine)
    frames = ZoomTextureFrames(1, (128, 128), c.camera.fov_deg, texture_px=512, seed=3)
    res = evaluate(c, ["dpr", "learned"], sites=["A"], max_steps=8, warmup_steps=2, frame_source=frames,
                   progress=False)
    return res, mine, hashlib.sha256(mine.read_bytes()).hexdigest()[:12], tmp


def test_learned_evaluation_names_its_checkpoint_everywhere(learned_run, monkeypatch):
    from dvsland.report import style

    res, mine, digest, tmp = learned_run
    ck = res.summary["estimators"]["learned"]["checkpoint"]
    assert ck["file"] == "mine.pt" and ck["sha256"] == digest and Path(ck["path"]) == mine
    assert "checkpoint" not in res.summary["estimators"]["dpr"]
    table = format_table(res.summary)
    assert f"learned = mine.pt sha256:{digest}" in table.splitlines()[1]
    titles = []
    real_save = style.save

    def keep(fig, path, dpi=None):
        titles.append(" ".join([fig._suptitle.get_text() if fig._suptitle else ""]
                               + [ax.get_title() for ax in fig.axes]))
        return real_save(fig, path, dpi)

    monkeypatch.setattr(style, "save", keep)
    paths = write_outputs(res, tmp / "out")
    assert len(titles) == 2 and all(f"mine.pt sha256:{digest}" in t for t in titles)
    data = json.loads(paths["json"].read_text())
    assert data["estimators"]["learned"]["checkpoint"]["sha256"] == digest
    assert data["checkpoints"] == {"learned": f"mine.pt sha256:{digest}"}
    assert f"mine.pt sha256:{digest}" in paths["table"].read_text()


def test_evaluation_times_are_cpu_ms_with_wall_beside(cfg, monkeypatch):
    """The time base is the process CPU time of the estimate stage (as dvsland bench): a process
    clock that advances 7 ms per reading gives 7 CPU ms per update whatever the wall clock says."""
    import dvsland.evaluate.run as run_mod

    ticks = iter(np.arange(0, 10.0, 0.007))
    monkeypatch.setattr(run_mod.time, "process_time", lambda: float(next(ticks)))
    frames = ZoomTextureFrames(1, (64, 64), cfg.camera.fov_deg, texture_px=256, seed=1)
    res = evaluate(cfg, ["oracle"], sites=["A"], max_steps=5, warmup_steps=1, frame_source=frames,
                   progress=False)
    e = res.summary["estimators"]["oracle"]
    assert res.summary["time_base"] == "CPU" and e["time_base"] == "CPU"
    assert e["cpu_ms_per_step_median"] == pytest.approx(7.0) and e["ms_per_step_median"] == pytest.approx(7.0)
    assert e["wall_ms_per_step_median"] is not None and e["wall_ms_per_step_median"] != pytest.approx(7.0)
    assert np.allclose(res.ms_per_step["oracle"], 7.0)
    table = format_table(res.summary)
    head = next(line for line in table.splitlines() if line.startswith("estimator") and "ms" in line)
    assert "CPU ms med" in head and "wall ms med" in head
    assert "CPU ms per update" in table


def test_recording_table_names_the_estimators_and_leaves_out_empty_tables():
    """A recording: one row per estimator (no row named after the file or 'none'), a header about
    the recording, no altitude-band table without altitude, CPU ms."""
    cfg = load_config("paper")
    res = evaluate_recording(cfg, DATA / "descent_A.npz", ["dpr", "oracle"], warmup_steps=5, max_steps=20,
                             progress=False)
    table = format_table(res.summary)
    lines = table.splitlines()
    assert lines[0].startswith("Open-loop divergence error of each estimator on the recording descent_A.npz")
    assert "oracle descents" not in table and "closed-form" not in table
    rows = [line.split()[0] for line in lines[3:] if line.strip() and not line.startswith(("-", " "))]
    rows = rows[:rows.index("By")] if "By" in rows else rows[:2]
    assert rows == ["dpr", "oracle"]
    assert not any(line.split()[:2] in (["dpr", "none"], ["oracle", "none"], ["dpr", "descent_A"])
                   for line in lines)
    alt = res.descents.altitude_m[0]
    if np.isfinite(alt[res.scored[0]]).any():  # the file has altitude: only bands with steps
        band_head = next(line for line in lines if line.startswith("By altitude band"))
        assert "recording" in band_head
        assert "> 2 km" not in table  # a 1 km descent has no step above 2 km
    assert "CPU ms med" in table


def test_recording_without_altitude_has_no_band_table(monkeypatch):
    from dvsland.evaluate.report import _band_lines

    summary = {"sites": ["rec"], "trajectory": "recording", "estimators": {"dpr": {
        "bands_all_sites": {b: {"n_steps": 0, "median_abs_rel_err": None, "within_10": None, "coverage": None}
                            for b in ("> 2 km", "2 km - 500 m", "< 500 m")}}}}
    assert _band_lines(summary) == []


def _descent_traces(n=120):
    t = np.arange(n) * 0.1
    z = np.linspace(1000.0, 50.0, n)
    v = np.full(n, -8.0)
    d_true = v / z
    rng = np.random.default_rng(0)
    d_est = d_true + 0.01 * rng.standard_normal(n)
    d_est[[10, 50]] = [3.0, -4.0]  # two wild estimates
    d_filt = d_true + 0.002
    tr = {"t_s": t, "z_m": z, "v_mps": v, "d_true": d_true, "d_est": d_est, "d_filtered": d_filt,
          "thrust_n": np.full(n, 5e3), "active": np.ones(n, dtype=bool)}
    return {k: np.asarray(a)[:, None] for k, a in tr.items()}


def test_descent_figure_d_panel_shows_filtered_and_marks_outliers(tmp_path, monkeypatch):
    """The raw estimates and the filtered D are separate legend entries; the truth sets the view;
    the two wild estimates are drawn on the axes' edges, counted in the legend, not dropped."""
    import matplotlib.pyplot as plt

    from dvsland.report.figures import descent_figure

    tr = _descent_traces()
    run = {"run": "A/x", "estimator": "learned", "outcome": "success", "t_end_s": 11.9,
           "lowest_altitude_m": 50.0, "loop_gain": 1.0, "checkpoint": {"file": "m.pt", "sha256": "0123456789ab"}}
    seen = {}
    monkeypatch.setattr(plt, "close", lambda fig: seen.setdefault("fig", fig))
    descent_figure(tr, 0, run, tmp_path / "d.png")
    fig = seen["fig"]
    assert "m.pt sha256:0123456789ab" in fig._suptitle.get_text()
    ax = fig.axes[2]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "D true" in labels and "D estimated (raw)" in labels
    assert any(lab.startswith("D filtered") for lab in labels)
    assert any("2 beyond the axes" in lab for lab in labels)
    lo, hi = ax.get_ylim()
    assert lo <= tr["d_true"].min() and hi >= tr["d_true"].max()  # the truth in view
    assert hi < 1.0 and lo > -1.0  # the two outliers do not flatten it
    edge = [ln for ln in ax.get_lines() if ln.get_marker() in ("^", "v") and len(ln.get_ydata())]
    ys = sorted(float(y) for ln in edge for y in ln.get_ydata())
    assert ys == pytest.approx([lo, hi])  # each outlier on the edge it passed
    filt = next(ln for ln in ax.get_lines() if str(ln.get_label()).startswith("D filtered"))
    assert np.allclose(filt.get_ydata(), tr["d_filtered"][:, 0])


def test_simulate_table_and_lowest_chart_name_a_checkpoint(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from dvsland.report.figures import lowest_altitude_chart
    from dvsland.report.table import format_table as sim_table

    ck = {"file": "m.pt", "sha256": "0123456789ab"}
    runs = [{"run": "A/s", "site": "A", "label": "s", "estimator": "learned", "checkpoint": ck,
             "outcome": "success", "t_end_s": 90.0, "lowest_altitude_m": 50.0, "v_end_mps": -2.0,
             "fuel_used_kg": 100.0, "max_thrust_n": 1e5, "z0_m": 1e4}]
    assert "checkpoint m.pt sha256:0123456789ab" in sim_table(runs)
    runs_dpr = [dict(runs[0], estimator="dpr", checkpoint=None)]
    assert "checkpoint" not in sim_table(runs_dpr, with_legend=False)
    seen = {}
    monkeypatch.setattr(plt, "close", lambda fig: seen.setdefault("fig", fig))
    lowest_altitude_chart(runs, tmp_path / "l.png")
    assert "m.pt sha256:0123456789ab" in seen["fig"].axes[0].get_title()


def test_error_table_has_no_duplicate_aggregate_rows():
    """A and H: rows A, H and all (no 'A' aggregate repeating row A); A and D: A, D and 'A,D' (no
    'all' repeating it); one recording: one row per estimator."""
    from dvsland.evaluate.report import _error_lines

    m = {"n_steps": 1, "coverage": 1.0, "median_abs_rel_err": 0.1, "rmse": 0.01, "within_10": 1.0,
         "within_20": 1.0, "bias_rel": 0.0}

    def rows(sites, tl):
        e = {"sites": {s: m for s in sites}, "sites_A_G": m, "all_sites": m}
        lines = _error_lines({"sites": sites, "target_label": tl, "estimators": {"dpr": e}})
        return [line.split()[1] for line in lines[3:] if line.startswith("dpr")]

    assert rows(["A", "H"], "A") == ["A", "H", "all"]
    assert rows(["A", "D"], "A,D") == ["A", "D", "A,D"]
    assert rows(["H", "I"], "none") == ["H", "I", "all"]
    assert rows(list("ABCDEFGHI"), "A-G") == list("ABCDEFGHI") + ["A-G", "all"]


def test_simulate_with_a_learned_estimator_records_its_checkpoint(tmp_path):
    """results.json of a learned run names the checkpoint in its header and in every run."""
    from dvsland import simulate
    from dvsland.report.checkpoint import file_sha256

    res = simulate("montecarlo_efference", estimator="learned", sites="D", quiet=True, out=tmp_path / "run",
                   overrides=["simulation.n_seeds=1", "simulation.t_max_s=2", "dispersion.terrain_variants=1"])
    doc = json.loads((res.run_dir / "results.json").read_text())
    ck = doc["checkpoint"]
    assert ck["file"] == "learned_cnn.pt" and ck["sha256"] == file_sha256(ck["path"])
    assert all(r["checkpoint"] == ck for r in doc["runs"])
    oracle = simulate("paper", estimator="oracle", sites="A", quiet=True, out=tmp_path / "oracle",
                      overrides=["simulation.t_max_s=1"])
    doc = json.loads((oracle.run_dir / "results.json").read_text())
    assert doc["checkpoint"] is None and "checkpoint" not in doc["runs"][0]
