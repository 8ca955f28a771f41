"""The build cache of dvsland's optional compiled kernels (the emulator's, ``cmax``'s).

Each kernel module (:mod:`dvsland.events.native`, :mod:`dvsland.estimators.native_cmax`) keeps its
own C++ source and its process state; this module holds what they share: the mode word read from
an environment variable, the extension's name (a hash of source, flags, functions, torch and
Python versions, so a stale build is never loaded), its folder in torch's extension cache, the
import of a cached build and the compile. Nothing here compiles unless :func:`build_extension` is
called.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import sys
from pathlib import Path
from typing import List, Optional

ON, OFF, AUTO = "on", "off", "auto"


def mode_from_env(env_var: str, chosen: Optional[bool]) -> str:
    """``"on"``, ``"off"`` or ``"auto"``: the process's ``chosen`` mode (True / False), else the
    environment variable ``env_var`` (empty or unset = auto).

    Raises:
        ValueError naming ``env_var`` when it holds another word.
    """
    if chosen is not None:
        return ON if chosen else OFF
    v = os.environ.get(env_var, "").strip().lower()
    if v in ("", AUTO):
        return AUTO
    if v in ("1", "on", "true", "yes"):
        return ON
    if v in ("0", "off", "false", "no"):
        return OFF
    raise ValueError(f"{env_var} must be auto, 1/on/true/yes or 0/off/false/no, got {v!r}")


@functools.lru_cache(maxsize=8)
def extension_name(prefix: str, src: str, flags: str, functions: str) -> str:
    """``{prefix}_{hash}``: 16 hex digits of the SHA-256 of source, flags, functions, torch and Python."""
    import torch

    h = hashlib.sha256("\0".join([src, flags, functions, torch.__version__, sys.version]).encode()).hexdigest()[:16]
    return f"{prefix}_{h}"


def extension_dir(name: str) -> Path:
    """The build folder of extension ``name`` (torch's extension folder, ``TORCH_EXTENSIONS_DIR`` if set)."""
    root = os.environ.get("TORCH_EXTENSIONS_DIR")
    if root is None:
        import torch
        from torch.utils.cpp_extension import get_default_build_root

        acc = "cpu" if torch.version.cuda is None else f"cu{torch.version.cuda.replace('.', '')}"
        if getattr(torch.version, "hip", None):
            acc = f"rocm{torch.version.hip.replace('.', '')}"
        py = f"py{sys.version_info.major}{sys.version_info.minor}{getattr(sys, 'abiflags', '')}"
        root = os.path.join(get_default_build_root(), f"{py}_{acc}")
    return Path(root) / name


def extension_library(name: str) -> Path:
    """The shared library a build of ``name`` leaves in :func:`extension_dir`."""
    from torch.utils.cpp_extension import LIB_EXT

    return extension_dir(name) / f"{name}{LIB_EXT}"


def extension_cached(name: str) -> bool:
    """Whether the build of ``name`` (this exact source) is in the cache."""
    try:
        return extension_library(name).is_file()
    except Exception:  # no home folder, ...
        return False


def import_extension(name: str):
    """Import the cached build of ``name`` (no compiler involved)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, str(extension_library(name)))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


#: torch's lock file in a build folder (torch.utils.file_baton: it waits while the file exists)
TORCH_LOCK = "lock"
#: dvsland's lock beside it: flock-ed for the whole build and holding the builder's pid; the
#: kernel releases a flock when its process dies, even by SIGKILL
OWNER_LOCK = "dvsland-build.lock"


def _read_owner(fd: int) -> str:
    """The pid a builder wrote into the owner lock ("" when none)."""
    try:
        return os.pread(fd, 32, 0).decode(errors="replace").strip()
    except OSError:
        return ""


def processes_in(d: Path) -> List[int]:
    """Pids of the processes (other than this one) whose working folder is ``d``: torch runs ninja
    and the compiler there, and they live on when the build's Python process is killed. Empty
    where /proc cannot be read (not Linux)."""
    target, out = os.path.realpath(d), []
    try:
        entries = os.listdir("/proc")
    except OSError:
        return out
    for e in entries:
        if e.isdigit() and int(e) != os.getpid():
            try:
                if os.readlink(f"/proc/{e}/cwd") == target:
                    out.append(int(e))
            except OSError:  # gone, or another user's
                pass
    return out


def _wait_for_orphans(d: Path, poll_s: float = 0.5) -> None:
    """Wait (interruptible by Ctrl-C) until no process works in ``d`` (:func:`processes_in`): a
    killed build's ninja and compiler finish before the folder is built again."""
    import time

    told = False
    while True:
        pids = processes_in(d)
        if not pids:
            return
        if not told:
            print(f"dvsland: waiting for the compiler processes {pids} of an earlier build in {d} to end",
                  file=sys.stderr, flush=True)
            told = True
        time.sleep(poll_s)


@contextlib.contextmanager
def build_lock(d: Path):
    """Hold folder ``d``'s build for this process (a flock on ``d/OWNER_LOCK``, this pid written in
    it). Another live builder is waited for (interruptible by Ctrl-C). Once held, no live dvsland
    build is running there, so torch's ``d/lock`` left behind is stale (a build killed mid-compile:
    torch would wait on it forever): once the compiler processes that build left in ``d`` have
    ended, it is removed with one RuntimeWarning naming the file."""
    import fcntl
    import warnings

    fd = os.open(d / OWNER_LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"dvsland: waiting for the build of process {_read_owner(fd) or '?'} in {d} to end",
                  file=sys.stderr, flush=True)
            fcntl.flock(fd, fcntl.LOCK_EX)
        previous = _read_owner(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        stale = d / TORCH_LOCK
        if stale.exists():
            _wait_for_orphans(d)
            by = f"process {previous}" if previous else "a build"
            warnings.warn(f"removed the stale build lock {stale}, left by {by} that ended without releasing "
                          f"it (killed mid-compile); building anew", RuntimeWarning, stacklevel=3)
            stale.unlink(missing_ok=True)
        yield
    finally:
        os.close(fd)  # releases the flock


def build_extension(name: str, src: str, functions: List[str], cflags: List[str], verbose: bool = False):
    """Compile (when not cached) and load extension ``name``; the module. Raises on any build error.
    The build holds :func:`build_lock` on its folder: a concurrent build is waited for, a stale
    lock of a killed build removed (with a warning naming it)."""
    from torch.utils.cpp_extension import load_inline

    d = extension_dir(name)
    d.mkdir(parents=True, exist_ok=True)
    with build_lock(d):
        return load_inline(name, cpp_sources=src, functions=functions, extra_cflags=cflags,
                           build_directory=str(d), verbose=verbose)


def load_or_warn(name: str, cached: bool, build, label: str):
    """The cached build of ``name`` imported (``cached``: the caller's word that it is there), else
    ``build()``'s module; None, with one
    RuntimeWarning naming ``label``, when either fails (no compiler, no headers, a broken cache
    entry, ...): the caller keeps its torch path."""
    import warnings

    try:
        return import_extension(name) if cached else build()
    except Exception as exc:
        warnings.warn(f"{label}: the compiled kernels could not be built or loaded ({exc}); using the torch path",
                      RuntimeWarning)
        return None


def timed_build(label: str, kernel_module) -> int:
    """Build ``kernel_module``'s extension (a module with ``cached()``, ``build()`` and ``build_dir()``)
    and print whether it was already cached, the wall and CPU time (the compiler's included) and the
    folder; 0, or 1 with the error on stderr when it cannot be built."""
    import resource
    import time

    was = kernel_module.cached()
    w0 = time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    try:
        kernel_module.build()
    except Exception as exc:
        print(f"could not build {label}: {exc}", file=sys.stderr)
        return 1
    r1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = sum(b.ru_utime + b.ru_stime - a.ru_utime - a.ru_stime for a, b in zip(r0, r1))
    print(f"{label}: {'already cached' if was else 'built'} in {time.perf_counter() - w0:.1f} s wall, "
          f"{cpu:.1f} s CPU (compiler included): {kernel_module.build_dir()}")
    return 0


__all__ = ["load_or_warn", "timed_build", "ON", "OFF", "AUTO", "mode_from_env", "extension_name", "extension_dir", "extension_library",
           "extension_cached", "import_extension", "build_extension", "build_lock"]
