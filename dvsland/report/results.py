"""results.json and traces.npz of a run, written atomically: the bytes go to a temporary file in
the same folder, which then replaces the target (``os.replace``), so a crash, a full disk or a
read-only file system leaves the previous complete file or none, never half a file. A failed
write is one :class:`RunWriteError` naming the path and the reason."""

from __future__ import annotations

import contextlib
import errno as _errno
import io
import json
import math
import os
from pathlib import Path
from typing import Dict, List, Union

import numpy as np


class RunWriteError(ValueError):
    """An output file could not be written (full disk, read-only file system, ...). The message
    names the path and the reason; ``path`` and ``errno`` keep them. A ``ValueError``, so the CLI
    prints it as one line."""

    def __init__(self, path, exc: OSError):
        self.path, self.errno = Path(path), exc.errno
        code = _errno.errorcode.get(exc.errno, "") if exc.errno else ""
        reason = f"{exc.strerror or exc}" + (f" ({code})" if code else "")
        super().__init__(f"cannot write {self.path}: {reason}; the previous version of the file, if any, is "
                         f"unchanged (free space or choose another output folder, then run again)")


def atomic_write_bytes(path, data: Union[bytes, bytearray, memoryview], fsync: bool = False) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and ``os.replace``.

    Raises:
        RunWriteError: any OSError (ENOSPC, EROFS, EACCES, ...); the temporary file is removed and
            ``path`` keeps its previous content (or stays absent).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            view = memoryview(data).cast("B")
            while view:
                view = view[os.write(fd, view):]
            if fsync:
                os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError):
            raise RunWriteError(path, exc) from None
        raise
    return path


@contextlib.contextmanager
def writes_under(path):
    """Context: an ``OSError`` raised inside (a full disk, a read-only folder, also from a writer's
    background thread that surfaces on its next call) becomes one :class:`RunWriteError` naming
    ``path``. For outputs written as a stream, e.g. TensorBoard event files: their records carry
    checksums, so what was flushed before the failure stays readable."""
    try:
        yield
    except OSError as exc:
        raise RunWriteError(path, exc) from None


def atomic_write_text(path, text: str, fsync: bool = False) -> Path:
    """:func:`atomic_write_bytes` of ``text`` as UTF-8."""
    return atomic_write_bytes(path, text.encode("utf-8"), fsync=fsync)


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
    """Write ``obj`` as strict JSON (see :func:`to_json`) via :func:`atomic_write_text`, so a
    crash or a full disk never leaves half a file (:class:`RunWriteError` names the path). The
    one JSON writer of dvsland: results.json, evaluation.json, bench and summary files."""
    return atomic_write_text(path, to_json(obj, indent))


def write_results_json(path, runs: List[dict], **meta) -> Path:
    """Write ``{"runs": runs, **meta}`` to ``path`` (strict JSON, atomically: :func:`write_json`)."""
    return write_json(path, {"runs": runs, **meta})


def read_results_json(path) -> dict:
    """Read a results.json back."""
    return json.loads(Path(path).read_text())


def write_traces_npz(path, traces: Dict[str, np.ndarray]) -> Path:
    """Write per-step traces (steps x runs arrays, plus label arrays) to ``path`` (.npz)."""
    buf = io.BytesIO()  # compressed in memory, then one atomic write (RunWriteError on failure)
    np.savez_compressed(buf, **traces)
    return atomic_write_bytes(path, buf.getbuffer())
