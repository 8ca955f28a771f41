"""Damaged recordings and ground truth (issue 28, "faults at the edges"): every reader turns an empty,
truncated or corrupt file into one RecordingError (a ValueError) naming the file, the format and
what is wrong; values outside the sensor, beyond int64 or not finite are errors; no read can hang.

The damaged files are read in one child process with a time limit (and a per-file watchdog), so
that a regression that hangs a reader fails these tests instead of hanging the suite."""

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from dvsland.events import GroundTruth, read_ground_truth, read_recording, save_events, write_ground_truth
from dvsland.events.recording import MAX_SENSOR_PX, RecordingError

DATA = Path(__file__).resolve().parent / "data"
HAS_DV = subprocess.run([sys.executable, "-c", "import dv_processing"], capture_output=True).returncode == 0

# the damages; zero-run and flip positions are fractions of the file (for descent_A.aedat4 both land in
# packets that send dv-processing 2.0.4 into an endless loop: the reader's time limit must end them)
DAMAGES = ["empty", "1byte", "half", "garbage", "zero-run", "flip16"]
# (variant, damage) pairs that may read to changed events: no checksum covers the bytes hit (npy, and
# HDF5 datasets stored without a filter); any other damaged file that reads must give the very same
# events as the good file (the damage hit bytes that hold nothing, e.g. unused B-tree space)
MAY_CHANGE = {("A.npy", "zero-run"), ("A.npy", "flip16"), ("own.h5", "zero-run"), ("own.h5", "flip16"),
              ("root.h5", "zero-run"), ("root.h5", "flip16")}


def _damage(raw: bytes, kind: str) -> bytes:
    n, b = len(raw), bytearray(raw)
    if kind == "empty":
        return b""
    if kind == "1byte":
        return raw[:1]
    if kind == "half":
        return raw[: n // 2]
    if kind == "garbage":
        return np.random.default_rng(0).integers(0, 256, n, dtype=np.uint8).tobytes()
    if kind == "zero-run":
        b[n * 4 // 30: n * 4 // 30 + 64] = bytes(64)
    else:  # 16 flipped bytes
        for i in range(n * 2 // 30, n * 2 // 30 + 16):
            b[i] ^= 0xFF
    return bytes(b)


def _variants(d: Path) -> dict:
    """One good file per format and HDF5 / npz layout: name -> path."""
    ref = read_recording(DATA / "descent_A.npz")
    ev = ref.events
    x, y, t, p = ev.x.numpy(), ev.y.numpy(), ev.t.numpy(), ev.p.numpy()
    p01 = (p > 0).astype(np.uint8)
    out = {f"A.{s}": DATA / f"descent_A.{s}" for s in ("csv", "h5", "npy", "npz")}
    if HAS_DV:
        out["A.aedat4"] = DATA / "descent_A.aedat4"
    out["gt.csv"] = DATA / "descent_A_gt.csv"
    out["own.h5"] = save_events(d / "own.h5", ev, sensor_size=(64, 48), batch_size=1)
    out["own.npz"] = save_events(d / "own.npz", ev, sensor_size=(64, 48), batch_size=1)
    with h5py.File(d / "v2e.h5", "w") as h5:
        h5.create_dataset("events", data=np.stack([t, x, y, p01], 1).astype(np.uint32), compression="gzip")
    with h5py.File(d / "root.h5", "w") as h5:
        for k, v in dict(x=x, y=y, ts=t, polarity=p).items():
            h5.create_dataset(k, data=v)
        h5.attrs["width"], h5.attrs["height"] = 64, 48
    with h5py.File(d / "dsec.h5", "w") as h5:
        g = h5.create_group("events")
        for k, v in dict(x=x.astype(np.uint16), y=y.astype(np.uint16), t=(t - 60_000_000).astype(np.uint32),
                         p=p01).items():
            g.create_dataset(k, data=v, compression="gzip")
        h5.create_dataset("t_offset", data=np.int64(60_000_000))
    for k in ("v2e.h5", "root.h5", "dsec.h5"):
        out[k] = d / k
    return out


# read every file given on the command line; one JSON line per file; a watchdog ends a hung read
_READER = r"""
import faulthandler, hashlib, json, sys, time
import dvsland.events.recording as R
R.AEDAT4_TIMEOUT_BASE_S = 3.0
for path in sys.argv[1:]:
    print(json.dumps({"path": path, "state": "start"}), flush=True)
    faulthandler.dump_traceback_later(60, exit=True)
    t0 = time.time()
    try:
        if "gt.csv" in path:
            g = R.read_ground_truth(path)
            arrs = [g.t_us, g.divergence]
        else:
            e = R.read_recording(path).events
            arrs = [e.t.numpy(), e.x.numpy(), e.y.numpy(), e.p.numpy()]
        res = {"type": "ok", "digest": hashlib.sha1(b"".join(a.tobytes() for a in arrs)).hexdigest()}
    except Exception as exc:
        res = {"type": type(exc).__name__, "recording_error": isinstance(exc, R.RecordingError), "msg": str(exc)}
    faulthandler.cancel_dump_traceback_later()
    print(json.dumps(dict(res, path=path, s=time.time() - t0)), flush=True)
"""


@pytest.fixture(scope="module")
def damaged(tmp_path_factory):
    """{(variant, damage): result} of reading every damaged file in one child process."""
    d = tmp_path_factory.mktemp("damaged")
    files = {}
    for name, good in _variants(d).items():
        raw = Path(good).read_bytes()
        files[str(good)] = (name, "none")
        for kind in DAMAGES:
            p = d / f"{kind}_{name}"
            p.write_bytes(_damage(raw, kind))
            files[str(p)] = (name, kind)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.run([sys.executable, "-c", _READER, *files], capture_output=True, text=True, timeout=600,
                          env=env)
    out, started = {}, None
    for line in proc.stdout.splitlines():
        r = json.loads(line)
        if r.get("state") == "start":
            started = r["path"]
            continue
        out[files[r["path"]]] = r
        started = None
    if started is not None:  # the watchdog ended the child inside this read
        out[files[started]] = {"type": "HANG", "msg": proc.stderr[-2000:]}
    return out


@pytest.mark.parametrize("damage", DAMAGES)
@pytest.mark.parametrize("variant", ["A.csv", "A.h5", "A.npy", "A.npz", "A.aedat4", "gt.csv", "own.h5", "own.npz",
                                     "v2e.h5", "root.h5", "dsec.h5"])
def test_damaged_file_one_error(damaged, variant, damage):
    if variant == "A.aedat4" and not HAS_DV:
        pytest.skip("dv-processing not installed")
    r = damaged.get((variant, damage))
    assert r is not None, "the reader child never got to this file (an earlier read hung?)"
    assert r["type"] != "HANG", f"the read hung:\n{r['msg']}"
    if r["type"] == "ok":
        same = r["digest"] == damaged[(variant, "none")]["digest"]
        assert same or (variant, damage) in MAY_CHANGE, f"a damaged file read to other events without a word"
        return
    assert r["recording_error"], f"{r['type']}: {r['msg']}"
    label = {"csv": "CSV", "h5": "HDF5", "npy": "npy", "npz": "npz", "aedat4": "AEDAT4"}[variant.split(".")[1]]
    assert f"{damage}_{variant} ({'ground-truth ' if variant == 'gt.csv' else ''}{label} file): " in r["msg"]
    assert "\n" not in r["msg"] and len(r["msg"]) < 600
    assert r["s"] < 30


@pytest.mark.parametrize("variant", ["A.csv", "A.h5", "A.npy", "A.npz", "A.aedat4", "own.h5", "own.npz", "v2e.h5",
                                     "root.h5", "dsec.h5"])
def test_good_files_same_events(tmp_path, variant):
    if variant == "A.aedat4" and not HAS_DV:
        pytest.skip("dv-processing not installed")
    ref = read_recording(DATA / "descent_A.npz")
    rec = read_recording(_variants(tmp_path)[variant])
    assert rec.events == ref.events and rec.sensor_size == (64, 48)
    inferred = variant in ("A.csv", "A.npy", "v2e.h5", "dsec.h5")
    assert rec.meta["sensor_size_from"] == ("inferred" if inferred else "file")


# --------------------------------------------------------------------------- AEDAT4: no hang
@pytest.mark.skipif(not HAS_DV, reason="dv-processing not installed")
def test_aedat4_framing_checked_before_dv(tmp_path):
    """A corrupt header size, packet size or table position is named without calling dv-processing."""
    raw = bytearray((DATA / "descent_A.aedat4").read_bytes())
    cases = {"hdr": (14, (10 ** 9).to_bytes(4, "little"), "the header declares 1000000000 bytes"),
             "pkt": (826, (10 ** 8).to_bytes(4, "little"),
                     r"packet 0 at byte 822 \(stream 0\) declares 100000000 bytes, but 91879 remain before the "
                     r"packet table at byte 92709"),
             "neg": (826, (2 ** 32 - 5).to_bytes(4, "little"), "declares -5 bytes"),
             "tab": (54, (10 ** 6).to_bytes(8, "little"), "puts the packet table at byte 1000000, outside")}
    for name, (at, new, match) in cases.items():
        b = bytearray(raw)
        b[at:at + len(new)] = new
        (tmp_path / f"{name}.aedat4").write_bytes(bytes(b))
        with pytest.raises(RecordingError, match=match):
            read_recording(tmp_path / f"{name}.aedat4")


@pytest.mark.skipif(not HAS_DV, reason="dv-processing not installed")
def test_aedat4_hang_is_interruptible(tmp_path):
    """16 flipped bytes that send dv-processing into an endless loop: Ctrl-C ends the read at once
    (KeyboardInterrupt) and leaves no parser process behind."""
    raw = (DATA / "descent_A.aedat4").read_bytes()
    path = tmp_path / "flip.aedat4"
    path.write_bytes(_damage(raw, "flip16"))
    code = ("import sys\nfrom dvsland.events import read_recording\nprint('go', flush=True)\n"
            "try:\n    read_recording(sys.argv[1])\nexcept KeyboardInterrupt:\n    sys.exit(130)\n"
            "except ValueError:\n    sys.exit(3)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE, env=env)
    try:
        assert proc.stdout.readline().strip() == b"go"
        time.sleep(1.5)  # inside the read (the child parser started)
        t0 = time.time()
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc in (130, 3) and time.time() - t0 < 10  # 3: the parse had already failed on its own
    left = subprocess.run(["pgrep", "-f", str(path)], capture_output=True, text=True).stdout.split()
    assert not left, f"parser processes left: {left}"


# --------------------------------------------------------------------------------- text files
def test_csv_cut_mid_line_names_the_line(tmp_path):
    text = (DATA / "descent_A.csv").read_text()
    (tmp_path / "cut.csv").write_text(text[: text.index("\n", 5000) + 6])
    n_line = text[: text.index("\n", 5000)].count("\n") + 2
    with pytest.raises(RecordingError, match=rf"cut.csv \(CSV file\): line {n_line}: .*cut mid-line"):
        read_recording(tmp_path / "cut.csv")
    (tmp_path / "mid.csv").write_text("t_us,x,y,p\n1,2,3,1\n2,2,x3,1\n3,1,1,1\n")
    with pytest.raises(RecordingError, match=r"line 3: field 'x3' is not a number"):
        read_recording(tmp_path / "mid.csv")
    (tmp_path / "nonl.csv").write_text("t_us,x,y,p\n1,2,3,1\n2,2,3,-1")  # no final newline: complete
    assert len(read_recording(tmp_path / "nonl.csv").events) == 2


@pytest.mark.parametrize("reader", ["events", "gt"])
def test_wrong_encodings(tmp_path, reader):
    read = read_recording if reader == "events" else read_ground_truth
    head = "t_us,x,y,p\n" if reader == "events" else "t_us,divergence\n"
    row = "1,2,3,1\n" if reader == "events" else "1,-0.1\n"
    (tmp_path / "latin1.csv").write_bytes((head + "# mesuré à 5 °C\n" + row).encode("latin-1"))
    with pytest.raises(RecordingError, match=r"latin1.csv \(.*CSV file\): not UTF-8 text: byte 0xe9 at byte \d+ "
                                             r"\(line 2\)"):
        read(tmp_path / "latin1.csv")
    (tmp_path / "bin.csv").write_bytes(head.encode() + b"\x00\x01\x02" + row.encode())
    with pytest.raises(RecordingError, match=r"bin.csv \(.*CSV file\): binary data, not a text table: a NUL byte "
                                             r"at byte \d+ \(line 2\)"):
        read(tmp_path / "bin.csv")
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + (head + row).encode())  # UTF-8 with a BOM reads
    read(tmp_path / "bom.csv")


# --------------------------------------------------------------------------- sensor and values
def test_coordinates_outside_a_declared_sensor(tmp_path):
    x, y, t, p = np.array([0, 64, 3]), np.array([0, 1, 47]), np.array([1, 2, 3]), np.array([1, 0, 1])
    np.savez(tmp_path / "w.npz", x=x, y=y, t=t, p=p, sensor_size=np.array([64, 48]))
    with pytest.raises(RecordingError, match=r"w.npz \(npz file\): event field 'x' must be in \[0, 64\) "
                                             r"\(sensor_size \(W, H\) = \(64, 48\) declared by the file\), got x = 64 "
                                             r"at event 1"):
        read_recording(tmp_path / "w.npz")
    with h5py.File(tmp_path / "w.h5", "w") as h5:
        for k, v in dict(x=x, y=y, t=t, p=p).items():
            h5.create_dataset(k, data=v)
        h5.attrs["width"], h5.attrs["height"] = 64, 47
    with pytest.raises(RecordingError, match=r"'x' must be in \[0, 64\).*got x = 64 at event 1"):
        read_recording(tmp_path / "w.h5")
    with pytest.raises(RecordingError, match=r"'y' must be in \[0, 40\) \(sensor_size \(W, H\) = \(100, 40\) given "
                                             r"as an argument\), got y = 47 at event 2"):
        read_recording(tmp_path / "w.h5", sensor_size=(100, 40))
    with pytest.raises(ValueError, match=r"sensor_size given as an argument is \(0, 5\)"):
        read_recording(tmp_path / "w.h5", sensor_size=(0, 5))
    with h5py.File(tmp_path / "huge.h5", "w") as h5:  # a corrupt attribute: no sensor is 10^12 px wide
        for k, v in dict(x=x, y=y, t=t, p=p).items():
            h5.create_dataset(k, data=v)
        h5.attrs["sensor_size"] = np.array([10 ** 12, 48])
    with pytest.raises(RecordingError, match=r"sensor_size declared by the file is .*must be \(W, H\)"):
        read_recording(tmp_path / "huge.h5")


def test_inferred_sensor_is_stated_and_bounded(tmp_path, caplog):
    (tmp_path / "wide.csv").write_text("t_us,x,y,p\n1,32767,3,1\n2,5,4,0\n")
    with caplog.at_level(logging.INFO, logger="dvsland.events.recording"):
        rec = read_recording(tmp_path / "wide.csv")
    assert rec.sensor_size == (32768, 5) and rec.meta["sensor_size_from"] == "inferred"
    assert "inferred (W, H) = (32768, 5)" in caplog.text
    for bad, match in (("1e18", r"'x' must be in \[0, 65536\) \(no sensor size declared.*got x = "
                                r"1000000000000000000 at event 0"),
                       (str(MAX_SENSOR_PX), r"'x' must be in \[0, 65536\).*got x = 65536 at event 0"),
                       ("-3", r"'x' must be >= 0, got x = -3 at event 0")):
        (tmp_path / "bad.csv").write_text(f"t_us,x,y,p\n1,{bad},3,1\n2,5,4,0\n")
        with pytest.raises(RecordingError, match=r"bad.csv \(CSV file\): event field " + match):
            read_recording(tmp_path / "bad.csv")
    arr = np.zeros(2, dtype=[("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "i1")])
    arr["x"] = [0, 70_000]
    np.save(tmp_path / "far.npy", arr)
    with pytest.raises(RecordingError, match=r"far.npy \(npy file\): .*got x = 70000"):
        read_recording(tmp_path / "far.npy")


def test_timestamps_never_wrap(tmp_path):
    big = np.array([1, 2 ** 63], dtype=np.uint64)
    with h5py.File(tmp_path / "u64.h5", "w") as h5:
        for k, v in dict(x=[0, 1], y=[0, 1], t=big, p=[1, 0]).items():
            h5.create_dataset(k, data=np.asarray(v))
    with pytest.raises(RecordingError, match=r"u64.h5 \(HDF5 file\): timestamp 9223372036854775808 at event 1 is "
                                             r"2\^63 or more"):
        read_recording(tmp_path / "u64.h5")
    np.savez(tmp_path / "ok.npz", x=[0, 1], y=[0, 1], t=np.array([1, 2 ** 63 - 1], np.uint64), p=[1, 0])
    assert read_recording(tmp_path / "ok.npz").events.t.tolist() == [1, 2 ** 63 - 1]
    (tmp_path / "big.csv").write_text("t_us,x,y,p\n1,0,0,1\n9223372036854775808,1,1,0\n")
    with pytest.raises(RecordingError, match=r"big.csv \(CSV file\): timestamps out of range"):
        read_recording(tmp_path / "big.csv")
    with h5py.File(tmp_path / "dsec.h5", "w") as h5:  # t + t_offset past int64
        g = h5.create_group("events")
        for k, v in dict(x=[0, 1], y=[0, 1], t=np.array([0, 2 ** 62], np.int64), p=[1, 0]).items():
            g.create_dataset(k, data=np.asarray(v))
        h5.create_dataset("t_offset", data=np.int64(2 ** 62))
    with pytest.raises(RecordingError, match=r"dsec.h5 \(HDF5 file\): t \+ t_offset .* leaves the int64 range"):
        read_recording(tmp_path / "dsec.h5")
    ns = np.array([1_700_000_000_123_456_789, 1_700_000_000_123_457_500], np.int64)  # exact, not via float64
    np.savez(tmp_path / "ns.npz", x=[0, 1], y=[0, 1], t=ns, p=[1, 0])
    assert read_recording(tmp_path / "ns.npz", t_unit="ns").events.t.tolist() == [1_700_000_000_123_457,
                                                                                1_700_000_000_123_458]


def test_corrupt_sizes_are_bounded_by_the_file(tmp_path):
    with h5py.File(tmp_path / "claims.h5", "w") as h5:  # a dataset declaring 8 TB in a tiny file
        g = h5.create_group("events")
        g.create_dataset("t", shape=(10 ** 12,), dtype=np.int64, chunks=(1024,))
        for k in ("x", "y", "p"):
            g.create_dataset(k, data=np.zeros(2, np.int64))
    with pytest.raises(RecordingError, match=r"claims.h5 \(HDF5 file\): dataset '/events/t' declares shape "
                                             r"\(1000000000000,\).*more than a file of \d+ bytes can hold"):
        read_recording(tmp_path / "claims.h5")
    arr = np.zeros(10, dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "i1")])
    np.save(tmp_path / "n.npy", arr)
    raw = (tmp_path / "n.npy").read_bytes().replace(b"(10,)", b"(99,)")
    (tmp_path / "n.npy").write_bytes(raw)
    with pytest.raises(RecordingError, match=r"n.npy \(npy file\): truncated: the header declares shape \(99,\)"):
        read_recording(tmp_path / "n.npy")


# ------------------------------------------------------------------------------- ground truth
def test_ground_truth_must_be_finite(tmp_path):
    (tmp_path / "nan.csv").write_text("t_us,divergence\n0,-0.1\n# a comment\n100000,nan\n200000,-0.1\n")
    with pytest.raises(RecordingError, match=r"nan.csv \(ground-truth CSV file\): column 'divergence' holds nan "
                                             r"at line 4"):
        read_ground_truth(tmp_path / "nan.csv")
    (tmp_path / "inf.csv").write_text("t_s,altitude_m,velocity_mps\n0,100,-5\n0.1,inf,-5\n")
    with pytest.raises(RecordingError, match=r"column 'altitude_m' holds inf at line 3"):
        read_ground_truth(tmp_path / "inf.csv")
    np.savez(tmp_path / "gt.npz", t_us=[0, 1, 2], divergence=[0.1, np.inf, 0.2])
    with pytest.raises(RecordingError, match=r"gt.npz \(ground-truth npz file\): ground truth column 'divergence' "
                                             r"holds inf at row 1"):
        read_ground_truth(tmp_path / "gt.npz")
    with pytest.raises(ValueError, match="'velocity_mps' holds nan at row 0"):
        GroundTruth.from_altitude([0, 1], [10.0, 9.0], [np.nan, -1.0])
    ok = write_ground_truth(tmp_path / "ok.csv", GroundTruth([0, 10], [-0.1, -0.2]))
    assert read_ground_truth(ok).divergence.tolist() == [-0.1, -0.2]


def test_ground_truth_inside_a_recording_checked(tmp_path):
    ref = read_recording(DATA / "descent_A.npz")
    save_events(tmp_path / "e.h5", ref.events, sensor_size=(64, 48), batch_size=1,
                ground_truth=GroundTruth([0, 10], [-0.1, -0.2]))
    with h5py.File(tmp_path / "e.h5", "r+") as h5:
        h5["ground_truth/divergence"][1] = np.nan
    with pytest.raises(RecordingError, match=r"e.h5 \(HDF5 file\): ground truth column 'divergence' holds nan "
                                             r"at row 1"):
        read_recording(tmp_path / "e.h5")


def test_cli_prints_one_line(tmp_path, capsys):
    from dvsland.cli.main import main

    (tmp_path / "cut.h5").write_bytes((DATA / "descent_A.h5").read_bytes()[:1000])
    rc = main(["evaluate", "paper", "--recording", str(tmp_path / "cut.h5"), "--estimators", "dpr", "--quiet",
               "--no-figures", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0 and "Traceback" not in err
    assert f"{tmp_path / 'cut.h5'} (HDF5 file): truncated or corrupt" in err
