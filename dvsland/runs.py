"""Run folders: ``logs/<name>-<UTC timestamp>/`` holding the resolved config and all output.

Every command makes its folder with :func:`make_run_dir`, the one output-folder guard: an empty
``--out``, a path that is a file, a folder that cannot be created (``/proc/x``), a run name that
would leave ``logging.root`` (``../../x``) and a folder that already holds a run are refused
with a :class:`RunDirError` (a ``ValueError``) that says why and what to do. It claims the folder
atomically (an exclusive create of ``.dvsland-run``; a new folder under ``logging.root`` by an
exclusive ``mkdir``), so of two commands started together on one folder the second is refused.
Files are written atomically (:func:`dvsland.report.results.atomic_write_bytes`); a full disk or a
read-only file system is one :class:`RunWriteError` naming the path.

:func:`guarded_run` wraps a command (``dvsland.simulate``, every CLI sub-command): SIGTERM is
turned into ``KeyboardInterrupt`` (so a ``kill`` is handled like Ctrl-C), and a run folder made
during the call that has no final ``results.json`` gets one saying ``status: "interrupted"``
(with the phase, set-up or run, and the error), so nothing already written is lost.
:func:`deferred_interrupts` holds Ctrl-C / SIGTERM back while such a final file is written.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import functools
import os
import signal
import socket
import sys
import threading
from pathlib import Path
from typing import List, Optional, Union

from .config import Config, ConfigError, dump_config
from .report.results import RunWriteError, atomic_write_text
from .watchdog import GRACE_S, InterruptWatchdog

#: the file a command creates exclusively to claim its run folder (it stays: the folder is taken)
CLAIM_FILE = ".dvsland-run"
#: files whose presence marks a folder as holding a dvsland run
RUN_MARKERS = ("config.yaml", "results.json", "tb", "evaluation.json", "traces.npz", CLAIM_FILE)


class RunDirError(ValueError):
    """The output folder cannot be used (the message says why)."""


def utc_stamp() -> str:
    """UTC timestamp for folder names, e.g. ``20261122T104512Z``."""
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")


def check_out_dir(out: Union[str, Path], overwrite: bool = False) -> Path:
    """Check an explicit output folder (``--out``) and create it.

    Raises:
        RunDirError: empty path, an existing file, a folder holding an earlier run (unless
            ``overwrite``), a folder another command claimed first, or a folder the OS will not
            create.
    """
    if out is None or str(out).strip() == "":
        raise RunDirError("--out: the output folder must not be empty (leave --out out for "
                          "logs/<name>-<UTC timestamp>/)")
    run_dir = Path(out)
    _check_name_lengths(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise RunDirError(f"--out {run_dir}: exists and is not a folder")
    if run_dir.is_dir() and not overwrite:
        held = [m for m in RUN_MARKERS if (run_dir / m).exists()]
        if held == [CLAIM_FILE]:
            raise _claimed(run_dir)
        if held:
            raise RunDirError(f"--out {run_dir}: already holds a run ({', '.join(held)}); choose a new folder "
                              f"or remove it (dvsland never mixes the files of two runs)")
    _mkdir(run_dir)
    _claim(run_dir, overwrite)
    return run_dir


def open_folder(out: Union[str, Path, None], flag: str = "--out", create: bool = True) -> Path:
    """Check and (``create``) create a folder a command writes into and may resume (a dataset),
    without the run claim of :func:`check_out_dir`: the same refusals of an empty path, a name too
    long for the file system, a file of that name and a folder the OS will not create (one
    :class:`RunDirError` naming ``flag`` and the path)."""
    if out is None or str(out).strip() == "":
        raise RunDirError(f"{flag}: the folder must not be empty")
    path = Path(out)
    try:
        _check_name_lengths(path)
    except RunDirError as exc:
        raise RunDirError(str(exc).replace("--out", flag, 1)) from None
    if path.exists() and not path.is_dir():
        raise RunDirError(f"{flag} {path}: exists and is not a folder")
    if not create:
        return path
    try:
        _mkdir(path)
    except RunDirError as exc:
        raise RunDirError(f"{flag} {path}: {exc}") from None
    return path


def lock_folder(folder: Union[str, Path], name: str, what: str):
    """Hold an exclusive lock on ``folder/name`` (released when the returned file is closed or the
    process ends, SIGKILL included); :class:`RunDirError` when another process holds it (``what``
    names the command, e.g. ``dvsland campaign``). None where there is no ``fcntl``."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        return None
    path = Path(folder) / name
    try:
        f = open(path, "a+")
    except OSError as exc:
        raise RunWriteError(path, exc) from None
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.seek(0)
        owner = f.read().strip() or "another process"
        f.close()
        raise RunDirError(f"{folder}: another {what} is running in this folder ({owner}); wait for it to end "
                          f"(or stop it), then run the command again") from None
    f.seek(0)
    f.truncate()
    f.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
    f.flush()
    return f


def _check_name_lengths(path: Path) -> None:
    """RunDirError when a part of ``path`` or the whole is longer than the file system takes."""
    try:
        name_max = os.pathconf(str(path.anchor or "."), "PC_NAME_MAX")
        path_max = os.pathconf(str(path.anchor or "."), "PC_PATH_MAX")
    except (OSError, ValueError, AttributeError):
        name_max, path_max = 255, 4096
    longest = max((len(os.fsencode(p)) for p in path.parts), default=0)
    if longest > name_max or len(os.fsencode(str(path.absolute()))) >= path_max:
        raise RunDirError(f"--out: a folder name may have at most {name_max} bytes and the whole path "
                          f"{path_max - 1}; got a {longest}-byte name in a "
                          f"{len(os.fsencode(str(path.absolute())))}-byte path")


def _mkdir(path: Path, exclusive: bool = False) -> None:
    """Create ``path`` (and its parents); ``exclusive``: FileExistsError when it exists."""
    try:
        if exclusive:
            path.parent.mkdir(parents=True, exist_ok=True)
            os.mkdir(path)
        else:
            path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        if exclusive:
            raise
        raise RunDirError(f"cannot write the run folder {path}: a file of that name exists") from None
    except OSError as exc:
        raise RunDirError(f"cannot write the run folder {path}: {exc.strerror or exc}") from None


def _claimed(run_dir: Path) -> RunDirError:
    try:
        owner = (run_dir / CLAIM_FILE).read_text().strip() or "unknown"
    except OSError:
        owner = "unknown"
    return RunDirError(f"--out {run_dir}: another dvsland command claimed this folder first ({owner}); choose "
                       f"a new folder (two runs never write into one folder)")


def _claim(run_dir: Path, overwrite: bool = False) -> None:
    """Create ``run_dir/.dvsland-run`` exclusively (``O_EXCL``): the atomic claim of the folder,
    and the probe that it can be written. ``overwrite`` replaces an earlier claim."""
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
    try:
        fd = os.open(run_dir / CLAIM_FILE, flags, 0o644)
    except FileExistsError:
        raise _claimed(run_dir) from None
    except OSError as exc:
        raise RunDirError(f"cannot write the run folder {run_dir}: {exc.strerror or exc}") from None
    try:
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()} at {utc_stamp()}\n".encode())
    except OSError as exc:
        raise RunDirError(f"cannot write the run folder {run_dir}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def make_run_dir(cfg: Config, out: Optional[Union[str, Path]] = None, kind: str = "",
                 overwrite: bool = False) -> Path:
    """Create the run folder and write ``config.yaml`` into it before any work starts.

    Args:
        cfg: the resolved, validated config.
        out: explicit folder (``--out``), checked by :func:`check_out_dir`; default
            ``<cfg.logging.root>/<name>[-kind]-<UTC stamp>/`` (a new folder, never an old one).
        kind: optional command name appended to the run name (``render``, ``events``...).
        overwrite: allow an ``out`` folder that already holds a run (its files are replaced).

    Returns:
        The folder path (created).

    Raises:
        RunDirError: see :func:`check_out_dir`; a run name that would leave ``logging.root``.
    """
    if out is None:
        from .config.validate import check_run_name

        name = cfg.name + (f"-{kind}" if kind else "")
        try:
            check_run_name(name, "name")
        except ConfigError as exc:
            raise RunDirError(str(exc)) from None
        if not str(cfg.logging.root).strip():
            raise RunDirError("logging.root: must not be empty")
        root = Path(cfg.logging.root)
        base = root / f"{name}-{utc_stamp()}"
        if os.path.commonpath([os.path.abspath(base), os.path.abspath(root)]) != os.path.abspath(root):
            raise RunDirError(f"name: {cfg.name!r} would put the run folder outside logging.root = {root}")
    else:
        base = None
    # the claim and the guards' note of the folder as one step: a Ctrl-C between the two (or while
    # config.yaml is written) left a claimed folder that no guard gave a results.json
    with deferred_interrupts():
        run_dir = _new_folder(base) if out is None else check_out_dir(out, overwrite)
        for frame in _GUARDS.stack:
            frame.append(run_dir)
    atomic_write_text(run_dir / "config.yaml", dump_config(cfg))  # RunWriteError names the path
    return run_dir


def _new_folder(base: Path) -> Path:
    """Create and claim ``base`` or, when it exists (another command in the same second),
    ``base-1``, ``base-2``...: each by an exclusive ``mkdir``, so two commands never share one."""
    run_dir, i = base, 1
    while True:
        try:
            _mkdir(run_dir, exclusive=True)
            break
        except FileExistsError:
            run_dir, i = Path(f"{base}-{i}"), i + 1
    _claim(run_dir)
    return run_dir


# ----------------------------------------------------------------------------- interruption
class _Guards(threading.local):
    def __init__(self):
        self.stack: List[list] = []
        self.watchdog: list = []  # the InterruptWatchdog of the innermost guarded command


_GUARDS = _Guards()


def _raise_interrupt(signum, frame):  # noqa: ARG001 - signal handler signature
    raise KeyboardInterrupt(f"terminated by signal {signal.Signals(signum).name}")


def failure_status(exc: BaseException, run_dir: Path) -> str:
    """The results.json status of a command that ended in ``exc``: ``failed`` for a plug-in that
    broke its contract (:class:`dvsland.plugins.PluginError`; its own traceback is written to
    ``run_dir/plugin_error.log`` when the folder takes it), ``interrupted`` for anything else
    (Ctrl-C, SIGTERM, a callback)."""
    from .plugins import PluginError

    if not isinstance(exc, PluginError):
        return "interrupted"
    if exc.plugin_traceback:
        try:
            (Path(run_dir) / "plugin_error.log").write_text(f"{exc}\n\n{exc.plugin_traceback}")
        except OSError:  # a full or read-only disk: the status and message still say what happened
            pass
    return "failed"


def _finish_interrupted(run_dir: Path, exc: BaseException) -> None:
    """Give ``run_dir`` a results.json saying ``interrupted`` (``failed`` for a plug-in fault)
    unless it already holds a final one."""
    from .report.results import read_results_json, write_results_json

    path = run_dir / "results.json"
    error = f"{type(exc).__name__}: {exc}"
    try:
        status = failure_status(exc, run_dir)
        if path.is_file():
            data = read_results_json(path)
            if data.get("status") not in ("running", None):
                return  # the command wrote its own final status
            runs = data.pop("runs", [])
            data.update(status=status, error=data.get("error") or error, phase=data.get("phase", "run"))
            write_results_json(path, runs, **data)
        else:
            write_results_json(path, [], status=status, phase="setup", error=error)
    except Exception:  # noqa: BLE001 - never hide the original error behind a bookkeeping one
        pass


#: errors of the disk rather than of the program: a full disk, a quota, a read-only file system
_DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG)


def _as_write_error(exc: BaseException, made: list):
    """A disk fault (:data:`_DISK_ERRNOS`) that reached a command unconverted becomes one
    :class:`RunWriteError` naming the file (or the run folder when the error names none); any
    other exception -> None (re-raised as it is)."""
    if not isinstance(exc, OSError) or isinstance(exc, RunWriteError) or exc.errno not in _DISK_ERRNOS:
        return None
    where = exc.filename or (made[-1] if made else None) or "the output folder"
    return RunWriteError(where, exc)


#: the exit status of a command that caught an interrupt itself (128 + SIGINT)
INTERRUPTED_STATUS = 130


def guarded_run(fn):
    """Decorator for a command: SIGTERM acts like Ctrl-C during the call, and every run folder
    made inside it (:func:`make_run_dir`) is left with a results.json when the call ends in an
    exception or an interrupt (``status: "interrupted"``, ``phase``: ``setup`` or ``run``), or
    returns :data:`INTERRUPTED_STATUS` (a command that caught Ctrl-C to print its own line: a
    campaign interrupted before its shards flew left a folder without results.json)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        made: list = []
        _GUARDS.stack.append(made)
        try:
            with _interrupt_handlers(made):
                status = fn(*args, **kwargs)
            if status == INTERRUPTED_STATUS:  # the command caught Ctrl-C itself and said so
                for run_dir in made:
                    _finish_interrupted(run_dir, KeyboardInterrupt("Ctrl-C"))
            return status
        except BaseException as exc:
            for run_dir in made:
                _finish_interrupted(run_dir, exc)
            write_fault = _as_write_error(exc, made)
            if write_fault is not None:
                raise write_fault from None
            raise
        finally:
            _GUARDS.stack.pop()

    return wrapper


@contextlib.contextmanager
def _interrupt_handlers(made: list):
    """SIGINT and SIGTERM raise KeyboardInterrupt in the main thread, and an
    :class:`~dvsland.watchdog.InterruptWatchdog` ends the process (after writing the status of the
    run folders in ``made``) when the main thread is stuck in native code and cannot raise it.
    A guarded call inside another (``simulate()`` under the CLI) keeps the outer one's handlers and
    watchdog: every run folder it makes is in the outer ``made`` too (:func:`make_run_dir`)."""
    if threading.current_thread() is not threading.main_thread() or _GUARDS.watchdog:
        yield
        return

    def stuck(signum: int) -> None:
        name = signal.Signals(signum).name
        for run_dir in made:
            _finish_interrupted(run_dir, KeyboardInterrupt(f"{name} inside a computation that could not stop; "
                                                           f"ended by the interrupt watchdog"))
        sys.stderr.write(f"dvsland: interrupted ({name}) inside a long computation that could not stop within "
                         f"{GRACE_S:g} s; the run folder keeps what was written\n")

    with InterruptWatchdog(stuck) as dog:
        def on_signal(signum, frame):  # noqa: ARG001 - signal handler signature
            dog.acknowledge()
            if signum == signal.SIGINT:
                raise KeyboardInterrupt()
            _raise_interrupt(signum, frame)

        old = {}
        try:
            for s in (signal.SIGINT, signal.SIGTERM):
                old[s] = signal.signal(s, on_signal)
        except (ValueError, OSError):  # not allowed here (embedded interpreters)
            pass
        _GUARDS.watchdog.append(dog)
        try:
            yield
        finally:
            _GUARDS.watchdog.pop()
            for s, h in old.items():
                signal.signal(s, h if h is not None else signal.SIG_DFL)


class deferred_interrupts:  # noqa: N801 - used like a function: ``with deferred_interrupts():``
    """Hold SIGINT and SIGTERM back inside the block and raise KeyboardInterrupt once it ends
    (unless it ends in an exception of its own), so a final file (results.json after an
    interrupt) is written whole even when Ctrl-C is pressed again. Main thread only; elsewhere
    it does nothing. ``during`` says what the block did (the raised interrupt's message)."""

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, during: str = "the results were written (they were written first)"):
        self.during = during

    def __enter__(self):
        self.caught, self.old = [], {}
        if threading.current_thread() is threading.main_thread():
            for s in self._SIGNALS:
                try:
                    self.old[s] = signal.signal(s, self._hold)
                except (ValueError, OSError):  # not allowed here (embedded interpreters)
                    pass
        return self

    def _hold(self, signum, frame):  # noqa: ARG002 - signal handler signature
        for dog in _GUARDS.watchdog[-1:]:
            dog.acknowledge()  # the main thread is responsive: no need to end the process
        self.caught.append(signum)

    def __exit__(self, exc_type, exc, tb):
        for s, old in self.old.items():
            signal.signal(s, old if old is not None else signal.SIG_DFL)
        if self.caught and exc_type is None:
            raise KeyboardInterrupt(f"{signal.Signals(self.caught[0]).name} while {self.during}")
        return False


__all__ = ["failure_status", "make_run_dir", "open_folder", "lock_folder", "check_out_dir",
           "guarded_run", "utc_stamp", "RunDirError", "RunWriteError",
           "RUN_MARKERS", "CLAIM_FILE", "deferred_interrupts"]
