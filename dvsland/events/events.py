"""Packed events of a batch of event cameras, and their standard representations.

Conventions (docs/events.md):

- ``b``: int64 batch index (which camera / descent), ``x``, ``y``: int64 pixel column and row
  (int64 so they index tensors directly), ``t``: int64 microseconds, ``p``: int8 polarity,
  +1 = ON (brighter), -1 = OFF (darker).
- Events are sorted by (b, t); ties keep their order of generation (stable sorts only).
- Count images are (B, 2, H, W) float32 with channel 0 = ON, channel 1 = OFF: the opposite of
  tonic's ``ToFrame`` (channel 0 = OFF, 1 = ON); ``to_count_image(..., polarity_order="tonic")``
  gives tonic's order.
- Voxel grids are (B, n_bins, H, W) float32, polarity-signed (+1 / -1), bilinear in time (E2VID).
- tonic interop: numpy structured arrays with fields x, y (int16), t (int64 µs), p (int8, OFF = 0,
  ON = 1) and ``sensor_size = (W, H, 2)``.
"""

from __future__ import annotations

from typing import Iterable, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from .validate import EventDataError, check_event_arrays, check_event_columns, check_events

DeviceLike = Union[str, torch.device, None]

#: numpy dtype of tonic's event arrays as written by :meth:`Events.to_tonic`.
TONIC_DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("t", np.int64), ("p", np.int8)])

_FIELDS = ("b", "x", "y", "t", "p")
_DTYPES = {"b": torch.int64, "x": torch.int64, "y": torch.int64, "t": torch.int64, "p": torch.int8}


def _lexsort_bt(b: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Permutation sorting by (b, t), stable (ties keep input order)."""
    order = torch.sort(t, stable=True).indices
    order = order[torch.sort(b[order], stable=True).indices]
    return order


class Events:
    """A packed set of events of B cameras, sorted by (b, t).

    Args:
        b: (N,) batch index, int64 (other integer dtypes are converted).
        x: (N,) pixel column, int64.
        y: (N,) pixel row, int64.
        t: (N,) timestamp, int64 µs.
        p: (N,) polarity, int8, +1 (ON) or -1 (OFF).
        sort: sort by (b, t) (stable). Leave False when the input is already sorted
            (the emulator's output is); :meth:`is_sorted` checks.

    All fields live on one device. Shapes and dtypes are checked; values are not (use
    :meth:`validate`).

    ``checked`` is None, or the (B, W, H) for which the events are known sorted by (b, t) with every
    b, x, y in range: the built-in emulator marks its output so (:meth:`marked_checked`), and the
    estimators' input check then trusts it without reading the values (no host sync). A new
    :class:`Events` (a subset too) starts unmarked.
    """

    __slots__ = _FIELDS + ("checked",)

    def __init__(self, b: torch.Tensor, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor,
                 p: torch.Tensor, sort: bool = False):
        vals = {}
        for name, v in zip(_FIELDS, (b, x, y, t, p)):
            v = torch.as_tensor(v)
            if v.dim() != 1:
                raise ValueError(f"Events field {name!r} must be 1-D (N,), got shape {tuple(v.shape)}")
            if v.is_floating_point() or v.is_complex():
                raise ValueError(f"Events field {name!r} must be an integer tensor, got {v.dtype}")
            vals[name] = v.to(_DTYPES[name])
        n = vals["b"].shape[0]
        dev = vals["b"].device
        for name, v in vals.items():
            if v.shape[0] != n:
                raise ValueError(f"Events fields must have equal length, got {name!r} of length "
                                 f"{v.shape[0]} and 'b' of length {n}")
            if v.device != dev:
                raise ValueError(f"Events fields must be on one device, got {name!r} on {v.device} "
                                 f"and 'b' on {dev}")
        if sort and n > 1:
            order = _lexsort_bt(vals["b"], vals["t"])
            vals = {k: v[order] for k, v in vals.items()}
        for k, v in vals.items():
            object.__setattr__(self, k, v)
        object.__setattr__(self, "checked", None)

    def marked_checked(self, batch_size: int, width: int, height: int) -> "Events":
        """These events (the same object) marked as sorted and in range for ``batch_size`` cameras
        of ``width`` x ``height`` pixels: only for a producer that guarantees it by construction."""
        object.__setattr__(self, "checked", (int(batch_size), int(width), int(height)))
        return self

    # ----------------------------------------------------------------- basics
    @classmethod
    def empty(cls, device: DeviceLike = None) -> "Events":
        """No events, on ``device`` (default CPU)."""
        dev = torch.device(device) if device is not None else torch.device("cpu")
        z = {k: torch.empty(0, dtype=_DTYPES[k], device=dev) for k in _FIELDS}
        return cls(**z)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def __repr__(self) -> str:
        return f"Events(n={len(self)}, device={self.device})"

    @property
    def device(self) -> torch.device:
        return self.t.device

    def fields(self) -> dict:
        """``{'b': ..., 'x': ..., 'y': ..., 't': ..., 'p': ...}``."""
        return {k: getattr(self, k) for k in _FIELDS}

    def __iter__(self):
        # without this, Python iterates through __getitem__(0), (1), ... and the first call fails
        # with "field 'b' must be 1-D, got shape ()", which says nothing about the real mistake
        raise TypeError(
            "Events is not iterable and does not unpack. If this came from `events, meta = "
            "load_events(path)`: load_events returns Events alone unless with_meta=True; write "
            "`events, meta = load_events(path, with_meta=True)` or `events = load_events(path)`. "
            "For the columns use events.b, .x, .y, .t, .p or events.fields(); for a subset, events[mask] "
            "or events[i:j].")

    def __getitem__(self, index) -> "Events":
        """Select events by a boolean mask (N,) or an index tensor / slice (order is kept as given).
        A single integer is refused (the result would not be an event list): use ``ev[i:i + 1]``."""
        if isinstance(index, (int, np.integer)) or (isinstance(index, torch.Tensor) and index.dim() == 0):
            raise TypeError(f"Events[{int(index)}]: select events with a slice (events[{int(index)}:{int(index) + 1}]), "
                            "a boolean mask or an index tensor; a single integer would give no event list. "
                            "(Unpacking Events, as in `events, meta = load_events(path)`, also ends here: "
                            "load_events returns (events, meta) only with with_meta=True.)")
        if isinstance(index, torch.Tensor) and index.dtype == torch.bool:
            if index.shape != self.t.shape:
                raise ValueError(f"mask must have shape ({len(self)},), got {tuple(index.shape)}")
            # the kept positions found once for the five fields (a mask per field finds them five times)
            idx = index.to(self.t.device).nonzero().squeeze(1)
            return Events(**{k: getattr(self, k).index_select(0, idx) for k in _FIELDS})
        return Events(**{k: getattr(self, k)[index] for k in _FIELDS})

    def to(self, device: DeviceLike) -> "Events":
        """Copy to ``device`` (no-op when already there)."""
        return Events(**{k: getattr(self, k).to(device) for k in _FIELDS})

    def clone(self) -> "Events":
        return Events(**{k: getattr(self, k).clone() for k in _FIELDS})

    @staticmethod
    def cat(events: Iterable["Events"]) -> "Events":
        """Concatenate and re-sort by (b, t) (stable: ties keep list order)."""
        events = list(events)
        if not events:
            return Events.empty()
        dev = events[0].device
        return Events(**{k: torch.cat([getattr(e, k).to(dev) for e in events]) for k in _FIELDS},
                      sort=True)

    def sort(self) -> "Events":
        """A copy sorted by (b, t), stable."""
        return Events(**self.fields(), sort=True)

    def is_sorted(self) -> bool:
        """Whether the events are sorted by (b, t) (one device sync)."""
        if len(self) < 2:
            return True
        b0, b1, t0, t1 = self.b[:-1], self.b[1:], self.t[:-1], self.t[1:]
        # comparisons, not differences: t1 - t0 overflows int64 for timestamps near +-2^62
        return bool(((b1 > b0) | ((b1 == b0) & (t1 >= t0))).all())

    def __eq__(self, other) -> bool:  # exact equality of all fields
        if not isinstance(other, Events) or len(self) != len(other):
            return False
        return all(torch.equal(getattr(self, k), getattr(other, k).to(self.device)) for k in _FIELDS)

    __hash__ = None

    def validate(self, batch_size: Optional[int] = None, height: Optional[int] = None,
                 width: Optional[int] = None) -> "Events":
        """Raise :class:`~dvsland.events.validate.EventDataError` (a ValueError) naming the field and
        its range when a value is out of range or the order is wrong; returns self."""
        if len(self) == 0:
            return self
        check_events(self, batch_size, width=width, height=height, what="Events")
        if not self.is_sorted():
            raise EventDataError("Events must be sorted by (b, t); use Events.sort()")
        return self

    # --------------------------------------------------------- selections
    def select_batch(self, b: int) -> "Events":
        """Events of batch element ``b`` (still with their ``b`` field)."""
        return self[self.b == int(b)]

    def time_window(self, t0_us: int, t1_us: int) -> "Events":
        """Events with t0_us <= t < t1_us."""
        return self[(self.t >= int(t0_us)) & (self.t < int(t1_us))]

    def batch_counts(self, batch_size: int) -> torch.Tensor:
        """(B,) int64 number of events per batch element."""
        _check_pos("batch_size", batch_size)
        return torch.bincount(self.b, minlength=int(batch_size))[: int(batch_size)]

    # --------------------------------------------------- representations
    def _flat_index(self, batch_size: int, channels: int, channel: torch.Tensor, height: int,
                    width: int) -> torch.Tensor:
        return ((self.b * channels + channel) * height + self.y) * width + self.x

    def _check_bounds(self, batch_size: int, height: int, width: int) -> None:
        if len(self) == 0:
            return
        bad = ((self.b < 0) | (self.b >= batch_size) | (self.x < 0) | (self.x >= width)
               | (self.y < 0) | (self.y >= height)).any()
        if bool(bad):
            self.validate(batch_size, height, width)  # raises with the offending field

    def to_count_image(self, batch_size: int, height: int, width: int,
                       polarity_order: str = "dvsland") -> torch.Tensor:
        """Per-pixel event counts, (B, 2, H, W) float32.

        Channel order: with ``polarity_order="dvsland"`` (the default, which every dvsland
        estimator and figure expects) channel 0 = ON, channel 1 = OFF. This is the **opposite**
        of tonic's ``ToFrame`` (channel 0 = OFF, channel 1 = ON, its polarity index); pass
        ``polarity_order="tonic"`` to get tonic's order, e.g. for a network trained on tonic
        frames. Either way the channel of an event is fixed by its sign, never by its position.

        Built with one ``bincount`` (no loops). The sum over the image equals ``len(self)``.
        Events outside the (B, H, W) range raise ValueError.
        """
        if polarity_order not in ("dvsland", "tonic"):
            raise ValueError(f"polarity_order must be 'dvsland' (channel 0 = ON) or 'tonic' (channel 0 = OFF), "
                             f"got {polarity_order!r}")
        for n, v in (("batch_size", batch_size), ("height", height), ("width", width)):
            _check_pos(n, v)
        B, H, W = int(batch_size), int(height), int(width)
        self._check_bounds(B, H, W)
        ch = ((self.p < 0) if polarity_order == "dvsland" else (self.p > 0)).to(torch.int64)
        idx = self._flat_index(B, 2, ch, H, W)
        counts = torch.bincount(idx, minlength=B * 2 * H * W)
        return counts.to(torch.float32).view(B, 2, H, W)

    def to_voxel_grid(self, n_bins: int, t0_us: int, t1_us: int, batch_size: int, height: int,
                      width: int) -> torch.Tensor:
        """Polarity-signed voxel grid, bilinear in time (E2VID), (B, n_bins, H, W) float32.

        An event at time t in [t0_us, t1_us] has normalised time
        ``u = (n_bins - 1) * (t - t0_us) / (t1_us - t0_us)`` and adds ``p * (1 - |u - k|)`` to the
        bins k = floor(u) and floor(u) + 1 (those inside [0, n_bins)). Events outside
        [t0_us, t1_us] are ignored. With n_bins = 1 every event adds p to bin 0.
        """
        for n, v in (("n_bins", n_bins), ("batch_size", batch_size), ("height", height),
                     ("width", width)):
            _check_pos(n, v)
        if not int(t1_us) > int(t0_us):
            raise ValueError(f"t1_us must be > t0_us, got t0_us={t0_us}, t1_us={t1_us}")
        B, H, W, K = int(batch_size), int(height), int(width), int(n_bins)
        grid = torch.zeros(B * K * H * W, dtype=torch.float32, device=self.device)
        if len(self) == 0:
            return grid.view(B, K, H, W)
        self._check_bounds(B, H, W)
        keep = (self.t >= int(t0_us)) & (self.t <= int(t1_us))
        ev = self[keep]
        u = (ev.t - int(t0_us)).to(torch.float64) * ((K - 1) / float(int(t1_us) - int(t0_us)))
        k0 = torch.floor(u)
        w1 = (u - k0).to(torch.float32)
        k0 = k0.to(torch.int64)
        pol = ev.p.to(torch.float32)
        for dk, w in ((0, 1.0 - w1), (1, w1)):
            k = k0 + dk
            ok = (k >= 0) & (k < K) & (w != 0)
            idx = ((ev.b * K + k) * H + ev.y) * W + ev.x
            grid.index_add_(0, idx[ok], (pol * w)[ok])
        return grid.view(B, K, H, W)

    # --------------------------------------------------------------- tonic
    def to_tonic(self, b: int = 0, height: Optional[int] = None,
                 width: Optional[int] = None) -> Tuple[np.ndarray, Tuple[int, int, int]]:
        """Events of batch element ``b`` as a tonic structured array.

        Returns:
            ``(events, sensor_size)``: ``events`` a numpy structured array with fields
            x, y (int16), t (int64 µs), p (int8, OFF = 0, ON = 1), in time order;
            ``sensor_size = (W, H, 2)`` (from ``height``/``width``, else max coordinate + 1).
        """
        ev = self.select_batch(b)
        arr = np.empty(len(ev), dtype=TONIC_DTYPE)
        x = ev.x.cpu().numpy()
        y = ev.y.cpu().numpy()
        if len(ev) and (x.min() < 0 or y.min() < 0 or x.max() > np.iinfo(np.int16).max
                        or y.max() > np.iinfo(np.int16).max):
            raise ValueError("x and y must be in [0, 32767] for tonic's int16 fields")
        arr["x"] = x
        arr["y"] = y
        arr["t"] = ev.t.cpu().numpy()
        arr["p"] = (ev.p.cpu().numpy() > 0).astype(np.int8)
        W = int(width) if width is not None else (int(x.max()) + 1 if len(ev) else 0)
        H = int(height) if height is not None else (int(y.max()) + 1 if len(ev) else 0)
        return arr, (W, H, 2)

    @classmethod
    def from_tonic(cls, arr: np.ndarray, b: int = 0, device: DeviceLike = None) -> "Events":
        """Events from a tonic structured array (fields x, y, t, p; p in {0, 1} or bool, 0 = OFF,
        or already in {-1, +1}); all get batch index ``b``. Sorted by t (stable)."""
        names = getattr(getattr(arr, "dtype", None), "names", None) or ()
        missing = [f for f in ("x", "y", "t", "p") if f not in names]
        if missing:
            raise EventDataError(f"tonic array must have fields x, y, t, p; missing {missing}")
        a = check_event_arrays({k: arr[k] for k in ("x", "y", "t", "p")}, polarity="any01pm1",
                               require_sorted=False, source="tonic array")
        return _pack(a, b, device, "tonic array", sort=True, cls=cls)


def _pack(cols: dict, b: int, device: DeviceLike, source: str, sort: bool = False, cls=None) -> Events:
    """Checked numpy columns x, y, t, p as :class:`Events` (or ``cls``) of batch element ``b`` on ``device``."""
    if int(b) < 0:
        raise EventDataError(f"{source}: batch index b must be >= 0, got {b}")
    dev = torch.device(device) if device is not None else torch.device("cpu")
    n = len(cols["t"])
    return (cls or Events)(b=torch.full((n,), int(b), dtype=torch.int64, device=dev),
                           **{k: torch.as_tensor(cols[k], device=dev) for k in ("x", "y", "t", "p")}, sort=sort)


def validate_events(x, y, t_us, p, sensor_size: Optional[Tuple[int, int]] = None, source: str = "events",
                    b: int = 0, device: DeviceLike = None) -> Events:
    """Check raw event columns and pack them into :class:`Events` (batch index ``b``), sorted by t.

    Args:
        x, y: (N,) integer-valued pixel column / row, >= 0 and < W / H when ``sensor_size`` is given.
        t_us: (N,) integer-valued timestamps, µs (see :func:`dvsland.events.validate.times_to_us`).
        p: (N,) polarity, either {0, 1} (0 = OFF; tonic, HDF5 and AEDAT files) or {-1, +1}
            (dvsland), or bool (False = OFF).
        sensor_size: (W, H) or None.
        source: a name for the messages (file name).

    Returns:
        Events with b, x, y, t int64 and p int8 ±1, stably sorted by t when not already.

    Raises:
        EventDataError: (a ValueError) naming the field, the allowed range and the source (the
            checks of :func:`dvsland.events.validate.check_event_columns`).
    """
    return _pack(check_event_columns(x, y, t_us, p, sensor_size, source), b, device, source)


def _check_pos(name: str, v) -> None:
    if int(v) < 1 or int(v) != v:
        raise ValueError(f"{name} must be an integer >= 1, got {v}")
