"""A whole split of a dataset folder in memory, as flat tensors, for fast training.

:func:`load_windows` reads every event of the split's samples once (shard by shard, sequential
reads) into one :class:`Windows`; :func:`gather_batch` cuts a batch of samples out of it with
tensor indexing only (no Python loop over samples or events). Random per-item reads through
:class:`~dvsland.data.EventWindowDataset` run at a few hundred samples per second; a gathered
batch costs well under a millisecond per sample.
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional, Tuple

import numpy as np
import torch

from .dataset import EventWindowDataset
from .splits import SplitRule


class Windows(NamedTuple):
    """S samples of one split. Events (N,): ``x``, ``y`` int16 px, ``frac`` float32 time as a
    fraction of its window [0, 1], ``p`` int8 +-1; ``offset`` (S + 1,) int64 (sample i's events
    are rows offset[i] .. offset[i+1] - 1). Per sample (S,): ``d_true`` float32 1/s, ``site``
    int64 index into ``sites``, ``descent`` int64 (a key unique over the split), ``step`` int64,
    ``z_m`` float32 m; ``next``, ``prev`` int64 the rows of the same descent's next and previous
    control steps (-1 = none).
    ``sites``: site names; ``sensor_size`` (W, H)."""

    x: torch.Tensor
    y: torch.Tensor
    frac: torch.Tensor
    p: torch.Tensor
    offset: torch.Tensor
    d_true: torch.Tensor
    site: torch.Tensor
    descent: torch.Tensor
    step: torch.Tensor
    z_m: torch.Tensor
    next: torch.Tensor
    prev: torch.Tensor
    sites: List[str]
    sensor_size: Tuple[int, int]

    @property
    def n_samples(self) -> int:
        """S (``len()`` of a NamedTuple counts its fields)."""
        return int(self.d_true.shape[0])


def _ranges(starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Concatenated aranges start..stop - 1 of every pair, int64, without a Python loop."""
    n = stops - starts
    if n.sum() == 0:
        return np.zeros(0, np.int64)
    first = np.repeat(starts - np.concatenate([[0], np.cumsum(n)[:-1]]), n)
    return first + np.arange(int(n.sum()), dtype=np.int64)


def load_windows(root, split: str = "train", split_rule: Optional[SplitRule] = None, keep_share: float = 1.0,
                 seed: int = 0) -> Windows:
    """Every valid sample of ``split`` of the dataset folder ``root`` (see :class:`Windows`).

    ``keep_share`` in (0, 1]: keep each event with this probability (seeded by ``seed`` and the
    shard; the shard's events are then read in blocks of samples, so that a large sensor's
    dataset fits in memory thinned); 1 = every event.

    Raises the errors of :class:`~dvsland.data.EventWindowDataset` (folder, split, shards).
    """
    import h5py

    if not 0.0 < float(keep_share) <= 1.0:
        raise ValueError(f"keep_share must be in (0, 1], got {keep_share}")
    ds = EventWindowDataset(root, representation="events", split=split, split_rule=split_rule)
    cols = {k: [] for k in ("x", "y", "frac", "p")}
    per = {k: [] for k in ("d_true", "site", "descent", "step", "z_m", "n")}
    for s, sh in enumerate(ds.shards):
        rows = ds.index[ds.index[:, 0] == s, 1]
        if len(rows) == 0:
            continue
        smp = sh["samples"]
        off = smp["event_offset"]
        span = np.maximum(smp["t_us"][rows] - smp["t0_us"][rows], 1).astype(np.float64)
        if keep_share >= 1.0:
            sel = _ranges(off[rows], off[rows + 1])
            with h5py.File(sh["path"], "r") as f:
                ev = {k: f[f"events/{k}"][()] for k in ("x", "y", "dt_us", "p")}
            n = off[rows + 1] - off[rows]
            part = _columns(ev, sel, np.repeat(span, n))
        else:
            part, n = _thinned(sh["path"], off, rows, span, keep_share, np.random.default_rng([seed, s]))
        for k in cols:
            cols[k].append(part[k])
        site_names = np.asarray([ds.sites.index(str(v)) for v in sh["descents"]["site"]], dtype=np.int64)
        d = smp["descent"][rows].astype(np.int64)
        per["d_true"].append(smp["d_true"][rows].astype(np.float32))
        per["site"].append(site_names[d])
        per["descent"].append(d + s * 1_000_000)
        per["step"].append(smp["step"][rows].astype(np.int64))
        per["z_m"].append(smp["z_m"][rows].astype(np.float32))
        per["n"].append(n.astype(np.int64))
    t = {k: torch.from_numpy(np.concatenate(v)) for k, v in {**cols, **per}.items()}
    offset = torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(t.pop("n"), 0)])
    return Windows(t["x"], t["y"], t["frac"], t["p"], offset, t["d_true"], t["site"], t["descent"], t["step"],
                   t["z_m"], *_links(t["descent"], t["step"]), list(ds.sites), tuple(ds.sensor_size))


def _columns(ev: dict, sel: np.ndarray, span: np.ndarray) -> dict:
    """Rows ``sel`` of a shard's event fields as the Windows columns (span: (len(sel),) µs)."""
    return {"x": ev["x"][sel].astype(np.int16), "y": ev["y"][sel].astype(np.int16),
            "frac": (ev["dt_us"][sel] / span).astype(np.float32), "p": ev["p"][sel].astype(np.int8)}


def _thinned(path, off: np.ndarray, rows: np.ndarray, span: np.ndarray, share: float, rng, block: int = 128):
    """(columns, events per sample) of samples ``rows`` of shard ``path``, each event kept with
    probability ``share``; read ``block`` samples at a time (a contiguous range of the file)."""
    import h5py

    parts, counts = [], []
    with h5py.File(path, "r") as f:
        for i in range(0, len(rows), block):  # blocks of samples, not events
            r = rows[i:i + block]
            a, z = int(off[r].min()), int(off[r + 1].max())
            ev = {k: f[f"events/{k}"][a:z] for k in ("x", "y", "dt_us", "p")}
            sel = _ranges(off[r] - a, off[r + 1] - a)
            n = off[r + 1] - off[r]
            keep = rng.random(len(sel)) < share
            owner = np.repeat(np.arange(len(r)), n)[keep]
            parts.append(_columns(ev, sel[keep], span[i:i + block][owner]))
            counts.append(np.bincount(owner, minlength=len(r)))
    cols = {k: np.concatenate([p[k] for p in parts]) for k in ("x", "y", "frac", "p")}
    return cols, np.concatenate(counts).astype(np.int64)


def _links(descent: torch.Tensor, step: torch.Tensor):
    """(next, prev) rows of every sample (:func:`next_rows`)."""
    nxt = next_rows(descent, step)
    prev = torch.full_like(nxt, -1)
    has = nxt >= 0
    prev[nxt[has]] = torch.nonzero(has).squeeze(1)
    return nxt, prev


def next_rows(descent: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """(S,) int64: for each sample the row with the same ``descent`` and ``step + 1``, or -1."""
    key = descent * (1 << 20) + step
    order = torch.argsort(key)
    k = key[order]
    nxt = torch.full_like(key, -1)
    follows = k[1:] == k[:-1] + 1
    nxt[order[:-1][follows]] = order[1:][follows]
    return nxt


def gather_batch(w: Windows, idx: torch.Tensor):
    """Events of samples ``idx`` (B,) int64 as flat columns: (b (M,) int64 row in the batch, x, y,
    frac, p) plus the per-sample event counts (B,) int64."""
    starts, stops = w.offset[idx], w.offset[idx + 1]
    n = stops - starts
    b = torch.repeat_interleave(torch.arange(len(idx)), n)
    first = torch.repeat_interleave(starts - (torch.cumsum(n, 0) - n), n)
    rows = first + torch.arange(int(n.sum()))
    return b, w.x[rows], w.y[rows], w.frac[rows], w.p[rows], n


def load_manifest_info(root) -> dict:
    """Provenance of a dataset folder for a checkpoint: config name and hash, estimator, sites,
    seeds, sensor size (W, H), principal point and focal length (px; None = not recorded),
    control step, variants and the complete shards."""
    from .manifest import load_manifest

    m = load_manifest(root)
    keys = ("config_hash", "estimator", "sites", "n_seeds", "seed_offset", "sensor_size", "dt_s", "n_variants",
            "dvsland_version")
    out = {k: m.get(k) for k in keys}
    W, H = out["sensor_size"]
    out["principal_point_px"] = m.get("principal_point_px", [(W - 1) / 2, (H - 1) / 2])
    out["focal_px"] = m.get("focal_px")  # None: a dataset written before (a 60 degree field of view)
    out["config"] = (m.get("config") or {}).get("name")
    out["shards"] = sorted(e["id"] if "id" in e else e.get("file") for e in m["shards"] if e.get("status") == "complete")
    return out


def concat_windows(parts: List[Windows], param: str = "data") -> Windows:
    """One Windows of several (datasets of one sensor): site names merged, descents kept apart.
    ValueError naming ``param`` when the sensors differ."""
    if len(parts) == 1:
        return parts[0]
    sizes = {tuple(w.sensor_size) for w in parts}
    if len(sizes) != 1:
        raise ValueError(f"{param}: the datasets are of different sensors {sorted(sizes)}; one model input needs one "
                         f"sensor (train one model per sensor)")
    sites: List[str] = []
    for w in parts:
        sites += [s for s in w.sites if s not in sites]
    cat = {k: [] for k in ("x", "y", "frac", "p", "d_true", "site", "descent", "step", "z_m")}
    offs, base = [torch.zeros(1, dtype=torch.int64)], 0
    for j, w in enumerate(parts):
        remap = torch.tensor([sites.index(s) for s in w.sites], dtype=torch.int64)
        for k in ("x", "y", "frac", "p", "d_true", "step", "z_m"):
            cat[k].append(getattr(w, k))
        cat["site"].append(remap[w.site])
        cat["descent"].append(w.descent + j * 10 ** 9)
        offs.append(w.offset[1:] + base)
        base += int(w.offset[-1])
    t = {k: torch.cat(v) for k, v in cat.items()}
    return Windows(t["x"], t["y"], t["frac"], t["p"], torch.cat(offs), t["d_true"], t["site"], t["descent"],
                   t["step"], t["z_m"], *_links(t["descent"], t["step"]), sites, parts[0].sensor_size)
