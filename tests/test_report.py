"""Run outputs: summary table, results.json, traces.npz, figures, TensorBoard image helpers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dvsland.report import format_table, read_results_json, write_results_json, write_traces_npz
from dvsland.report.tensorboard import counts_to_rgb, draw_centroids, frame_to_rgb, run_folder_name


def _run(**kw):
    r = {"run": "A/Kp5e6-n5", "site": "A", "label": "Kp5e6-n5", "kp": 5e6, "n_bin": 5, "estimator": "oracle",
         "outcome": "success", "t_end_s": 93.1, "z_end_m": 49.4, "v_end_mps": -11.7, "lowest_altitude_m": 49.4,
         "fuel_used_kg": 560.0, "max_thrust_n": 4.47e5, "loop_gain": 125.0, "held_steps": 0,
         "z0_m": 1e4, "v0_mps": -200.0}
    r.update(kw)
    return r


def test_table_text_and_markdown():
    runs = [_run(), _run(run="H/Kp4e6-n10", site="H", label="Kp4e6-n10", outcome="crash", lowest_altitude_m=812.3,
                         max_thrust_n=2.123e11)]
    text = format_table(runs)
    lines = text.splitlines()
    assert lines[0].split()[:4] == ["run", "outcome", "t_end", "[s]"]
    for unit in ("t_end [s]", "lowest [m]", "v_end [m/s]", "fuel [kg]", "λ [1/s]", "held [steps]"):
        assert unit in lines[0], unit
    assert "H/Kp4e6-n10" in lines[3] and "812.3" in lines[3] and "crash" in lines[3]
    assert "447.0 kN" in lines[2] and "212300.0 MN" not in lines[3] and "212.3 GN" in lines[3]
    assert "outcomes: crash 1, success 1" in lines
    legend = "\n".join(lines[lines.index("outcomes: crash 1, success 1") + 1:])
    for col in ("t_end [s]:", "lowest [m]:", "v_end [m/s]:", "max thrust:", "λ [1/s]:", "held [steps]:"):
        assert col in legend, col
    assert "success = reached z <= 50 m" in legend and "crash = |D|" in legend and "0.5 1/s" in legend
    md = format_table(runs, markdown=True, with_legend=False)
    assert md.startswith("| run | outcome") and md.count("\n") == 3
    assert "columns:" in format_table(runs, markdown=True)


@pytest.mark.parametrize("n, text", [(None, "-"), (950.0, "950 N"), (1e5, "100.0 kN"), (2.123e8, "212.3 MN"),
                                     (-3e6, "-3.0 MN")])
def test_format_force(n, text):
    from dvsland.report.table import format_force

    assert format_force(n) == text


def test_results_json_nan_is_null(tmp_path):
    p = write_results_json(tmp_path / "results.json", [_run(z_end_m=float("nan"))], status="complete",
                           wall_time_s=np.float64(1.5))
    d = read_results_json(p)
    assert d["runs"][0]["z_end_m"] is None and d["wall_time_s"] == 1.5 and d["status"] == "complete"
    assert not (tmp_path / "results.json.tmp").exists()
    json.loads(p.read_text())  # strict JSON (no NaN tokens)


def test_traces_npz_roundtrip(tmp_path):
    tr = {"z_m": np.arange(6.0).reshape(3, 2), "run_label": np.asarray(["A/x", "B/y"])}
    p = write_traces_npz(tmp_path / "traces.npz", tr)
    back = np.load(p)
    np.testing.assert_array_equal(back["z_m"], tr["z_m"])
    assert list(back["run_label"]) == ["A/x", "B/y"]


def test_image_helpers():
    assert run_folder_name("A/Kp5e6-n5/s1") == "A_Kp5e6-n5_s1"
    rgb = frame_to_rgb(np.random.default_rng(0).random((16, 20)))
    assert rgb.shape == (16, 20, 3) and rgb.dtype == np.uint8
    counts = np.zeros((2, 16, 20))
    counts[0, 3, 4] = 5  # ON (Events.to_count_image channel 0) -> red
    counts[1, 7, 8] = 5  # OFF (channel 1) -> blue
    ev = counts_to_rgb(counts)
    assert ev[3, 4, 0] == 255 and ev[3, 4, 2] == 0
    assert ev[7, 8, 2] == 255 and ev[7, 8, 0] == 0
    out = draw_centroids(np.zeros((16, 20, 3), np.uint8), np.array([[4.0, 3.0], [np.nan, np.nan], [100.0, 1.0]]))
    assert tuple(out[3, 4]) == (0, 255, 0) and out.sum() > 0


def test_figures_written(tmp_path):
    from dvsland.sim import simulate

    r = simulate(None, estimator="oracle", sites="D", out=tmp_path / "fig", quiet=True,
                 overrides=["logging.tensorboard=false", "simulation.t_max_s=10"])
    figs = sorted(p.name for p in (r.run_dir / "figures").glob("*.png"))
    assert figs == ["descent_D_Kp4e6-n10.png", "descent_D_Kp5e6-n5.png", "lowest_altitude.png"]
    assert all((r.run_dir / "figures" / f).stat().st_size > 5000 for f in figs)
    assert not math.isnan(r.timings_s["figures"])


def test_descent_figure_labels_and_thrust_unit(tmp_path, monkeypatch):
    from dvsland.report import figures, style

    n = 5
    tr = {"t_s": np.arange(n)[:, None] * 0.1, "z_m": np.linspace(4000, 3900, n)[:, None],
          "v_mps": np.full((n, 1), -100.0), "d_true": np.full((n, 1), -0.025), "d_est": np.full((n, 1), -0.03),
          "d_filtered": np.full((n, 1), -0.028), "thrust_n": np.array([[1e4], [3.4e7], [0.0], [0.0], [0.0]]),
          "active": np.array([[True]] * (n - 1) + [[False]])}
    seen = {}
    real_savefig = None

    def grab(fig, path, **kw):
        seen["labels"] = [a.get_ylabel() for a in fig.axes] + [fig.axes[-1].get_xlabel()]
        seen["title"] = fig._suptitle.get_text()
        return real_savefig(fig, path, **kw)

    plt = style.pyplot()
    real_savefig = plt.Figure.savefig
    monkeypatch.setattr(plt.Figure, "savefig", lambda self, path, **kw: grab(self, path, **kw))
    figures.descent_figure(tr, 0, _run(run="D/x", loop_gain=200.0), tmp_path / "d.png")
    assert seen["labels"] == ["altitude z [m]", "velocity v [m/s]", "divergence D [1/s]", "thrust [MN]",
                              "flight time t [s]"]
    assert "loop gain λ = 200 1/s" in seen["title"]
    assert all(style.has_unit(label) for label in seen["labels"])


def _two_descents():
    """Traces of two runs (columns): run 0 flies 60 steps with the closed form, D estimates far
    outside the axes and MN thrust; run 1 flies 25 steps, without z0 (no closed form), no outliers
    and kN thrust. Times in s, altitudes in m, D in 1/s, thrust in N."""
    n = 61
    rng = np.random.default_rng(3)
    t = np.arange(n) * 0.5
    active = np.zeros((n, 2), bool)
    active[:60, 0], active[:25, 1] = True, True
    d_true = np.stack([np.linspace(-0.02, -0.05, n), np.linspace(-0.1, -0.2, n)], 1)
    d_est = d_true + rng.normal(0.0, 0.003, (n, 2))
    d_est[[5, 40], 0] = [3.0, -4.0]  # run 0 only: beyond the axes, marked on the edge
    tr = {"t_s": np.stack([t, t], 1), "active": active, "d_true": d_true, "d_est": d_est, "d_filtered": d_est * 0.9,
          "z_m": np.stack([np.linspace(1e4, 800, n), np.linspace(3e3, 2e3, n)], 1),
          "v_mps": np.stack([np.linspace(-200, -20, n), np.linspace(-80, -60, n)], 1),
          "thrust_n": np.stack([np.full(n, 2e6), np.full(n, 4e4)], 1)}
    for k in ("z_m", "v_mps", "d_true", "d_est", "d_filtered", "thrust_n"):
        tr[k][26:, 1] = np.nan  # run 1 ended
    runs = [_run(run="A/x", estimator="dpr", outcome="ascent", t_end_s=30.0, lowest_altitude_m=800.0),
            _run(run="B/y", estimator="dpr", outcome="crash", t_end_s=12.5, lowest_altitude_m=2000.0,
                 loop_gain=None, z0_m=None)]
    return tr, runs


def test_reused_descent_figure_matches_a_fresh_one(tmp_path, monkeypatch):
    """write_figures draws every descent on one reused figure: the second descent must not keep the
    first one's lines, outside-the-axes markers, legend entries, colours or limits, and its PNG is
    the one a fresh figure gives, pixel for pixel."""
    from PIL import Image

    from dvsland.report import figures

    tr, runs = _two_descents()
    seen = []
    real_save = figures.save_atomic

    def record(fig, path, **kw):
        seen.append([([t.get_text() for t in a.get_legend().get_texts()], [ln.get_color() for ln in a.lines],
                      a.get_xlim(), a.get_ylim(), a.get_ylabel()) for a in fig.axes])
        return real_save(fig, path, **kw)

    monkeypatch.setattr(figures, "save_atomic", record)
    fig = figures._descent_axes()
    try:
        for b, run in enumerate(runs):
            figures.descent_figure(tr, b, run, tmp_path / f"reused{b}.png", _fig=fig)
    finally:
        figures._plt().close(fig[0])
    figures.descent_figure(tr, 1, runs[1], tmp_path / "fresh1.png")
    first, reused, fresh = seen
    assert any("beyond the axes" in t for t in first[2][0]) and "closed form" in first[0][0]
    assert reused == fresh
    assert reused[0][0] == ["altitude"] and reused[1][0] == ["velocity"] and reused[3][4] == "thrust [kN]"
    assert not any("beyond the axes" in t for t in reused[2][0]) and reused[0][2][1] < 15.0
    a, f = (np.asarray(Image.open(tmp_path / n)) for n in ("reused1.png", "fresh1.png"))
    np.testing.assert_array_equal(a, f)
