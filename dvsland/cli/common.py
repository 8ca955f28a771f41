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


#: sub-command flags that are shortcuts for a config value (applied before ``--set``)
FLAG_KEYS = {"estimator": "estimator.name", "renderer": "render.renderer", "device": "simulation.device"}


def config_from_args(args: argparse.Namespace, extra_overrides=()) -> Config:
    """Load the config named by ``args.config`` with the shortcut flags (``--estimator``,
    ``--renderer``, ``--device``, ``--quiet``), ``extra_overrides`` and ``--set`` applied, so the
    run folder's config.yaml records what actually ran."""
    overrides = [f"{key}={getattr(args, flag)}" for flag, key in FLAG_KEYS.items()
                 if getattr(args, flag, None) is not None]  # '--estimator ""' is checked, not dropped
    overrides += list(extra_overrides) + list(getattr(args, "overrides", []) or [])
    if getattr(args, "quiet", False):
        overrides.append("logging.quiet=true")
    return load_config(args.config, overrides)
