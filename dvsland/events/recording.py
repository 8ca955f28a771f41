"""Recordings in and out: AEDAT4, HDF5, tonic structured arrays, plain npz and CSV, with an optional
ground-truth time series.

:func:`read_recording` returns a :class:`Recording` (one camera: events with b = 0, the sensor
size, the ground truth when the file or a side file has one); :func:`write_recording` writes one
batch element of :class:`~dvsland.events.Events` in any of the formats. Layouts read:

============  ==================================================================================
format        layouts
============  ==================================================================================
``.aedat4``   the event stream of an AEDAT4 file (iniVation DV), through ``dv-processing``
              (``pip install dvsland[aedat]``); polarity bool, True = ON
``.h5/.hdf5`` dvsland's own (``/events/{b,x,y,t,p}`` + a ``format`` tag); a group ``events`` with
              datasets ``x, y, t|ts|timestamp, p|polarity`` (the DSEC layout; a root ``t_offset``
              is added to t); the same datasets at the root; one ``events`` table (N, 4) with
              columns ``t, x, y, p`` (v2e's order; ``columns=`` for another) or a structured
              ``events`` dataset. gzip, lzf and szip filters are read by h5py; blosc and others
              need ``hdf5plugin`` imported first.
``.npz``      dvsland's own; arrays ``x, y, t|ts|timestamp, p|polarity``; or one structured
              array (tonic)
``.npy``      a tonic structured array (fields x, y, t, p)
``.csv/.txt`` comma- or blank-separated columns; a header row names them (``t_us`` / ``t_s`` /
              ``t``, ``x``, ``y``, ``p``), without one the order is ``t x y p`` (the event-camera
              dataset text format, t in seconds)
============  ==================================================================================

Polarity: {0, 1} (0 = OFF) and {-1, +1} are both read (:func:`validate_events` checks it). Time:
integer µs, or another unit by ``t_unit`` ("ns", "us", "ms", "s"); without it, integer columns
are µs and fractional ones seconds, and a header name ``t_s`` / ``t_ms`` / ``t_ns`` says it.

Ground truth: a time series of divergence D (1/s), or of altitude (m) and vertical velocity (m/s)
from which D = v / z. In npz: arrays ``gt_t_us`` and ``gt_divergence`` or ``gt_altitude_m`` +
``gt_velocity_mps``; in HDF5: a group ``ground_truth`` with ``t_us`` and the same names without
``gt_``; or a side file (CSV with a header ``t_us|t_s,divergence`` or
``t_us|t_s,altitude_m,velocity_mps``, or such an npz) passed as ``ground_truth=``. A ``gt_b``
(``b``) array holds several batch elements' series: the rows of element ``b`` are read. Event files
written by ``dvsland events`` carry their per-frame ground truth this way.
"""

from __future__ import annotations

import csv
import io as _io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from .events import TONIC_DTYPE, Events, validate_events
from .ground_truth import GroundTruth
from .io import load_events
from .validate import TIME_UNITS, times_to_us

PathLike = Union[str, Path]

FORMATS = ("aedat4", "h5", "npz", "npy", "csv")
_SUFFIX = {".aedat4": "aedat4", ".h5": "h5", ".hdf5": "h5", ".hdf": "h5", ".npz": "npz", ".npy": "npy",
           ".csv": "csv", ".txt": "csv"}
_T_NAMES = ("t", "t_us", "ts", "timestamp", "timestamps", "t_s", "t_ms", "t_ns", "time")
_P_NAMES = ("p", "polarity", "pol")
_UNIT_OF_NAME = {"t_s": "s", "t_ms": "ms", "t_ns": "ns", "t_us": "us"}


# ------------------------------------------------------------------------------ data types
@dataclass
class Recording:
    """One event camera's recording.

    Attributes:
        events: :class:`Events` (b = 0), sorted by t.
        sensor_size: (W, H) px.
        ground_truth: :class:`GroundTruth` or None.
        source: file name (or "array").
        format: the format read.
    """

    events: Events
    sensor_size: Tuple[int, int]
    ground_truth: Optional[GroundTruth] = None
    source: str = "array"
    format: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def t_range_us(self) -> Tuple[int, int]:
        """(first, last) event time, µs ((0, 0) without events)."""
        if len(self.events) == 0:
            return (0, 0)
        return int(self.events.t[0]), int(self.events.t[-1])


def _format_of(path: Path, fmt: Optional[str]) -> str:
    if fmt is None:
        fmt = _SUFFIX.get(path.suffix.lower())
        if fmt is None:
            raise ValueError(f"cannot tell the format of {path.name!r} from its suffix: use one of "
                             f"{sorted(_SUFFIX)} or pass format= one of {FORMATS}")
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    return fmt


def _pick(names, candidates, what: str, source: str) -> str:
    lower = {n.lower(): n for n in names}
    for c in candidates:
        if c in lower:
            return lower[c]
    raise ValueError(f"{source}: no {what} column; expected one of {list(candidates)}, found {list(names)}")


def _sensor_from(attrs, source) -> Optional[Tuple[int, int]]:
    if attrs is None:
        return None
    if "sensor_size" in attrs:
        s = np.asarray(attrs["sensor_size"]).reshape(-1)
        return int(s[0]), int(s[1])
    keys = {k.lower(): k for k in attrs.keys()}
    if "width" in keys and "height" in keys:
        return int(np.asarray(attrs[keys["width"]])), int(np.asarray(attrs[keys["height"]]))
    return None


def _from_columns(cols: Dict[str, np.ndarray], sensor_size, t_unit, source, b=0) -> Tuple[Events, Tuple[int, int]]:
    names = list(cols)
    tn = _pick(names, _T_NAMES, "time", source)
    pn = _pick(names, _P_NAMES, "polarity", source)
    xn, yn = _pick(names, ("x",), "x", source), _pick(names, ("y",), "y", source)
    unit = t_unit if t_unit is not None else _UNIT_OF_NAME.get(tn.lower())
    t = times_to_us(cols[tn], unit, source)
    ev = validate_events(cols[xn], cols[yn], t, cols[pn], sensor_size, source, b=b)
    if sensor_size is None:
        sensor_size = (int(ev.x.max()) + 1, int(ev.y.max()) + 1) if len(ev) else (1, 1)
    return ev, (int(sensor_size[0]), int(sensor_size[1]))


def _gt_from_mapping(m, prefix: str, source: str, b: int = 0) -> Optional[GroundTruth]:
    keys = set(m.keys())
    if f"{prefix}t_us" not in keys and f"{prefix}t_s" not in keys:
        return None
    if f"{prefix}b" in keys:  # several batch elements (dvsland events files): element b's rows
        rows = np.asarray(m[f"{prefix}b"]).reshape(-1) == int(b)
        if not rows.any():
            return None
        m = {k: np.asarray(m[k]).reshape(-1)[rows] for k in keys
             if k.startswith(prefix) and k != f"{prefix}b" and np.asarray(m[k]).ndim == 1
             and len(np.asarray(m[k])) == len(rows)}
        keys = set(m.keys())
    t = (np.asarray(m[f"{prefix}t_us"]) if f"{prefix}t_us" in keys
         else times_to_us(np.asarray(m[f"{prefix}t_s"]), "s", source))
    if f"{prefix}altitude_m" in keys and f"{prefix}velocity_mps" in keys:
        return GroundTruth.from_altitude(t, np.asarray(m[f"{prefix}altitude_m"]),
                                         np.asarray(m[f"{prefix}velocity_mps"]))
    if f"{prefix}divergence" in keys:
        return GroundTruth(t, np.asarray(m[f"{prefix}divergence"]))
    raise ValueError(f"{source}: ground truth has times but neither divergence nor altitude_m + velocity_mps")


# ------------------------------------------------------------------------------- readers
def read_ground_truth(path: PathLike, b: int = 0) -> GroundTruth:
    """A ground-truth side file: CSV with a header (``t_us`` or ``t_s``; ``divergence`` or
    ``altitude_m`` and ``velocity_mps``) or npz with those arrays (optionally ``gt_``-prefixed;
    a ``b`` / ``gt_b`` column selects element ``b``, as in dvsland events files)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(path)
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:
            gt = _gt_from_mapping(z, "gt_", str(path), b) or _gt_from_mapping(z, "", str(path), b)
    else:
        cols = _read_table(path, header_required=True)
        gt = _gt_from_mapping(cols, "", str(path), b)
    if gt is None:
        raise ValueError(f"{path}: no ground-truth time column (t_us or t_s)" + (f" for element b = {b}" if b else ""))
    return gt


def _read_table(path: Path, header_required: bool = False, columns: Optional[Sequence[str]] = None):
    text = path.read_text()
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{path}: empty file")
    delim = "," if "," in lines[0] else None
    first = lines[0].split(delim) if delim else lines[0].split()
    first = [f.strip() for f in first]

    def numeric(s):
        try:
            float(s)
            return True
        except ValueError:
            return False

    has_header = not all(numeric(f) for f in first)
    if has_header:
        names, body = first, lines[1:]
    else:
        if header_required:
            raise ValueError(f"{path}: needs a header row naming the columns")
        names, body = list(columns or ("t", "x", "y", "p")), lines
    if body:
        try:
            data = np.loadtxt(_io.StringIO("\n".join(body)), delimiter=delim, ndmin=2, dtype=np.float64)
        except ValueError as e:
            raise ValueError(f"{path}: not a numeric table ({e})") from None
    else:
        data = np.empty((0, len(names)))
    if data.shape[1] != len(names):
        raise ValueError(f"{path}: {data.shape[1]} columns but {len(names)} names {names}")
    cols = {}
    for i, n in enumerate(names):
        c = data[:, i]
        cols[n] = c.astype(np.int64) if c.size and np.all(c == np.floor(c)) and np.abs(c).max() < 2 ** 53 else c
    return cols


def _read_h5(path: Path, t_unit, columns, b: int):
    import h5py

    try:
        import hdf5plugin  # noqa: F401  (registers blosc, zstd, ... filters when installed)
    except ImportError:
        pass
    src = str(path)
    with h5py.File(path, "r") as h5:
        g = h5.get("events")
        gt = None
        if "ground_truth" in h5:
            gt = _gt_from_mapping({k: h5["ground_truth"][k][()] for k in h5["ground_truth"]}, "", src, b)
        sensor = _sensor_from(h5.attrs, src)
        if isinstance(g, h5py.Group) and g.attrs.get("format", "") != "" and "b" in g:
            ev, meta = load_events(path, with_meta=True)
            ev = ev.select_batch(b)
            ev = Events(torch.zeros_like(ev.b), ev.x, ev.y, ev.t, ev.p)
            ss = meta.get("sensor_size")
            return ev, (ss[0], ss[1]) if ss else None, gt, "dvsland"
        if isinstance(g, h5py.Group):
            sensor = sensor or _sensor_from(g.attrs, src)
            cols = {k: g[k][()] for k in g if isinstance(g[k], h5py.Dataset)}
            if "t_offset" in h5:
                tn = _pick(list(cols), _T_NAMES, "time", src)
                cols[tn] = cols[tn].astype(np.int64) + int(np.asarray(h5["t_offset"][()]).reshape(-1)[0])
            layout = "events group"
        elif isinstance(g, h5py.Dataset):
            sensor = sensor or _sensor_from(g.attrs, src)
            arr = g[()]
            if arr.dtype.names:
                cols = {n: arr[n] for n in arr.dtype.names}
                layout = "structured events"
            else:
                if arr.ndim != 2 or arr.shape[1] != len(columns):
                    raise ValueError(f"{src}: dataset 'events' has shape {arr.shape}; expected (N, {len(columns)}) "
                                     f"with columns {list(columns)}")
                cols = {n: arr[:, i] for i, n in enumerate(columns)}
                layout = "events table"
        else:
            cols = {k: h5[k][()] for k in h5 if isinstance(h5[k], h5py.Dataset)}
            layout = "root datasets"
    ev, sensor = _from_columns(cols, sensor, t_unit, src)
    return ev, sensor, gt, layout


def _read_aedat4(path: Path):
    try:
        import dv_processing as dv
    except ImportError:
        raise ImportError("reading AEDAT4 needs dv-processing: pip install 'dvsland[aedat]' "
                          "(or pip install dv-processing)") from None
    rec = dv.io.MonoCameraRecording(str(path))
    if not rec.isEventStreamAvailable():
        raise ValueError(f"{path}: no event stream in this AEDAT4 file")
    W, H = rec.getEventResolution()
    parts = []
    while rec.isRunning():
        batch = rec.getNextEventBatch()
        if batch is None:
            break
        if batch.size():
            parts.append(batch.numpy())
    arr = np.concatenate(parts) if parts else np.empty(0, dtype=[("timestamp", "<i8"), ("x", "<i2"),
                                                                  ("y", "<i2"), ("polarity", "i1")])
    ev = validate_events(arr["x"], arr["y"], arr["timestamp"].astype(np.int64), arr["polarity"], (W, H), str(path))
    return ev, (int(W), int(H))


def read_recording(path, format: Optional[str] = None, ground_truth: Optional[PathLike] = None,
                   t_unit: Optional[str] = None, sensor_size: Optional[Tuple[int, int]] = None,
                   columns: Sequence[str] = ("t", "x", "y", "p"), b: int = 0, device=None) -> Recording:
    """Read a recording (see the module docstring for the layouts).

    Args:
        path: file, or a numpy structured array (tonic) with fields x, y, t, p.
        format: one of "aedat4", "h5", "npz", "npy", "csv"; default from the suffix.
        ground_truth: side file with the ground truth (overrides one inside the file).
        t_unit: unit of the time column ("ns", "us", "ms", "s"); default: guessed (module doc).
        sensor_size: (W, H); default from the file, else max coordinate + 1.
        columns: column order of header-less tables and (N, 4) HDF5 tables.
        b: which batch element of a dvsland events file.
        device: device of the events.

    Returns:
        :class:`Recording`.

    Raises:
        FileNotFoundError: no such file.
        ValueError: bad layout or values (the message names the file and field).
        ImportError: AEDAT4 without dv-processing.
    """
    if t_unit is not None and t_unit not in TIME_UNITS:
        raise ValueError(f"t_unit must be one of {sorted(TIME_UNITS)}, got {t_unit!r}")
    if isinstance(path, np.ndarray):
        names = path.dtype.names or ()
        ev, ss = _from_columns({n: path[n] for n in names}, sensor_size, t_unit, "array")
        gt = read_ground_truth(ground_truth) if ground_truth is not None else None
        return Recording(ev.to(device) if device else ev, ss, gt, "array", "tonic")
    path = Path(path)
    fmt = _format_of(path, format)
    if not path.exists():
        raise FileNotFoundError(path)
    src = str(path)
    gt = None
    layout = fmt
    if fmt == "aedat4":
        ev, ss = _read_aedat4(path)
    elif fmt == "h5":
        ev, ss, gt, layout = _read_h5(path, t_unit, columns, b)
    elif fmt == "npz":
        try:
            z = np.load(path, allow_pickle=False)
        except Exception as e:  # zipfile.BadZipFile, EOFError, ...
            raise ValueError(f"{src}: not a readable npz file ({type(e).__name__}: {e})") from None
        with z:
            files = z.files
            if "meta_format" in files and "b" in files:
                ev, meta = load_events(path, with_meta=True)
                ev = ev.select_batch(b)
                ev = Events(torch.zeros_like(ev.b), ev.x, ev.y, ev.t, ev.p)
                ss = tuple(meta["sensor_size"][:2]) if "sensor_size" in meta else None
                layout = "dvsland"
            else:
                structured = [k for k in files if z[k].dtype.names]
                if structured:
                    arr = z[structured[0]]
                    cols = {n: arr[n] for n in arr.dtype.names}
                else:
                    cols = {k: z[k] for k in files if z[k].ndim == 1 and not k.startswith("gt_")}
                ss = sensor_size or (tuple(int(v) for v in z["sensor_size"][:2]) if "sensor_size" in files else None)
                ev, ss = _from_columns(cols, ss, t_unit, src)
            gt = _gt_from_mapping(z, "gt_", src, b)
    elif fmt == "npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as e:
            raise ValueError(f"{src}: not a readable npy file ({type(e).__name__}: {e})") from None
        if not arr.dtype.names:
            raise ValueError(f"{src}: expected a structured array with fields x, y, t, p (tonic), got {arr.dtype}")
        ev, ss = _from_columns({n: arr[n] for n in arr.dtype.names}, sensor_size, t_unit, src)
    else:
        ev, ss = _from_columns(_read_table(path, columns=columns), sensor_size, t_unit, src)
    if sensor_size is not None:
        ss = (int(sensor_size[0]), int(sensor_size[1]))
        ev.validate(1, ss[1], ss[0])
    if ss is None:
        ss = (int(ev.x.max()) + 1, int(ev.y.max()) + 1) if len(ev) else (1, 1)
    if ground_truth is not None:
        gt = read_ground_truth(ground_truth, b)
    if device is not None:
        ev = ev.to(device)
    return Recording(ev, (int(ss[0]), int(ss[1])), gt, src, fmt, {"layout": layout})


# ------------------------------------------------------------------------------- writers
def _columns_of(events: Events, b: int, polarity: str):
    if polarity not in ("pm1", "01"):
        raise ValueError(f"polarity must be 'pm1' (-1/+1, dvsland) or '01' (0 = OFF, tonic), got {polarity!r}")
    ev = events.select_batch(b) if len(events) and int(events.b.max()) > 0 else events
    x = ev.x.cpu().numpy()
    y = ev.y.cpu().numpy()
    if len(ev) and (x.min() < 0 or y.min() < 0 or x.max() > 32767 or y.max() > 32767):
        raise ValueError("x and y must be in [0, 32767] to be written as int16")
    p = ev.p.cpu().numpy()
    p = (p > 0).astype(np.int8) if polarity == "01" else p.astype(np.int8)
    return x.astype(np.int16), y.astype(np.int16), ev.t.cpu().numpy().astype(np.int64), p


def write_recording(path: PathLike, events: Events, sensor_size: Tuple[int, int],
                    ground_truth: Optional[GroundTruth] = None, format: Optional[str] = None,
                    polarity: str = "pm1", b: int = 0, compression: Optional[str] = "gzip",
                    compression_level: int = 4, chunk_events: int = 1 << 16) -> Path:
    """Write batch element ``b`` of ``events`` as a recording.

    Args:
        path: output file; the format from the suffix unless ``format`` is given.
        events: :class:`Events` (any device).
        sensor_size: (W, H) px.
        ground_truth: written into npz (``gt_*`` arrays) and HDF5 (``/ground_truth``); for CSV,
            AEDAT4 and npy write it with :func:`write_ground_truth`.
        polarity: "pm1" writes -1/+1 (dvsland), "01" writes 0/1 with 0 = OFF (tonic, most HDF5
            tools). npy (a tonic array) and AEDAT4 (bool) always use their own 0/1 / bool form.
        compression: HDF5 filter ("gzip", "lzf" or None); npz is always zip-compressed.
        compression_level: gzip level 0-9.
        chunk_events: HDF5 chunk length (events), >= 1.

    Returns:
        The path written.
    """
    path = Path(path)
    fmt = _format_of(path, format)
    W, H = int(sensor_size[0]), int(sensor_size[1])
    if W < 1 or H < 1:
        raise ValueError(f"sensor_size must be (W, H) with W, H >= 1, got {sensor_size}")
    if compression not in ("gzip", "lzf", None):
        raise ValueError(f"compression must be 'gzip', 'lzf' or None, got {compression!r}")
    if not 0 <= int(compression_level) <= 9:
        raise ValueError(f"compression_level must be in [0, 9], got {compression_level}")
    if int(chunk_events) < 1:
        raise ValueError(f"chunk_events must be >= 1, got {chunk_events}")
    x, y, t, p = _columns_of(events, b, polarity)
    if len(x) and (x.max() >= W or y.max() >= H):
        raise ValueError(f"events reach ({x.max()}, {y.max()}), outside sensor_size (W, H) = ({W}, {H})")
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "h5":
        import h5py

        with h5py.File(path, "w") as h5:
            g = h5.create_group("events")
            n = len(x)
            kw = {}
            if n:
                kw["chunks"] = (min(int(chunk_events), n),)
                if compression is not None:
                    kw["compression"] = compression
                    if compression == "gzip":
                        kw["compression_opts"] = int(compression_level)
                    kw["shuffle"] = True
            for name, a in (("x", x), ("y", y), ("t", t), ("p", p)):
                g.create_dataset(name, data=a, **kw)
            g.attrs["t_unit"] = "us"
            g.attrs["polarity"] = "0 = OFF, 1 = ON" if polarity == "01" else "-1 = OFF, +1 = ON"
            h5.attrs["sensor_size"] = np.array([W, H], dtype=np.int64)
            h5.attrs["width"], h5.attrs["height"] = W, H
            if ground_truth is not None:
                gg = h5.create_group("ground_truth")
                for k, v in ground_truth.arrays().items():
                    gg.create_dataset(k, data=v)
    elif fmt == "npz":
        extra = ground_truth.arrays("gt_") if ground_truth is not None else {}
        with open(path, "wb") as fh:
            np.savez_compressed(fh, x=x, y=y, t=t, p=p, sensor_size=np.array([W, H], dtype=np.int64), **extra)
    elif fmt == "npy":
        arr = np.empty(len(x), dtype=TONIC_DTYPE)
        arr["x"], arr["y"], arr["t"], arr["p"] = x, y, t, (p > 0).astype(np.int8)
        with open(path, "wb") as fh:
            np.save(fh, arr)
    elif fmt == "csv":
        with open(path, "w", newline="") as fh:
            fh.write("t_us,x,y,p\n")
            if len(x):
                np.savetxt(fh, np.stack([t, x.astype(np.int64), y.astype(np.int64), p.astype(np.int64)], 1),
                           fmt="%d", delimiter=",")
    else:
        _write_aedat4(path, x, y, t, p, W, H)
    return path


def _write_aedat4(path: Path, x, y, t, p, W: int, H: int) -> None:
    try:
        import dv_processing as dv
    except ImportError:
        raise ImportError("writing AEDAT4 needs dv-processing: pip install 'dvsland[aedat]' "
                          "(or pip install dv-processing)") from None
    cfg = dv.io.MonoCameraWriter.EventOnlyConfig("dvsland", (W, H))
    writer = dv.io.MonoCameraWriter(str(path), cfg)
    store = dv.EventStore()
    # dv-processing's Python API has no bulk constructor: one push per event (~1 µs each)
    for ti, xi, yi, pi in zip(t.tolist(), x.tolist(), y.tolist(), (p > 0).tolist()):
        store.push_back(ti, xi, yi, pi)
    if store.size():
        writer.writeEvents(store)
    del writer  # closes the file


def write_ground_truth(path: PathLike, gt: GroundTruth) -> Path:
    """Write ``gt`` as CSV (header ``t_us,divergence[,altitude_m,velocity_mps]``) or npz (by suffix)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrs = gt.arrays()
    if path.suffix.lower() == ".npz":
        with open(path, "wb") as fh:
            np.savez(fh, **arrs)
        return path
    names = list(arrs)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for row in zip(*(arrs[n].tolist() for n in names)):
            w.writerow([repr(v) if isinstance(v, float) else v for v in row])
    return path


__all__ = ["Recording", "GroundTruth", "read_recording", "write_recording", "read_ground_truth",
           "write_ground_truth", "FORMATS"]
