"""One shard file: the event windows of a group of descents in HDF5, one dataset per field.

Layout (``format = "dvsland-event-windows"``, ``format_version = 1``)::

    /events/x      (N,) uint16  pixel column
    /events/y      (N,) uint16  pixel row
    /events/dt_us  (N,) int32   event time minus its window's start t0_us, µs, in [1, t_us - t0_us]
    /events/p      (N,) int8    polarity +1 (ON) / -1 (OFF)
    /samples/event_offset (S + 1,) int64  sample i's events are rows offset[i] .. offset[i + 1] - 1
    /samples/<field>      (S,)   one row per sample (:data:`SAMPLE_FIELDS`)
    /descents/<field>     (n_descents,) one row per descent (:data:`DESCENT_FIELDS`)
    attrs: format, format_version, sensor_size (W, H), dt_s, shard_id, seed_offset, n_seeds,
           config_hash, estimator, n_samples, n_events, n_descents, complete

The events of a sample are sorted by time (ties by row-major pixel, the emulator's order). A shard
is written to ``<name>.tmp<pid>`` and renamed when complete, so a killed build never leaves a
half-written shard under its final name.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Dict, Optional

import numpy as np

FORMAT = "dvsland-event-windows"
FORMAT_VERSION = 1

#: event fields: name -> numpy dtype
EVENT_FIELDS = {"x": np.uint16, "y": np.uint16, "dt_us": np.int32, "p": np.int8}

#: per-sample fields: name -> (numpy dtype, unit and meaning)
SAMPLE_FIELDS = {
    "descent": (np.int32, "row of the descent in /descents"),
    "step": (np.int32, "control step k of the descent (0 = first frame, no events)"),
    "t0_us": (np.int64, "window start, µs of flight time (the previous step's time; = t_us at step 0)"),
    "t_us": (np.int64, "window end = the step's time, µs of flight time"),
    "t_s": (np.float64, "the step's flight time, s"),
    "d_true": (np.float64, "true divergence v/z at t_s, 1/s (< 0 descending)"),
    "tau_s": (np.float64, "true time to contact z/(-v) at t_s, s (+inf when not descending)"),
    "z_m": (np.float64, "true altitude at t_s, m"),
    "v_mps": (np.float64, "true vertical velocity at t_s, m/s (< 0 descending)"),
    "d_est": (np.float64, "the flying estimator's D_hat, 1/s (NaN = none; the truth with 'oracle')"),
    "thrust_n": (np.float64, "thrust held over [t_s, t_s + dt), N"),
    "valid": (np.bool_, "step > 0 and descending (tau finite): a usable training target"),
}

#: per-descent fields: name -> numpy dtype (strings are variable-length UTF-8)
DESCENT_FIELDS = {
    "site": str, "scene": str, "setting": str, "variant": np.int16, "seed": np.int64, "seed_index": np.int32,
    "z0_m": np.float64, "v0_mps": np.float64, "sun_elevation_deg": np.float64, "threshold_scale": np.float64,
    "mismatch_sigma": np.float64, "background_rate_hz": np.float64, "refractory_us": np.float64, "outcome": str,
}

#: events buffered in memory before a write (about 9 MB)
FLUSH_EVENTS = 1 << 20
EVENT_CHUNK = 1 << 14  # events per HDF5 chunk: 16384 read 3x faster at random than 65536 (measured)


def _str_dtype():
    import h5py

    return h5py.string_dtype("utf-8")


class ShardWriter:
    """Appends samples to ``<path>.tmp<pid>``; :meth:`finish` renames it to ``path``.

    Args:
        path: final file path (``.h5``).
        attrs: root attributes (sensor_size, dt_s, shard_id, ...).
        compression: ``"gzip"`` (level 4, byte shuffle), ``"lzf"`` or ``None``.
    """

    def __init__(self, path, attrs: dict, compression: Optional[str] = "gzip"):
        import h5py

        if compression not in ("gzip", "lzf", None):
            raise ValueError(f"compression must be 'gzip', 'lzf' or None, got {compression!r}")
        self.path = Path(path)
        self.tmp = self.path.with_name(f"{self.path.name}.tmp{os.getpid()}")
        self._room_for(64 << 10)  # the file's header and empty datasets
        self.f = h5py.File(self.tmp, "w")
        kw = {} if compression is None else {"compression": compression, "shuffle": True}
        if compression == "gzip":
            kw["compression_opts"] = 4
        for name, dt in EVENT_FIELDS.items():
            self.f.create_dataset(f"events/{name}", shape=(0,), maxshape=(None,), dtype=dt, chunks=(EVENT_CHUNK,), **kw)
        for name, (dt, _) in SAMPLE_FIELDS.items():
            self.f.create_dataset(f"samples/{name}", shape=(0,), maxshape=(None,), dtype=dt, chunks=(4096,), **kw)
        self.f.attrs.update({"format": FORMAT, "format_version": FORMAT_VERSION, "complete": False, **attrs})
        self.n_events = 0
        self.offsets = [0]
        self._buf: list = []
        self._buf_events = 0

    def append(self, events: Dict[str, np.ndarray], counts: np.ndarray, samples: Dict[str, np.ndarray]) -> None:
        """Add n samples: ``events`` {x, y, dt_us, p} (sum(counts),) arrays grouped by sample,
        ``counts`` (n,) events per sample, ``samples`` {field: (n,)} of :data:`SAMPLE_FIELDS`.

        Buffered in memory and written in blocks of about :data:`FLUSH_EVENTS` events (a compressed
        chunk written piece by piece is recompressed at every piece: 2x slower builds, measured)."""
        self._buf.append((events, samples))
        self._buf_events += int(np.sum(counts))
        self.offsets.extend((self.n_events + np.cumsum(counts)).tolist())
        self.n_events += int(np.sum(counts))
        if self._buf_events >= FLUSH_EVENTS:
            self._flush()

    def _room_for(self, n_bytes: int) -> None:
        """Refuse a write that the disk cannot take before HDF5 starts it: HDF5 fails on a full
        disk part-way through its own bookkeeping and leaves a file that cannot even be closed.

        Raises:
            RunWriteError: fewer than ``n_bytes`` plus 1 MiB free in the shard's folder (ENOSPC).
        """
        import errno
        import shutil

        from dvsland.report.results import RunWriteError

        free = shutil.disk_usage(self.tmp.parent).free
        if free < n_bytes + (1 << 20):
            raise RunWriteError(self.path, OSError(errno.ENOSPC, f"No space left on device: {free} bytes free, "
                                                                 f"the shard needs up to {n_bytes} more (before compression)"))

    def _flush(self) -> None:
        if not self._buf:
            return
        self._room_for(sum(a.nbytes for e, s in self._buf for a in (*e.values(), *s.values())))
        for name in EVENT_FIELDS:
            _extend(self.f[f"events/{name}"], np.concatenate([e[name] for e, _ in self._buf]))
        for name in SAMPLE_FIELDS:
            _extend(self.f[f"samples/{name}"], np.concatenate([s[name] for _, s in self._buf]))
        self._buf, self._buf_events = [], 0

    def finish(self, descents: Dict[str, np.ndarray]) -> Path:
        """Write the descent table and the offsets, mark complete, close and rename; the path."""
        self._flush()
        self._room_for(8 * len(self.offsets) + 256 * len(descents["site"]) * len(DESCENT_FIELDS))
        for name, dt in DESCENT_FIELDS.items():
            vals = descents[name]
            if dt is str:
                self.f.create_dataset(f"descents/{name}", data=np.asarray(vals, dtype=object), dtype=_str_dtype())
            else:
                self.f.create_dataset(f"descents/{name}", data=np.asarray(vals, dtype=dt))
        self.f.create_dataset("samples/event_offset", data=np.asarray(self.offsets, dtype=np.int64))
        self.f.attrs.update({"n_samples": len(self.offsets) - 1, "n_events": self.n_events,
                             "n_descents": len(descents["site"]), "complete": True})
        self.f.close()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Close and delete the temporary file (an interrupted shard)."""
        try:
            self.f.close()
        finally:
            self.tmp.unlink(missing_ok=True)


def _extend(ds, values) -> None:
    v = np.asarray(values, dtype=ds.dtype)
    n = ds.shape[0]
    ds.resize((n + len(v),))
    ds[n:] = v


class ShardError(ValueError):
    """A shard file that cannot be read as a complete dvsland event-window shard."""


def read_index(path) -> dict:
    """A shard's small tables, read into memory: ``{"attrs", "samples", "descents"}``.

    ``samples`` holds every :data:`SAMPLE_FIELDS` array and ``event_offset`` (S + 1,);
    ``descents`` every :data:`DESCENT_FIELDS` array (strings as ``str``). The events stay on disk
    (:func:`read_events`).

    Raises:
        ShardError: the file is missing, truncated or corrupt, of another format, or incomplete
            (names the file and what is wrong).
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise ShardError(f"shard {str(path)!r}: file missing")
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
            _check_attrs(path, attrs)
            samples = {k: f[f"samples/{k}"][()] for k in (*SAMPLE_FIELDS, "event_offset")}
            descents = {k: _read_col(f[f"descents/{k}"], dt) for k, dt in DESCENT_FIELDS.items()}
            n_ev = {k: f[f"events/{k}"].shape[0] for k in EVENT_FIELDS}
    except ShardError:
        raise
    except (OSError, KeyError, ValueError) as exc:
        raise ShardError(f"shard {str(path)!r}: truncated or corrupt HDF5 file ({type(exc).__name__}: {exc})") from None
    _check_sizes(path, attrs, samples, n_ev)
    return {"attrs": attrs, "samples": samples, "descents": descents}


def _read_col(ds, dt):
    v = ds[()]
    return np.asarray([s.decode() if isinstance(s, bytes) else str(s) for s in v], dtype=object) if dt is str else v


def _check_attrs(path: Path, attrs: dict) -> None:
    if attrs.get("format") != FORMAT:
        raise ShardError(f"shard {str(path)!r}: not a {FORMAT} file (format attribute {attrs.get('format')!r})")
    if int(attrs.get("format_version", -1)) != FORMAT_VERSION:
        raise ShardError(f"shard {str(path)!r}: format_version {attrs.get('format_version')} (this dvsland reads "
                         f"{FORMAT_VERSION})")
    if not bool(attrs.get("complete", False)):
        raise ShardError(f"shard {str(path)!r}: incomplete (written by an interrupted build)")


def _check_sizes(path: Path, attrs: dict, samples: dict, n_ev: dict) -> None:
    off = samples["event_offset"]
    S = int(attrs["n_samples"])
    bad = [k for k, (_, _) in SAMPLE_FIELDS.items() if samples[k].shape != (S,)]
    if bad or off.shape != (S + 1,) or set(n_ev.values()) != {int(attrs["n_events"])} or int(off[-1]) != int(
            attrs["n_events"]) or (S and bool(np.any(np.diff(off) < 0))):
        raise ShardError(f"shard {str(path)!r}: inconsistent sizes (n_samples {S}, n_events {attrs['n_events']}, "
                         f"fields {sorted(bad)}, offsets {off.shape}, event arrays {n_ev})")


def read_events(f, start: int, stop: int) -> Dict[str, np.ndarray]:
    """Events rows ``start .. stop - 1`` of an open h5py file: {x, y, dt_us, p} numpy arrays."""
    return {k: f[f"events/{k}"][start:stop] for k in EVENT_FIELDS}
