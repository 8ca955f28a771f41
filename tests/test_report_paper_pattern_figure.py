"""paper_pattern.png: every text >= 10 pt at the saved size, and the legend uses the printed
table's words (reached 50 m / failed late / failed early), not the internal class names."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

from dvsland.config.schema import SITE_NAMES  # noqa: E402
from dvsland.report import paper_pattern as pp  # noqa: E402


def _runs(per_site):
    a = [("success", 140.0), ("ascent", 100.0), ("crash", 120.0), ("ascent", 10.0)]
    runs = []
    for s in SITE_NAMES:
        z0, v0 = (1e4, -200.0) if s in "ABC" else (4e3, -100.0)
        for i, (o, t) in enumerate(a[:per_site]):
            runs.append({"site": s, "label": f"set{i % 2}", "run": f"{s}/{i}", "outcome": o, "t_end_s": t,
                         "lowest_altitude_m": 50.0 if o == "success" else 300.0 + i, "z0_m": z0, "v0_mps": v0})
    return runs


@pytest.mark.parametrize("per_site", [2, 4])  # 2: one run per setting (one panel); 4: pooled
def test_paper_pattern_fonts_and_words(tmp_path, monkeypatch, per_site):
    seen = {}
    monkeypatch.setattr(plt, "close", lambda fig: seen.setdefault("fig", fig))
    path = pp.paper_pattern_chart(_runs(per_site), tmp_path / "p.png", 0.25)
    assert path.is_file()
    fig = seen["fig"]
    assert fig.dpi >= 100 or pp.DPI >= 100
    texts = [t for t in fig.findobj(matplotlib.text.Text) if t.get_text().strip() and t.get_visible()]
    assert texts
    small = [(t.get_text(), t.get_fontsize()) for t in texts if t.get_fontsize() < 10]
    assert not small, small
    words = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
    assert {"reached 50 m", "failed late", "failed early"} <= set(words)
    assert not {"reached", "late", "early"} & set(words)
