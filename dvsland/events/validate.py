"""One check for event arrays coming from outside (files, other libraries): :func:`validate_events`.

Every reader of :mod:`dvsland.events.recording` passes its raw columns through here, so a bad file
(NaN or negative time, a polarity of 5, coordinates off the sensor, columns of unequal length)
gets the same clear ValueError naming the field, the allowed range and the source, whatever its
format.
"""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import torch

from .events import Events

#: time units accepted by the readers, in µs per unit
TIME_UNITS = {"ns": 1e-3, "us": 1.0, "ms": 1e3, "s": 1e6}


def _as_1d(name: str, a, source: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 1:
        raise ValueError(f"{source}: events field {name!r} must be 1-D, got shape {a.shape}")
    if a.dtype.kind not in "biuf":
        raise ValueError(f"{source}: events field {name!r} must be numeric, got dtype {a.dtype}")
    return a


def times_to_us(t, unit: Optional[str], source: str = "events") -> np.ndarray:
    """Timestamps to int64 µs (rounded to nearest).

    Args:
        t: (N,) numeric.
        unit: one of "ns", "us", "ms", "s", or None = guess: integer values -> µs, floats with a
            fractional part -> seconds (the text format of the event-camera datasets).
    """
    t = _as_1d("t", t, source)
    if t.dtype.kind == "f" and t.size and not np.isfinite(t).all():
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise ValueError(f"{source}: timestamps must be finite, got {t[bad]} at event {bad}")
    if unit is None:
        unit = "s" if t.dtype.kind == "f" and t.size and np.any(t != np.floor(t)) else "us"
    if unit not in TIME_UNITS:
        raise ValueError(f"{source}: time unit must be one of {sorted(TIME_UNITS)}, got {unit!r}")
    scale = TIME_UNITS[unit]
    if t.dtype.kind in "iub" and scale == 1.0:
        out = t.astype(np.int64)
    else:
        tf = t.astype(np.float64) * scale
        if tf.size and np.abs(tf).max() > 2.0 ** 62:
            raise ValueError(f"{source}: timestamps out of range (|t| > 2^62 µs)")
        out = np.floor(tf + 0.5).astype(np.int64)
    return out


def validate_events(x, y, t_us, p, sensor_size: Optional[Tuple[int, int]] = None, source: str = "events",
                    b: int = 0, device=None) -> Events:
    """Check raw event columns and pack them into :class:`Events` (batch index ``b``), sorted by t.

    Args:
        x, y: (N,) integer-valued pixel column / row, >= 0 and < W / H when ``sensor_size`` is given.
        t_us: (N,) integer-valued timestamps, µs (see :func:`times_to_us` for other units).
        p: (N,) polarity, either {0, 1} (0 = OFF; tonic, HDF5 and AEDAT files) or {-1, +1}
            (dvsland), or bool (False = OFF).
        sensor_size: (W, H) or None.
        source: a name for the messages (file name).

    Returns:
        Events with b, x, y, t int64 and p int8 ±1, stably sorted by t when not already.

    Raises:
        ValueError naming the field, the allowed range and the source.
    """
    cols = {"x": _as_1d("x", x, source), "y": _as_1d("y", y, source), "t": _as_1d("t", t_us, source),
            "p": _as_1d("p", p, source)}
    n = len(cols["x"])
    for k, a in cols.items():
        if len(a) != n:
            raise ValueError(f"{source}: events fields must have equal length, got x of {n} and {k} of {len(a)}")
    for k in ("x", "y", "t"):
        a = cols[k]
        if a.dtype.kind == "f":
            if n and not np.isfinite(a).all():
                bad = int(np.flatnonzero(~np.isfinite(a))[0])
                raise ValueError(f"{source}: events field {k!r} must be finite, got {a[bad]} at event {bad}")
            if n and np.any(a != np.floor(a)):
                bad = int(np.flatnonzero(a != np.floor(a))[0])
                raise ValueError(f"{source}: events field {k!r} must be integer-valued, got {a[bad]} at event {bad}")
        cols[k] = a.astype(np.int64)
    if sensor_size is not None:
        if len(sensor_size) < 2 or int(sensor_size[0]) < 1 or int(sensor_size[1]) < 1:
            raise ValueError(f"{source}: sensor_size must be (W, H) with W, H >= 1, got {sensor_size}")
    limits = {"x": None if sensor_size is None else int(sensor_size[0]),
              "y": None if sensor_size is None else int(sensor_size[1])}
    for k, hi in limits.items():
        a = cols[k]
        if n:
            lo_v, hi_v = int(a.min()), int(a.max())
            if lo_v < 0 or (hi is not None and hi_v >= hi):
                rng = f"[0, {hi})" if hi is not None else ">= 0"
                raise ValueError(f"{source}: events field {k!r} must be in {rng}, got values in [{lo_v}, {hi_v}]")
    pr = cols["p"]
    if pr.dtype.kind == "f":
        if n and not np.isfinite(pr).all():
            raise ValueError(f"{source}: polarity p must be 0/1 or -1/+1, got non-finite values")
    vals = np.unique(pr) if n else np.empty(0)
    if n and not (set(vals.tolist()) <= {0, 1} or set(vals.tolist()) <= {-1, 1}):
        shown = vals[:6].tolist()
        raise ValueError(f"{source}: polarity p must be in {{0, 1}} (0 = OFF) or {{-1, +1}}, got values {shown}"
                         + (" ..." if len(vals) > 6 else ""))
    p8 = np.where(pr > 0, 1, -1).astype(np.int8)
    t = cols["t"]
    if n > 1 and np.any(t[1:] < t[:-1]):
        order = np.argsort(t, kind="stable")
        cols = {k: v[order] for k, v in cols.items()}
        p8, t = p8[order], cols["t"]
    dev = torch.device(device) if device is not None else torch.device("cpu")
    return Events(b=torch.full((n,), int(b), dtype=torch.int64, device=dev),
                  x=torch.as_tensor(cols["x"], device=dev), y=torch.as_tensor(cols["y"], device=dev),
                  t=torch.as_tensor(t, device=dev), p=torch.as_tensor(p8, device=dev))


__all__ = ["validate_events", "times_to_us", "TIME_UNITS"]
