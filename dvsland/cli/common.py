"""Arguments and helpers shared by the sub-commands."""

from __future__ import annotations

import argparse
import os
from typing import List, Optional, Sequence

from dvsland.checks import available_devices, check_device  # noqa: F401 - the CLI's names
from dvsland.config import Config, load_config
from dvsland.config.sites import check_configured_sites, restrict_sites  # noqa: F401  (the commands' names)


def add_config_args(parser: argparse.ArgumentParser, out: bool = True) -> None:
    """Add ``[CONFIG] [--set key=value ...] [--out DIR] [--quiet]`` to a sub-command."""
    parser.add_argument("config", nargs="?", default=None,
                        help="YAML config, or the name of a shipped one such as 'paper' or 'realistic' "
                             "(default: paper)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value, e.g. --set controller.c2=0.4 (repeatable)")
    if out:
        parser.add_argument("--out", default=None, metavar="DIR",
                            help="run folder (default: logs/<name>-<UTC timestamp>/)")
        parser.add_argument("--quiet", action="store_true",
                            help="no progress bar or summary; only the run folder is printed")


#: sub-command flags that are shortcuts for a config value (applied before ``--set``)
FLAG_KEYS = {"estimator": "estimator.name", "renderer": "render.renderer", "device": "simulation.device",
             "controller": "controller.name"}


# ------------------------------------------------------------------ threads
def max_threads() -> int:
    """The most threads ``--threads`` accepts: 4 per CPU core of this machine (at least 4)."""
    return 4 * max(1, os.cpu_count() or 1)


def parse_threads(text, param: str = "--threads") -> int:
    """``text`` as a thread count in 1..:func:`max_threads`; ValueError naming ``param`` and the range."""
    hi = max_threads()
    try:
        n = int(str(text).strip())
    except ValueError:
        n = None
    if n is None or not 1 <= n <= hi:
        raise ValueError(f"{param} must be an integer from 1 to {hi} (4 per CPU core, "
                         f"{os.cpu_count() or 1} cores here), got {text!r}")
    return n


def _threads_type(text) -> int:
    try:
        return parse_threads(text)
    except ValueError as exc:  # argparse prints "argument --threads: <message>", exit status 2
        raise argparse.ArgumentTypeError(str(exc).replace("--threads ", "", 1)) from None


def add_threads_arg(parser: argparse.ArgumentParser, what: str = "") -> None:
    """Add ``--threads N`` (checked by :func:`parse_threads` while the arguments are parsed, before
    any work). :func:`config_from_args` turns it into ``simulation.torch_threads=N`` and
    ``render.threads=N``."""
    parser.add_argument(
        "--threads", type=_threads_type, default=None, metavar="N",
        help=f"CPU threads of this process{what}: torch's (simulation.torch_threads) and the fast "
             f"renderer's sampling (render.threads); 1 to {max_threads()} (default: the config's, 1 in every "
             "shipped preset: on a shared machine more threads are slower, docs/howto/devices.md)")


def thread_overrides(args: argparse.Namespace) -> List[str]:
    """``--set`` strings of ``--threads N`` (none when it is not given)."""
    n = getattr(args, "threads", None)
    if n is None:
        return []
    n = parse_threads(n)
    return [f"simulation.torch_threads={n}", f"render.threads={n}"]


def apply_threads(cfg: Config) -> int:
    """Set torch's CPU threads to ``simulation.torch_threads`` (0 leaves torch's default); return
    the count in force."""
    import torch

    n = int(cfg.simulation.torch_threads)
    if n > 0 and torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return torch.get_num_threads()


# ------------------------------------------------------------------ sites
def ranged(kind, low, high, param: str):
    """An argparse ``type`` that reads ``kind`` (int or float) and refuses values outside
    [low, high] (NaN and inf too) with a message naming ``param`` and the range."""
    import math

    def parse(text):
        try:
            value = kind(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"{param} must be a{'n integer' if kind is int else ' number'} "
                                             f"from {low} to {high}, got {text!r}") from None
        if not (math.isfinite(value) and low <= value <= high):
            raise argparse.ArgumentTypeError(f"{param} must be from {low} to {high}, got {text!r}")
        return value

    return parse


def add_sites_arg(parser: argparse.ArgumentParser, help: str) -> None:
    """Add ``--sites A,B~1,...`` (parsed by :func:`parse_sites`)."""
    parser.add_argument("--sites", default=None, metavar="A,B,...", help=help)


def parse_sites(text: Optional[str], param: str = "--sites") -> Optional[List[str]]:
    """Site names from ``"A, E,H~2"``: each a shipped site (A-I) or a terrain variant ``<site>~<k>``
    (:func:`dvsland.terrain.spec.split_site_name`). None for None; ValueError naming ``param`` for an
    unknown name, an empty list or a repeated name. Every command parses ``--sites`` with this,
    before any run folder is made."""
    if text is None:
        return None
    from dvsland.terrain.spec import split_site_name

    names = [s.strip() for s in str(text).split(",") if s.strip()]
    if not names:
        raise ValueError(f"{param}: give at least one site, e.g. {param} A,E")
    for n in names:
        try:
            split_site_name(n)
        except ValueError as exc:
            raise ValueError(f"{param}: {exc}") from None
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{param}: {', '.join(dup)} named twice")
    return names


def config_from_args(args: argparse.Namespace, extra_overrides=()) -> Config:
    """Load the config named by ``args.config`` with the shortcut flags (``--estimator``,
    ``--controller``, ``--renderer``, ``--device``, ``--threads``, ``--quiet``; an empty value is
    checked, not dropped), ``extra_overrides`` and ``--set``
    applied, so the run folder's config.yaml records what actually ran.

    The device (``--device`` or ``simulation.device``) is checked against this machine here, before
    any command makes its run folder.
    """
    overrides = [f"{key}={getattr(args, flag)}" for flag, key in FLAG_KEYS.items()
                 if getattr(args, flag, None) is not None]  # '--estimator ""' is checked, not dropped
    overrides += list(extra_overrides) + list(getattr(args, "overrides", []) or [])
    overrides += thread_overrides(args)  # the flag wins over --set simulation.torch_threads / render.threads
    if getattr(args, "quiet", False):
        overrides.append("logging.quiet=true")
    if getattr(args, "device", None):  # the flag first: its error names --device
        check_device(args.device, "--device")
    cfg = load_config(args.config, overrides)
    check_device(cfg.simulation.device, "simulation.device")
    return cfg


# ------------------------------------------------------------------ input files
def check_input_file(path, param: str) -> None:
    """ValueError naming ``param`` unless ``path`` is an existing file (a missing file, a folder,
    or a name the OS cannot look up); every command checks its input files with this before its
    run folder is made."""
    from pathlib import Path

    text = str(path)
    try:
        ok, exists = Path(text).is_file(), Path(text).exists()
    except OSError as exc:
        raise ValueError(f"{param}: {text[:60]!r}{'...' if len(text) > 60 else ''} cannot be looked up "
                         f"({exc.strerror or exc})") from None
    if not text.strip() or not ok:
        what = "is a folder, not a file" if exists else "no such file"
        raise ValueError(f"{param}: {what}: {text!r}" if text.strip() else f"{param}: give a file, got ''")
