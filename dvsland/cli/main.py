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


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the ``dvsland`` command line ``argv`` (default: ``sys.argv[1:]``); return the exit
    status: 0 done, 1 a run that ended incomplete, 2 bad input (one line naming it), 130
    interrupted (SIGINT or SIGTERM, at any moment)."""
    old = _own_signals()  # first: a Ctrl-C while the sub-commands are imported is ours too
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
        exec("pass")  # noqa: S102 - a constant string
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
