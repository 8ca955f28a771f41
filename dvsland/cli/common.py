"""Arguments and helpers shared by the sub-commands."""

from __future__ import annotations

import argparse
from typing import List

from dvsland.config import Config, load_config


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
FLAG_KEYS = {"estimator": "estimator.name", "renderer": "render.renderer", "device": "simulation.device"}


def available_devices() -> List[str]:
    """The torch devices this machine can run on: ``cpu``, then ``cuda:0``... and ``mps`` when present."""
    import torch

    devs = ["cpu"]
    if torch.cuda.is_available():
        devs += [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        devs.append("mps")
    return devs


def check_device(name, param: str = "simulation.device"):
    """Validate a torch device name against this machine before any work (or run folder) starts.

    Args:
        name: ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"``, ...
        param: how the user set it (``--device`` or ``simulation.device``), named in the error.

    Returns:
        The :class:`torch.device`.

    Raises:
        ValueError: naming ``param``, the value, and the devices available here.
    """
    import torch

    avail = available_devices()
    try:
        dev = torch.device(str(name))
    except (RuntimeError, ValueError, TypeError):
        raise ValueError(f"{param}={name!r} is not a torch device; available on this machine: "
                         f"{', '.join(avail)}") from None
    if dev.type == "cpu":
        return dev
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "torch was built without CUDA" if torch.version.cuda is None else "no CUDA device is visible"
            raise ValueError(f"{param}={name!r}: CUDA is not available ({why}, torch {torch.__version__}); "
                             f"available on this machine: {', '.join(avail)}")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{param}={name!r}: only {torch.cuda.device_count()} CUDA device(s) here; "
                             f"available on this machine: {', '.join(avail)}")
        return dev
    if dev.type == "mps" and "mps" in avail:
        return dev
    raise ValueError(f"{param}={name!r}: device type {dev.type!r} is not available or not supported by dvsland; "
                     f"available on this machine: {', '.join(avail)}")


def config_from_args(args: argparse.Namespace, extra_overrides=()) -> Config:
    """Load the config named by ``args.config`` with the shortcut flags (``--estimator``,
    ``--renderer``, ``--device``, ``--quiet``), ``extra_overrides`` and ``--set`` applied, so the
    run folder's config.yaml records what actually ran.

    The device (``--device`` or ``simulation.device``) is checked against this machine here, before
    any command makes its run folder.
    """
    overrides = [f"{key}={getattr(args, flag)}" for flag, key in FLAG_KEYS.items()
                 if getattr(args, flag, None) is not None]  # '--estimator ""' is checked, not dropped
    overrides += list(extra_overrides) + list(getattr(args, "overrides", []) or [])
    if getattr(args, "quiet", False):
        overrides.append("logging.quiet=true")
    if getattr(args, "device", None):  # the flag first: its error names --device
        check_device(args.device, "--device")
    cfg = load_config(args.config, overrides)
    check_device(cfg.simulation.device, "simulation.device")
    return cfg
