"""The figure helper (dvsland.report.style) and the figures built with it: units on every axis,
legends inside the saved file, shared contrast stretch, labelled tiles, text overlays."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from dvsland.report import style


def test_label_requires_units():
    plt = style.pyplot()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1], label="line")
    style.label(ax, "t [s]", "z [m]", "title", legend=True)
    assert ax.get_xlabel() == "t [s]" and ax.get_title() == "title" and ax.get_legend() is not None
    with pytest.raises(ValueError, match="xlabel 'time' has no unit"):
        style.label(ax, "time", "z [m]")
    with pytest.raises(ValueError, match="ylabel"):
        style.label(ax, None, "altitude")
    assert style.has_unit("count [-]") and not style.has_unit("count")
    plt.close(fig)


def test_save_keeps_an_outside_legend(tmp_path):
    plt = style.pyplot()
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.plot([0, 1], [0, 1], label="a rather long legend entry that sticks out")
    style.label(ax, "x [m]", "y [m]", legend="outside")
    fig.canvas.draw()
    legend_right = ax.get_legend().get_window_extent().x1
    assert legend_right > fig.bbox.x1  # outside the figure's own box ...
    p = style.save(fig, tmp_path / "f.png", dpi=100)
    assert Image.open(p).size[0] > 4 * 100  # ... and inside the saved file


def test_log_stretch_and_image_grid(tmp_path):
    frames = np.exp(np.random.default_rng(0).normal(size=(2, 3, 8, 8)))
    frames[1] *= 10.0  # a brighter row stays brighter on a shared stretch
    log, lo, hi = style.log_stretch(frames)
    assert log.shape == frames.shape and lo < hi
    np.testing.assert_allclose(np.quantile(log, [0.01, 0.995]), [lo, hi])
    fig = style.image_grid(log, ["1000 m", "50 m"], ["site A", "site B", "site C"], title="t", vmin=lo, vmax=hi)
    axes = fig.axes
    assert [a.get_title() for a in axes[:3]] == ["site A", "site B", "site C"]
    assert axes[0].get_ylabel() == "1000 m" and axes[3].get_ylabel() == "50 m"
    ims = [a.images[0] for a in axes[:6]]
    assert all(im.get_clim() == (lo, hi) for im in ims)  # one stretch for every tile
    assert axes[-1].get_ylabel() == "log irradiance [-]"  # the colorbar
    style.save(fig, tmp_path / "grid.png")
    with pytest.raises(ValueError, match="row_labels"):
        style.image_grid(log, ["a"], ["b", "c", "d"])
    with pytest.raises(ValueError, match=r"\(R, C, H, W\)"):
        style.image_grid(log[0], ["a"], ["b"])


def test_renderer_pairs_figure(tmp_path):
    rng = np.random.default_rng(1)
    pairs = [[(np.exp(rng.normal(size=(8, 8))), np.exp(rng.normal(size=(8, 8)))) for _ in range(2)] for _ in range(3)]
    p = style.renderer_pairs_figure(pairs, ["A", "E", "H"], [1000.0, 50.0], tmp_path / "cmp.png")
    assert p.is_file() and Image.open(p).size[0] > 400
    with pytest.raises(ValueError, match="need 3 sites and 2 altitudes"):
        style.renderer_pairs_figure(pairs, ["A"], [1000.0, 50.0], tmp_path / "x.png")


def test_annotate_image_draws_text():
    img = Image.new("L", (128, 64), color=128)
    style.annotate_image(img, "site A  1,000 m")
    a = np.asarray(img)
    assert (a == 0).any() and (a == 255).any() and (a[40:, :] == 128).all()


def test_polarity_legend():
    plt = style.pyplot()
    fig, ax = plt.subplots()
    leg = style.polarity_legend(ax)
    assert [t.get_text() for t in leg.get_texts()] == ["ON (brighter)", "OFF (darker)"]
    plt.close(fig)


def test_speed_vs_error_figure(tmp_path, monkeypatch):
    from dvsland.evaluate.report import plot_speed_vs_error

    seen = {}
    real_save = style.save

    def keep(fig, path, dpi=None):
        fig.canvas.draw()
        ax = fig.axes[0]
        seen["xticks"] = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
        seen["legend"] = [t.get_text() for t in ax.get_legend().get_texts()]
        seen["xlabel"], seen["ylabel"] = ax.get_xlabel(), ax.get_ylabel()
        return real_save(fig, path, dpi)

    monkeypatch.setattr(style, "save", keep)
    summary = {"sites": ["A", "D"], "device": "cpu", "estimators": {
        "dpr": {"ms_per_step_median": 1.3, "sites_A_G": {"median_abs_rel_err": 0.29}},
        "cmax[window_ms=300]": {"ms_per_step_median": 2.1, "sites_A_G": {"median_abs_rel_err": 0.05}}}}
    plot_speed_vs_error(summary, tmp_path / "s.png")
    assert len(seen["xticks"]) >= 3  # several tick labels, not one
    assert any(t.startswith("dpr: 1.3 CPU ms, 29.0 %") for t in seen["legend"])  # the time base is named
    assert any("cmax[window_ms=300]" in t for t in seen["legend"])
    assert any("target: 10 %" in t for t in seen["legend"])  # the dashed line is labelled
    assert "[ms]" in seen["xlabel"] and "CPU time" in seen["xlabel"] and "[%]" in seen["ylabel"]


def test_descent_gif_and_montage_are_labelled(tmp_path, monkeypatch):
    from dvsland.cli.main import main

    monkeypatch.setenv("DVSLAND_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "r"
    assert main(["render", "--sites", "A,H", "--altitudes", "1000,50", "--gif-frames", "3", "--out", str(out),
                 "--set", "camera.width_px=32", "--set", "camera.height_px=32", "--quiet"]) == 0
    gif = Image.open(out / "descent_A.gif")
    first = np.asarray(gif.convert("L"))
    assert first.shape[0] >= 256 and (first[:20, :100] == 255).any() and (first[:20, :100] == 0).any()
    mont = Image.open(out / "montage.png")
    assert mont.size[0] > 300 and mont.size[1] > 300
