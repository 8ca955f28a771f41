"""dvsland.data: building, reading and streaming labelled event windows (tiny builds: two sites,
one or two seeds, two seconds of flight)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from dvsland.data import (REPRESENTATIONS, EventWindowDataset, LoopStream, ShardError, SplitRule, build_dataset,
                          collate_events)
from dvsland.data.represent import represent
from dvsland.data.shardfile import read_index
from dvsland.events import TONIC_DTYPE, Events

CONFIG = "montecarlo_efference"
SETS = ["render.threads=1", "simulation.torch_threads=1", "simulation.t_max_s=2"]
# seed 0 flies the evaluation terrains (variant 0), seed 1 variant 1; D is of the held-out type
TINY = dict(n_seeds=2, sites="A,D", shard_size=1, overrides=SETS, quiet=True)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "tiny"
    res = build_dataset(CONFIG, out=out, **TINY)
    assert res.status == "complete" and res.n_shards == 2 and res.n_shards_built == 2
    return out


def _arrays(folder):
    return [read_index(p) for p in sorted((folder / "shards").glob("*.h5"))]


def _events_of(folder):
    import h5py

    out = []
    for p in sorted((folder / "shards").glob("*.h5")):
        with h5py.File(p, "r") as f:
            out.append({k: f[f"events/{k}"][()] for k in ("x", "y", "dt_us", "p")})
    return out


def test_build_is_deterministic(built, tmp_path):
    again = tmp_path / "again"
    build_dataset(CONFIG, out=again, **TINY)
    for a, b in zip(_arrays(built), _arrays(again)):
        for k in a["samples"]:
            np.testing.assert_array_equal(a["samples"][k], b["samples"][k], err_msg=k)
        for k in a["descents"]:
            np.testing.assert_array_equal(a["descents"][k], b["descents"][k], err_msg=k)
    for a, b in zip(_events_of(built), _events_of(again)):
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_samples_shapes_dtypes_and_units(built):
    ds = EventWindowDataset(built, representation="count", split="all")
    vox = EventWindowDataset(built, representation="voxel", split="all", n_bins=4)
    evs = EventWindowDataset(built, representation="events", split="all")
    for i in (0, len(ds) // 2, len(ds) - 1):
        x, y = ds[i]
        assert x.shape == (2, 128, 128) and x.dtype == torch.float32
        a, _ = evs[i]
        assert a.dtype == TONIC_DTYPE and set(np.unique(a["p"])) <= {0, 1}
        assert x.sum() == len(a) == y["n_events"] and x[0].sum() == (a["p"] == 1).sum()  # channel 0 = ON
        v, _ = vox[i]
        assert v.shape == (4, 128, 128) and v.dtype == torch.float32
        assert float(v.sum()) == pytest.approx(float((a["p"] == 1).sum() - (a["p"] == 0).sum()), abs=1e-2)  # signed
        t_end = round(float(y["t_s"]) * 1e6)
        assert len(a) == 0 or (a["t"].max() <= t_end and a["t"].min() > t_end - 100_000)  # the window (t - dt, t]
        assert {k: t.dtype for k, t in y.items() if k in ("d_true", "tau_s", "z_m", "v_mps", "t_s")} == dict.fromkeys(
            ("d_true", "tau_s", "z_m", "v_mps", "t_s"), torch.float32)
        assert y["valid"].dtype == torch.bool and y["step"].dtype == torch.int64 and bool(y["valid"])
        assert float(y["d_true"]) == pytest.approx(float(y["v_mps"] / y["z_m"]), rel=1e-6)  # 1/s, < 0 descending
        assert float(y["tau_s"]) == pytest.approx(-1.0 / float(y["d_true"]), rel=1e-5)  # s
        assert 3000 < float(y["z_m"]) < 12000 and float(y["v_mps"]) < -50  # m, m/s: the start of the descents
    # with valid_only=False the step-0 samples (no events yet, invalid) are there too
    every = EventWindowDataset(built, split="all", valid_only=False)
    assert len(every) == len(ds) + 4 and not bool(every[0][1]["valid"]) and every[0][0].sum() == 0


def test_voxel_polarity_is_signed():
    """OFF events subtract (tonic's to_voxel_grid adds them): a window of OFF events only is negative."""
    ev = {"x": np.array([3, 3], np.uint16), "y": np.array([2, 2], np.uint16), "dt_us": np.array([10, 90], np.int32),
          "p": np.array([-1, -1], np.int8)}
    v = represent(ev, 1000, 1100, (8, 4), "voxel", n_bins=2)
    assert v.shape == (2, 4, 8) and float(v.sum()) == pytest.approx(-2.0) and float(v.max()) == 0.0
    c = represent(ev, 1000, 1100, (8, 4), "count")
    assert c[1, 2, 3] == 2 and c[0].sum() == 0
    a = represent(ev, 1000, 1100, (8, 4), "events")
    assert a["t"].tolist() == [1010, 1090] and a["p"].tolist() == [0, 0]


def test_no_evaluation_scene_in_train(built):
    train = EventWindowDataset(built, split="train")
    infos = [train.info(i) for i in range(len(train))]
    assert {i["site"] for i in infos} == {"A"} and {i["variant"] for i in infos} == {1}  # D: held-out type
    test = EventWindowDataset(built, split="test")
    assert {(i["site"], i["variant"]) for i in map(test.info, range(len(test)))} == {("A", 0), ("D", 0), ("D", 1)}


@pytest.mark.parametrize("preset", ["montecarlo", "montecarlo_efference"])
def test_monte_carlo_presets_never_train_on_an_evaluation_scene(preset):
    from dvsland.config import load_config
    from dvsland.layout import build_layout

    cfg = load_config(preset, ["simulation.n_seeds=20"])
    lay = build_layout(cfg)
    split = SplitRule().assign(lay.site, lay.dispersed["terrain_variant"], cfg.dispersion.terrain_variants)
    scenes = np.asarray(lay.scene, dtype=object)
    assert {s.split("@")[0] for s in scenes[split != "test"]}.isdisjoint(set("ABCDEFGHI"))  # never a shipped site
    assert all(s[0] not in "DE" for s in scenes[split == "train"])
    assert set(split) == {"train", "val", "test"} and all("~4" in s for s in scenes[split == "val"])


def test_resume_skips_complete_shards_and_cleans_up(tmp_path):
    out = tmp_path / "r"
    first = build_dataset(CONFIG, out=out, max_shards=1, **TINY)
    assert first.status == "incomplete" and first.n_shards_built == 1
    done = out / first.manifest["shards"][0]["file"]
    stamp = done.stat().st_mtime_ns
    (out / "shards" / "g000-s00001.h5.tmp999").write_bytes(b"half a shard")  # a killed build's leftover
    second = build_dataset(CONFIG, out=out, **TINY)
    assert second.status == "complete" and second.n_shards_built == 1 and done.stat().st_mtime_ns == stamp
    assert not list((out / "shards").glob("*.tmp*"))
    assert build_dataset(CONFIG, out=out, **TINY).n_shards_built == 0
    with pytest.raises(ValueError, match=r"another request \(n_seeds: 2 there, 3 now\)"):
        build_dataset(CONFIG, out=out, **{**TINY, "n_seeds": 3})


def test_interrupted_build_keeps_complete_shards(tmp_path, monkeypatch):
    import dvsland.data.build as b

    class Interrupted(b.ShardWriter):
        def append(self, *a, **k):
            if self.path.name.startswith("g000-s00001") and len(self.offsets) > 5:
                raise KeyboardInterrupt
            super().append(*a, **k)

    monkeypatch.setattr(b, "ShardWriter", Interrupted)
    out = tmp_path / "i"
    with pytest.raises(KeyboardInterrupt):
        build_dataset(CONFIG, out=out, **TINY)
    status = [e["status"] for e in b.load_manifest(out)["shards"]]
    assert status == ["complete", "pending"]
    assert sorted(p.name for p in (out / "shards").iterdir()) == ["g000-s00000.h5"]
    assert len(EventWindowDataset(out, split="all")) > 0  # the complete shard reads


def test_corrupted_shard_is_named_and_does_not_lose_the_others(built, tmp_path):
    out = tmp_path / "c"
    shutil.copytree(built, out)
    bad = out / "shards" / "g000-s00001.h5"
    bad.write_bytes(bad.read_bytes()[: bad.stat().st_size // 2])  # truncated
    with pytest.raises(ShardError, match=r"g000-s00001\.h5.*truncated or corrupt"):
        EventWindowDataset(out, split="all")
    with pytest.warns(UserWarning, match="g000-s00001"):
        ds = EventWindowDataset(out, split="all", on_bad_shard="skip")
    assert len(ds) == len(EventWindowDataset(built, split="all")) // 2 and list(ds.skipped) == [str(bad)]
    res = build_dataset(CONFIG, out=out, **TINY)  # resume rebuilds the bad shard only
    assert res.n_shards_built == 1 and len(EventWindowDataset(out, split="all")) == 2 * len(ds)


def test_errors_name_the_parameter(built, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"root=.*empty.*not a dvsland dataset \(an empty folder\)"):
        EventWindowDataset(tmp_path / "empty")
    with pytest.raises(ValueError, match=r"root=.*nowhere.*no such folder"):
        EventWindowDataset(tmp_path / "nowhere")
    with pytest.raises(ValueError, match=r"representation must be one of \['count', 'voxel', 'events'\], got 'frames'"):
        EventWindowDataset(built, representation="frames")
    with pytest.raises(ValueError, match=r"split must be one of \['train', 'val', 'test', 'all'\], got 'dev'"):
        EventWindowDataset(built, split="dev")
    with pytest.raises(ValueError, match=r"split='val': no sample"):
        EventWindowDataset(built, split="val")
    with pytest.raises(ValueError, match="n_bins"):
        EventWindowDataset(built, representation="voxel", n_bins=0)
    with pytest.raises(ValueError, match="on_bad_shard"):
        EventWindowDataset(built, on_bad_shard="ignore")
    with pytest.raises(ValueError, match="hold_out_type"):
        SplitRule("volcanic")
    with pytest.raises(ValueError, match=r"--sites must be a non-empty subset"):
        build_dataset(CONFIG, out=tmp_path / "x", **{**TINY, "sites": "A,Q"})
    with pytest.raises(ValueError, match="representation"):
        LoopStream(CONFIG, representation="frames")


def test_stream_yields_the_built_samples(built):
    ds = EventWindowDataset(built, split="train")
    stream = LoopStream(CONFIG, split="train", **{k: v for k, v in TINY.items() if k != "quiet"})
    got = list(stream)
    assert len(got) == len(ds) > 0
    for (xs, ys), i in zip(got, range(len(ds))):
        x, y = ds[i]
        assert torch.equal(xs, x) and all(torch.equal(ys[k], y[k]) for k in y)
    batches = list(torch.utils.data.DataLoader(stream, batch_size=8, num_workers=0))
    assert sum(len(b[0]) for b in batches) == len(ds) and batches[0][0].shape == (8, 2, 128, 128)


def test_collate_events_and_dataloader_workers(built):
    ds = EventWindowDataset(built, representation="events", split="all")
    ev, y = collate_events([ds[0], ds[1], ds[2]])
    n = [len(ds[i][0]) for i in range(3)]
    assert ev["lengths"].tolist() == n and ev["b"].tolist() == [0] * n[0] + [1] * n[1] + [2] * n[2]
    e = Events(**{k: ev[k] for k in "bxytp"})
    assert e.is_sorted() and set(e.p.tolist()) <= {-1, 1} and y["d_true"].shape == (3,)
    loader = torch.utils.data.DataLoader(ds, batch_size=16, collate_fn=collate_events, num_workers=2)
    assert sum(int(b[0]["lengths"].sum()) for b in loader) == sum(int(ds[i][1]["n_events"]) for i in range(len(ds)))


def test_cli_build_and_info(tmp_path, capsys):
    from dvsland.cli.main import main

    out = tmp_path / "cli"
    argv = ["dataset", "build", CONFIG, "--n-seeds", "1", "--sites", "A", "--out", str(out), "--quiet",
            "--set", "simulation.seed_offset=1"] + [a for s in SETS for a in ("--set", s)]
    assert main(argv) == 0
    assert "complete: 1/1 shards" in capsys.readouterr().out
    assert main(["dataset", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "1/1 shards complete" in text and "valid samples per split: train 19, val 0, test 0" in text
    assert sorted(REPRESENTATIONS) == ["count", "events", "voxel"]


@pytest.mark.slow
def test_davis346_sensor(tmp_path):
    """Another shipped sensor: the shards record its size and the representations follow it."""
    out = tmp_path / "davis"
    build_dataset(CONFIG, out=out, n_seeds=1, sites="A", shard_size=1, quiet=True,
                  overrides=SETS + ["camera.sensor=davis346", "simulation.seed_offset=1"])
    ds = EventWindowDataset(out, representation="voxel", split="train", n_bins=3)
    assert ds.sensor_size == (346, 260) and ds[0][0].shape == (3, 260, 346)
    assert ds[0][0].abs().sum() > 0


def test_recording_camera_of_an_offcentre_principal_point():
    """An off-centre principal point is recorded as the window of a larger centred sensor of the
    same pixel angle; a centred one as itself; a fractional offset is an error naming the field."""
    from dvsland.config import CameraConfig
    from dvsland.data.crop import focal_px, recording_camera

    cam = CameraConfig(sensor="davis346", principal_point_px=[140.5, 150.5])
    big, crop = recording_camera(cam)
    assert (big.width_px, big.height_px) == (346 + 64, 260 + 42) and big.principal_point_px is None
    assert crop == (64, 0, 346, 260)  # pixel (140.5, 150.5) of the window = the big sensor's centre
    assert (crop.x0 + 140.5, crop.y0 + 150.5) == ((big.width_px - 1) / 2, (big.height_px - 1) / 2)
    assert focal_px(big) == pytest.approx(focal_px(cam)) == pytest.approx(5.5 / 18.5e-3)
    assert recording_camera(CameraConfig(sensor="davis346")) == (CameraConfig(sensor="davis346"), None)
    with pytest.raises(ValueError, match="camera.principal_point_px"):
        recording_camera(CameraConfig(principal_point_px=[60.2, 63.5]))


def test_offcentre_build_is_the_window_of_the_centred_sensor(tmp_path):
    """A build with an off-centre principal point records exactly the events of its window of the
    larger centred sensor (built on its own here), with the geometry in the manifest."""
    from dvsland.config import load_config
    from dvsland.data.crop import recording_camera

    base = SETS + ["simulation.t_max_s=0.6", "camera.width_px=48", "camera.height_px=40"]
    off = base + ["camera.principal_point_px=[19.5, 24.5]"]
    big, crop = recording_camera(load_config(CONFIG, off).camera)
    build_dataset(CONFIG, out=tmp_path / "off", n_seeds=1, sites="A", shard_size=1, quiet=True, overrides=off)
    build_dataset(CONFIG, out=tmp_path / "big", n_seeds=1, sites="A", shard_size=1, quiet=True,
                  overrides=SETS + ["simulation.t_max_s=0.6", f"camera.width_px={big.width_px}",
                                    f"camera.height_px={big.height_px}", f"camera.fov_deg={big.fov_deg!r}"])
    a = EventWindowDataset(tmp_path / "off", representation="events", split="all", valid_only=False)
    b = EventWindowDataset(tmp_path / "big", representation="events", split="all", valid_only=False)
    assert a.sensor_size == (48, 40) and a.principal_point_px == (19.5, 24.5)
    assert a.focal_px == pytest.approx(48 / (2 * np.tan(np.radians(30.0))))
    assert len(a) == len(b) > 3
    n = 0
    for i in range(len(a)):
        ea, eb = a[i][0], b[i][0]
        win = (eb["x"] >= crop.x0) & (eb["x"] < crop.x0 + 48) & (eb["y"] >= crop.y0) & (eb["y"] < crop.y0 + 40)
        assert np.array_equal(ea["x"], eb["x"][win] - crop.x0) and np.array_equal(ea["y"], eb["y"][win] - crop.y0)
        assert np.array_equal(ea["t"], eb["t"][win]) and np.array_equal(ea["p"], eb["p"][win])
        n += len(ea)
    assert n > 0
    old = EventWindowDataset(tmp_path / "big", representation="events", split="all", valid_only=False)
    assert old.principal_point_px == ((big.width_px - 1) / 2, (big.height_px - 1) / 2)


@pytest.mark.parametrize("kind", ["file", "other_run", "user_file", "shards_file"])
def test_build_refuses_an_out_that_is_not_its_dataset(tmp_path, kind):
    """--out an existing file, a folder holding another run or a user's file, or a dataset folder
    whose shards entry is a file: one clear error naming out, nothing written or mixed."""
    out = tmp_path / "ds"
    if kind == "file":
        out.write_text("not a folder")
        msg = "exists and is not a folder"
    elif kind in ("other_run", "user_file"):
        out.mkdir()
        (out / ("results.json" if kind == "other_run" else "notes.txt")).write_text("{}")
        msg = "holds files that are not a dataset"
    else:
        build_dataset(CONFIG, out=out, max_shards=1, **TINY)
        shutil.rmtree(out / "shards")
        (out / "shards").write_text("oops")
        msg = "entry is a file, not the shards folder"
    before = sorted(p.name for p in out.iterdir()) if out.is_dir() else None
    with pytest.raises(ValueError, match=msg):
        build_dataset(CONFIG, out=out, **TINY)
    assert (sorted(p.name for p in out.iterdir()) if out.is_dir() else None) == before


@pytest.mark.parametrize("kind", ["other_build", "copy"])
def test_reader_refuses_a_foreign_or_copied_shard(tmp_path, kind):
    """A shard swapped in from another build, or a copy of another shard under this one's name, is
    a ShardError naming the file (raised, or skipped with on_bad_shard='skip'), never read silently."""
    out = tmp_path / "ds"
    build_dataset(CONFIG, out=out, **TINY)
    files = sorted((out / "shards").glob("*.h5"))
    assert len(files) >= 2
    if kind == "other_build":
        other = tmp_path / "other"
        build_dataset(CONFIG, out=other, **{**TINY, "overrides": list(TINY["overrides"]) + ["emulator.threshold=0.2"]})
        shutil.copy(sorted((other / "shards").glob("*.h5"))[0], files[0])
        msg = "from another build"
    else:
        shutil.copy(files[1], files[0])
        msg = "a copy of shard"
    with pytest.raises(ShardError, match=msg):
        EventWindowDataset(out, split="all")
    with pytest.warns(UserWarning, match=msg):
        ds = EventWindowDataset(out, split="all", on_bad_shard="skip")
    assert str(files[0]) in ds.skipped
