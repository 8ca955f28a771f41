"""Load YAML configs into validated dataclasses; apply ``--set key=value`` overrides; dump."""

from __future__ import annotations

import copy
import dataclasses
import typing
from importlib import resources
from pathlib import Path
from typing import Iterable, Optional, Union

import yaml

from .schema import LIST_ITEM_TYPES, Config
from .validate import ConfigError, _strip_optional, validate_config

PathLike = Union[str, Path]


def repo_root() -> Path:
    """The folder above the package (the source checkout when installed editable; in an installed
    wheel, site-packages). Use :func:`configs_dir` for the shipped configs."""
    return Path(__file__).resolve().parents[2]


def configs_dir() -> Path:
    """Folder of the YAML configs shipped inside the package (``dvsland/configs``; the source
    checkout's ``configs/`` is a link to it), found through importlib.resources so that an
    installed wheel finds them too."""
    return Path(str(resources.files("dvsland") / "configs"))


def resolve_config_path(path: PathLike) -> Path:
    """``path`` if it is a file; otherwise a shipped config of that name: ``paper``,
    ``paper.yaml`` and ``configs/paper.yaml`` all name ``dvsland/configs/paper.yaml``. A name
    found nowhere is a ConfigError listing the shipped configs."""
    p = Path(path)
    if p.is_file():
        return p
    name = p.name if p.suffix in (".yaml", ".yml") else p.name + ".yaml"
    shipped = configs_dir() / name
    if (len(p.parts) == 1 or p.parent.name == "configs") and shipped.is_file():
        return shipped
    known = sorted(q.stem for q in configs_dir().glob("*.yaml"))
    raise ConfigError(f"config file not found: {path} (shipped configs, usable by name: {', '.join(known)})")


def read_yaml(path: PathLike) -> dict:
    """Read a YAML mapping; a missing file or a non-mapping is a ConfigError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections")
    return data


def _resolve_path(cls, keys: list, text: str):
    """Check that dotted ``keys`` name a field of dataclass ``cls``; return the field's type."""
    tp = cls
    owner, name = None, ""
    for i, key in enumerate(keys):
        tp, _ = _strip_optional(tp)
        if dataclasses.is_dataclass(tp):
            names = [f.name for f in dataclasses.fields(tp)]
            if key not in names:
                where = ".".join(keys[:i]) or "config"
                raise ConfigError(f"--set {text}: unknown key '{'.'.join(keys[:i + 1])}'; "
                                  f"known keys in {where}: {sorted(names)}")
            owner, name = tp, key
            tp = typing.get_type_hints(tp)[key]
        elif (tp is list or typing.get_origin(tp) is list) and key.isdigit():
            tp = LIST_ITEM_TYPES.get((owner, name), object)
        elif tp is dict:
            return object  # free-form parameters
        else:
            raise ConfigError(f"--set {text}: '{'.'.join(keys[:i])}' has no sub-key '{key}'")
    return tp


def apply_overrides(data: dict, overrides: Iterable[str]) -> dict:
    """Return a copy of raw config ``data`` with ``section.key=value`` overrides applied.

    Values are parsed as YAML (``5e6``, ``[1, 2]``, ``null``) and typed later by the
    dataclass field. List elements are addressed by index: ``simulation.sites.0.z0_m=5000``.
    """
    data = copy.deepcopy(data)
    for text in overrides or ():
        if "=" not in text:
            raise ConfigError(f"--set {text!r}: expected section.key=value")
        key, raw = text.split("=", 1)
        keys = [k for k in key.strip().split(".") if k]
        if not keys:
            raise ConfigError(f"--set {text!r}: empty key")
        _resolve_path(Config, keys, text)
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError:
            value = raw
        node, defaults = data, config_to_dict(Config())
        for i, k in enumerate(keys):
            last = i == len(keys) - 1
            if isinstance(node, list):
                idx = int(k)
                if idx >= len(node):
                    where = ".".join(keys[:i])
                    raise ConfigError(f"--set {text}: index {idx} is out of range: {where} has {len(node)} "
                                      f"item{'s' if len(node) != 1 else ''} (indices 0 to {len(node) - 1})"
                                      if node else f"--set {text}: index {idx} is out of range: {where} is empty")
                if last:
                    node[idx] = value
                else:
                    node = node[idx]
                defaults = defaults[idx] if isinstance(defaults, list) and idx < len(defaults) else None
            elif isinstance(node, dict):
                default_k = defaults.get(k) if isinstance(defaults, dict) else None
                if last:
                    node[k] = value
                else:
                    if node.get(k) is None:  # a section or list the file leaves out: start from its default
                        node[k] = copy.deepcopy(default_k) if isinstance(default_k, (dict, list)) else {}
                    node = node[k]
                defaults = default_k
            else:
                raise ConfigError(f"--set {text}: '{'.'.join(keys[:i])}' is {node!r}, not a section or list")
    return data


def load_config(path: Optional[PathLike] = None, overrides: Iterable[str] = ()) -> Config:
    """Load, override and validate a config.

    Args:
        path: YAML file; ``None`` gives the defaults (``configs/paper.yaml`` if present).
        overrides: ``section.key=value`` strings, applied after the file.

    Raises:
        ConfigError: unknown key, wrong type, or value out of range (message names it).
    """
    if path is None:
        default = configs_dir() / "paper.yaml"
        path = default if default.is_file() else None
    if path is not None:
        path = resolve_config_path(path)
    data = read_yaml(path) if path is not None else {}
    overrides = list(overrides or ())
    source = str(path) if path is not None else "defaults"
    if overrides:
        source += " with --set overrides"
    data = apply_overrides(data, overrides)
    return validate_config(data, source=source)


def config_to_dict(cfg) -> dict:
    """Plain nested dict of a config dataclass (for YAML, JSON, TensorBoard)."""
    return dataclasses.asdict(cfg)


def dump_config(cfg, path: Optional[PathLike] = None) -> str:
    """YAML text of ``cfg``; also written to ``path`` when given."""
    text = yaml.safe_dump(config_to_dict(cfg), sort_keys=False, default_flow_style=None)
    if path is not None:
        Path(path).write_text(text)
    return text
