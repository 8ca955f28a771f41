"""results.json and traces.npz of a run (written atomically: a crash never leaves half a file)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Dict, List

import numpy as np


def _clean(x):
    """JSON-safe: NaN/inf -> None, numpy scalars and arrays -> Python, tuples -> lists, Paths -> str."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def to_json(obj, indent: int = 2) -> str:
    """Strict JSON text of ``obj``: NaN and inf become ``null`` (bare ``NaN`` is not JSON)."""
    return json.dumps(_clean(obj), indent=indent, allow_nan=False, default=str)


def write_json(path, obj, indent: int = 2) -> Path:
    """Write ``obj`` as strict JSON (see :func:`to_json`) via a temporary file and a rename, so a
    crash never leaves half a file. The one JSON writer of dvsland: results.json, evaluation.json,
    bench and summary files."""
    path = Path(path)
    text = to_json(obj, indent)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def write_results_json(path, runs: List[dict], **meta) -> Path:
    """Write ``{"runs": runs, **meta}`` to ``path`` (strict JSON, via a temporary file and rename)."""
    return write_json(path, {"runs": runs, **meta})


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
