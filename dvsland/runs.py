"""Run folders: ``logs/<name>-<UTC timestamp>/`` holding the resolved config and all output."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import Optional, Union

from .config import Config, dump_config


def utc_stamp() -> str:
    """UTC timestamp for folder names, e.g. ``20261122T104512Z``."""
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")


def make_run_dir(cfg: Config, out: Optional[Union[str, Path]] = None, kind: str = "") -> Path:
    """Create the run folder and write ``config.yaml`` into it before any work starts.

    Args:
        cfg: the resolved, validated config.
        out: explicit folder (``--out``); default ``<cfg.logging.root>/<name>[-kind]-<UTC stamp>/``.
        kind: optional command name appended to the run name (``render``, ``events``...).

    Returns:
        The folder path (created; an existing ``--out`` folder is reused).
    """
    if out is None:
        name = cfg.name + (f"-{kind}" if kind else "")
        base = Path(cfg.logging.root) / f"{name}-{utc_stamp()}"
        run_dir, i = base, 1
        while run_dir.exists():
            run_dir = Path(f"{base}-{i}")
            i += 1
    else:
        run_dir = Path(out)
    run_dir.mkdir(parents=True, exist_ok=True)
    dump_config(cfg, run_dir / "config.yaml")
    return run_dir
