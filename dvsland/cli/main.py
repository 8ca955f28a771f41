"""Entry point of the ``dvsland`` console script.

Sub-commands are discovered from the ``dvsland.cli.cmd_*`` modules, each with a
``register(subparsers)`` function, so a stage adds its command without touching this file.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from typing import Optional, Sequence

from dvsland import __version__
from dvsland.config import ConfigError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dvsland",
        description="Event-camera-guided spacecraft landing: render, emulate events, estimate "
                    "time-to-contact, fly batched closed-loop descents.")
    parser.add_argument("--version", action="version", version=f"dvsland {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    import dvsland.cli as cli_pkg

    for mod in sorted(m.name for m in pkgutil.iter_modules(cli_pkg.__path__) if m.name.startswith("cmd_")):
        importlib.import_module(f"dvsland.cli.{mod}").register(subparsers)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from dvsland.runs import guarded_run

    try:
        return int(guarded_run(args.func)(args) or 0)  # SIGTERM = Ctrl-C; partial results kept
    except ConfigError as exc:
        print(f"dvsland: config error: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:  # bad input named by the library
        print(f"dvsland: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"dvsland: interrupted ({str(exc) or 'Ctrl-C'}); what was gathered so far was written", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
