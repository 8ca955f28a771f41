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
