"""Run folders: ``logs/<name>-<UTC timestamp>/`` holding the resolved config and all output.

Every command makes its folder with :func:`make_run_dir`, the one output-folder guard: an empty
``--out``, a path that is a file, a folder that cannot be created (``/proc/x``), a run name that
would leave ``logging.root`` (``../../x``) and a folder that already holds a run are refused
with a :class:`RunDirError` (a ``ValueError``) that says why and what to do.

:func:`guarded_run` wraps a command (``dvsland.simulate``, every CLI sub-command): SIGTERM is
turned into ``KeyboardInterrupt`` (so a ``kill`` is handled like Ctrl-C), and a run folder made
during the call that has no final ``results.json`` gets one saying ``status: "interrupted"``
(with the phase, set-up or run, and the error), so nothing already written is lost.
"""

from __future__ import annotations

import datetime as _dt
import functools
import os
import signal
import threading
from pathlib import Path
from typing import List, Optional, Union

from .config import Config, ConfigError, dump_config

#: files whose presence marks a folder as holding a dvsland run
RUN_MARKERS = ("config.yaml", "results.json", "tb", "evaluation.json", "traces.npz")


class RunDirError(ValueError):
    """The output folder cannot be used (the message says why)."""


def utc_stamp() -> str:
    """UTC timestamp for folder names, e.g. ``20261122T104512Z``."""
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")


def check_out_dir(out: Union[str, Path], overwrite: bool = False) -> Path:
    """Check an explicit output folder (``--out``) and create it.

    Raises:
        RunDirError: empty path, an existing file, a folder holding an earlier run (unless
            ``overwrite``), or a folder the OS will not create.
    """
    if out is None or str(out).strip() == "":
        raise RunDirError("--out: the output folder must not be empty (leave --out out for "
                          "logs/<name>-<UTC timestamp>/)")
    run_dir = Path(out)
    if run_dir.exists() and not run_dir.is_dir():
        raise RunDirError(f"--out {run_dir}: exists and is not a folder")
    if run_dir.is_dir() and not overwrite:
        held = [m for m in RUN_MARKERS if (run_dir / m).exists()]
        if held:
            raise RunDirError(f"--out {run_dir}: already holds a run ({', '.join(held)}); choose a new folder "
                              f"or remove it (dvsland never mixes the files of two runs)")
    _mkdir(run_dir)
    return run_dir


def _mkdir(path: Path) -> None:
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".dvsland-write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise RunDirError(f"cannot write the run folder {path}: {exc.strerror or exc}") from None


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
        run_dir, i = base, 1
        while run_dir.exists():
            run_dir = Path(f"{base}-{i}")
            i += 1
        _mkdir(run_dir)
    else:
        run_dir = check_out_dir(out, overwrite)
    dump_config(cfg, run_dir / "config.yaml")
    for frame in _GUARDS.stack:
        frame.append(run_dir)
    return run_dir


# ----------------------------------------------------------------------------- interruption
class _Guards(threading.local):
    def __init__(self):
        self.stack: List[list] = []


_GUARDS = _Guards()


def _raise_interrupt(signum, frame):  # noqa: ARG001 - signal handler signature
    raise KeyboardInterrupt(f"terminated by signal {signal.Signals(signum).name}")


def _finish_interrupted(run_dir: Path, exc: BaseException) -> None:
    """Give ``run_dir`` a results.json saying ``interrupted`` unless it already holds a final one."""
    from .report.results import read_results_json, write_results_json

    from .plugins import PluginError

    path = run_dir / "results.json"
    error = f"{type(exc).__name__}: {exc}"
    status = "failed" if isinstance(exc, PluginError) else "interrupted"  # a plug-in broke its contract
    try:
        if isinstance(exc, PluginError) and exc.plugin_traceback:
            (run_dir / "plugin_error.log").write_text(f"{exc}\n\n{exc.plugin_traceback}")
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


def guarded_run(fn):
    """Decorator for a command: SIGTERM acts like Ctrl-C during the call, and every run folder
    made inside it (:func:`make_run_dir`) is left with a results.json when the call ends in an
    exception or an interrupt (``status: "interrupted"``, ``phase``: ``setup`` or ``run``)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        old = None
        main = threading.current_thread() is threading.main_thread()
        if main:
            try:
                old = signal.signal(signal.SIGTERM, _raise_interrupt)
            except (ValueError, OSError):  # not allowed here (embedded interpreters)
                main = False
        made: list = []
        _GUARDS.stack.append(made)
        try:
            return fn(*args, **kwargs)
        except BaseException as exc:
            for run_dir in made:
                _finish_interrupted(run_dir, exc)
            raise
        finally:
            _GUARDS.stack.pop()
            if main:
                signal.signal(signal.SIGTERM, old if old is not None else signal.SIG_DFL)

    return wrapper


__all__ = ["make_run_dir", "check_out_dir", "guarded_run", "utc_stamp", "RunDirError", "RUN_MARKERS"]
