"""``EventWindowDataset``: a built dataset folder as a map-style torch ``Dataset``.

Each item is ``(input, targets)``: ``input`` in the chosen representation and ``targets`` a
dict of 0-d tensors (:mod:`dvsland.data.represent`). The small tables of every shard (samples,
descents) are read when the dataset is made; the events are read per item from the shard's
HDF5 file, opened lazily once per process (a DataLoader worker opens its own handles: the
dataset pickles without them, so ``num_workers > 0`` works with any start method).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Callable, Dict, List, Optional

import numpy as np
import torch

from dvsland.config.schema import DEFAULT_FOV_DEG, focal_length_px

from .manifest import load_manifest
from .represent import check_representation, represent, targets_of
from .shardfile import ShardError, read_events, read_index
from .splits import SplitRule, check_split


class EventWindowDataset(torch.utils.data.Dataset):
    """Labelled event windows of a folder written by :func:`dvsland.data.build_dataset`.

    Args:
        root: the dataset folder (with ``dataset.json``).
        representation: ``"count"`` (2, H, W), ``"voxel"`` (n_bins, H, W) or ``"events"`` (tonic
            array; batch with :func:`dvsland.data.collate_events`).
        split: ``"train"``, ``"val"``, ``"test"`` (:mod:`dvsland.data.splits`) or ``"all"``.
        n_bins: time bins of the voxel grid.
        valid_only: keep only samples with a usable target (``valid``: step > 0, descending).
        split_rule: a :class:`~dvsland.data.splits.SplitRule` (default: site type ``craters_rocks``
            held out).
        on_bad_shard: ``"raise"`` (default) or ``"skip"`` (warn and read the other shards) for a
            shard file that is missing, truncated or corrupt.
        transform, target_transform: callables applied to the input and to the targets dict.

    Attributes:
        sites: site names (``targets["site_index"]`` indexes them).
        sensor_size: (W, H) pixels.
        manifest: the folder's manifest.
        skipped: ``{shard file: error}`` of the shards skipped with ``on_bad_shard="skip"``.

    Raises:
        ValueError: unknown representation, split or on_bad_shard; a folder that is empty, holds
            no dataset or no complete shard; a bad shard with ``on_bad_shard="raise"`` (names the
            file); a split with no sample.
    """

    def __init__(self, root, representation: str = "count", split: str = "train", n_bins: int = 5,
                 valid_only: bool = True, split_rule: Optional[SplitRule] = None, on_bad_shard: str = "raise",
                 transform: Optional[Callable] = None, target_transform: Optional[Callable] = None):
        check_representation(representation, n_bins)
        check_split(split)
        if on_bad_shard not in ("raise", "skip"):
            raise ValueError(f"on_bad_shard must be 'raise' or 'skip', got {on_bad_shard!r}")
        self.root = Path(root)
        self.manifest = load_manifest(self.root)
        self.representation, self.split, self.n_bins = representation, split, int(n_bins)
        self.sites: List[str] = list(self.manifest["sites"])
        self.sensor_size = tuple(self.manifest["sensor_size"])
        W, H = self.sensor_size
        #: (cx, cy) px and the focal length in px of the camera (older datasets: centre, 60 degrees)
        self.principal_point_px = tuple(float(v) for v in self.manifest.get("principal_point_px",
                                                                             ((W - 1) / 2, (H - 1) / 2)))
        self.focal_px = float(self.manifest.get("focal_px", focal_length_px(W, DEFAULT_FOV_DEG)))
        self.rule = split_rule or SplitRule()
        self.transform, self.target_transform = transform, target_transform
        self.skipped: Dict[str, str] = {}
        self.shards = self._read_shards(on_bad_shard)
        self.index = self._make_index(valid_only)
        if len(self.index) == 0:
            raise ValueError(f"split={split!r}: no sample of {self.root} falls in it (rule {self.rule}; "
                             f"{self._counts(valid_only)})")
        self._handles: Dict[int, object] = {}
        self._pid = os.getpid()

    # ------------------------------------------------------------------ loading
    def _read_shards(self, on_bad_shard: str) -> List[dict]:
        done = [e for e in self.manifest["shards"] if e.get("status") == "complete"]
        if not done:
            raise ValueError(f"root={str(self.root)!r}: the dataset has no complete shard yet "
                             f"({len(self.manifest['shards'])} planned); resume its build")
        shards = []
        for e in done:
            path = self.root / e["file"]
            try:
                shards.append({"path": path, **self._own_shard(path, e, read_index(path))})
            except ShardError as exc:
                if on_bad_shard == "raise":
                    raise ShardError(f"{exc}; rebuild it with the same `dvsland dataset build` command, or pass "
                                     "on_bad_shard='skip' to read the other shards") from None
                warnings.warn(f"skipping {exc}", stacklevel=3)
                self.skipped[str(path)] = str(exc)
        if not shards:
            raise ValueError(f"root={str(self.root)!r}: every shard is unreadable ({len(self.skipped)} skipped)")
        return shards

    def _own_shard(self, path, entry: dict, index: dict) -> dict:
        """``index`` when the shard is this dataset's own ``entry``; ShardError naming the file when
        it came from another build (another ``config_hash``) or is a copy of another shard."""
        attrs = index["attrs"]
        want, got = self.manifest.get("config_hash"), attrs.get("config_hash")
        if want is not None and got is not None and str(got) != str(want):
            raise ShardError(f"shard {str(path)!r}: from another build (config_hash {got}, the dataset's is {want})")
        sid = attrs.get("shard_id")
        if sid is not None and "id" in entry and str(sid) != str(entry["id"]):
            raise ShardError(f"shard {str(path)!r}: a copy of shard {str(sid)!r}, not {entry['id']!r}")
        return index

    def _descent_split(self, sh: dict) -> np.ndarray:
        d = sh["descents"]
        return self.rule.assign(d["site"], d["variant"], int(self.manifest.get("n_variants", 1)))

    def _make_index(self, valid_only: bool) -> np.ndarray:
        """(n, 2) int64 rows (shard, sample) of this split, in shard then file order."""
        rows = []
        for s, sh in enumerate(self.shards):
            smp = sh["samples"]
            keep = np.ones(len(smp["step"]), dtype=bool) if not valid_only else smp["valid"].astype(bool)
            if self.split != "all":
                keep &= self._descent_split(sh)[smp["descent"]] == self.split
            r = np.flatnonzero(keep)
            rows.append(np.stack([np.full(len(r), s), r], axis=1))
        return np.concatenate(rows).astype(np.int64) if rows else np.zeros((0, 2), np.int64)

    def _counts(self, valid_only: bool) -> str:
        out = {}
        for sh in self.shards:
            smp = sh["samples"]
            sp = self._descent_split(sh)[smp["descent"]]
            if valid_only:
                sp = sp[smp["valid"].astype(bool)]
            for k in ("train", "val", "test"):
                out[k] = out.get(k, 0) + int((sp == k).sum())
        return "samples per split: " + ", ".join(f"{k} {v}" for k, v in out.items())

    # ------------------------------------------------------------------ items
    def __len__(self) -> int:
        return int(len(self.index))

    def _file(self, s: int):
        import h5py

        if self._pid != os.getpid():  # a forked worker: never share the parent's handles
            self._handles, self._pid = {}, os.getpid()
        f = self._handles.get(s)
        if f is None:
            f = self._handles[s] = h5py.File(self.shards[s]["path"], "r")
        return f

    def __getitem__(self, i: int):
        s, r = (int(v) for v in self.index[i])
        sh = self.shards[s]
        smp = sh["samples"]
        a, b = int(smp["event_offset"][r]), int(smp["event_offset"][r + 1])
        ev = read_events(self._file(s), a, b)
        x = represent(ev, int(smp["t0_us"][r]), int(smp["t_us"][r]), self.sensor_size, self.representation,
                      self.n_bins)
        d = int(smp["descent"][r])
        y = targets_of(smp, r, sh["descents"], self.sites.index(str(sh["descents"]["site"][d])), b - a)
        if self.transform is not None:
            x = self.transform(x)
        if self.target_transform is not None:
            y = self.target_transform(y)
        return x, y

    def info(self, i: int) -> dict:
        """Where sample ``i`` comes from: shard file, descent row, site, scene, seed, split, step."""
        s, r = (int(v) for v in self.index[i])
        sh = self.shards[s]
        d = int(sh["samples"]["descent"][r])
        desc = {k: (v[d].item() if hasattr(v[d], "item") else v[d]) for k, v in sh["descents"].items()}
        return {"shard": str(sh["path"]), "row": r, "descent": d, "split": str(self._descent_split(sh)[d]),
                "step": int(sh["samples"]["step"][r]), **desc}

    def close(self) -> None:
        """Close the open shard files (reopened on the next item)."""
        for f in self._handles.values():
            f.close()
        self._handles = {}

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_handles"] = {}
        return state
