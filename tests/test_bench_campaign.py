"""dvsland bench campaign: what one campaign batch costs, per stage and per descent."""

from __future__ import annotations

import json

import pytest

from dvsland.bench.campaign import LOOP_STAGES, bench_campaign, campaign_lines
from dvsland.bench.report import CAMPAIGN_BEGIN, CAMPAIGN_END
from dvsland.bench.run import run_bench
from dvsland.cli.cmd_bench import parse_campaign_runs


@pytest.fixture(scope="module")
def row():
    return bench_campaign("montecarlo_efference", "dpr", n_seeds=1, t_max_s=1.5, sites=["D", "H"], log=lambda *a: None)


def test_campaign_row_fields(row):
    assert row["batch_size"] == 2 and row["n_steps"] == 15 and row["descent_steps"] == 30
    per = row["cpu_ms_per_descent_step"]
    assert set(LOOP_STAGES) <= set(per) and per["estimate"] > 0 and per["render"] > 0
    assert per["total"] == pytest.approx(sum(per[k] for k in LOOP_STAGES))
    assert row["setup_cpu_s"] > 0 and row["descents_per_cpu_min"] > 0
    assert sum(row["outcomes"].values()) == 2 and sum(row["scene_sources"].values()) == 2
    assert row["torch_threads"] >= 1 and row["load_average_start"] is not None
    text = "\n".join(campaign_lines([row]))
    assert "montecarlo_efference + dpr" in text and f"{per['total']:.3f}" in text


def test_campaign_bad_input():
    with pytest.raises(ValueError, match="n_seeds"):
        bench_campaign(n_seeds=0)
    with pytest.raises(ValueError, match="t_max_s"):
        bench_campaign(t_max_s=-1)
    assert parse_campaign_runs("7x60,1x") == ((7, 60.0), (1, None)) and parse_campaign_runs(None) is None
    for bad in ("0x60", "ax", "3x-1", ","):
        with pytest.raises(ValueError, match="--campaign-runs"):
            parse_campaign_runs(bad)


def test_campaign_part_replaces_only_its_block_of_the_docs_page(tmp_path):
    docs = tmp_path / "docs"
    docs.mkdir()
    page = docs / "benchmarks.md"
    page.write_text("# Benchmarks\n\n## Speed against error\n\nkept table\n\n"
                    f"{CAMPAIGN_BEGIN}\nold campaign table\n{CAMPAIGN_END}\n\n## After\n\nkept too\n")
    rep = run_bench(["campaign"], out=tmp_path / "run", docs=docs, sites=["D"], log=lambda *a: None,
                    campaign=dict(preset="montecarlo_efference", estimator="oracle", runs=((1, 1.0),)))
    text = page.read_text()
    assert "kept table" in text and "kept too" in text and "old campaign table" not in text
    assert text.count(CAMPAIGN_BEGIN) == 1 and "montecarlo_efference + oracle" in text
    saved = json.loads((tmp_path / "run" / "bench.json").read_text())
    assert saved["campaign"]["rows"][0]["batch_size"] == 1 and rep["status"] == "complete"
