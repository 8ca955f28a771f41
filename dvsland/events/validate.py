"""One check for events on their way in: arrays read from a file, other tools' recordings, tonic
arrays, and the events every estimator's ``update`` receives.

Every reader (dvsland npz / HDF5 in :mod:`dvsland.events.io`; AEDAT4, HDF5 layouts, tonic, npz and
CSV recordings in :mod:`dvsland.events.recording` through :func:`dvsland.events.validate_events`,
which packs what :func:`check_event_columns` passed; tonic arrays) passes its raw arrays through
:func:`check_event_arrays` before building :class:`~dvsland.events.Events`; the estimators'
``update`` passes its events through :func:`checked_for_estimator`. This module sits below the
:class:`~dvsland.events.Events` container: it checks arrays and duck-typed events and never builds
``Events`` itself. A bad value is an
:class:`EventDataError` (a ``ValueError``) that names the field, the allowed range and, for a
file, the path; never a numpy or torch error from deep inside.

Rules (the dvsland conventions: ``b, x, y`` int64, ``t`` int64 µs, ``p`` int8 +1 / -1):

- every field is one-dimensional, of one length, and integer-valued: an integer dtype, a bool
  (p only), or a float array whose values are all finite whole numbers (NaN / inf never pass);
- ``p`` in {-1, +1}, or in {0, 1} where the source declares it (tonic: 0 = OFF);
- ``b`` in [0, batch_size), ``x`` in [0, W), ``y`` in [0, H) where those sizes are known;
- ``t`` within int64, and non-decreasing within each batch element where sortedness is required.
"""

from __future__ import annotations

from typing import Dict, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch

FIELDS = ("b", "x", "y", "t", "p")
_I64 = np.iinfo(np.int64)


class EventDataError(ValueError):
    """Events or an event file hold values dvsland cannot use (the message names field and range)."""


class RecordingError(EventDataError):
    """A recording or ground-truth file cannot be read: empty, truncated, corrupt, not text where
    text is expected, too slow to parse, or holding values dvsland cannot use. The one error of
    every reader (:func:`dvsland.events.read_recording`, :func:`dvsland.events.read_ground_truth`);
    the message names the file, the format and what is wrong."""


def _where(source: Optional[str]) -> str:
    return f"{source}: " if source else ""


def _as_int64(name: str, a, source: Optional[str]) -> np.ndarray:
    """Field ``a`` as a 1-D int64 numpy array; floats must be finite whole numbers."""
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    try:
        a = np.asarray(a)
    except Exception as exc:  # ragged or odd objects
        raise EventDataError(f"{_where(source)}event field {name!r} is not an array: {exc}") from None
    if a.ndim != 1:
        raise EventDataError(f"{_where(source)}event field {name!r} must be 1-D (N,), got shape {a.shape}")
    kind = a.dtype.kind
    if kind == "b":
        return a.astype(np.int64)
    if kind in "iu":
        if kind == "u" and a.size and int(a.max()) > _I64.max:
            raise EventDataError(f"{_where(source)}event field {name!r} has values above the int64 range")
        return a.astype(np.int64)
    if kind == "f":
        if a.size:
            finite = np.isfinite(a)
            if not finite.all():
                bad = a[~finite][0]
                raise EventDataError(f"{_where(source)}event field {name!r} contains {bad} "
                                     f"({int((~finite).sum())} of {a.size} values); it must hold finite integers")
            if (a != np.round(a)).any():
                raise EventDataError(f"{_where(source)}event field {name!r} holds non-integer values; "
                                     f"it must hold integers")
            if a.min() < -2.0 ** 63 or a.max() >= 2.0 ** 63:
                raise EventDataError(f"{_where(source)}event field {name!r} has values outside the int64 range")
        return a.astype(np.int64)
    raise EventDataError(f"{_where(source)}event field {name!r} must be integer, got dtype {a.dtype}")


def _range_check(name: str, a: np.ndarray, lo: int, hi: Optional[int], source: Optional[str],
                 bound: str = "") -> None:
    """``a`` in [lo, hi) (hi None: only >= lo); else EventDataError naming the field, the range (and
    ``bound``, what sets hi), the first value outside it and its event index."""
    if not a.size:
        return
    vmin, vmax = int(a.min()), int(a.max())
    if vmin < lo or (hi is not None and vmax >= hi):
        rng = f"in [{lo}, {hi})" if hi is not None else f">= {lo}"
        i = int(np.argmax((a < lo) | (a >= hi))) if hi is not None else int(np.argmax(a < lo))
        why = f" ({bound})" if bound else ""
        raise EventDataError(f"{_where(source)}event field {name!r} must be {rng}{why}, got {name} = "
                             f"{int(a[i])} at event {i} (values in [{vmin}, {vmax}])")


def check_event_arrays(arrays: Mapping[str, object], *, sensor_size: Optional[Sequence[int]] = None,
                       batch_size: Optional[int] = None, polarity: str = "pm1",
                       require_sorted: bool = True, source: Optional[str] = None) -> dict:
    """Check raw event arrays and return them as numpy ``{b, x, y, t: int64, p: int8 (+1/-1)}``.

    Args:
        arrays: mapping with keys x, y, t, p and optionally b (default: all 0).
        sensor_size: (W, H) in pixels; x and y must be below it. None: only >= 0 is checked.
        batch_size: B; b must be below it. None: only >= 0 is checked.
        polarity: "pm1" (p in {-1, +1}), "01" (p in {0, 1}, 0 = OFF: tonic) or "any01pm1"
            (either convention; {0, 1} only when no -1 occurs).
        require_sorted: t must be non-decreasing within each b, and b non-decreasing.
        source: file name or origin for the messages.

    Raises:
        EventDataError: a field is missing, of the wrong shape or type, or out of range.
    """
    missing = [k for k in ("x", "y", "t", "p") if k not in arrays]
    if missing:
        raise EventDataError(f"{_where(source)}events need fields x, y, t, p; missing {missing}")
    out = {k: _as_int64(k, arrays[k], source) for k in ("x", "y", "t", "p")}
    n = out["t"].shape[0]
    out["b"] = _as_int64("b", arrays["b"], source) if arrays.get("b") is not None else np.zeros(n, np.int64)
    for k in FIELDS:
        if out[k].shape[0] != n:
            raise EventDataError(f"{_where(source)}event fields must have equal length: {k!r} has "
                                 f"{out[k].shape[0]}, 't' has {n}")
    p = out["p"]
    if polarity == "pm1":
        allowed = (-1, 1)
    elif polarity == "01":
        allowed = (0, 1)
    elif polarity == "any01pm1":
        allowed = (-1, 1) if (p == -1).any() else (0, 1)
    else:
        raise ValueError(f"polarity must be 'pm1', '01' or 'any01pm1', got {polarity!r}")
    if p.size and not np.isin(p, allowed).all():
        bad = p[~np.isin(p, allowed)]
        raise EventDataError(f"{_where(source)}polarity p (field 'p') must be in {{{allowed[0]}, {allowed[1]}}}, "
                             f"got {int(bad[0])} ({bad.size} of {p.size} values)")
    out["p"] = np.where(p > 0, 1, -1).astype(np.int8)
    W = H = None
    if sensor_size is not None:
        if len(sensor_size) < 2 or int(sensor_size[0]) < 1 or int(sensor_size[1]) < 1:
            raise EventDataError(f"{_where(source)}sensor_size must be (W, H) with W, H >= 1, got {tuple(sensor_size)}")
        W, H = int(sensor_size[0]), int(sensor_size[1])
    if batch_size is not None and int(batch_size) < 0:
        raise EventDataError(f"{_where(source)}batch_size must be >= 0, got {batch_size}")
    _range_check("b", out["b"], 0, None if batch_size is None else int(batch_size), source)
    for k, hi in (("x", W), ("y", H)):
        _range_check(k, out[k], 0, hi, source, f"sensor_size (W, H) = ({W}, {H})" if W is not None else "")
    if require_sorted and n > 1:
        b, t = out["b"], out["t"]
        ok = (b[1:] > b[:-1]) | ((b[1:] == b[:-1]) & (t[1:] >= t[:-1]))  # comparisons: no overflow
        if not ok.all():
            i = int(np.argmin(ok))
            raise EventDataError(f"{_where(source)}events must be sorted by (b, t): event {i + 1} "
                                 f"(b={int(b[i + 1])}, t={int(t[i + 1])}) comes after (b={int(b[i])}, t={int(t[i])})")
    return out


def check_events(events, batch_size: Optional[int] = None, width: Optional[int] = None,
                 height: Optional[int] = None, what: str = "events") -> None:
    """Check the values of an :class:`~dvsland.events.Events`: b in [0, batch_size), x in [0, width),
    y in [0, height) (a bound left None: only >= 0), p in {-1, +1}. Raise EventDataError naming the
    field. Does not check the order (see :meth:`Events.is_sorted`); a few reductions, one sync.
    """
    if len(events) == 0:
        return
    W, H = width, height
    stats = torch.stack([events.b.min(), events.b.max(), events.x.min(), events.x.max(),
                         events.y.min(), events.y.max(),
                         ((events.p != 1) & (events.p != -1)).sum()]).tolist()
    for name, lo_v, hi_v, hi in (("b", stats[0], stats[1], batch_size), ("x", stats[2], stats[3], W),
                                 ("y", stats[4], stats[5], H)):
        if lo_v < 0 or (hi is not None and hi_v >= hi):
            rng = f"[0, {hi})" if hi is not None else ">= 0"
            raise EventDataError(f"{what}: field {name!r} must be in {rng}, got values in [{lo_v}, {hi_v}]")
    if stats[6]:
        raise EventDataError(f"{what}: polarity field 'p' must be +1 or -1 (int8), {stats[6]} values are not")




def checked_for_estimator(events, batch_size: int, width: int, height: int, what: str = "events"):
    """The estimators' gate (:class:`dvsland.estimators.DivergenceEstimator` runs it before every
    ``update``): values in range (EventDataError otherwise) and sorted by (b, t) (sorted here,
    stably, if they are not: every estimator then sees the same stream). One device sync, none for
    events their producer marked checked for this batch and sensor (:meth:`Events.marked_checked`).

    Returns:
        ``events``, or a sorted copy.
    """
    if events is None or len(events) < 1:
        return events
    if getattr(events, "checked", None) == (batch_size, width, height):  # marked by its producer (the emulator)
        return events
    b, t = events.b, events.t
    if len(events) > 1:  # sorted by (b, t): t never decreases unless b increases
        unsorted = ((t[1:] < t[:-1]) & (b[1:] <= b[:-1])).any() | (b[1:] < b[:-1]).any()
    else:
        unsorted = torch.zeros((), dtype=torch.bool, device=b.device)
    p_lo, p_hi = torch.aminmax(events.p)
    stats = torch.stack([*torch.aminmax(b), *torch.aminmax(events.x), *torch.aminmax(events.y),
                         ((p_lo < -1) | (p_hi > 1) | (events.p == 0).any()).long(), unsorted.long()]).tolist()
    for name, lo_v, hi_v, hi in (("b", stats[0], stats[1], batch_size), ("x", stats[2], stats[3], width),
                                 ("y", stats[4], stats[5], height)):
        if lo_v < 0 or hi_v >= hi:
            raise EventDataError(f"{what}: field {name!r} must be in [0, {hi}), got values in [{lo_v}, {hi_v}]")
    if stats[6]:
        bad = int(((events.p != 1) & (events.p != -1)).sum())
        raise EventDataError(f"{what}: polarity field 'p' must be +1 or -1 (int8), {bad} values are not")
    return events.sort() if stats[7] else events


#: time units accepted by the readers, in µs per unit
TIME_UNITS = {"ns": 1e-3, "us": 1.0, "ms": 1e3, "s": 1e6}


def _as_1d(name: str, a, source: str) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    a = np.asarray(a)
    if a.ndim != 1:
        raise EventDataError(f"{source}: events field {name!r} must be 1-D, got shape {a.shape}")
    if a.dtype.kind not in "biuf":
        raise EventDataError(f"{source}: events field {name!r} must be numeric, got dtype {a.dtype}")
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
        raise EventDataError(f"{source}: timestamps must be finite, got {t[bad]} at event {bad}")
    if unit is None:
        unit = "s" if t.dtype.kind == "f" and t.size and np.any(t != np.floor(t)) else "us"
    if unit not in TIME_UNITS:
        raise EventDataError(f"{source}: time unit must be one of {sorted(TIME_UNITS)}, got {unit!r}")
    if t.dtype.kind in "iub":
        return _int_times_to_us(t, unit, source)
    tf = t.astype(np.float64) * TIME_UNITS[unit]
    if tf.size and np.abs(tf).max() > 2.0 ** 62:
        raise EventDataError(f"{source}: timestamps out of range (|t| > 2^62 µs)")
    return np.floor(tf + 0.5).astype(np.int64)


_US_PER_UNIT = {"us": 1, "ms": 1_000, "s": 1_000_000}


def _int_times_to_us(t: np.ndarray, unit: str, source: str) -> np.ndarray:
    """Integer timestamps to int64 µs in exact integer arithmetic (ns rounded half up): never a
    wrap. Unsigned values of 2^63 or more, and values whose µs do not fit int64, are an error."""
    if t.size and t.dtype.kind == "u" and int(t.max()) > _I64.max:
        i = int(np.argmax(t > _I64.max))
        raise EventDataError(f"{source}: timestamp {int(t[i])} at event {i} is 2^63 or more: it does not fit "
                             f"int64 (it would wrap to a negative time)")
    t = t.astype(np.int64)
    if unit == "ns":
        q, r = np.divmod(t, 1000)
        return q + (r >= 500)
    mul = _US_PER_UNIT[unit]
    if mul > 1 and t.size and max(int(t.max()), -int(t.min())) > _I64.max // mul:
        raise EventDataError(f"{source}: timestamps in {unit} reach {max(int(t.max()), int(t.min()), key=abs)}, "
                             f"beyond the int64 µs range")
    return t * mul


def check_event_columns(x, y, t_us, p, sensor_size: Optional[Tuple[int, int]] = None,
                        source: str = "events") -> Dict[str, np.ndarray]:
    """The checks of raw event columns on their way into :class:`~dvsland.events.Events` (what
    :func:`dvsland.events.validate_events` packs).

    Args:
        x, y: (N,) integer-valued pixel column / row, >= 0 and < W / H when ``sensor_size`` is given.
        t_us: (N,) integer-valued timestamps, µs (see :func:`times_to_us` for other units).
        p: (N,) polarity, either {0, 1} (0 = OFF; tonic, HDF5 and AEDAT files) or {-1, +1}
            (dvsland), or bool (False = OFF).
        sensor_size: (W, H) or None.
        source: a name for the messages (file name).

    Returns:
        {"x", "y", "t", "p"}: numpy columns (int64, p int8 ±1), stably sorted by t when not already.

    Raises:
        EventDataError: (a ValueError) naming the field, the allowed range and the source (the
            checks of :func:`check_event_arrays`).
    """
    cols = {k: _as_1d(k, v, source) for k, v in (("x", x), ("y", y), ("t", t_us), ("p", p))}
    n = len(cols["x"])
    for k, a in cols.items():
        if len(a) != n:
            raise EventDataError(f"{source}: events fields must have equal length, got x of {n} and {k} of {len(a)}")
    a = check_event_arrays(cols, sensor_size=sensor_size, polarity="any01pm1", require_sorted=False, source=source)
    t = a["t"]
    if n > 1 and np.any(t[1:] < t[:-1]):
        order = np.argsort(t, kind="stable")
        a = {k: v[order] for k, v in a.items()}
    return a

__all__ = ["EventDataError", "RecordingError", "check_event_arrays", "check_event_columns", "check_events",
           "checked_for_estimator", "times_to_us", "TIME_UNITS", "FIELDS"]
