"""Recordings in and out (dvsland.events.recording): every format's round trip, the common foreign
layouts, the shipped tiny recordings, validation errors, and evaluation on a recording."""

from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from dvsland.events import (Events, EventEmulator, GroundTruth, read_ground_truth, read_recording,
                            validate_events, write_ground_truth, write_recording)

DATA = Path(__file__).resolve().parent / "data"
FORMATS = ["h5", "npz", "npy", "csv", "aedat4"]


def _needs(fmt):
    if fmt == "aedat4":
        pytest.importorskip("dv_processing")


@pytest.fixture(scope="module")
def events():
    """Two batch elements of emulator events on a non-square 30 x 20 sensor, both polarities."""
    g = torch.Generator().manual_seed(0)
    f0 = torch.rand(2, 20, 30, generator=g) + 0.05
    f1 = f0 * torch.exp(torch.randn(2, 20, 30, generator=g) * 0.4)
    emu = EventEmulator()
    emu.reset(f0, 5_000_000_000)  # large times: int64 µs must survive every format
    ev = emu.step(f1, 5_000_100_000)
    assert (ev.p == -1).any() and (ev.p == 1).any()
    return ev


@pytest.fixture(scope="module")
def gt():
    return GroundTruth.from_altitude([5_000_000_000, 5_000_050_000, 5_000_100_000], [500.0, 495.0, 490.1],
                                     [-100.0, -99.0, -98.7])


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("polarity", ["pm1", "01"])
def test_round_trip_every_format(tmp_path, events, gt, fmt, polarity):
    _needs(fmt)
    for b in (0, 1):
        p = write_recording(tmp_path / f"r{b}.{fmt}", events, (30, 20), ground_truth=gt, polarity=polarity, b=b)
        rec = read_recording(p)
        want = events.select_batch(b)
        want = Events(torch.zeros_like(want.b), want.x, want.y, want.t, want.p)
        assert rec.events == want, fmt
        assert rec.sensor_size == (30, 20) or fmt in ("npy", "csv")  # those carry no sensor size
        if fmt in ("h5", "npz"):
            assert np.array_equal(rec.ground_truth.t_us, gt.t_us)
            np.testing.assert_array_equal(rec.ground_truth.divergence, gt.divergence)
            np.testing.assert_array_equal(rec.ground_truth.altitude_m, gt.altitude_m)


def test_tonic_polarity_keeps_off_events(tmp_path, events):
    """The tonic array (npy) and the '01' option write OFF as 0 and ON as 1: nothing tonic reads as
    bool or as a channel index can turn OFF into ON or drop it."""
    ev0 = events.select_batch(0)
    n_off = int((ev0.p == -1).sum())
    arr = np.load(write_recording(tmp_path / "t.npy", events, (30, 20)))
    assert set(np.unique(arr["p"]).tolist()) == {0, 1} and int((arr["p"] == 0).sum()) == n_off
    assert arr.dtype.names == ("x", "y", "t", "p")
    with h5py.File(write_recording(tmp_path / "t.h5", events, (30, 20), polarity="01"), "r") as h5:
        p = h5["events/p"][()]
        assert set(np.unique(p).tolist()) == {0, 1} and int((p == 0).sum()) == n_off
    # a tonic structured array handed over directly
    rec = read_recording(arr, sensor_size=(30, 20))
    assert int((rec.events.p == -1).sum()) == n_off


def test_hdf5_compressed_and_chunked(tmp_path, events):
    for comp in ("gzip", "lzf", None):
        p = write_recording(tmp_path / f"c_{comp}.h5", events, (30, 20), compression=comp, chunk_events=100)
        with h5py.File(p, "r") as h5:
            d = h5["events/t"]
            assert d.chunks == (100,) and d.compression == comp
        assert read_recording(p).events == read_recording(tmp_path / "c_gzip.h5").events


def test_foreign_hdf5_layouts(tmp_path, events):
    ev = events.select_batch(0)
    x, y, t = ev.x.numpy(), ev.y.numpy(), ev.t.numpy()
    p01 = (ev.p.numpy() > 0).astype(np.uint8)
    want = Events(torch.zeros_like(ev.b), ev.x, ev.y, ev.t, ev.p)
    # DSEC: events/{x,y,t,p} with t relative to a root t_offset, blosc-free gzip
    with h5py.File(tmp_path / "dsec.h5", "w") as h5:
        g = h5.create_group("events")
        g.create_dataset("x", data=x.astype(np.uint16), compression="gzip")
        g.create_dataset("y", data=y.astype(np.uint16), compression="gzip")
        g.create_dataset("t", data=(t - 4_000_000_000).astype(np.uint32), compression="gzip")
        g.create_dataset("p", data=p01, compression="gzip")
        h5.create_dataset("t_offset", data=np.int64(4_000_000_000))
    assert read_recording(tmp_path / "dsec.h5").events == want
    # datasets at the root, named ts / polarity, width/height attributes
    with h5py.File(tmp_path / "root.h5", "w") as h5:
        h5.create_dataset("x", data=x)
        h5.create_dataset("y", data=y)
        h5.create_dataset("ts", data=t)
        h5.create_dataset("polarity", data=ev.p.numpy())
        h5.attrs["width"], h5.attrs["height"] = 30, 20
    rec = read_recording(tmp_path / "root.h5")
    assert rec.events == want and rec.sensor_size == (30, 20)
    # v2e: one (N, 4) uint32 table, columns t, x, y, p (t in µs, p 0/1)
    tab = np.stack([t - 4_999_000_000, x, y, p01], 1).astype(np.uint32)
    with h5py.File(tmp_path / "v2e.h5", "w") as h5:
        h5.create_dataset("events", data=tab, compression="gzip")
    rec = read_recording(tmp_path / "v2e.h5")
    assert torch.equal(rec.events.t, ev.t - 4_999_000_000) and torch.equal(rec.events.p, ev.p)
    # a structured events dataset
    arr = np.empty(len(x), dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    arr["t"], arr["x"], arr["y"], arr["p"] = t, x, y, ev.p.numpy()
    with h5py.File(tmp_path / "struct.h5", "w") as h5:
        h5.create_dataset("events", data=arr)
    assert read_recording(tmp_path / "struct.h5").events == want


def test_text_layouts_and_units(tmp_path, events):
    ev = events.select_batch(0)
    want = Events(torch.zeros_like(ev.b), ev.x, ev.y, ev.t, ev.p)
    t_s = ev.t.numpy() / 1e6
    # the event-camera dataset text format: "t x y p", t in seconds, no header, blank separated
    rows = "\n".join(f"{a!r} {b} {c} {d}" for a, b, c, d in zip(t_s.tolist(), ev.x.tolist(), ev.y.tolist(),
                                                               (ev.p.numpy() > 0).astype(int).tolist()))
    (tmp_path / "ev.txt").write_text(rows + "\n")
    assert read_recording(tmp_path / "ev.txt").events == want
    # header names the unit and the order
    (tmp_path / "ev.csv").write_text("x,y,p,t_ms\n" + "\n".join(
        f"{b},{c},{d},{a / 1000!r}" for a, b, c, d in zip(ev.t.tolist(), ev.x.tolist(), ev.y.tolist(),
                                                          ev.p.tolist())))
    assert read_recording(tmp_path / "ev.csv").events == want
    # plain npz with x/y/t/p, t in ns through t_unit
    np.savez(tmp_path / "ns.npz", x=ev.x.numpy(), y=ev.y.numpy(), t=ev.t.numpy() * 1000, p=ev.p.numpy())
    assert read_recording(tmp_path / "ns.npz", t_unit="ns").events == want


def test_ground_truth_side_files(tmp_path, gt):
    for suffix in ("csv", "npz"):
        p = write_ground_truth(tmp_path / f"gt.{suffix}", gt)
        back = read_ground_truth(p)
        assert np.array_equal(back.t_us, gt.t_us)
        np.testing.assert_array_equal(back.divergence, gt.divergence)
        np.testing.assert_array_equal(back.velocity_mps, gt.velocity_mps)
    (tmp_path / "d.csv").write_text("t_s,divergence\n1.0,-0.2\n1.5,-0.25\n")
    d = read_ground_truth(tmp_path / "d.csv")
    assert d.t_us.tolist() == [1_000_000, 1_500_000] and d.altitude_m is None
    np.testing.assert_allclose(d.at([1_250_000, 2_000_000])["divergence"], [-0.225, np.nan])


@pytest.mark.parametrize("case,match", [
    (dict(t=[0.0, np.nan, 3.0]), "finite"),
    (dict(p=[1, 5, 0]), "polarity"),
    (dict(p=[-1, 0, 1]), "polarity"),
    (dict(x=[0, 31, 2]), "'x' must be in \\[0, 30\\)"),
    (dict(y=[-1, 0, 0]), "'y'"),
    (dict(x=[0.5, 1, 2]), "integer"),
    (dict(t=[1, 2]), "equal length"),
])
def test_validate_events_errors(case, match):
    cols = dict(x=[0, 1, 2], y=[0, 1, 2], t=[1, 2, 3], p=[0, 1, 1])
    cols.update(case)
    with pytest.raises(ValueError, match=match):
        validate_events(np.array(cols["x"]), np.array(cols["y"]), np.array(cols["t"]), np.array(cols["p"]),
                        sensor_size=(30, 20), source="test")


def test_bad_files_and_options(tmp_path, events):
    with pytest.raises(FileNotFoundError):
        read_recording(tmp_path / "missing.h5")
    with pytest.raises(ValueError, match="suffix"):
        read_recording(tmp_path / "x.bin")
    good = write_recording(tmp_path / "g.npz", events, (30, 20))
    (tmp_path / "trunc.npz").write_bytes(good.read_bytes()[:200])
    with pytest.raises(ValueError, match="trunc.npz"):
        read_recording(tmp_path / "trunc.npz")
    np.savez(tmp_path / "p5.npz", x=[1, 2], y=[1, 2], t=[1, 2], p=[1, 5])
    with pytest.raises(ValueError, match=r"p5.npz \(npz file\): polarity"):
        read_recording(tmp_path / "p5.npz")
    np.savez(tmp_path / "nox.npz", y=[1, 2], t=[1, 2], p=[1, 0])
    with pytest.raises(ValueError, match="no x column"):
        read_recording(tmp_path / "nox.npz")
    with pytest.raises(ValueError, match="polarity"):
        write_recording(tmp_path / "a.h5", events, (30, 20), polarity="bool")
    with pytest.raises(ValueError, match="compression"):
        write_recording(tmp_path / "a.h5", events, (30, 20), compression="zstd")
    with pytest.raises(ValueError, match="outside sensor_size"):
        write_recording(tmp_path / "a.h5", events, (10, 10))
    with pytest.raises(ValueError, match="t_unit"):
        read_recording(good, t_unit="fortnight")


# ---------------------------------------------------------------------- shipped recordings
def test_shipped_recordings_agree():
    """tests/data/descent_A.* (scripts/make_test_recordings.py): one recording in every format,
    each < 200 KB, all read to the same events and ground truth."""
    recs = {}
    for fmt in FORMATS:
        p = DATA / f"descent_A.{fmt}"
        assert p.stat().st_size < 200_000
        if fmt == "aedat4" and pytest.importorskip("dv_processing") is None:
            continue
        recs[fmt] = read_recording(p, ground_truth=DATA / "descent_A_gt.csv" if fmt in ("csv", "npy", "aedat4")
                                   else None)
    ref = recs["npz"]
    assert len(ref.events) > 5000 and ref.sensor_size == (64, 48)
    for fmt, r in recs.items():
        assert r.events == ref.events, fmt
        np.testing.assert_array_equal(r.ground_truth.divergence, ref.ground_truth.divergence)


def test_evaluate_recording_matches_across_formats_and_cli(tmp_path):
    from dvsland.cli.main import main
    from dvsland.config import load_config
    from dvsland.evaluate import evaluate_recording

    cfg = load_config("paper")
    out = {}
    for fmt in ("npz", "csv"):
        res = evaluate_recording(cfg, DATA / f"descent_A.{fmt}", ["dpr", "oracle"], warmup_steps=5,
                                 max_steps=20, progress=False,
                                 ground_truth=DATA / "descent_A_gt.csv" if fmt == "csv" else None)
        out[fmt] = res
        s = res.summary["estimators"]
        assert s["oracle"]["all_sites"]["median_abs_rel_err"] < 1e-6  # float32 estimates
        assert s["oracle"]["all_sites"]["n_steps"] == 15
        assert res.summary["sensor_size"] == [64, 48] and res.summary["has_ground_truth"]
    np.testing.assert_array_equal(out["npz"].d_hat["dpr"], out["csv"].d_hat["dpr"])
    assert np.isfinite(out["npz"].d_hat["dpr"]).any()
    # the CLI, without ground truth in the file: metrics NaN, estimates kept
    rc = main(["evaluate", "paper", "--recording", str(DATA / "descent_A.npy"), "--estimators", "dpr",
               "--max-steps", "12", "--out", str(tmp_path / "run"), "--no-figures", "--quiet"])
    assert rc == 0
    import json

    js = json.loads((tmp_path / "run" / "evaluation.json").read_text())
    assert js["trajectory"] == "recording" and js["has_ground_truth"] is False
    tr = np.load(tmp_path / "run" / "traces.npz")
    assert np.isfinite(tr["d_hat_dpr"]).any()
    # misused flags: exit status 2 with a message naming them
    assert main(["evaluate", "paper", "--recording", str(DATA / "descent_A.npz"), "--sites", "A", "--quiet"]) == 2
    assert main(["evaluate", "paper", "--ground-truth", str(DATA / "descent_A_gt.csv"), "--quiet"]) == 2


@pytest.mark.parametrize("suffix", ["h5", "npz"])
def test_dvsland_events_files_read_as_recordings(tmp_path, events, suffix):
    from dvsland.events import save_events

    p = save_events(tmp_path / f"ev.{suffix}", events, sensor_size=(30, 20), batch_size=2)
    for b in (0, 1):
        rec = read_recording(p, b=b)
        want = events.select_batch(b)
        assert rec.events == Events(torch.zeros_like(want.b), want.x, want.y, want.t, want.p)
        assert rec.sensor_size == (30, 20) and rec.meta["layout"] == "dvsland"


def test_bin_recording_pixels_order_and_errors():
    """Binning F x F: x // F, y // F on a (W // F, H // F) sensor, the partial last column dropped, times,
    polarities and order kept, the factor recorded; a principal point moves to the larger pixels."""
    from dvsland.events import Recording, bin_recording, binned_pixel

    x = torch.tensor([0, 1, 2, 5, 6, 6, 3])
    y = torch.tensor([0, 3, 1, 2, 0, 5, 4])
    t = torch.arange(7, dtype=torch.int64) * 10
    p = torch.tensor([1, -1, 1, 1, -1, 1, -1], dtype=torch.int8)
    rec = Recording(Events(torch.zeros(7, dtype=torch.int64), x, y, t, p), (7, 6), source="array")
    got = bin_recording(rec, 2)
    assert got.sensor_size == (3, 3) and got.meta["bin_factor"] == 2
    keep = x < 6  # column 6 is the partial bin of a 7-px-wide sensor
    assert torch.equal(got.events.x, (x // 2)[keep]) and torch.equal(got.events.y, (y // 2)[keep])
    assert torch.equal(got.events.t, t[keep]) and torch.equal(got.events.p, p[keep])
    assert bin_recording(got, 3).meta["bin_factor"] == 6 and bin_recording(rec, 1).events == rec.events
    assert binned_pixel((0.5, 2.5), 2) == (0.0, 1.0) and binned_pixel((3.0, 3.0), 1) == (3.0, 3.0)
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="factor must be an integer"):
            bin_recording(rec, bad)
    with pytest.raises(ValueError, match="no whole bin"):
        bin_recording(rec, 7)


def test_evaluate_a_binned_recording(tmp_path):
    """The shipped 64 x 48 recording binned 2x: evaluated on a 32 x 24 sensor with the principal point
    moved (the oracle stays exact; the CLI's --bin F and --bin dvs128 report the binning), and bad
    --bin values give exit status 2."""
    import dataclasses
    import json

    from dvsland.cli.main import main
    from dvsland.config import load_config
    from dvsland.evaluate import evaluate_recording
    from dvsland.evaluate.recording import _sized_config, dvs128_bin_factor
    from dvsland.events import bin_recording

    cfg = load_config("paper")
    rec = bin_recording(read_recording(DATA / "descent_A.npz"), 2)
    res = evaluate_recording(cfg, rec, ["cmax", "oracle"], warmup_steps=5, max_steps=20, progress=False)
    assert res.summary["sensor_size"] == [32, 24] and res.summary["bin_factor"] == 2
    assert res.summary["estimators"]["oracle"]["all_sites"]["median_abs_rel_err"] < 1e-6
    cam = dataclasses.replace(cfg.camera, principal_point_px=[40.5, 20.5])
    sized = _sized_config(dataclasses.replace(cfg, camera=cam), rec).camera
    assert (sized.width_px, sized.height_px) == (32, 24) and sized.principal_point_px == [20.0, 10.0]
    assert sized.fov_deg == cfg.camera.fov_deg
    assert dvs128_bin_factor(cfg, (128, 128)) == 1 and dvs128_bin_factor(cfg, (1280, 720)) == 10
    assert dvs128_bin_factor(dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, fov_deg=120.0)),
                             (1280, 720)) == 5
    out = tmp_path / "run"
    assert main(["evaluate", "paper", "--recording", str(DATA / "descent_A.npz"), "--bin", "2", "--estimators",
                 "oracle", "--max-steps", "12", "--out", str(out), "--no-figures", "--quiet"]) == 0
    js = json.loads((out / "evaluation.json").read_text())
    assert js["sensor_size"] == [32, 24] and js["bin_factor"] == 2
    assert "binned 2x2" in (out / "table.txt").read_text()
    assert main(["evaluate", "paper", "--recording", str(DATA / "descent_A.npz"), "--bin", "dvs128", "--estimators",
                 "oracle", "--max-steps", "12", "--out", str(tmp_path / "r2"), "--no-figures", "--quiet"]) == 0
    for bad in ("0", "x", "49"):
        assert main(["evaluate", "paper", "--recording", str(DATA / "descent_A.npz"), "--bin", bad, "--quiet",
                     "--out", str(tmp_path / "bad")]) == 2
    assert main(["evaluate", "paper", "--bin", "2", "--quiet"]) == 2
