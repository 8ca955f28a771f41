"""End to end: fast renderer -> event emulator -> dpr -> controller -> dynamics (short flights)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvsland.sim import simulate


def test_fast_dpr_short_flight(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    r = simulate(None, estimator="dpr", renderer="fast", sites="D", out=tmp_path / "e2e", quiet=True,
                 overrides=["simulation.t_max_s=2", "logging.figures=false", "logging.image_every_s=0.2"])
    assert r.status == "complete" and len(r.runs) == 2
    assert {x["outcome"] for x in r.runs} <= {"timeout", "ascent", "crash"}
    tr = r.traces
    assert np.isfinite(tr["d_est"][1:]).any(), "dpr gave no estimate at all"
    assert np.isnan(tr["d_est"][0]).all()  # no events before the second frame
    assert np.isfinite(tr["thrust_n"][:-1]).all() and (tr["thrust_n"][:-1] >= 0).all()
    assert r.timings_s["render"] > 0 and r.timings_s["emulate"] > 0
    res = json.loads((r.run_dir / "results.json").read_text())
    assert res["renderer"] == "fast" and res["estimator"] == "dpr"
    images, scalars = set(), set()
    for run in ("D_Kp5e6-n5", "D_Kp4e6-n10"):
        acc = EventAccumulator(str(r.run_dir / "tb" / run), size_guidance={"images": 0}).Reload()
        images |= set(acc.Tags()["images"])
        scalars |= set(acc.Tags()["scalars"])
    assert {"images/frame", "images/events"} <= images
    assert "tracking/n_centroids" in scalars


@pytest.mark.slow
def test_paper_experiment_fast_dpr(tmp_path):
    r = simulate(None, estimator="dpr", renderer="fast", out=tmp_path / "paper", quiet=True)
    assert r.status == "complete" and len(r.runs) == 18
    assert all(x["outcome"] in ("success", "ascent", "crash", "timeout") for x in r.runs)
    assert (r.run_dir / "figures" / "lowest_altitude.png").is_file()
