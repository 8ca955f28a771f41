"""The dataset folder's manifest ``dataset.json``: what was asked for and which shards are done.

Folder::

    dataset.json          the manifest (written atomically after every finished shard)
    config.yaml           the resolved config the descents flew (written once, before any shard)
    shards/<id>.h5        one file per shard (:mod:`dvsland.data.shardfile`)

Manifest keys: ``format``, ``format_version``, ``config`` (the plan's config as a plain dict),
``config_hash``, ``estimator``, ``sites``, ``n_seeds``, ``seed_offset`` (first seed index),
``shard_size`` (seeds per shard), ``sensor_size`` ([W, H]), ``dt_s``, ``n_variants`` (terrain
variants), ``dvsland_version`` and ``shards``: one entry per planned shard, ``{id, file,
seed_offset, n_seeds, status ("pending" | "complete"), n_samples, n_events, n_descents, bytes,
seconds}``.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
from pathlib import Path
from typing import Optional

MANIFEST = "dataset.json"
SHARDS_DIR = "shards"

#: config keys that change how fast a build runs, not what it writes (left out of the hash)
UNHASHED = (("logging",), ("render", "threads"), ("simulation", "torch_threads"))


def config_hash(config: dict) -> str:
    """sha256 (hex, 16 characters) of the config's canonical JSON, without :data:`UNHASHED` keys."""
    c = copy.deepcopy(config)
    for path in UNHASHED:
        node = c
        for k in path[:-1]:
            node = node.get(k, {})
        node.pop(path[-1], None)
    text = json.dumps(c, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def manifest_path(folder) -> Path:
    return Path(folder) / MANIFEST


def shard_file(folder, shard_id: str) -> Path:
    return Path(folder) / SHARDS_DIR / f"{shard_id}.h5"


def load_manifest(folder, param: str = "root", check_entries: bool = True) -> dict:
    """The manifest of a dataset folder.

    Args:
        check_entries: check every complete shard entry (:func:`check_shard_entries`); the build,
            which repairs damaged entries on resume, reads without.

    Raises:
        ValueError: the folder is missing or empty, has no ``dataset.json``, or the manifest is
            unreadable or names a shard file it cannot (names ``param``, the folder and what is wrong).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{param}={str(folder)!r}: no such folder")
    path = manifest_path(folder)
    if not path.is_file():
        what = "an empty folder" if not any(folder.iterdir()) else f"no {MANIFEST} in it"
        raise ValueError(f"{param}={str(folder)!r}: not a dvsland dataset ({what}); build one with "
                         f"`dvsland dataset build CONFIG --n-seeds N --out {folder}`")
    try:
        m = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{param}={str(folder)!r}: {MANIFEST} is unreadable ({exc})") from None
    if not isinstance(m, dict) or m.get("format") != "dvsland-event-windows" or not isinstance(m.get("shards"), list):
        raise ValueError(f"{param}={str(folder)!r}: {MANIFEST} is not a dvsland event-window manifest")
    if check_entries:
        check_shard_entries(folder, m, param)
    return m


def check_shard_entries(folder: Path, m: dict, param: str) -> None:
    """ValueError naming ``param``, the folder and the entry when a shard entry is not an object, or a
    complete one names no file, or a file outside ``folder`` (a damaged or hand-edited manifest)."""
    root = os.path.realpath(folder)
    for i, e in enumerate(m["shards"]):
        if not isinstance(e, dict):
            raise ValueError(f"{param}={str(folder)!r}: {MANIFEST} shards[{i}] is not an object; rebuild with "
                             f"`dvsland dataset build ... --out {folder}` (it repairs damaged entries)")
        if e.get("status") != "complete":
            continue
        f = e.get("file")
        inside = isinstance(f, str) and f.strip() and \
            os.path.commonpath([root, os.path.realpath(os.path.join(root, f))]) == root
        if not inside:
            raise ValueError(f"{param}={str(folder)!r}: {MANIFEST} shards[{i}] names no shard file inside the folder "
                             f"(file {f!r}); rebuild with `dvsland dataset build ... --out {folder}` (it repairs "
                             f"damaged entries)")


def save_manifest(folder, manifest: dict) -> Path:
    """Write ``dataset.json`` atomically (temporary file + rename)."""
    path = manifest_path(folder)
    tmp = path.with_name(f"{MANIFEST}.tmp{os.getpid()}")
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, path)
    return path


def same_request(old: dict, new: dict) -> Optional[str]:
    """None when ``old`` (a folder's manifest) was built with the request of ``new``; else what differs."""
    keys = ("config_hash", "estimator", "sites", "n_seeds", "seed_offset", "shard_size", "format_version")
    diff = [k for k in keys if old.get(k) != new.get(k)]
    if not diff:
        return None
    return ", ".join(f"{k}: {old.get(k)!r} there, {new.get(k)!r} now" for k in diff)
