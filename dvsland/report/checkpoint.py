"""Which trained model a report shows: a checkpoint's file name and a short content hash.

Every table, figure title and JSON file of a run with a trained estimator (``learned``, ``snn``)
names its checkpoint the same way: ``learned_cnn.pt sha256:1a2b3c4d5e6f`` (the file name and the
first 12 hex digits of the SHA-256 of its bytes), so two reports of the same name but different
weights can be told apart. :func:`estimator_checkpoint` finds the file an estimator of a config
reads (an instance's own ``checkpoint`` attribute first), :func:`checkpoint_identity` hashes it and
:func:`checkpoint_text` writes it out.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

from dvsland.checks import HASH_DIGITS, file_sha256  # noqa: F401 (re-exported)


def checkpoint_identity(path) -> dict:
    """``{"file": name, "sha256": first 12 hex digits, "path": path}`` of a checkpoint file."""
    path = Path(path)
    return {"file": path.name, "sha256": file_sha256(path), "path": str(path)}


def checkpoint_text(identity: Optional[dict]) -> str:
    """``"learned_cnn.pt sha256:1a2b3c4d5e6f"`` of a :func:`checkpoint_identity` (or a run's
    ``checkpoint`` field); ``""`` for None."""
    if not identity:
        return ""
    if isinstance(identity, str):
        return identity
    return f"{identity['file']} sha256:{identity['sha256']}"


def _configured_path(cfg, name: str) -> Optional[Path]:
    """The checkpoint file the config gives the estimator ``name`` (``learned``, ``snn``), else None."""
    base = str(name).split("[", 1)[0].strip()
    if base == "learned":
        from dvsland.estimators.learned.estimator import resolve_checkpoint

        return Path(resolve_checkpoint(cfg.estimator.learned.checkpoint))
    if base == "snn":
        from dvsland.estimators.snn.estimator import DEFAULT_CHECKPOINT

        ck = cfg.estimator.snn.checkpoint
        return Path(ck) if ck else Path(DEFAULT_CHECKPOINT)
    return None


def estimator_checkpoint(cfg, name: str, estimator=None) -> Optional[dict]:
    """The :func:`checkpoint_identity` of the checkpoint an estimator reads, or None when it reads
    none (dpr, cmax, oracle, a third-party estimator without a ``checkpoint`` attribute).

    Args:
        cfg: the (variant) config the estimator was built from.
        name: the registered estimator name (``learned``, ``snn``; a ``name[...]`` spec is read
            by its name).
        estimator: the built instance, if any: its ``checkpoint`` attribute (a path to a file)
            wins over the config.
    """
    own = getattr(estimator, "checkpoint", None) if estimator is not None else None
    if isinstance(own, (str, os.PathLike)) and str(own) and Path(own).is_file():
        return checkpoint_identity(own)
    path = _configured_path(cfg, name)
    if path is None or not path.is_file():
        return None
    return checkpoint_identity(path)


__all__ = ["HASH_DIGITS", "file_sha256", "checkpoint_identity", "checkpoint_text", "estimator_checkpoint"]
