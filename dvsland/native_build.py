"""The build cache of dvsland's compiled kernels (the terrain's, the renderer's, the emulator's,
``cmax``'s, ``dpr``'s).

The kernels are plain C++ behind a C interface (raw pointers and sizes, no torch or Python headers),
so a build is one call of the C++ compiler that takes a second or two, and the library does not
depend on the torch or Python version. Each kernel module (:mod:`dvsland.terrain.native_noise`,
:mod:`dvsland.render.native_render`, :mod:`dvsland.events.native`,
:mod:`dvsland.estimators.native_cmax`, :mod:`dvsland.estimators.native_dpr`) keeps its own source
and its ``ctypes`` bindings; this module holds what they share: :class:`NativeLibrary` (a library's
mode word read from an environment variable and its process state), the library's name (a hash of
source, flags, compiler and machine, so a stale build is never loaded), its folder, the compile
(atomic, under a lock), the load, the binding helpers and :func:`build_in_background` (a run's
builds started while it prepares its scenes).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from typing import Optional, Sequence

ON, OFF, AUTO = "on", "off", "auto"
#: bumped when the way a library is built or called changes (a part of every library's name)
ABI = "dvsland-c-abi-1"


#: C++ shared by the kernels' sources (which include <algorithm>, <cstdint>, <thread> and <vector>
#: before it): ``parallel_ranges(n, n_threads, f)`` runs f(lo, hi) over [0, n) split into contiguous
#: ranges on that many threads
PARALLEL_RANGES = r"""// f(lo, hi) over [0, n) split into n_threads contiguous ranges (one call when n_threads <= 1)
template <class F> static void parallel_ranges(int64_t n, int64_t n_threads, F f) {
  const int64_t k = std::min<int64_t>(std::max<int64_t>(n_threads, 1), std::max<int64_t>(n, 1));
  if (k <= 1) { f(0, n); return; }
  std::vector<std::thread> pool;
  for (int64_t i = 0; i < k; ++i) pool.emplace_back(f, n * i / k, n * (i + 1) / k);
  for (auto& t : pool) t.join();
}
"""


#: C++ shared by the kernels' sources: the ``DVS_CLONES`` (one clone per x86-64 instruction-set level,
#: picked at load time, on GCC >= 11 / Linux; nothing elsewhere) and ``DVS_INLINE`` attributes
CLONES = r"""// DVS_CLONES: a function compiled per instruction set (x86-64-v4: AVX-512, v3: AVX2 + FMA, and the
// baseline), the clone picked at load time; __builtin_fmaf is one instruction in the first two and an
// (exact, slower) libm call in the baseline. DVS_INLINE: inlined into each clone.
#if defined(__x86_64__) && defined(__linux__) && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11
#define DVS_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define DVS_CLONES
#endif
#define DVS_INLINE __attribute__((always_inline)) static inline
"""


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


def compiler() -> Optional[str]:
    """The C++ compiler: ``$CXX``, else ``c++``, ``g++`` or ``clang++`` on the PATH; None when none is found
    (looked up once per value of ``$CXX`` and ``$PATH``)."""
    return _find_compiler(os.environ.get("CXX", "").strip(), os.environ.get("PATH", ""))


@functools.lru_cache(maxsize=8)
def _find_compiler(cxx: str, path: str) -> Optional[str]:
    if cxx:
        return shutil.which(cxx, path=path) or cxx
    for c in ("c++", "g++", "clang++"):
        found = shutil.which(c, path=path)
        if found:
            return found
    return None


#: GCC-only flags that let the vectoriser load scattered texels with AVX2 / AVX-512 gather instructions.
#: GCC's generic tuning emulates every gather with scalar loads and lane inserts; the renderer's bilinear
#: samples (eight texels a pixel) then run about 2x slower on the Intel Xeon (Sapphire Rapids) this was
#: measured on. The loads change, not the arithmetic: the same bits.
GATHER_FLAGS = ("-mtune-ctrl=use_gather_2parts,use_gather_4parts,use_gather",)


def is_gcc(cxx: Optional[str], min_major: int = 12) -> bool:
    """Whether the compiler ``cxx`` is GCC (its ``--version`` names the Free Software Foundation, not
    clang) of major version ``min_major`` or later (GCC 12 is the first to take every
    :data:`GATHER_FLAGS` word)."""
    return bool(cxx) and _gcc_major(str(cxx)) >= min_major


@functools.lru_cache(maxsize=8)
def _gcc_major(cxx: str) -> int:
    """GCC's major version of ``cxx``, 0 for another compiler or one that cannot be run."""
    try:
        out = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=30).stdout
        if "clang" in out.lower() or "Free Software Foundation" not in out:
            return 0
        ver = subprocess.run([cxx, "-dumpversion"], capture_output=True, text=True, timeout=30).stdout
        return int(ver.strip().split(".")[0])
    except Exception:
        return 0


@functools.lru_cache(maxsize=8)
def library_name(prefix: str, src: str, flags: str) -> str:
    """``{prefix}_{hash}``: 16 hex digits of the SHA-256 of source, flags, compiler, machine and :data:`ABI`."""
    parts = [src, flags, str(compiler()), platform.system(), platform.machine(), ABI]
    return f"{prefix}_{hashlib.sha256(chr(0).join(parts).encode()).hexdigest()[:16]}"


def library_dir(name: str) -> Path:
    """The build folder of library ``name``: ``$TORCH_EXTENSIONS_DIR/name`` if that is set, else
    ``<user cache>/torch_extensions/dvsland/name`` (``$XDG_CACHE_HOME`` or ``~/.cache``)."""
    root = os.environ.get("TORCH_EXTENSIONS_DIR")
    if root is None:
        cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(cache, "torch_extensions", "dvsland")
    return Path(root) / name


def library_file(name: str) -> Path:
    """The shared library a build of ``name`` leaves in :func:`library_dir`."""
    return library_dir(name) / f"{name}.so"


def library_cached(name: str) -> bool:
    """Whether the build of ``name`` (this exact source) is in the cache."""
    try:
        return library_file(name).is_file()
    except Exception:  # no home folder, ...
        return False


def load_library(name: str) -> ctypes.CDLL:
    """Load the cached build of ``name`` (no compiler involved)."""
    return ctypes.CDLL(str(library_file(name)))


def bind_functions(lib: ctypes.CDLL, signatures: dict) -> ctypes.CDLL:
    """``lib`` with the argument and result types of its functions set from ``signatures``
    (name -> (list of ctypes argument types, ctypes result type or None))."""
    for name, (args, res) in signatures.items():
        f = getattr(lib, name)
        f.argtypes, f.restype = args, res
    return lib


def tensor_address(t, dtype, what: str, numel: Optional[int] = None) -> Optional[int]:
    """The address of torch tensor ``t``'s data (None for an empty tensor), after checking that it is
    a contiguous CPU tensor of ``dtype`` (the kernels read raw memory) holding ``numel`` elements
    (any number when None); RuntimeError naming ``what``."""
    if numel is not None and t.numel() != numel:
        raise RuntimeError(f"{what} must hold {numel} elements, got {tuple(t.shape)}")
    if t.dtype != dtype or t.device.type != "cpu" or not t.is_contiguous():
        raise RuntimeError(f"{what} must be a contiguous {dtype} CPU tensor, got {t.dtype} on {t.device}"
                           f"{'' if t.is_contiguous() else ' (not contiguous)'}")
    return t.data_ptr() if t.numel() else None


#: the lock file in a build folder: flock-ed for the whole build and holding the builder's pid;
#: the kernel releases a flock when its process dies, even by SIGKILL
OWNER_LOCK = "dvsland-build.lock"


def _read_owner(fd: int) -> str:
    """The pid a builder wrote into the owner lock ("" when none)."""
    try:
        return os.pread(fd, 32, 0).decode(errors="replace").strip()
    except OSError:
        return ""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process
        return True
    return True


def _remove_stale_partials(d: Path) -> None:
    """Remove the partial libraries (``*.so.<pid>.tmp``) of builds whose process has ended (a build
    killed mid-compile); a live build's are kept."""
    for f in d.glob("*.so.*.tmp"):
        pid = f.name.rsplit(".", 2)[-2]
        if not pid.isdigit() or not _pid_alive(int(pid)):
            f.unlink(missing_ok=True)


#: the descriptors of the build locks this process has open, and the mutex that keeps a fork from
#: coming between a lock's open (or close) and its entry here
_LOCK_FDS: set = set()
_LOCK_FDS_MUTEX = threading.Lock()


def _close_inherited_lock_fds() -> None:
    """In a forked child: close the copies of the parent's build-lock descriptors. A flock belongs to
    the open file, which lives while any copy of its descriptor is open: a child that kept them would
    hold its parent's lock (and wait forever on it) after the parent's build thread, which the child
    does not have, released it. Closing a copy leaves the parent's lock held (no LOCK_UN)."""
    for fd in _LOCK_FDS:
        try:
            os.close(fd)
        except OSError:
            pass
    _LOCK_FDS.clear()
    _LOCK_FDS_MUTEX.release()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=_LOCK_FDS_MUTEX.acquire, after_in_parent=_LOCK_FDS_MUTEX.release,
                        after_in_child=_close_inherited_lock_fds)


@contextlib.contextmanager
def build_lock(d: Path):
    """Hold folder ``d``'s build for this process (a flock on ``d/OWNER_LOCK``, this pid written in
    it). Another live builder is waited for (interruptible by Ctrl-C); a builder killed mid-compile
    released its flock when it died, and its partial output (never the library's name: the compile
    writes a temporary file that is renamed when complete) is removed."""
    import fcntl

    with _LOCK_FDS_MUTEX:
        fd = os.open(d / OWNER_LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        _LOCK_FDS.add(fd)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"dvsland: waiting for the build of process {_read_owner(fd) or '?'} in {d} to end",
                  file=sys.stderr, flush=True)
            fcntl.flock(fd, fcntl.LOCK_EX)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        _remove_stale_partials(d)
        yield
    finally:
        with _LOCK_FDS_MUTEX:
            _LOCK_FDS.discard(fd)
            os.close(fd)  # releases the flock


def build_library(name: str, src: str, flags: Sequence[str], verbose: bool = False) -> Path:
    """Compile library ``name`` from ``src`` (when not cached) with :func:`compiler` and ``flags``;
    its path. The compile writes a temporary file renamed into place when complete, under
    :func:`build_lock` (a concurrent build of the same library is waited for and not repeated).

    Raises:
        RuntimeError: no C++ compiler, or the compile failed (its last lines of output in the message).
    """
    cxx = compiler()
    if cxx is None:
        raise RuntimeError("no C++ compiler found (install g++ or clang++, or set CXX)")
    d = library_dir(name)
    d.mkdir(parents=True, exist_ok=True)
    out = library_file(name)
    with build_lock(d):
        if out.is_file():
            return out
        src_file = d / f"{name}.cpp"
        src_file.write_text(src)
        tmp = d / f"{name}.so.{os.getpid()}.tmp"
        cmd = [cxx, *flags, "-shared", "-fPIC", "-o", str(tmp), str(src_file)]
        if verbose:
            print(" ".join(cmd), file=sys.stderr, flush=True)
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            tmp.unlink(missing_ok=True)
            tail = "\n".join((res.stderr or res.stdout).strip().splitlines()[-12:])
            raise RuntimeError(f"{os.path.basename(cxx)} failed ({res.returncode}) on {src_file}:\n{tail}")
        os.replace(tmp, out)
    return out


def load_or_warn(make, label: str, env_var: Optional[str] = None):
    """``make()`` (build when needed, load and bind a library); None, with one RuntimeWarning naming
    ``label`` (and how to skip or relocate the build), when it fails (a compile error, a read-only
    cache folder, a broken cache entry, ...): the caller keeps its torch path."""
    import warnings

    try:
        return make()
    except Exception as exc:
        hint = f" (set {env_var}=0 to skip them, or TORCH_EXTENSIONS_DIR to a writable folder)" if env_var else ""
        warnings.warn(f"{label}: the compiled kernels could not be built or loaded ({exc}); using the torch path"
                      f"{hint}", RuntimeWarning)
        return None


class NativeLibrary:
    """One compiled library's process state and mode: the C++ source, its flags, the environment
    variable of its mode (:func:`mode_from_env`: auto, on or off) and ``bind``, which makes the
    Python bindings of a loaded ``ctypes.CDLL``. Auto (the default) and on build it on first use
    (when not cached) and load it; auto without a cached build or a compiler stays silent and off,
    a failed build or load warns once; either way the caller runs its torch path."""

    def __init__(self, prefix: str, src: str, flags: Sequence[str], env_var: str, label: str, bind,
                 gcc_flags: Sequence[str] = ()):
        self.prefix, self.src, self.env_var, self.label, self.bind = prefix, src, env_var, label, bind
        self.base_flags, self.gcc_flags = list(flags), list(gcc_flags)
        self.chosen: Optional[bool] = None
        self._bound = None
        self._failed = False
        self._absent = False  # auto found neither a cached build nor a compiler (not looked for again)
        self._pending: Optional[threading.Event] = None  # set when a background build has ended
        self._pending_pid = 0  # the process whose thread runs that build (a forked child has no such thread)

    @property
    def flags(self) -> list:
        """The compile flags: the library's own, and its ``gcc_flags`` where :func:`compiler` is GCC."""
        return self.base_flags + (self.gcc_flags if self.gcc_flags and is_gcc(compiler()) else [])

    def use(self, on: Optional[bool] = True) -> None:
        """Pick the mode for this process: True = on, False = off, None = back to the environment's."""
        self.chosen = None if on is None else bool(on)

    def mode(self) -> str:
        """``"on"``, ``"off"`` or ``"auto"`` (raises ValueError naming the environment variable)."""
        return mode_from_env(self.env_var, self.chosen)

    def name(self) -> str:
        return library_name(self.prefix, self.src, " ".join(self.flags))

    def build_dir(self) -> Path:
        return library_dir(self.name())

    def cached(self) -> bool:
        return library_cached(self.name())

    def enabled(self) -> bool:
        """Whether the kernels should be used now: on; or auto with the build cached, loaded, or a
        compiler to build it with. Never compiles. In auto mode the cache and the compiler are looked
        for once per process."""
        m = self.mode()
        if m == ON:
            return True
        if m == OFF or self._failed or self._absent:
            return False
        if self._bound is not None or self.cached() or compiler() is not None:
            return True
        self._absent = True
        return False

    def build(self, verbose: bool = False):
        """Compile (when not cached) and load; the bindings. Raises on any build error."""
        build_library(self.name(), self.src, self.flags, verbose)
        return self.bind(load_library(self.name()))

    def kernel_for(self, t):
        """The bindings for work on tensor ``t``'s device: :meth:`load` for a CPU tensor, None (the
        caller's torch path) on any other device."""
        return self.load() if t.device.type == "cpu" else None

    def load(self, force: bool = False):
        """The bindings, built once when needed, or None: not :meth:`enabled` now (unless ``force``;
        a mode switched off after a load gives None too), or a failed build or load (one warning,
        then None for the rest of the process)."""
        if not (force or self.enabled()):
            return None
        if self._bound is not None or self._failed:
            return self._bound
        if self._pending is not None:  # a background build (build_in_background): wait for its end
            if self._pending_pid == os.getpid():  # (in a forked child the thread is gone: the lock waits)
                self._pending.wait()
            self._pending = None
        self._bound = load_or_warn(lambda: self.bind(load_library(self.name())) if self.cached() else self.build(),
                                   self.label, self.env_var)
        self._failed = self._bound is None
        return self._bound


def build_in_background(libraries: Sequence["NativeLibrary"]) -> int:
    """Compile, one after the other in a background thread, those of ``libraries`` that would be
    built on first use (:meth:`NativeLibrary.enabled`, not cached, not loaded, no build pending), so
    that the compiler runs as its own process while this one prepares the run; a library's
    :meth:`~NativeLibrary.load` waits for its build. A build that fails here is left to ``load``,
    which builds again and warns as it would have. Returns the number of builds started (0 when
    every library is cached, off or without a compiler: nothing is started)."""
    todo = [lib for lib in libraries if lib._pending is None and lib._bound is None and not lib._failed
            and lib.enabled() and not lib.cached()]
    if not todo:
        return 0
    for lib in todo:
        lib._pending, lib._pending_pid = threading.Event(), os.getpid()

    def run():
        for lib, done in [(lib, lib._pending) for lib in todo]:
            try:
                build_library(lib.name(), lib.src, lib.flags)
            except Exception:  # pragma: no cover - load() builds again and warns
                pass
            finally:
                done.set()

    threading.Thread(target=run, name="dvsland-native-builds", daemon=True).start()
    return len(todo)


def timed_build(what: str, library: "NativeLibrary") -> int:
    """Build ``library`` (a :class:`NativeLibrary`) and print ``what`` with its module, whether it was
    already cached, the wall and CPU time (the compiler's included) and the folder; 0, or 1 with the
    error on stderr when it cannot be built."""
    import resource
    import time

    label = f"{what} ({library.label})"
    was = library.cached()
    w0 = time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    try:
        library.build()
    except Exception as exc:
        print(f"could not build {label}: {exc}", file=sys.stderr)
        return 1
    r1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = sum(b.ru_utime + b.ru_stime - a.ru_utime - a.ru_stime for a, b in zip(r0, r1))
    print(f"{label}: {'already cached' if was else 'built'} in {time.perf_counter() - w0:.1f} s wall, "
          f"{cpu:.1f} s CPU (compiler included): {library.build_dir()}")
    return 0


__all__ = ["CLONES", "PARALLEL_RANGES", "load_or_warn", "build_in_background", "timed_build", "ON", "OFF", "AUTO",
           "ABI", "mode_from_env", "compiler", "library_name", "library_dir", "library_file", "library_cached",
           "load_library", "build_library", "build_lock", "NativeLibrary", "bind_functions", "tensor_address"]
