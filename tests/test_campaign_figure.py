"""The campaign figure carries a title (preset/estimator/seeds) and a legend on both panels."""

import matplotlib
import numpy as np

matplotlib.use("Agg")


def test_campaign_figure_title_and_legends(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from dvsland.campaign.report import campaign_figure
    from dvsland.report.stats import group_stats

    runs = [{"site": s, "label": "set0", "estimator": "dpr", "outcome": "success" if k % 3 else "crash",
             "seed_index": k, "lowest_altitude_m": 50.0, "v_at_50m_mps": 1.0 + 0.1 * k, "fuel_used_kg": 1.0}
            for s in ("A", "D") for k in range(6)]
    by = ["site", "label", "estimator"]
    groups = group_stats(runs, by)
    seen = {}
    monkeypatch.setattr(plt, "close", lambda fig: seen.setdefault("fig", fig))
    out = campaign_figure(tmp_path / "c.png", runs, groups, by, meta={"n_seeds": 6, "preset": "paper"})
    assert out.is_file()
    fig = seen["fig"]
    title = fig._suptitle.get_text()
    assert "preset paper" in title and "dpr" in title and "6 seeds" in title
    ax1, ax2 = fig.axes
    for ax in (ax1, ax2):
        leg = ax.get_legend()
        assert leg is not None and leg.get_texts()
    labels = [t.get_text() for t in ax2.get_legend().get_texts()]
    assert "median" in labels and "one successful descent" in labels


def test_campaign_figure_draws_the_tables_median(tmp_path, monkeypatch):
    """An even number of landings per site: the figure's median bar is the table's median (the mean
    of the middle two), not the upper middle value."""
    import matplotlib.pyplot as plt

    from dvsland.campaign.report import campaign_figure
    from dvsland.report.stats import format_group_table, group_stats, median

    speeds = {"A": [1.5, 2.0, 2.06, 2.12], "D": [0.9, 1.1, 1.3, 1.7, 2.9, 3.0]}
    runs = [{"site": s, "label": "set0", "estimator": "dpr", "outcome": "success", "seed_index": k,
             "lowest_altitude_m": 50.0, "v_at_50m_mps": v, "fuel_used_kg": 1.0}
            for s, vs in speeds.items() for k, v in enumerate(vs)]
    by = ["site", "label", "estimator"]
    groups = group_stats(runs, by)
    seen = {}
    monkeypatch.setattr(plt, "close", lambda fig: seen.setdefault("fig", fig))
    campaign_figure(tmp_path / "c.png", runs, groups, by, meta={"n_seeds": 4})
    ax2 = seen["fig"].axes[1]
    bars = [ln for ln in ax2.get_lines() if ln.get_linestyle() == "-" and len(ln.get_ydata()) == 2]
    drawn = sorted(float(ln.get_ydata()[0]) for ln in bars)
    table = sorted(g["v50_mps_median"] for g in groups)
    assert drawn == table
    assert np.allclose(table, [1.5, 2.03])  # (1.3 + 1.7) / 2 and (2.0 + 2.06) / 2, not 1.7 and 2.06
    assert f"{median(speeds['A']):.2f}" in format_group_table(groups, by)


def test_campaign_figure_title_names_a_checkpoint():
    from dvsland.campaign.report import figure_title

    ck = {"file": "mine.pt", "sha256": "0123456789ab", "path": "/x/mine.pt"}
    runs = [{"site": "A", "estimator": "learned", "checkpoint": ck, "seed_index": 0}]
    assert "learned (mine.pt sha256:0123456789ab)" in figure_title(runs, {"n_seeds": 1})
    assert "sha256" not in figure_title([{"site": "A", "estimator": "dpr", "seed_index": 0}], {"n_seeds": 1})
