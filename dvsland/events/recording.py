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

Damaged files: every reader turns a file it cannot use - empty, truncated, corrupt, not UTF-8 text,
a CSV line cut short, a coordinate outside the declared sensor (or beyond :data:`MAX_SENSOR_PX`
when the size is inferred), a timestamp beyond int64, ground truth that is not finite - into one
:class:`RecordingError` (a ValueError) ``"<file> (<format> file): <what is wrong>"``. Sizes read
from a file are checked against the file's size before anything is allocated, and AEDAT4 is parsed
by dv-processing in a child process with a time limit (it can loop forever on a corrupt packet),
so no read can hang and Ctrl-C always stops one.
"""

from __future__ import annotations

import csv
import io as _io
import logging
import os
import struct
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from .events import TONIC_DTYPE, Events, validate_events
from .ground_truth import GroundTruth
from .io import Unreadable, check_npz, h5_read, load_events, load_npy, open_npz
from .validate import TIME_UNITS, EventDataError, RecordingError, _range_check, times_to_us

PathLike = Union[str, Path]
log = logging.getLogger(__name__)

FORMATS = ("aedat4", "h5", "npz", "npy", "csv")
_SUFFIX = {".aedat4": "aedat4", ".h5": "h5", ".hdf5": "h5", ".hdf": "h5", ".npz": "npz", ".npy": "npy",
           ".csv": "csv", ".txt": "csv"}
_LABEL = {"aedat4": "AEDAT4", "h5": "HDF5", "npz": "npz", "npy": "npy", "csv": "CSV"}
_T_NAMES = ("t", "t_us", "ts", "timestamp", "timestamps", "t_s", "t_ms", "t_ns", "time")
_P_NAMES = ("p", "polarity", "pol")
_UNIT_OF_NAME = {"t_s": "s", "t_ms": "ms", "t_ns": "ns", "t_us": "us"}
_I64 = np.iinfo(np.int64)

#: largest sensor side (px): a declared size must be within it, and without one every coordinate
#: must be below it (the sensor is then inferred from the largest coordinates, and logged)
MAX_SENSOR_PX = 65536
#: dv-processing parses an AEDAT4 file in a child process given BASE + PER_MB * (file size in MB)
#: seconds; past that the read is an error ("could not be parsed in N s")
AEDAT4_TIMEOUT_BASE_S = 10.0
AEDAT4_TIMEOUT_PER_MB_S = 0.5


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
        meta: {"layout": the layout read, "sensor_size_from": "argument", "file" or "inferred"}.
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


# ------------------------------------------------------------------------ one error per file
def _fail(path, fmt: str, what: str) -> RecordingError:
    """The one reader error: ``"<file> (<format> file): <what is wrong>"``."""
    return RecordingError(f"{path} ({_LABEL.get(fmt, fmt)} file): {what}")


def _first_line(exc: BaseException) -> str:
    """The telling line of an exception's message (dv-processing's carry a C++ stack trace)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    msg = next((ln for ln in lines if "Error info:" in ln), lines[0] if lines else type(exc).__name__)
    return msg if len(msg) <= 300 else msg[:300] + " ..."


def _as_recording_error(exc: Exception, path, fmt: str) -> RecordingError:
    """Any exception of a reader (dvsland's check or a library's failure) as the one error."""
    msg, src = _first_line(exc), f"{path}: "
    if msg.startswith(src):
        return _fail(path, fmt, msg[len(src):])
    if isinstance(exc, (EventDataError, Unreadable)):
        return _fail(path, fmt, msg)
    if isinstance(exc, (PermissionError, IsADirectoryError)):
        return _fail(path, fmt, f"cannot be opened ({type(exc).__name__}: {msg})")
    return _fail(path, fmt, f"truncated or corrupt ({type(exc).__name__}: {msg})")


class _Opts(NamedTuple):
    t_unit: Optional[str]
    columns: Tuple[str, ...]
    b: int


# --------------------------------------------------------------------------- columns, sensor
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
        return s[0], s[1]
    keys = {k.lower(): k for k in attrs.keys()}
    if "width" in keys and "height" in keys:
        return np.asarray(attrs[keys["width"]]).reshape(-1)[0], np.asarray(attrs[keys["height"]]).reshape(-1)[0]
    return None


def _sensor_pair(size, origin: str) -> Tuple[int, int]:
    """(W, H) of a declared sensor: whole numbers in [1, MAX_SENSOR_PX] (Unreadable otherwise)."""
    try:
        W, H = int(size[0]), int(size[1])
        ok = W == size[0] and H == size[1] and 1 <= W <= MAX_SENSOR_PX and 1 <= H <= MAX_SENSOR_PX
    except (TypeError, ValueError, IndexError, OverflowError):
        ok = False
    if not ok:
        try:
            size = tuple(np.asarray(size).reshape(-1).tolist())
        except (TypeError, ValueError):
            pass
        raise Unreadable(f"sensor_size {origin} is {size!r}; it must be (W, H), whole numbers in "
                         f"[1, {MAX_SENSOR_PX}]")
    return W, H


def _settle_sensor(ev: Events, declared, origin: str, src: str) -> Tuple[Tuple[int, int], str]:
    """The recording's sensor (W, H) and where it comes from ("argument", "file" or "inferred").

    A ``declared`` size (``origin`` says by whom) must hold every event: an x or y outside it is an
    EventDataError naming the coordinate, its event and the size. Without one the size is inferred
    from the largest coordinates, each below MAX_SENSOR_PX (an absurd coordinate is an error), and
    the inferred size is logged (INFO).
    """
    x, y = ev.x.cpu().numpy(), ev.y.cpu().numpy()
    if declared is not None:
        W, H = _sensor_pair(declared, origin)
        why = f"sensor_size (W, H) = ({W}, {H}) {origin}"
        _range_check("x", x, 0, W, src, why)
        _range_check("y", y, 0, H, src, why)
        return (W, H), ("argument" if origin.startswith("given") else "file")
    why = f"no sensor size declared, and a sensor inferred from the data is at most {MAX_SENSOR_PX} px"
    _range_check("x", x, 0, MAX_SENSOR_PX, src, why)
    _range_check("y", y, 0, MAX_SENSOR_PX, src, why)
    W, H = (int(x.max()) + 1, int(y.max()) + 1) if len(x) else (1, 1)
    log.info("%s: no sensor size declared; inferred (W, H) = (%d, %d) from the largest coordinates", src, W, H)
    return (W, H), "inferred"


def _from_columns(cols: Dict[str, np.ndarray], t_unit, source, b=0) -> Events:
    """Events from named columns (time, x, y, polarity; names as in the module doc), every value
    checked (:func:`validate_events`) except against a sensor size (:func:`_settle_sensor`)."""
    names = list(cols)
    tn = _pick(names, _T_NAMES, "time", source)
    pn = _pick(names, _P_NAMES, "polarity", source)
    xn, yn = _pick(names, ("x",), "x", source), _pick(names, ("y",), "y", source)
    unit = t_unit if t_unit is not None else _UNIT_OF_NAME.get(tn.lower())
    t = times_to_us(cols[tn], unit, source)
    _note_disorder(t, source)
    return validate_events(cols[xn], cols[yn], t, cols[pn], None, source, b=b)


def _note_disorder(t: np.ndarray, source: str) -> None:
    """Log (WARNING) events out of time order: they are sorted (stably), but in a file without a
    checksum (npy, CSV, uncompressed HDF5) a run of them may be damage rather than the recording."""
    if t.size > 1:
        back = int(np.count_nonzero(t[1:] < t[:-1]))
        if back:
            log.warning("%s: %d of %d events go back in time; sorted by t (a damaged file?)", source, back, t.size)


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
    try:  # GroundTruth checks the values (finite, increasing): its ValueError names column and row
        t = (np.asarray(m[f"{prefix}t_us"]) if f"{prefix}t_us" in keys
             else times_to_us(np.asarray(m[f"{prefix}t_s"]), "s", source))
        if f"{prefix}altitude_m" in keys and f"{prefix}velocity_mps" in keys:
            return GroundTruth.from_altitude(t, np.asarray(m[f"{prefix}altitude_m"]),
                                             np.asarray(m[f"{prefix}velocity_mps"]))
        if f"{prefix}divergence" in keys:
            return GroundTruth(t, np.asarray(m[f"{prefix}divergence"]))
    except ValueError as exc:
        raise Unreadable(str(exc)) from None
    raise ValueError(f"{source}: ground truth has times but neither divergence nor altitude_m + velocity_mps")


# ------------------------------------------------------------------------------- text tables
def _read_text(path: Path) -> str:
    """A text file's content (UTF-8, an optional BOM). Binary data or another encoding is an
    Unreadable naming the byte and its line."""
    raw = path.read_bytes()
    nul = raw.find(b"\x00")
    if nul >= 0:
        line = raw.count(b"\n", 0, nul) + 1
        raise Unreadable(f"binary data, not a text table: a NUL byte at byte {nul} (line {line})")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        at = min(exc.start + (3 if raw.startswith(b"\xef\xbb\xbf") else 0), len(raw) - 1)
        line = raw.count(b"\n", 0, at) + 1
        raise Unreadable(f"not UTF-8 text: byte 0x{raw[at]:02x} at byte {at} (line {line}) is not valid "
                         f"UTF-8 (latin-1 or binary?); save the table as UTF-8 or ASCII") from None


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _check_row(row: Tuple[int, str], names, delim, last: bool = False) -> None:
    """A data line has one number per column name (Unreadable naming the line otherwise)."""
    no, text = row
    text = text.split("#", 1)[0]  # an end-of-line comment, as numpy reads it
    fields = [f.strip() for f in (text.split(delim) if delim else text.split())]
    bad = next((f for f in fields if not _is_number(f)), None)
    if len(fields) == len(names) and bad is None:
        return
    what = (f"{len(fields)} fields where the columns {', '.join(names)} need {len(names)}"
            if len(fields) != len(names) else f"field {bad!r} is not a number")
    cut = " (the last line: was the file cut mid-line?)" if last else ""
    raise Unreadable(f"line {no}: {what}{cut}")


def _parse_rows(body, names, delim) -> np.ndarray:
    """The numbers of the data lines as (N, len(names)): int64 where every value is an integer
    (exact, no float rounding of large timestamps), else float64. The last line is checked first
    (a file cut mid-line), any bad line is named by its number."""
    if not body:
        return np.empty((0, len(names)))
    _check_row(body[-1], names, delim, last=True)
    text = "\n".join(ln for _, ln in body)
    for dtype in (np.int64, np.float64):
        try:
            return np.loadtxt(_io.StringIO(text), delimiter=delim, ndmin=2, dtype=dtype)
        except (ValueError, OverflowError):
            pass
    for row in body:
        _check_row(row, names, delim)
    raise Unreadable("not a numeric table")


def _read_table(path: Path, header_required: bool = False, columns: Optional[Sequence[str]] = None):
    """The columns of a text table (comma- or blank-separated, ``#`` comment lines, an optional
    header row) and the file line number of every data row ((N,) int64)."""
    rows = [(i, ln) for i, ln in enumerate(_read_text(path).split("\n"), 1)
            if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise Unreadable("no data: only blank or comment lines")
    delim = "," if "," in rows[0][1] else None
    first = [f.strip() for f in (rows[0][1].split(delim) if delim else rows[0][1].split())]
    if not all(_is_number(f) for f in first):
        names, body = first, rows[1:]
    elif header_required:
        raise Unreadable("needs a header row naming the columns")
    else:
        names, body = list(columns or ("t", "x", "y", "p")), rows
    data = _parse_rows(body, names, delim)
    if data.shape[1] != len(names):
        raise Unreadable(f"{data.shape[1]} columns but {len(names)} names {names}")
    cols = {}
    for i, n in enumerate(names):
        c = data[:, i]
        whole = c.dtype.kind == "f" and c.size and np.all(c == np.floor(c)) and np.abs(c).max() < 2 ** 53
        cols[n] = c.astype(np.int64) if whole else c
    return cols, np.array([i for i, _ in body], dtype=np.int64)


# ----------------------------------------------------------------------------- ground truth
_GT_COLUMNS = ("t_us", "t_s", "divergence", "altitude_m", "velocity_mps", "b")


def read_ground_truth(path: PathLike, b: int = 0) -> GroundTruth:
    """A ground-truth side file: CSV with a header (``t_us`` or ``t_s``; ``divergence`` or
    ``altitude_m`` and ``velocity_mps``) or npz with those arrays (optionally ``gt_``-prefixed;
    a ``b`` / ``gt_b`` column selects element ``b``, as in dvsland events files).

    Raises:
        FileNotFoundError: no such file.
        RecordingError: (a ValueError) an empty, truncated, corrupt or non-UTF-8 file, a line cut
            short, or a value that is not finite (naming the file, the column and the line / row).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(path)
    kind = "ground-truth npz" if path.suffix.lower() == ".npz" else "ground-truth CSV"
    try:
        if path.stat().st_size == 0:
            raise Unreadable("empty file (0 bytes)")
        gt = _read_gt_npz(path, b) if kind.endswith("npz") else _read_gt_csv(path, b)
    except (ImportError, RecordingError):
        raise
    except Exception as exc:
        raise _as_recording_error(exc, path, kind) from None
    if gt is None:
        raise _fail(path, kind, "no ground-truth time column (t_us or t_s)" + (f" for element b = {b}" if b else ""))
    return gt


def _read_gt_csv(path: Path, b: int) -> Optional[GroundTruth]:
    cols, lines = _read_table(path, header_required=True)
    for name in _GT_COLUMNS:
        c = cols.get(name)
        if c is not None and c.dtype.kind == "f" and not np.isfinite(c).all():
            i = int(np.argmax(~np.isfinite(c)))
            raise Unreadable(f"column {name!r} holds {c[i]} at line {lines[i]}; ground truth must be finite")
    return _gt_from_mapping(cols, "", str(path), b)


def _read_gt_npz(path: Path, b: int) -> Optional[GroundTruth]:
    with open_npz(path) as z:
        check_npz(z, path)
        arrs = {k: z[k] for k in z.files}
    return _gt_from_mapping(arrs, "gt_", str(path), b) or _gt_from_mapping(arrs, "", str(path), b)


# ------------------------------------------------------------------------------ the formats
def _dvsland_events(path: Path, b: int) -> Tuple[Events, Optional[Tuple[int, int]]]:
    """Element ``b`` of a dvsland events file (as b = 0) and the sensor size it stores."""
    ev, meta = load_events(path, with_meta=True)
    ev = ev.select_batch(b)
    ss = meta.get("sensor_size")
    return (Events(torch.zeros_like(ev.b), ev.x, ev.y, ev.t, ev.p),
            (ss[0], ss[1]) if ss and ss[0] > 0 and ss[1] > 0 else None)


def _read_csv(path: Path, o: _Opts):
    cols, _ = _read_table(path, columns=o.columns)
    return _from_columns(cols, o.t_unit, str(path)), None, None, "csv"


def _read_npy(path: Path, o: _Opts):
    arr = load_npy(path)
    if not arr.dtype.names:
        raise Unreadable(f"expected a structured array with fields x, y, t, p (tonic), got {arr.dtype}")
    return _from_columns({n: arr[n] for n in arr.dtype.names}, o.t_unit, str(path)), None, None, "npy"


def _read_npz(path: Path, o: _Opts):
    src = str(path)
    with open_npz(path) as z:
        check_npz(z, path)
        arrs = {k: z[k] for k in z.files}
    gt = _gt_from_mapping(arrs, "gt_", src, o.b)
    if "meta_format" in arrs and "b" in arrs:
        ev, ss = _dvsland_events(path, o.b)
        return ev, ss, gt, "dvsland"
    structured = [k for k, a in arrs.items() if a.dtype.names]
    if structured:
        a = arrs[structured[0]]
        cols = {n: a[n] for n in a.dtype.names}
    else:
        cols = {k: a for k, a in arrs.items() if a.ndim == 1 and not k.startswith("gt_")}
    ss = np.asarray(arrs["sensor_size"]).reshape(-1)[:2] if "sensor_size" in arrs else None
    return _from_columns(cols, o.t_unit, src), ss, gt, "npz"


def _add_offset(t: np.ndarray, off, src: str) -> np.ndarray:
    """DSEC's ``t + t_offset``: in int64 when both are integers (beyond int64 is an error, never a
    wrap), else in float64."""
    off = np.asarray(off).reshape(-1)
    if off.size != 1:
        raise Unreadable(f"t_offset must hold one value, got shape {off.shape}")
    if t.dtype.kind not in "iub" or off.dtype.kind not in "iub":
        return t.astype(np.float64) + float(off[0])
    t, o = times_to_us(t, "us", src), int(off[0])
    if t.size and not (_I64.min <= int(t.min()) + o and int(t.max()) + o <= _I64.max):
        raise Unreadable(f"t + t_offset ({o}) leaves the int64 range")
    return t + np.int64(o) if t.size else t


def _h5_columns(h5, g, columns, src: str, size: int):
    """(columns, sensor declared by attributes, layout name) of a foreign HDF5 layout."""
    import h5py

    sensor = _sensor_from(h5.attrs, src)
    if isinstance(g, h5py.Group):
        cols = {k: h5_read(g[k], size) for k in g if isinstance(g[k], h5py.Dataset)}
        if "t_offset" in h5:
            tn = _pick(list(cols), _T_NAMES, "time", src)
            cols[tn] = _add_offset(cols[tn], h5_read(h5["t_offset"], size), src)
        return cols, sensor or _sensor_from(g.attrs, src), "events group"
    if isinstance(g, h5py.Dataset):
        sensor = sensor or _sensor_from(g.attrs, src)
        arr = h5_read(g, size)
        if arr.dtype.names:
            return {n: arr[n] for n in arr.dtype.names}, sensor, "structured events"
        if arr.ndim != 2 or arr.shape[1] != len(columns):
            raise Unreadable(f"dataset 'events' has shape {arr.shape}; expected (N, {len(columns)}) with "
                             f"columns {list(columns)}")
        return {n: arr[:, i] for i, n in enumerate(columns)}, sensor, "events table"
    cols = {k: h5_read(h5[k], size) for k in h5 if isinstance(h5[k], h5py.Dataset) and h5[k].ndim == 1}
    return cols, sensor, "root datasets"


def _read_h5(path: Path, o: _Opts):
    import h5py

    try:
        import hdf5plugin  # noqa: F401  (registers blosc, zstd, ... filters when installed)
    except ImportError:
        pass
    src, size = str(path), path.stat().st_size
    with h5py.File(path, "r") as h5:
        gt = None
        if isinstance(h5.get("ground_truth"), h5py.Group):
            gg = h5["ground_truth"]
            gt = _gt_from_mapping({k: h5_read(gg[k], size) for k in gg if isinstance(gg[k], h5py.Dataset)},
                                  "", src, o.b)
        g = h5.get("events")
        if isinstance(g, h5py.Group) and g.attrs.get("format", "") != "" and "b" in g:
            ev, ss = _dvsland_events(path, o.b)
            return ev, ss, gt, "dvsland"
        cols, sensor, layout = _h5_columns(h5, g, o.columns, src, size)
    return _from_columns(cols, o.t_unit, src), sensor, gt, layout


# ----------------------------------------------------------------------------------- AEDAT4
_AEDAT4_MAGIC = b"#!AER-DAT4.0\r\n"


def _aedat4_header(buf: bytes) -> Tuple[int, int]:
    """(compression, dataTablePosition) of an AEDAT4 IOHeader flatbuffer, every offset checked."""
    def get(fmt: str, at: int):
        if at < 0 or at + struct.calcsize(fmt) > len(buf):
            raise Unreadable("the IOHeader is corrupt: an offset points outside it")
        return struct.unpack_from(fmt, buf, at)[0]

    root = get("<I", 0)
    vtable = root - get("<i", root)
    vt_len = get("<H", vtable)
    slot = [get("<H", vtable + 4 + 2 * i) if 4 + 2 * i + 2 <= vt_len else 0 for i in range(2)]
    compression = get("<i", root + slot[0]) if slot[0] else 0
    table = get("<q", root + slot[1]) if slot[1] else -1
    return compression, table


def _aedat4_frame(fh, size: int) -> Tuple[int, int, str]:
    """Check the version line and the header of an open AEDAT4 file of ``size`` bytes; return
    (first packet byte, end of the packets, what that end is) - the data table or the file's end."""
    head = fh.read(len(_AEDAT4_MAGIC) + 4)
    if not head.startswith(_AEDAT4_MAGIC):
        if _AEDAT4_MAGIC.startswith(head):
            raise Unreadable(f"truncated: the file ends inside its version line ({size} bytes)")
        raise Unreadable("not an AEDAT4 file: it does not begin with the version line '#!AER-DAT4.0'")
    if len(head) < len(_AEDAT4_MAGIC) + 4:
        raise Unreadable(f"truncated: the file ends before its header ({size} bytes)")
    start = len(head) + struct.unpack("<i", head[-4:])[0]
    if not len(head) < start <= size:
        raise Unreadable(f"the header declares {start - len(head)} bytes; the file holds {size - len(head)} "
                         f"after the version line: truncated or corrupt")
    compression, table = _aedat4_header(fh.read(start - len(head)))
    if compression not in range(5):
        raise Unreadable(f"the header names compression {compression}, not one of AEDAT4's 0-4: corrupt")
    if table == -1:
        return start, size, f"the end of the file (byte {size})"
    if not start <= table < size:
        raise Unreadable(f"the header puts the packet table at byte {table}, outside the packets' bytes "
                         f"[{start}, {size}): truncated or corrupt")
    return start, table, f"the packet table at byte {table}"


def _check_aedat4(path: Path) -> int:
    """Check the framing of an AEDAT4 file against its size before dv-processing sees it: the
    version line, the header, and every packet's (stream, size) chaining exactly to the packet
    table or the file's end. Reads 8 bytes per packet (bounded by the file size); returns the
    number of packets. Unreadable naming the packet and its byte otherwise."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        pos, end, what_end = _aedat4_frame(fh, size)
        k = 0
        while pos < end:
            fh.seek(pos)
            head = fh.read(8)
            if len(head) < 8 or pos + 8 > end:
                raise Unreadable(f"packet {k} at byte {pos}: its 8-byte header runs past {what_end}: "
                                 f"truncated or corrupt")
            stream, n = struct.unpack("<ii", head)
            if stream < 0 or n <= 0 or n > end - pos - 8:
                raise Unreadable(f"packet {k} at byte {pos} (stream {stream}) declares {n} bytes, but "
                                 f"{end - pos - 8} remain before {what_end}: truncated or corrupt")
            pos, k = pos + 8 + n, k + 1
    return k


#: run by :func:`_aedat4_events` as ``python -c`` in a child process: argv = file, output npz
_AEDAT4_CHILD = r"""
import signal, sys
signal.signal(signal.SIGINT, signal.SIG_DFL)
try:
    import numpy as np
    import dv_processing as dv
    rec = dv.io.MonoCameraRecording(sys.argv[1])
    if not rec.isEventStreamAvailable():
        raise RuntimeError("no event stream in this AEDAT4 file")
    W, H = rec.getEventResolution()
    parts = []
    while rec.isRunning():
        batch = rec.getNextEventBatch()
        if batch is None:
            break
        if batch.size():
            a = batch.numpy()
            parts.append((a["timestamp"].astype(np.int64), a["x"], a["y"], a["polarity"]))
    cols = [np.concatenate([p[i] for p in parts]) if parts else np.empty(0, d)
            for i, d in enumerate((np.int64, np.int16, np.int16, np.bool_))]
    with open(sys.argv[2], "wb") as fh:
        np.savez(fh, t=cols[0], x=cols[1], y=cols[2], p=cols[3], size=np.array([W, H], np.int64))
except Exception as exc:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()] or [type(exc).__name__]
    sys.stderr.write(next((ln for ln in lines if "Error info:" in ln), lines[0])[:300])
    sys.exit(2)
"""


def _run_child(cmd, timeout_s: float) -> Tuple[Optional[int], str]:
    """Run ``cmd``; (exit status, stderr text), or (None, "") when it ran past ``timeout_s``. The
    child is killed on a timeout and on any exception here (Ctrl-C included)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, env=env)
    except OSError as exc:
        raise Unreadable(f"could not start the Python process that runs dv-processing ({exc})") from None
    try:
        _, err = proc.communicate(timeout=timeout_s)
        return proc.returncode, err.decode("utf-8", "replace").strip()
    except subprocess.TimeoutExpired:
        return None, ""
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _aedat4_events(path: Path) -> Tuple[Dict[str, np.ndarray], Tuple[int, int]]:
    """The event stream of an AEDAT4 file ({t, x, y, p} arrays) and its resolution (W, H).

    dv-processing parses the file in a child process: on some corrupt packets it spins forever
    inside C++ holding the GIL, where neither a thread's timeout nor Ctrl-C could stop it. The
    child gets AEDAT4_TIMEOUT_BASE_S + AEDAT4_TIMEOUT_PER_MB_S per MB; past that it is killed and
    the read is an Unreadable "could not be parsed in N s". Ctrl-C kills the child too.
    """
    budget = AEDAT4_TIMEOUT_BASE_S + AEDAT4_TIMEOUT_PER_MB_S * path.stat().st_size / 1e6
    with tempfile.TemporaryDirectory(prefix="dvsland-aedat4-") as tmp:
        out = Path(tmp) / "events.npz"
        rc, err = _run_child([sys.executable, "-c", _AEDAT4_CHILD, str(path), str(out)], budget)
        if rc is None:
            raise Unreadable(f"could not be parsed in {budget:.0f} s (dv-processing did not finish: a corrupt "
                             f"packet?)")
        if rc != 0 or not out.exists():
            raise Unreadable(f"dv-processing: {err}" if err else f"the dv-processing reader exited with status {rc}")
        with np.load(out, allow_pickle=False) as z:
            return {k: z[k] for k in ("t", "x", "y", "p")}, (z["size"][0], z["size"][1])


def _read_aedat4(path: Path, o: _Opts):
    try:
        import dv_processing  # noqa: F401
    except ImportError:
        raise ImportError("reading AEDAT4 needs dv-processing: pip install 'dvsland[aedat]' "
                          "(or pip install dv-processing)") from None
    _check_aedat4(path)
    a, size = _aedat4_events(path)
    _note_disorder(a["t"], str(path))
    return validate_events(a["x"], a["y"], a["t"], a["p"], None, str(path)), size, None, "aedat4"


_READERS = {"aedat4": _read_aedat4, "h5": _read_h5, "npz": _read_npz, "npy": _read_npy, "csv": _read_csv}


# ----------------------------------------------------------------------------- read_recording
def bin_recording(recording: Recording, factor: int) -> Recording:
    """The recording seen through pixels ``factor`` x ``factor`` times larger: each event keeps its time
    and polarity at pixel (x // factor, y // factor) of a (W // factor, H // factor) sensor; events of the
    partial last column or row of bins (when W or H is not a multiple) are dropped. The events stay in
    time order. ``meta["bin_factor"]`` records the factor (multiplied over repeated binning), so that a
    principal point given in the full sensor's pixels can be moved to the binned one
    (:func:`binned_pixel`).

    Raises:
        ValueError: naming ``factor`` when it is not an integer >= 1 or leaves no whole bin.
    """
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or int(factor) < 1:
        raise ValueError(f"factor must be an integer >= 1, got {factor!r}")
    f = int(factor)
    W, H = recording.sensor_size
    if W // f < 1 or H // f < 1:
        raise ValueError(f"factor {f} leaves no whole bin of the {W} x {H} sensor (at most {min(W, H)})")
    meta = dict(recording.meta, bin_factor=int(recording.meta.get("bin_factor", 1)) * f)
    if f == 1:
        return Recording(recording.events, (W, H), recording.ground_truth, recording.source, recording.format, meta)
    ev = recording.events
    b, t, p = ev.b, ev.t, ev.p
    x, y = torch.div(ev.x, f, rounding_mode="floor"), torch.div(ev.y, f, rounding_mode="floor")
    keep = (x < W // f) & (y < H // f)
    if not bool(keep.all()):
        idx = keep.nonzero().squeeze(1)
        b, x, y, t, p = (v.index_select(0, idx) for v in (b, x, y, t, p))
    return Recording(Events(b, x, y, t, p), (W // f, H // f), recording.ground_truth, recording.source,
                     recording.format, meta)


def binned_pixel(xy: Sequence[float], factor: int) -> Tuple[float, float]:
    """A point (x, y) in pixel units of a full sensor (pixel centres at integers) in those of the
    sensor binned ``factor`` x: ((x + 0.5) / factor - 0.5, (y + 0.5) / factor - 0.5)."""
    f = float(factor)
    return ((float(xy[0]) + 0.5) / f - 0.5, (float(xy[1]) + 0.5) / f - 0.5)


def read_recording(path, format: Optional[str] = None, ground_truth: Optional[PathLike] = None,
                   t_unit: Optional[str] = None, sensor_size: Optional[Tuple[int, int]] = None,
                   columns: Sequence[str] = ("t", "x", "y", "p"), b: int = 0, device=None) -> Recording:
    """Read a recording (see the module docstring for the layouts).

    Args:
        path: file, or a numpy structured array (tonic) with fields x, y, t, p.
        format: one of "aedat4", "h5", "npz", "npy", "csv"; default from the suffix.
        ground_truth: side file with the ground truth (overrides one inside the file).
        t_unit: unit of the time column ("ns", "us", "ms", "s"); default: guessed (module doc).
        sensor_size: (W, H); default from the file, else inferred: max coordinate + 1 (each
            coordinate must then be below MAX_SENSOR_PX). ``meta["sensor_size_from"]`` says which:
            "argument", "file" or "inferred" (logged).
        columns: column order of header-less tables and (N, 4) HDF5 tables.
        b: which batch element of a dvsland events file.
        device: device of the events.

    Returns:
        :class:`Recording`.

    Raises:
        FileNotFoundError: no such file.
        RecordingError: (a ValueError) one error for every damaged file or unusable value: empty,
            truncated, corrupt, not UTF-8, a line cut short, a coordinate outside the sensor,
            a timestamp beyond int64, unparseable in the time allowed; it names the file, the
            format and what is wrong.
        ValueError: a bad argument (format, t_unit, sensor_size).
        ImportError: AEDAT4 without dv-processing.
    """
    if t_unit is not None and t_unit not in TIME_UNITS:
        raise ValueError(f"t_unit must be one of {sorted(TIME_UNITS)}, got {t_unit!r}")
    if sensor_size is not None:
        sensor_size = _sensor_pair(sensor_size, "given as an argument")
    if isinstance(path, np.ndarray):
        ev = _from_columns({n: path[n] for n in path.dtype.names or ()}, t_unit, "array")
        ss, origin = _settle_sensor(ev, sensor_size, "given as an argument", "array")
        gt = read_ground_truth(ground_truth) if ground_truth is not None else None
        return Recording(ev.to(device) if device else ev, ss, gt, "array", "tonic", {"sensor_size_from": origin})
    path = Path(path)
    fmt = _format_of(path, format)
    if not path.exists():
        raise FileNotFoundError(path)
    ev, ss, gt, meta = _read_checked(path, fmt, _Opts(t_unit, tuple(columns), int(b)), sensor_size)
    if ground_truth is not None:
        gt = read_ground_truth(ground_truth, b)
    if device is not None:
        ev = ev.to(device)
    return Recording(ev, ss, gt, str(path), fmt, meta)


def _read_checked(path: Path, fmt: str, o: _Opts, sensor_size):
    """(events, sensor size, ground truth, meta) of a file; any failure as the one RecordingError."""
    try:
        if path.stat().st_size == 0:
            raise Unreadable("empty file (0 bytes)")
        ev, declared, gt, layout = _READERS[fmt](path, o)
        origin = "given as an argument" if sensor_size is not None else "declared by the file"
        ss, source = _settle_sensor(ev, sensor_size or declared, origin, str(path))
    except (ImportError, RecordingError):
        raise
    except Exception as exc:  # dvsland's checks and the libraries' failures alike
        raise _as_recording_error(exc, path, fmt) from None
    return ev, ss, gt, {"layout": layout, "sensor_size_from": source}


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


__all__ = ["Recording", "GroundTruth", "RecordingError", "read_recording", "write_recording",
           "read_ground_truth", "write_ground_truth", "FORMATS", "MAX_SENSOR_PX"]
