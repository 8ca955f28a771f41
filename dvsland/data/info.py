"""``dataset_info``: a dataset folder's shards, samples, events, bytes and split sizes."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from .manifest import load_manifest
from .shardfile import ShardError, read_index
from .splits import SplitRule


def dataset_info(root, split_rule: Optional[SplitRule] = None) -> dict:
    """Summary of folder ``root``: ``{root, config_hash, estimator, sites, sensor_size, shards_total,
    shards_complete, bad_shards {file: error}, samples, valid_samples, events, bytes, bytes_per_sample,
    events_per_sample, splits {train, val, test: valid samples}}``."""
    root = Path(root)
    m = load_manifest(root)
    rule = split_rule or SplitRule()
    out = {"root": str(root), "config_hash": m["config_hash"], "estimator": m["estimator"], "sites": m["sites"],
           "sensor_size": m["sensor_size"], "shards_total": len(m["shards"]), "shards_complete": 0, "bad_shards": {},
           "samples": 0, "valid_samples": 0, "events": 0, "bytes": 0, "splits": {"train": 0, "val": 0, "test": 0}}
    for e in (e for e in m["shards"] if e.get("status") == "complete"):
        try:
            ix = read_index(root / e["file"])
        except ShardError as exc:
            out["bad_shards"][e["file"]] = str(exc)
            continue
        s, d = ix["samples"], ix["descents"]
        valid = s["valid"].astype(bool)
        split = rule.assign(d["site"], d["variant"], int(m.get("n_variants", 1)))[s["descent"]][valid]
        out["shards_complete"] += 1
        out["samples"] += len(valid)
        out["valid_samples"] += int(valid.sum())
        out["events"] += int(ix["attrs"]["n_events"])
        out["bytes"] += (root / e["file"]).stat().st_size
        for k in out["splits"]:
            out["splits"][k] += int(np.sum(split == k))
    n = out["samples"]
    out["bytes_per_sample"] = out["bytes"] / n if n else None
    out["events_per_sample"] = out["events"] / n if n else None
    return out


def format_info(info: dict) -> str:
    """The summary of :func:`dataset_info` as a few lines of text."""
    lines = [f"{info['root']}: {info['shards_complete']}/{info['shards_total']} shards complete, config "
             f"{info['config_hash']}, estimator {info['estimator']}, sites {','.join(info['sites'])}, sensor "
             f"{info['sensor_size'][0]}x{info['sensor_size'][1]}",
             f"{info['samples']} samples ({info['valid_samples']} valid), {info['events']} events, "
             f"{info['bytes']} bytes"]
    if info["samples"]:
        lines.append(f"{info['bytes_per_sample']:.0f} bytes/sample, {info['events_per_sample']:.0f} events/sample")
    lines.append("valid samples per split: " + ", ".join(f"{k} {v}" for k, v in info["splits"].items()))
    lines += [f"bad shard {k}: {v}" for k, v in info["bad_shards"].items()]
    return "\n".join(lines)
