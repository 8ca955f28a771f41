"""Event windows as network inputs, and the targets of a sample.

Representations (``representation=``):

- ``"count"``: (2, H, W) float32 per-pixel event counts, channel 0 = ON, 1 = OFF (dvsland's order,
  :meth:`dvsland.events.Events.to_count_image`);
- ``"voxel"``: (n_bins, H, W) float32 voxel grid over the window ``[t0_us, t_us]``, bilinear in
  time, polarity-SIGNED (an OFF event subtracts; :meth:`dvsland.events.Events.to_voxel_grid`);
- ``"events"``: the raw events as a tonic structured array (:data:`dvsland.events.TONIC_DTYPE`:
  x, y int16, t int64 µs of flight time, p int8 with OFF = 0 and ON = 1, tonic's convention),
  batched by :func:`collate_events`.

Targets (a dict of tensors, :func:`targets_of`): ``d_true`` (1/s, < 0 descending), ``tau_s`` (s,
+inf when not descending), ``z_m`` (m), ``v_mps`` (m/s, < 0 descending), ``t_s`` (s of flight),
float32 each; ``valid`` (bool); ``step``, ``seed_index``, ``variant``, ``site_index`` (index into
the dataset's ``sites``) and ``n_events``, int64 each; every one a 0-d tensor.
"""

from __future__ import annotations

from typing import Dict, List, Sequence, Tuple

import numpy as np
import torch

REPRESENTATIONS = ("count", "voxel", "events")

#: float32 targets and their units
FLOAT_TARGETS = {"d_true": "1/s", "tau_s": "s", "z_m": "m", "v_mps": "m/s", "t_s": "s"}
#: int64 targets
INT_TARGETS = ("step", "seed_index", "variant", "site_index", "n_events")


def check_representation(representation: str, n_bins: int) -> None:
    """ValueError naming ``representation`` (or ``n_bins``) when it is not accepted."""
    if representation not in REPRESENTATIONS:
        raise ValueError(f"representation must be one of {list(REPRESENTATIONS)}, got {representation!r}")
    if representation == "voxel" and (not isinstance(n_bins, int) or n_bins < 1):
        raise ValueError(f"n_bins must be an int >= 1 for representation='voxel', got {n_bins!r}")


def _events(ev: Dict[str, np.ndarray], t0_us: int):
    """dvsland :class:`~dvsland.events.Events` (b = 0) of one window's stored arrays."""
    from dvsland.events import Events

    n = len(ev["x"])
    return Events(b=torch.zeros(n, dtype=torch.int64), x=torch.from_numpy(ev["x"].astype(np.int64)),
                  y=torch.from_numpy(ev["y"].astype(np.int64)),
                  t=torch.from_numpy(ev["dt_us"].astype(np.int64) + int(t0_us)), p=torch.from_numpy(ev["p"]))


def represent(ev: Dict[str, np.ndarray], t0_us: int, t_us: int, sensor_size: Tuple[int, int],
              representation: str, n_bins: int = 5):
    """One window ``(t0_us, t_us]`` of stored events ({x, y, dt_us, p} arrays) as ``representation``.

    Args:
        sensor_size: (W, H) pixels.

    Returns:
        (2, H, W) or (n_bins, H, W) float32 tensor, or a tonic structured array (N,).
    """
    W, H = int(sensor_size[0]), int(sensor_size[1])
    if representation == "events":
        arr = np.empty(len(ev["x"]), dtype=tonic_dtype())
        arr["x"], arr["y"] = ev["x"], ev["y"]
        arr["t"] = ev["dt_us"].astype(np.int64) + int(t0_us)
        arr["p"] = (ev["p"] > 0).astype(np.int8)
        return arr
    e = _events(ev, t0_us)
    if representation == "count":
        return e.to_count_image(1, H, W)[0]
    if t_us <= t0_us:  # step 0: no window yet
        return torch.zeros(n_bins, H, W, dtype=torch.float32)
    return e.to_voxel_grid(n_bins, int(t0_us), int(t_us), 1, H, W)[0]


def tonic_dtype() -> np.dtype:
    from dvsland.events import TONIC_DTYPE

    return TONIC_DTYPE


def targets_of(row: Dict[str, np.ndarray], i: int, descent: Dict[str, np.ndarray], site_index: int,
               n_events: int) -> Dict[str, torch.Tensor]:
    """The target dict of sample ``i`` of a shard's sample table ``row`` (see the module doc)."""
    d = int(row["descent"][i])
    out = {k: torch.tensor(float(row[k][i]), dtype=torch.float32) for k in FLOAT_TARGETS}
    out["valid"] = torch.tensor(bool(row["valid"][i]))
    ints = {"step": row["step"][i], "seed_index": descent["seed_index"][d], "variant": descent["variant"][d],
            "site_index": site_index, "n_events": n_events}
    out.update({k: torch.tensor(int(v), dtype=torch.int64) for k, v in ints.items()})
    return out


def collate_events(batch: Sequence[Tuple[np.ndarray, Dict[str, torch.Tensor]]]):
    """Batch ``(events, targets)`` samples of ``representation="events"`` (variable lengths).

    Returns:
        ``(events, targets)``: ``events`` a dict of int64 tensors ``b`` (sample index in the batch),
        ``x``, ``y``, ``t`` (µs of flight time) and ``p`` (int8, +1 ON / -1 OFF: dvsland's
        convention, so ``Events(**{k: events[k] for k in "bxytp"})`` is the batch as the estimators
        take it),
        each (N,) with N the total events, sorted by (b, t), plus ``lengths`` (B,) int64;
        ``targets`` a dict of (B,) tensors (:func:`torch.stack` of each target).
    """
    arrays: List[np.ndarray] = [s[0] for s in batch]
    lengths = torch.tensor([len(a) for a in arrays], dtype=torch.int64)
    cat = np.concatenate(arrays) if arrays else np.zeros(0, tonic_dtype())
    events = {"b": torch.repeat_interleave(torch.arange(len(arrays)), lengths),
              "x": torch.from_numpy(cat["x"].astype(np.int64)), "y": torch.from_numpy(cat["y"].astype(np.int64)),
              "t": torch.from_numpy(cat["t"].astype(np.int64)),
              "p": torch.from_numpy(np.where(cat["p"] > 0, 1, -1).astype(np.int8)), "lengths": lengths}
    targets = {k: torch.stack([s[1][k] for s in batch]) for k in batch[0][1]} if batch else {}
    return events, targets
