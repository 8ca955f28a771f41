"""The paper's reported pattern beside the flown one (dvsland.report.paper_pattern)."""

from __future__ import annotations

import pytest

from dvsland.config.schema import SITE_NAMES
from dvsland.report import paper_pattern as pp


def _runs(outcomes):
    runs = []
    for site, (o1, t1, low1), (o2, t2, low2) in outcomes:
        for lab, o, t, low in (("Kp5e6-n5", o1, t1, low1), ("Kp4e6-n10", o2, t2, low2)):
            z0, v0 = (1e4, -200.0) if site in "ABC" else (4e3, -100.0)
            runs.append({"site": site, "label": lab, "run": f"{site}/{lab}", "outcome": o, "t_end_s": t,
                         "lowest_altitude_m": low, "z0_m": z0, "v0_mps": v0})
    return runs


def test_transcription_says_only_what_the_paper_says():
    p = pp.load_paper_pattern()
    assert p["descents"] == 18 and p["reached_50m"] == 2 and p["reached_50m_runs"] == "unknown"
    assert set(p["sites"]) == set(SITE_NAMES)
    assert [p["sites"][s]["pattern"] for s in "ABCDEFGHI"] == ["late", "early", "late"] + ["best"] * 4 + ["jittery"] * 2
    assert p["sites"]["H"]["crashes"] == 1 and p["sites"]["I"]["crashes"] == "unknown"
    assert all(v["lowest_altitude_m"] == "unknown" for v in p["sites"].values())


def test_classify_by_the_closed_form_time():
    # c2 = 0.25, D site: tau0 = 40 s, t(50 m) = 40 (1 - (50/4000)^0.25) / 0.25 = 106.4 s; half = 53.2 s
    run = {"outcome": "ascent", "t_end_s": 60.0, "z0_m": 4e3, "v0_mps": -100.0}
    assert pp.classify_run(run, 0.25) == "late"
    assert pp.classify_run(dict(run, t_end_s=50.0), 0.25) == "early"
    assert pp.classify_run(dict(run, outcome="success"), 0.25) == "reached"


def test_comparison_text_and_chart(tmp_path):
    rows = [(s, ("success", 100.0, 49.0) if s == "D" else ("ascent", 90.0, 120.0), ("ascent", 10.0, 3000.0))
            for s in SITE_NAMES]
    runs = _runs(rows)
    assert pp.applies(runs) and not pp.applies(runs[:4])
    text = pp.format_comparison(runs, 0.25)
    assert "reached 50 m: paper 2 of 18; flown 1 of 18" in text
    assert "ascents in the first 30 s: paper none reported; flown 9" in text
    assert "after half the nominal time): paper A, C late; B early; flown 8 of 17" in text
    assert text.count("\n") >= 12
    path = pp.paper_pattern_chart(runs, tmp_path / "pattern.png", 0.25)
    assert path.is_file() and path.stat().st_size > 10_000
    with pytest.raises(KeyError):
        pp.classify_run({"t_end_s": 1.0}, 0.25)


def _pooled_runs():
    """Site A, 4 finished runs: 1 reached, 2 failed late, 1 failed early (an ascent at 10 s); every
    other site: 2 reached; site B also has one run still running (not counted)."""
    # A (z0 10 km, v0 -200 m/s, c2 0.25): t(50 m) = 50 (1 - 0.005^0.25) / 0.25 = 146.8 s, half = 73.4 s
    a = [("success", 140.0), ("ascent", 100.0), ("crash", 120.0), ("ascent", 10.0)]
    runs = [{"site": "A", "label": f"set{i % 2}", "outcome": o, "t_end_s": t, "lowest_altitude_m": 60.0 + i,
             "z0_m": 1e4, "v0_mps": -200.0, "estimator": "dpr"} for i, (o, t) in enumerate(a)]
    for s in SITE_NAMES[1:]:
        z0, v0 = (1e4, -200.0) if s in "BC" else (4e3, -100.0)
        runs += [{"site": s, "label": f"set{i}", "outcome": "success", "t_end_s": 100.0, "lowest_altitude_m": 50.0,
                  "z0_m": z0, "v0_mps": v0, "estimator": "dpr"} for i in range(2)]
    runs.append(dict(runs[-1], site="B", outcome="running", t_end_s=5.0))
    return runs


def test_pooled_pattern_hand_computed():
    from dvsland.report.stats import wilson_interval

    p = pp.pooled_pattern(_pooled_runs(), 0.25)
    assert list(p) == list(SITE_NAMES) + ["all"]
    a = p["A"]
    assert (a["n"], a["n_reached"], a["n_late"], a["n_early"], a["early_ascents"]) == (4, 1, 2, 1, 1)
    assert (a["reached_rate"], a["late_rate"], a["early_rate"]) == (0.25, 0.5, 0.25)
    # Wilson 95 % for 1 of 4: (0.0456, 0.6994); 2 of 4: (0.1500, 0.8500)
    assert a["reached_lo"] == pytest.approx(0.0456, abs=1e-4) and a["reached_hi"] == pytest.approx(0.6994, abs=1e-4)
    assert a["late_lo"] == pytest.approx(0.1500, abs=1e-4) and a["late_hi"] == pytest.approx(0.8500, abs=1e-4)
    assert (a["early_lo"], a["early_hi"]) == wilson_interval(1, 4)
    b = p["B"]
    assert (b["n"], b["n_running"], b["n_reached"], b["reached_rate"]) == (2, 1, 2, 1.0)
    allp = p["all"]  # 4 + 8 x 2 finished runs, 17 reached
    assert (allp["n"], allp["n_reached"], allp["n_late"], allp["n_early"], allp["n_running"]) == (20, 17, 2, 1, 1)
    assert allp["reached_rate"] == pytest.approx(0.85)


def test_pooled_comparison_text_and_chart(tmp_path):
    runs = _pooled_runs()
    text = pp.format_pooled_comparison(runs, 0.25)
    row_a = next(line for line in text.splitlines() if line.startswith("A "))
    assert "late" in row_a and "unstable only near the end" in row_a
    assert "25 % [5-70]" in row_a and "50 % [15-85]" in row_a and row_a.split()[-2:] == ["4", "1"]
    row_all = next(line for line in text.splitlines() if line.startswith("all"))
    assert "2/18 reached" in row_all and "85 % [" in row_all and row_all.split()[-2:] == ["20", "1"]
    md = pp.format_pooled_comparison(runs, 0.25, markdown=True)
    assert md.startswith("| site | paper |") and "| A | late | unstable only near the end | 25 % [5-70] |" in md
    # several runs per site: the simulate comparison switches to the pooled table (+ the checks)
    full = pp.format_comparison(runs, 0.25)
    assert "pooled over seeds and settings" in full and "reached 50 m: paper 2 of 18; flown 17 of 21" in full
    path = pp.paper_pattern_chart(runs, tmp_path / "pooled.png", 0.25)  # auto: pooled (two panels)
    assert path.is_file() and 10_000 < path.stat().st_size < 100_000


def test_campaign_report_writes_the_pooled_pattern(tmp_path):
    from dvsland.campaign.report import write_paper_pattern

    runs = _pooled_runs()
    (tmp_path / "config.yaml").write_text("controller: {c2: 0.25}\nsimulation: {success_altitude_m: 50.0}\n")
    out = write_paper_pattern(tmp_path, runs, ["site", "label", "estimator"])
    assert {"paper_pattern.txt", "paper_pattern.md", "paper_pattern.json", "paper_pattern.png"} <= set(out)
    assert (tmp_path / "figures" / "paper_pattern.png").is_file()
    import json

    data = json.loads((tmp_path / "paper_pattern.json").read_text())
    assert data["flown"]["dpr"]["sites"]["A"]["n_late"] == 2 and data["paper"]["reached_50m"] == 2
    assert "[dpr] paper (section 6 / Fig. 7)" in (tmp_path / "paper_pattern.txt").read_text()
    # two estimators: one table and one chart each; other sites than the paper's nine: nothing
    two = runs + [dict(r, estimator="oracle", outcome="success") for r in runs if r["outcome"] != "running"]
    out2 = write_paper_pattern(tmp_path / "two", two, ["site", "label", "estimator"])
    assert {"paper_pattern-0.png", "paper_pattern-1.png"} <= set(out2)
    assert "[oracle]" in (tmp_path / "two" / "paper_pattern.txt").read_text()
    assert write_paper_pattern(tmp_path / "none", [r for r in runs if r["site"] != "I"], ["site"]) == {}


def test_paper_montecarlo_config_is_paper_plus_dispersions():
    from dvsland.config import config_to_dict, load_config

    mc, paper, disp = (config_to_dict(load_config(n)) for n in ("paper_montecarlo", "paper", "montecarlo"))
    assert mc["dispersion"]["enabled"] is True and mc["dispersion"] == disp["dispersion"]
    assert mc["name"] == "paper_montecarlo"
    for section in mc:
        if section not in ("name", "dispersion"):
            assert mc[section] == paper[section], section
    from dvsland.config import configs_dir

    text = (configs_dir() / "paper_montecarlo.yaml").read_text()
    section = text[text.index("\ndispersion:"):]
    assert all("not in paper" in line for line in section.strip().splitlines())


def test_campaign_figure_with_no_or_all_successes(tmp_path):
    # a group with 0 of n (or n of n) successes: its Wilson bound sits a rounding error past the
    # rate; the error bars must still draw (matplotlib refuses negative lengths)
    from dvsland.campaign.report import campaign_figure
    from dvsland.report.stats import group_stats

    runs = [{"site": s, "label": "set0", "estimator": "dpr", "outcome": o, "lowest_altitude_m": 60.0,
             "v_at_50m_mps": None, "fuel_used_kg": 1.0} for s, o in (("A", "ascent"), ("B", "success"))
            for _ in range(12)]
    groups = group_stats(runs, ["site", "label", "estimator"])
    assert campaign_figure(tmp_path / "c.png", runs, groups, ["site", "label", "estimator"]).is_file()
