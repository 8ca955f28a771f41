"""Entry point of the ``dvsland`` console script.

Sub-commands are discovered from the ``dvsland.cli.cmd_*`` modules, each with a
``register(subparsers)`` function, so a stage adds its command without touching this file.

:func:`main` owns the signals from its first instruction: SIGTERM acts like Ctrl-C, and an
interrupt at any moment (while the sub-commands are imported, while the arguments are parsed,
or during the command) ends in one line and exit status 130, never a traceback. This module
imports nothing heavy at its top, so the window before :func:`main` runs is a few milliseconds.
"""

from __future__ import annotations

import argparse
import signal
import sys
from typing import Optional, Sequence


def build_parser() -> argparse.ArgumentParser:
    import importlib
    import pkgutil

    import dvsland.cli as cli_pkg
    from dvsland import __version__

    parser = argparse.ArgumentParser(
        prog="dvsland",
        description="Event-camera-guided spacecraft landing: render, emulate events, estimate "
                    "time-to-contact, fly batched closed-loop descents.")
    parser.add_argument("--version", action="version", version=f"dvsland {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in sorted(m.name for m in pkgutil.iter_modules(cli_pkg.__path__) if m.name.startswith("cmd_")):
        importlib.import_module(f"dvsland.cli.{mod}").register(subparsers)
    return parser


def _on_sigterm(signum, frame):  # noqa: ARG001 - signal handler signature
    raise KeyboardInterrupt(signal.Signals(signum).name)


def _own_signals() -> dict:
    """SIGTERM raises KeyboardInterrupt, and SIGINT does too where it is left at the default
    (not where a parent ignores it, as ``nohup`` does); returns the handlers replaced. Main thread
    only; elsewhere (an embedded interpreter, a worker thread) nothing is changed."""
    old = {}
    try:
        old[signal.SIGTERM] = signal.signal(signal.SIGTERM, _on_sigterm)
        if signal.getsignal(signal.SIGINT) is signal.SIG_DFL:
            old[signal.SIGINT] = signal.signal(signal.SIGINT, signal.default_int_handler)
    except (ValueError, OSError):
        pass
    return old


def _resend_later(signum: int) -> None:
    """Send ``signum`` to this process again in 50 ms, from a daemon thread (which does not keep a
    finishing process alive)."""
    import os
    import threading

    timer = threading.Timer(0.05, os.kill, (os.getpid(), signum))
    timer.daemon = True
    timer.start()


class _InterruptInCallback:
    """A ``sys.unraisablehook`` for the length of :func:`main`: an interrupt that lands while Python
    runs a callback whose exceptions it cannot raise (a weakref callback such as the import lock's,
    a ``__del__``, a finaliser) was printed as "Exception ignored in ... Traceback ... KeyboardInterrupt"
    and then dropped, so the command went on as if never interrupted. Here it is kept quiet and the
    signal is sent again 50 ms later, when it lands in ordinary code and ends the command as usual.
    Any other unraisable exception goes to the hook that was there before."""

    def __init__(self):
        self.previous = None

    def __call__(self, unraisable) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            _resend_later(signal.SIGTERM if "SIGTERM" in str(unraisable.exc_value) else signal.SIGINT)
            return
        (self.previous or sys.__unraisablehook__)(unraisable)

    def install(self) -> None:
        self.previous, sys.unraisablehook = sys.unraisablehook, self

    def remove(self) -> None:
        if sys.unraisablehook is self:
            sys.unraisablehook = self.previous


class _TorchImportGuard:
    """A ``sys.meta_path`` finder that holds SIGINT and SIGTERM back while torch imports (wherever
    a command first imports it) and delivers the interrupt once it is imported: a KeyboardInterrupt
    raised inside torch's import, where its C++ calls back into Python, aborted the process
    ("terminate called after throwing an instance of 'pybind11::error_already_set'", status -6)."""

    def find_spec(self, name, path=None, target=None):
        if name != "torch":
            return None
        import importlib.util

        self.remove()  # once: and find the real spec without coming back here
        spec = importlib.util.find_spec("torch")
        if spec is None or spec.loader is None:
            return spec
        spec.loader = _HeldLoader(spec.loader)
        return spec

    def install(self) -> None:
        if "torch" not in sys.modules and self not in sys.meta_path:
            sys.meta_path.insert(0, self)

    def remove(self) -> None:
        if self in sys.meta_path:
            sys.meta_path.remove(self)


class _HeldLoader:
    """Runs torch's own loader with SIGINT and SIGTERM held back, then sends the first again
    (50 ms later, past the import machinery) to the handler the command has."""

    def __init__(self, loader):
        self.loader = loader

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module):
        caught, old = [], {}

        def hold(signum, frame):  # noqa: ARG001 - signal handler signature
            runs = sys.modules.get("dvsland.runs")  # a command's interrupt watchdog: the main thread answers
            for dog in (runs._GUARDS.watchdog[-1:] if runs is not None else []):
                dog.acknowledge()
            caught.append(signum)

        try:  # a plain handler here (not dvsland.runs': importing it could itself be interrupted)
            for s in (signal.SIGINT, signal.SIGTERM):
                old[s] = signal.signal(s, hold)
        except (ValueError, OSError):  # not the main thread: nothing to hold
            pass
        try:
            self.loader.exec_module(module)
        finally:
            for s, h in old.items():
                signal.signal(s, h if h is not None else signal.SIG_DFL)
        if caught:  # sent again once the import is done: raised here, it failed the import and left
            _resend_later(caught[0])  # torch half registered (a later import: "Only a single TORCH_LIBRARY ...")

    def __getattr__(self, name):  # anything else the import system asks of the real loader
        return getattr(self.loader, name)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the ``dvsland`` command line ``argv`` (default: ``sys.argv[1:]``); return the exit
    status: 0 done, 1 a run that ended incomplete, 2 bad input (one line naming it), 130
    interrupted (SIGINT or SIGTERM, at any moment). As the program (``argv`` None) it first keeps
    freed memory in the process for the next step (:func:`dvsland.allocator.tune_allocator`)."""
    old = _own_signals()  # first: a Ctrl-C while the sub-commands are imported is ours too
    if argv is None:  # the command line itself (not a caller's in-process run): before torch loads
        from dvsland.allocator import tune_allocator

        tune_allocator()
    guard, in_callback = _TorchImportGuard(), _InterruptInCallback()
    guard.install()
    in_callback.install()
    started = []
    try:
        return _run(argv, started)
    except KeyboardInterrupt as exc:
        what = ("what was gathered so far was written" if started
                else "before the command started; nothing was written")
        print(f"dvsland: interrupted ({str(exc) or 'Ctrl-C'}); {what}", file=sys.stderr)
        return 130
    finally:
        # an interrupt raised inside code that exec() ran from a string (dataclasses and namedtuples
        # build their methods so, in every import) leaves CPython's "unhandled KeyboardInterrupt"
        # flag set even when it is handled (here, or by a command that returns 130 after saving its
        # work), and the interpreter would then end itself by SIGINT at exit instead of with the
        # status returned; running exec() once more clears it
        for _ in range(3):  # a signal landing inside this exec() sets the flag again: once more
            try:
                exec("pass")  # noqa: S102 - a constant string
                break
            except KeyboardInterrupt:
                continue
        guard.remove()
        in_callback.remove()
        for s, h in old.items():
            try:
                signal.signal(s, h if h is not None else signal.SIG_DFL)
            except (ValueError, OSError):
                pass


def _run(argv: Optional[Sequence[str]], started: list) -> int:
    """Parse ``argv`` and run its command under :func:`dvsland.runs.guarded_run`; bad input is one
    line on stderr and status 2. ``started`` gets an item once the command runs."""
    from dvsland.config import ConfigError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from dvsland.runs import guarded_run

    try:
        started.append(args.command)
        return int(guarded_run(args.func)(args) or 0)  # SIGTERM = Ctrl-C; partial results kept
    except ConfigError as exc:
        print(f"dvsland: config error: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:  # bad input named by the library
        print(f"dvsland: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
