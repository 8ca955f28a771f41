"""``dvsland dataset zoom``: event windows of procedural textures zoomed at known divergences
(tiny builds: a few descents of a few steps)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dvsland.config import load_config
from dvsland.data import EventWindowDataset
from dvsland.data.shardfile import read_index
from dvsland.data.zoom import ZoomRequest, build_zoom_dataset, descent_profiles

pytestmark = pytest.mark.usefixtures("one_thread")
REQ = ZoomRequest(n_descents=5, steps=4, shard_size=3, seed=7)


@pytest.fixture(scope="module")
def cfg():
    return load_config("montecarlo_efference", [])


@pytest.fixture(scope="module")
def built(tmp_path_factory, cfg):
    out = tmp_path_factory.mktemp("zoom") / "z"
    m = build_zoom_dataset(cfg, REQ, out)
    assert [e["status"] for e in m["shards"]] == ["complete", "complete"]
    return out


def _shards(folder):
    return [read_index(p) for p in sorted((folder / "shards").glob("*.h5"))]


def test_profiles_follow_the_exact_zoom():
    p = descent_profiles(ZoomRequest(n_descents=50, steps=40), 0, 50, 0.1)
    d, z = p["d"], p["z"]
    assert d.shape == z.shape == (50, 41) and (d < 0).all()
    assert (np.abs(d) >= 0.004 - 1e-12).all() and (np.abs(d) <= 0.6 + 1e-12).all()
    assert (z[:, -1] >= 20.0 * (1 - 1e-12)).all()
    # z(t + dt) = z(t) exp(trapezoid of D): D is linear in t, so exactly
    step = np.log(z[:, 1:] / z[:, :-1])
    np.testing.assert_allclose(step, 0.05 * (d[:, 1:] + d[:, :-1]), rtol=1e-9, atol=1e-12)
    assert np.abs(d[:, 0]).min() < 0.02 and np.abs(d[:, 0]).max() > 0.2  # the range is spanned
    again = descent_profiles(ZoomRequest(n_descents=50, steps=40), 10, 5, 0.1)  # per-descent draws
    np.testing.assert_array_equal(again["d"], d[10:15])


def test_samples_are_labelled_with_the_profile(built):
    sh = _shards(built)
    prof = descent_profiles(REQ, 0, 3, 0.1)
    s = sh[0]["samples"]
    assert len(s["d_true"]) == 3 * 4 and s["valid"].all()
    k, b = s["step"] - 0, s["descent"]
    np.testing.assert_array_equal(s["d_true"], prof["d"][b, k])
    np.testing.assert_array_equal(s["z_m"], prof["z"][b, k])
    np.testing.assert_allclose(s["tau_s"], -1.0 / s["d_true"])
    np.testing.assert_allclose(s["v_mps"] / s["z_m"], s["d_true"], rtol=1e-12)
    n_ev = np.diff(s["event_offset"])
    assert n_ev.sum() > 1000 and (n_ev > 0).mean() > 0.5  # windows hold events (a slow, high one may not)
    d = sh[1]["descents"]
    assert list(d["scene"]) == ["T~3", "T~4"] and list(d["variant"]) == [3, 4] and set(d["site"]) == {"T"}


def test_reads_as_a_dataset_with_splits(built):
    ds = EventWindowDataset(built, representation="count", split="all")
    assert len(ds) == 5 * 4
    x, y = ds[0]
    assert x.shape == (2, 128, 128) and float(x.sum()) == float(y["n_events"]) > 0
    t_end = round(float(y["t_s"]) * 1e6)
    ev, _ = EventWindowDataset(built, representation="events", split="all")[0]
    assert ev["t"].max() <= t_end and ev["t"].min() > t_end - 100_000
    sizes = {s: len(EventWindowDataset(built, split=s)) for s in ("train", "val", "test")}
    assert sizes == {"train": 12, "val": 4, "test": 4}  # variants 1-3 / 4 / 0


def test_deterministic_and_resumes(built, tmp_path, cfg):
    again = tmp_path / "again"
    build_zoom_dataset(cfg, REQ, again)
    for a, b in zip(_shards(built), _shards(again)):
        for k in a["samples"]:
            np.testing.assert_array_equal(a["samples"][k], b["samples"][k], err_msg=k)
    (again / "shards" / "z000003.h5").unlink()
    before = (again / "shards" / "z000000.h5").stat().st_mtime_ns
    build_zoom_dataset(cfg, REQ, again)  # rebuilds the missing shard, keeps the other
    assert (again / "shards" / "z000000.h5").stat().st_mtime_ns == before
    np.testing.assert_array_equal(_shards(again)[1]["samples"]["d_true"], _shards(built)[1]["samples"]["d_true"])
    with pytest.raises(ValueError, match="holds a dataset of another request"):
        build_zoom_dataset(cfg, REQ._replace(seed=8), again)


@pytest.mark.parametrize("field, value", [("n_descents", 0), ("steps", 1), ("d_min", 0.0), ("d_max", 9.0),
                                          ("d_ratio", 0.5), ("z_min", 5.0), ("shard_size", 0)])
def test_bad_request_names_the_field(field, value, tmp_path, cfg):
    with pytest.raises(ValueError, match=field):
        build_zoom_dataset(cfg, REQ._replace(**{field: value}), tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_cli(tmp_path, capsys):
    from dvsland.cli.main import main

    out = tmp_path / "cli"
    assert main(["dataset", "zoom", "montecarlo_efference", "--n-descents", "2", "--steps", "2", "--out", str(out),
                 "--quiet", "--d-range", "0.1,0.3"]) == 0
    assert "complete: 1 shards, 4 samples" in capsys.readouterr().out
    d = read_index(out / "shards" / "z000000.h5")["samples"]["d_true"]
    assert (np.abs(d) >= 0.1 - 1e-12).all() and (np.abs(d) <= 0.3 + 1e-12).all()
    assert main(["dataset", "zoom", "--n-descents", "2", "--out", str(tmp_path / "y"), "--d-range", "fast"]) == 2
    assert "--d-range must be two numbers" in capsys.readouterr().err
    assert math.isfinite(float(d[0]))


def test_a_folder_of_other_files_is_refused_and_left_alone(tmp_path, cfg):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="not a dataset"):
        build_zoom_dataset(cfg, REQ, tmp_path / "mine")
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["notes.txt"]
