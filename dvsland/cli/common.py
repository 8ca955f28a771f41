"""Arguments and helpers shared by the sub-commands."""

from __future__ import annotations

import argparse

from dvsland.config import Config, load_config


def add_config_args(parser: argparse.ArgumentParser, out: bool = True) -> None:
    """Add ``[CONFIG] [--set key=value ...] [--out DIR] [--quiet]`` to a sub-command."""
    parser.add_argument("config", nargs="?", default=None,
                        help="YAML config (default: configs/paper.yaml)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value, e.g. --set controller.c2=0.4 (repeatable)")
    if out:
        parser.add_argument("--out", default=None, metavar="DIR",
                            help="run folder (default: logs/<name>-<UTC timestamp>/)")
        parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def config_from_args(args: argparse.Namespace, extra_overrides=()) -> Config:
    """Load the config named by ``args.config`` with ``--set`` and command-specific overrides."""
    overrides = list(extra_overrides) + list(getattr(args, "overrides", []) or [])
    if getattr(args, "quiet", False):
        overrides.append("logging.quiet=true")
    return load_config(args.config, overrides)
