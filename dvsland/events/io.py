"""Save and load :class:`~dvsland.events.Events` as ``.npz`` or ``.h5`` (exact round trip).

Both formats hold one array per field with explicit dtypes: b int64, x int16, y int16, t int64
(µs), p int8 (+1 ON / -1 OFF), plus metadata: ``sensor_size = (W, H, 2)`` (tonic's order),
``batch_size``, ``threshold``, ``threshold_off``, ``refractory_us`` and a ``format`` tag. In HDF5
the fields are datasets under ``/events`` and the metadata are attributes of that group; in npz
the metadata are 0-d / 1-d arrays named ``meta_<key>``.

x and y are stored as int16 (sensors up to 32767 px, as tonic) and come back as int64.

Ground truth (optional, ``save_events(..., ground_truth=...)``): per batch element a time series
of altitude, vertical velocity and divergence D = v / z, as arrays ``gt_b``, ``gt_t_us``,
``gt_altitude_m``, ``gt_velocity_mps``, ``gt_divergence`` (npz) or datasets ``b``, ``t_us``, ...
of a root group ``/ground_truth`` (HDF5). ``dvsland events`` writes one sample per frame;
:func:`~dvsland.events.read_recording` (and so ``dvsland evaluate --recording``) reads it back
for the element it reads; :func:`load_events` ignores it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, Optional, Tuple, Union

import numpy as np
import torch

from .events import Events
from .validate import EventDataError, check_event_arrays

FORMAT_TAG = "dvsland.events/1"
_STORE_DTYPES = {"b": np.int64, "x": np.int16, "y": np.int16, "t": np.int64, "p": np.int8}
_META_KEYS = ("sensor_size", "batch_size", "threshold", "threshold_off", "refractory_us")

PathLike = Union[str, Path]


class Unreadable(ValueError):
    """A reader's own finding that a file is damaged (truncated, a size beyond the file, ...). The
    message says what is wrong but not which file: the caller adds the file and the format."""


#: deflate expands at most ~1032:1; a dataset claiming more bytes than this times the file size
#: (plus 1 MiB of slack for fill values) cannot be stored in the file
_MAX_EXPANSION = 1100


def npy_header(fh, available: int) -> Tuple[tuple, np.dtype, int]:
    """Read an .npy header from ``fh`` (at its start) and check it against ``available`` bytes.

    Returns:
        (shape, dtype, header length in bytes).

    Raises:
        Unreadable: no npy magic, an unreadable header, an object dtype, or more data declared
            than ``available - header`` bytes (a truncated file).
    """
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, _, dtype = read(fh)
    except (ValueError, OSError, EOFError, SyntaxError) as exc:
        raise Unreadable(f"not an npy array (bad header: {exc})") from None
    if dtype.hasobject:
        raise Unreadable(f"array of Python objects ({dtype}); only numeric arrays are read")
    head = fh.tell()
    need = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if need > available - head:
        raise Unreadable(f"truncated: the header declares shape {shape} of {dtype} ({need} bytes) but "
                         f"{max(available - head, 0)} bytes follow it")
    return shape, dtype, head


def load_npy(path: Path) -> np.ndarray:
    """An .npy file, its header checked against the file size first (:func:`npy_header`)."""
    with open(path, "rb") as fh:
        npy_header(fh, path.stat().st_size)
    return np.load(path, allow_pickle=False)


def open_npz(path: Path):
    """``np.load`` of an npz (no pickles) once its first bytes say it is a zip archive: numpy would
    take anything else for a pickle and say so."""
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic not in (b"PK\x03\x04", b"PK\x05\x06"):
        why = "truncated" if b"PK\x03\x04".startswith(magic) else "not an npz (zip) archive"
        raise Unreadable(f"{why}: it begins with {magic!r}, not a zip header (PK)")
    return np.load(path, allow_pickle=False)


def check_npz(z, path: Path) -> None:
    """Check every ``.npy`` member header of an open npz (``np.load``) against its stored size, so that
    no corrupt shape asks for more memory than the file holds. The members' CRCs are checked by
    zipfile as numpy reads them (a flipped byte is a ``BadZipFile``)."""
    for info in z.zip.infolist():
        if info.filename.endswith(".npy"):
            with z.zip.open(info) as fh:
                try:
                    npy_header(fh, info.file_size)
                except Unreadable as exc:
                    raise Unreadable(f"member {info.filename!r}: {exc}") from None


def h5_read(dset, file_size: int) -> np.ndarray:
    """All of an HDF5 dataset, after checking that its declared size fits a file of ``file_size``
    bytes (even deflated): a corrupt shape is an :class:`Unreadable`, not a huge allocation."""
    need = int(np.prod(dset.shape, dtype=object)) * dset.dtype.itemsize
    if need > _MAX_EXPANSION * file_size + (1 << 20):
        raise Unreadable(f"dataset {dset.name!r} declares shape {dset.shape} of {dset.dtype} ({need} bytes), "
                         f"more than a file of {file_size} bytes can hold: corrupt")
    return dset[()]


def _fmt(path: Path, fmt: Optional[str]) -> str:
    if fmt is None:
        suffix = path.suffix.lower()
        fmt = {".npz": "npz", ".h5": "h5", ".hdf5": "h5"}.get(suffix)
        if fmt is None:
            raise ValueError(f"cannot tell the format from {path.name!r}: use .npz, .h5 or .hdf5, "
                             f"or pass format='npz'|'h5'")
    if fmt not in ("npz", "h5"):
        raise ValueError(f"format must be 'npz' or 'h5', got {fmt!r}")
    return fmt


def _arrays(events: Events) -> Dict[str, np.ndarray]:
    out = {}
    for k, dt in _STORE_DTYPES.items():
        a = getattr(events, k).cpu().numpy()
        if k in ("x", "y") and a.size and (a.min() < 0 or a.max() > np.iinfo(np.int16).max):
            raise ValueError(f"{k} must be in [0, 32767] to be stored as int16")
        out[k] = a.astype(dt)
    return out


def _ground_truth_arrays(ground_truth, batch_size: int) -> Dict[str, np.ndarray]:
    """``gt_*`` arrays of a GroundTruth (element 0), a sequence of them (element = index) or a
    mapping {b: GroundTruth}; empty for None."""
    if ground_truth is None:
        return {}
    from .ground_truth import GroundTruth

    if isinstance(ground_truth, GroundTruth):
        items = [(0, ground_truth)]
    elif isinstance(ground_truth, dict):
        items = sorted((int(b), g) for b, g in ground_truth.items())
    else:
        items = list(enumerate(ground_truth))
    for b, g in items:
        if not isinstance(g, GroundTruth):
            raise ValueError(f"ground_truth[{b}] must be a GroundTruth, got {type(g).__name__}")
        if not 0 <= b < max(batch_size, 1):
            raise ValueError(f"ground_truth for element {b}, but batch_size is {batch_size}")
    with_alt = all(g.altitude_m is not None for _, g in items)
    out = {"gt_b": np.concatenate([np.full(len(g.t_us), b, np.int64) for b, g in items]),
           "gt_t_us": np.concatenate([g.t_us for _, g in items]).astype(np.int64),
           "gt_divergence": np.concatenate([g.divergence for _, g in items])}
    if with_alt:
        out["gt_altitude_m"] = np.concatenate([g.altitude_m for _, g in items])
        out["gt_velocity_mps"] = np.concatenate([g.velocity_mps for _, g in items])
    return out


def save_events(path: PathLike, events: Events, sensor_size: Optional[Tuple[int, int]] = None,
                batch_size: Optional[int] = None, threshold: Optional[float] = None,
                threshold_off: Optional[float] = None, refractory_us: Optional[float] = None,
                format: Optional[str] = None, ground_truth=None) -> Path:
    """Write ``events`` to ``path`` (.npz or .h5; ``format`` overrides the suffix).

    Args:
        events: the events (any device; copied to CPU).
        sensor_size: (W, H) in pixels; stored as (W, H, 2). Default: max coordinate + 1.
        batch_size: B; default max b + 1.
        threshold, threshold_off, refractory_us: emulator settings stored as metadata (NaN if None).
        ground_truth: optional :class:`~dvsland.events.GroundTruth` of element 0, a list of them
            (one per element b, in order) or a dict {b: GroundTruth}; stored as described in the
            module docstring and read back by :func:`~dvsland.events.read_recording`.

    Returns:
        The path written.
    """
    path = Path(path)
    fmt = _fmt(path, format)
    arrs = _arrays(events)
    n = len(events)
    if sensor_size is None:
        sensor_size = (int(arrs["x"].max()) + 1 if n else 0, int(arrs["y"].max()) + 1 if n else 0)
    if len(sensor_size) not in (2, 3):
        raise ValueError(f"sensor_size must be (W, H), got {sensor_size}")
    W, H = int(sensor_size[0]), int(sensor_size[1])
    if batch_size is None:
        batch_size = int(arrs["b"].max()) + 1 if n else 0
    nan = float("nan")
    meta = {
        "sensor_size": np.array([W, H, 2], dtype=np.int64),
        "batch_size": np.int64(batch_size),
        "threshold": np.float64(nan if threshold is None else threshold),
        "threshold_off": np.float64(nan if threshold_off is None else threshold_off),
        "refractory_us": np.float64(nan if refractory_us is None else refractory_us),
    }
    gt = _ground_truth_arrays(ground_truth, int(batch_size))
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "npz":
        with open(path, "wb") as fh:  # keep the exact name (np.savez appends .npz otherwise)
            np.savez(fh, **arrs, **{f"meta_{k}": v for k, v in meta.items()},
                     meta_format=np.array(FORMAT_TAG), **gt)
    else:
        import h5py

        with h5py.File(path, "w") as h5:
            g = h5.create_group("events")
            for k, a in arrs.items():
                g.create_dataset(k, data=a, dtype=a.dtype)
            for k, v in meta.items():
                g.attrs[k] = v
            g.attrs["format"] = FORMAT_TAG
            if gt:
                gg = h5.create_group("ground_truth")
                for k, a in gt.items():
                    gg.create_dataset(k[len("gt_"):], data=a)
    return path


def load_events(path: PathLike, device=None, format: Optional[str] = None,
                with_meta: bool = False):
    """Read events written by :func:`save_events`.

    Returns:
        :class:`Events` (fields as int64 / int8, on ``device``), or ``(events, meta)`` only with
        ``with_meta=True``; ``meta`` has sensor_size (W, H, 2) tuple, batch_size int, threshold,
        threshold_off, refractory_us floats (NaN = not stored). ``events, meta = load_events(p)``
        without ``with_meta=True`` is a TypeError that says so (Events does not unpack).
    """
    path = Path(path)
    fmt = _fmt(path, format)
    if not path.exists():
        raise FileNotFoundError(path)
    try:
        arrs, raw = _read_npz(path) if fmt == "npz" else _read_h5(path)
    except EventDataError:
        raise
    except Exception as exc:  # zipfile, OSError, EOFError, h5py, pickle refusals ...
        raise EventDataError(f"truncated or corrupt event file {path}: {type(exc).__name__}: {exc}") from None
    meta = _check_meta(raw, path)
    src = str(path)
    if "sensor_size" in meta:
        W, H = meta["sensor_size"][:2]
        sensor = (W, H) if W > 0 and H > 0 else None
    else:
        sensor = None
    checked = check_event_arrays(arrs, sensor_size=sensor, batch_size=meta.get("batch_size") or None,
                                 polarity="pm1", require_sorted=True, source=src)
    dev = torch.device(device) if device is not None else torch.device("cpu")
    ev = Events(**{k: torch.as_tensor(a, device=dev) for k, a in checked.items()})
    if not with_meta:
        return ev
    return ev, meta


def _read_npz(path: Path):
    with open_npz(path) as z:
        check_npz(z, path)
        missing = [k for k in _STORE_DTYPES if k not in z.files]
        if missing:
            raise EventDataError(f"{path}: not a dvsland events file (missing {missing})")
        arrs = {k: z[k] for k in _STORE_DTYPES}
        raw = {k: z[f"meta_{k}"] for k in _META_KEYS if f"meta_{k}" in z.files}
    return arrs, raw


def _read_h5(path: Path):
    import h5py

    with h5py.File(path, "r") as h5:
        if "events" not in h5:
            raise EventDataError(f"{path}: not a dvsland events file (no /events group)")
        g = h5["events"]
        missing = [k for k in _STORE_DTYPES if k not in g]
        if missing:
            raise EventDataError(f"{path}: not a dvsland events file (missing {missing})")
        size = path.stat().st_size
        arrs = {k: h5_read(g[k], size) for k in _STORE_DTYPES}
        raw = {k: g.attrs[k] for k in _META_KEYS if k in g.attrs}
    return arrs, raw


def _check_meta(raw: dict, path: Path) -> Dict[str, Any]:
    """Metadata of an event file, typed and checked (EventDataError naming the key)."""
    meta: Dict[str, Any] = {}
    try:
        if "sensor_size" in raw:
            ss = np.asarray(raw["sensor_size"]).reshape(-1)
            if ss.size != 3 or not np.isfinite(ss.astype(np.float64)).all() or (ss < 0).any():
                raise EventDataError(f"{path}: meta sensor_size must be (W, H, 2) with W, H >= 0, got {ss.tolist()}")
            meta["sensor_size"] = tuple(int(v) for v in ss)
        if "batch_size" in raw:
            bs = np.asarray(raw["batch_size"]).reshape(-1)
            if bs.size != 1 or not np.isfinite(float(bs[0])) or float(bs[0]) < 0:
                raise EventDataError(f"{path}: meta batch_size must be an integer >= 0, got {bs.tolist()}")
            meta["batch_size"] = int(bs[0])
        for k in ("threshold", "threshold_off", "refractory_us"):
            if k in raw:
                meta[k] = float(np.asarray(raw[k]).reshape(-1)[0])
    except EventDataError:
        raise
    except (TypeError, ValueError, IndexError) as exc:
        raise EventDataError(f"{path}: unreadable metadata: {exc}") from None
    return meta


# recordings of other tools (AEDAT4, HDF5 layouts, tonic, CSV) are dvsland.events.recording, which
# reads dvsland's own files through this module (dvsland.events.read_recording, write_recording)
__all__ = ["save_events", "load_events", "FORMAT_TAG", "EventDataError", "Unreadable", "npy_header",
           "load_npy", "open_npz", "check_npz", "h5_read"]
