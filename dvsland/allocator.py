"""The process's memory allocator, set for simulation runs (what the ``dvsland`` command does first).

A loop step at a large batch allocates a few arrays of tens of megabytes and frees them again (a
B = 576 batch: float64 per-pixel arrays of 75 MB). glibc's malloc serves every block above 32 MB
from fresh ``mmap`` pages and gives them back on ``free``, so each step pays page faults and the
kernel's zeroing of every page it touches: about 124,000 faults and 0.35 s of system time per step
at B = 576 on the project's CPU (docs/benchmarks.md). :func:`tune_allocator` keeps freed memory in
the process for the next step, and asks for transparent huge pages for large torch tensors:

- ``mallopt(M_MMAP_MAX, 0)`` and ``mallopt(M_TRIM_THRESHOLD, 2 GiB - 1)`` (glibc, Linux): blocks
  come from the heap and freed ones are reused, not returned to the system. The process keeps
  its peak memory until it ends.
- ``THP_MEM_ALLOC_ENABLE=1`` (PyTorch's own switch): CPU tensors of 2 MB or more are aligned to
  huge pages and ``madvise``-d for them. torch reads it once, at its first allocation, so it
  takes effect only when set before torch allocates (the command line sets it before it imports
  torch; a spawned campaign worker inherits it).

Nothing changes a result: only where memory comes from. ``DVSLAND_KEEP_FREED_MEMORY=0`` turns
both off for a run. A library user can call :func:`tune_allocator` at the start of a long run
(before importing torch, for the huge pages).
"""

from __future__ import annotations

import ctypes
import os
import sys
from typing import Dict

#: the environment switch (default on; 0, false, no or off turns it off)
ENV = "DVSLAND_KEEP_FREED_MEMORY"

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_TRIM_BYTES = 2 ** 31 - 1  # mallopt takes a C int


#: what :func:`tune_allocator` set in this process (empty until it runs)
_TUNED: Dict[str, bool] = {}


def tuned() -> bool:
    """Whether :func:`tune_allocator` kept freed memory in this process (what a campaign's spawned
    workers then do too)."""
    return bool(_TUNED.get("keep_freed"))


def enabled() -> bool:
    """Whether ``DVSLAND_KEEP_FREED_MEMORY`` asks for the tuning (default yes)."""
    return os.environ.get(ENV, "1").strip().lower() not in ("0", "false", "no", "off")


def tune_allocator() -> Dict[str, bool]:
    """Keep freed memory in the process and ask for huge pages (module doc), where the platform
    allows and ``DVSLAND_KEEP_FREED_MEMORY`` is not off. Returns ``{"keep_freed": ..., "huge_pages":
    ...}``: what was set (False where the platform has no glibc ``mallopt`` or the switch is off;
    an explicit ``THP_MEM_ALLOC_ENABLE=0`` in the environment is left as it is)."""
    out = {"keep_freed": False, "huge_pages": False}
    if not enabled():
        return out
    os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")
    out["huge_pages"] = os.environ["THP_MEM_ALLOC_ENABLE"].strip() not in ("", "0")
    if sys.platform.startswith("linux"):
        try:
            mallopt = ctypes.CDLL(None).mallopt
        except (OSError, AttributeError):  # no glibc malloc (musl and others): nothing to set
            return out
        mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
        out["keep_freed"] = mallopt(_M_MMAP_MAX, 0) == 1 and mallopt(_M_TRIM_THRESHOLD, _TRIM_BYTES) == 1
    _TUNED.update(out)
    return out
