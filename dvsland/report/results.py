"""results.json and traces.npz of a run (written atomically: a crash never leaves half a file)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Dict, List

import numpy as np


def _clean(x):
    """JSON-safe: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_results_json(path, runs: List[dict], **meta) -> Path:
    """Write ``{"runs": runs, **meta}`` to ``path`` (via a temporary file and rename)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(_clean({"runs": runs, **meta}), indent=2))
    os.replace(tmp, path)
    return path


def read_results_json(path) -> dict:
    """Read a results.json back."""
    return json.loads(Path(path).read_text())


def write_traces_npz(path, traces: Dict[str, np.ndarray]) -> Path:
    """Write per-step traces (steps x runs arrays, plus label arrays) to ``path`` (.npz)."""
    path = Path(path)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, **traces)
    os.replace(tmp, path)
    return path
