"""Datasets of labelled event windows for learning: built from the closed loop, read as torch datasets.

Every control step of every descent is one sample: the events of the window ``(t_prev, t]`` and
the true divergence, time to contact, altitude and velocity at ``t`` (docs/learning.md).

Public names:
    build_dataset, BuildResult: fly dispersed descents on :func:`dvsland.sim.loop_step` and write
        sharded, resumable HDF5 files with a manifest (:mod:`.build`).
    EventWindowDataset: a built folder as a map-style torch Dataset (:mod:`.dataset`).
    LoopStream: the same samples straight from the loop, an IterableDataset (:mod:`.stream`).
    collate_events: batches ``representation="events"`` samples of variable length.
    SplitRule, SPLITS: train / val / test by site type and terrain variant (:mod:`.splits`).
    REPRESENTATIONS: ``"count"``, ``"voxel"``, ``"events"``.
    load_windows, gather_batch, Windows: a whole split in memory as flat tensors, batches cut by
        indexing (:mod:`.tensors`), for training.
    ShardError: a shard file that cannot be read (a ValueError naming the file).
"""

from .build import BuildResult, build_dataset
from .dataset import EventWindowDataset
from .represent import REPRESENTATIONS, collate_events
from .shardfile import ShardError
from .splits import SPLITS, SplitRule
from .stream import LoopStream
from .tensors import Windows, concat_windows, gather_batch, load_manifest_info, load_windows

__all__ = ["build_dataset", "BuildResult", "EventWindowDataset", "LoopStream", "collate_events", "SplitRule",
           "SPLITS", "REPRESENTATIONS", "ShardError", "Windows", "load_windows", "gather_batch",
           "load_manifest_info", "concat_windows"]
