"""Load YAML configs into validated dataclasses; apply ``--set key=value`` overrides; dump.

A config file may name its base with ``extends: <preset name or path>`` and give only what
differs: the base is resolved first (it may extend another), then the file is merged over it,
mappings key by key (deeply), lists and other values replaced whole. A name or a relative path is
looked up next to the extending file first, then among the shipped presets. :func:`resolve_config`
returns the merged mapping and, for each value, the file (or ``--set``) it came from.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import typing
from importlib import resources
from pathlib import Path
from typing import Iterable, Optional, Sequence, Union

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


def _is_file(path: Path, what: str = "config file") -> bool:
    """``path.is_file()``, but a path the OS refuses to look up (a name longer than NAME_MAX, a
    path longer than PATH_MAX) is a ConfigError naming it and ``what``, not an OSError."""
    try:
        return path.is_file()
    except OSError as exc:
        text = str(path)
        raise ConfigError(f"{what}: {text[:60]!r}{'...' if len(text) > 60 else ''} ({len(text)} characters) "
                          f"cannot be looked up: {exc.strerror or exc}; a file name may have up to 255 bytes, "
                          f"a path up to 4096") from None


def resolve_config_path(path: PathLike) -> Path:
    """``path`` if it is a file; otherwise a shipped config of that name: ``paper``,
    ``paper.yaml`` and ``configs/paper.yaml`` all name ``dvsland/configs/paper.yaml``. A name
    found nowhere, or one too long to look up, is a ConfigError (the former listing the shipped
    configs)."""
    p = Path(path)
    if _is_file(p):
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
    if not _is_file(path):
        raise ConfigError(f"config file not found: {path}")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a UTF-8 text file (byte {exc.object[exc.start]:#04x} at offset "
                          f"{exc.start} is not UTF-8); save the config as UTF-8 YAML") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections")
    return data


#: the key naming a config's base
EXTENDS_KEY = "extends"
#: origin of a value no file and no --set gave
DEFAULT_ORIGIN = "default"


def _find_base(name, where: Path) -> Path:
    """The file ``extends: name`` in the file ``where`` names: next to ``where`` first (with or
    without ``.yaml``), then a shipped preset."""
    if not isinstance(name, str) or not name.strip():
        raise ConfigError(f"{where}: '{EXTENDS_KEY}' must name a preset or a YAML file, got {name!r}")
    p = Path(name.strip()).expanduser()
    what = f"{where}: {EXTENDS_KEY}"
    if not p.is_absolute():
        for cand in (where.parent / p, where.parent / (str(p) + ".yaml")):
            if _is_file(cand, what):
                return cand
    elif _is_file(p, what):
        return p
    try:
        return resolve_config_path(name.strip())
    except ConfigError as exc:
        raise ConfigError(f"{where}: {EXTENDS_KEY}: {name!r}: {exc}") from None


def _leaves(data, prefix: tuple = ()):
    """Dotted paths of the values of a nested mapping (a list is one value)."""
    if isinstance(data, dict) and data:
        for k, v in data.items():
            yield from _leaves(v, prefix + (str(k),))
    elif prefix:
        yield prefix


def _merge(base: dict, over: dict) -> dict:
    """``over`` merged into a copy of ``base``: mappings key by key, everything else replaced."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _display_path(path: Path) -> str:
    """A file as an origin names it: a shipped preset as ``dvsland/configs/<name>.yaml``, another
    file relative to the working directory when inside it, else absolute."""
    path = Path(path).resolve()
    shipped = configs_dir().resolve()
    if path.parent == shipped:
        return f"dvsland/configs/{path.name}"
    try:
        rel = os.path.relpath(path)
    except ValueError:  # another drive
        return str(path)
    return rel if not rel.startswith("..") else str(path)


def resolve_config(path: PathLike, _chain: tuple = ()) -> tuple:
    """Read a config file and the chain of files it ``extends``.

    Returns:
        ``(data, origins)``: the merged raw mapping (without ``extends``) and {dotted path: the
        file that set it} for every value a file gives.

    Raises:
        ConfigError: a file that is missing or not a mapping, an ``extends`` that names nothing,
            or a cycle (the message lists the chain).
    """
    path = Path(path)
    key = path.resolve()
    if key in _chain:
        names = " -> ".join(str(p) for p in (*_chain, key))
        raise ConfigError(f"{path}: '{EXTENDS_KEY}' makes a cycle: {names}")
    data = read_yaml(path)
    base_name = data.pop(EXTENDS_KEY, None)
    origin = _display_path(path)
    own = {".".join(p): origin for p in _leaves(data)}
    if base_name is None:
        return data, own
    base, origins = resolve_config(_find_base(base_name, path), (*_chain, key))
    for p in list(origins):  # a value this file replaces whole (a list, a section set to null ...)
        if any(p == q or p.startswith(q + ".") for q in own):
            del origins[p]
    origins.update(own)
    return _merge(base, data), origins


def origin_of(origins: dict, dotted: str) -> str:
    """Where the value at ``dotted`` (``camera.fov_deg``, ``simulation.sites.0.z0_m``) came from:
    the longest recorded prefix's origin, else ``default``."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        o = origins.get(".".join(parts[:n]))
        if o is not None:
            return o
    return DEFAULT_ORIGIN


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
    cfg, _ = load_config_with_origins(path, overrides)
    return cfg


def load_config_with_origins(path: Optional[PathLike] = None, overrides: Iterable[str] = ()) -> tuple:
    """:func:`load_config`, and where each value came from.

    Returns:
        ``(cfg, origins)``: the validated :class:`Config` and {dotted path: origin}, the origin
        being a file of the ``extends`` chain or ``--set key=value``; look a value up with
        :func:`origin_of` (values nobody set are ``default``).
    """
    if path is None:
        default = configs_dir() / "paper.yaml"
        path = default if default.is_file() else None
    if path is not None:
        path = resolve_config_path(path)
    data, origins = resolve_config(path) if path is not None else ({}, {})
    overrides = list(overrides or ())
    source = str(path) if path is not None else "defaults"
    if overrides:
        source += " with --set overrides"
    data = apply_overrides(data, overrides)
    set_keys = []
    for text in overrides:
        key = ".".join(k for k in text.split("=", 1)[0].strip().split(".") if k)
        set_keys.append(key)
        for p in [p for p in origins if p == key or p.startswith(key + ".")]:
            del origins[p]
        origins[key] = f"--set {text.strip()}"
    data = apply_recommended(data, set_keys, origins, source)
    return validate_config(data, source=source), origins


def apply_recommended(data: dict, set_keys: Sequence[str], origins: dict, source: str = "") -> dict:
    """Apply a preset's ``recommended:`` section: {estimator name: {dotted.key: value}}, the settings
    the preset flies that estimator with (e.g. the filter's confidence threshold of a learned
    model). Only the entry of the configured ``estimator.name`` (its base name before ``[``)
    applies, and only to keys the user did not ``--set``; the section itself leaves the config.

    Raises:
        ConfigError: a ``recommended`` section that is not a mapping of mappings (names ``source``).
    """
    rec = data.pop("recommended", None) if isinstance(data, dict) else None
    if not rec:
        return data
    if not isinstance(rec, dict) or not all(isinstance(v, dict) for v in rec.values()):
        raise ConfigError(f"recommended (in {source}): expected {{estimator name: {{section.key: value}}}}, got {rec!r}")
    name = str((data.get("estimator") or {}).get("name", "dpr"))
    base = name.split("[", 1)[0].split("=", 1)[-1].strip()
    chosen = rec.get(name, rec.get(base)) or {}
    todo = [f"{k}={_flow(v)}" for k, v in chosen.items()
            if not any(k == s or k.startswith(s + ".") or s.startswith(k + ".") for s in set_keys)]
    if todo:
        data = apply_overrides(data, todo)
        for text in todo:
            origins[text.split("=", 1)[0]] = f"recommended for estimator {base!r} ({source})"
    return data


def config_to_dict(cfg) -> dict:
    """Plain nested dict of a config dataclass (for YAML, JSON, TensorBoard)."""
    return dataclasses.asdict(cfg)


def dump_config(cfg, path: Optional[PathLike] = None) -> str:
    """YAML text of ``cfg``; also written to ``path`` when given."""
    text = yaml.safe_dump(config_to_dict(cfg), sort_keys=False, default_flow_style=None)
    if path is not None:
        Path(path).write_text(text)
    return text


def _flow(value) -> str:
    """One YAML value on one line (flow style)."""
    return yaml.safe_dump(value, default_flow_style=True, sort_keys=False, width=1 << 30).strip().removesuffix("\n...").strip()


def dump_config_with_origins(cfg, origins: dict) -> str:
    """YAML of ``cfg`` (as :func:`dump_config`, one value per line) with a comment after each value
    naming where it came from (:func:`load_config_with_origins`): a file of the ``extends`` chain,
    ``--set key=value`` or ``default``. The text loads back to the same config; a list item changed
    by ``--set`` names that too."""
    lines = []

    def walk(node, path, indent):
        pad = "  " * indent
        for k, v in node.items():
            dotted = ".".join((*path, str(k)))
            if isinstance(v, dict) and v:
                lines.append(f"{pad}{k}:")
                walk(v, (*path, str(k)), indent + 1)
            elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
                lines.append(f"{pad}{k}:  # {origin_of(origins, dotted)}")
                for i, item in enumerate(v):
                    sub = [f"{p}" for p in origins if p.startswith(f"{dotted}.{i}.") or p == f"{dotted}.{i}"]
                    note = f"  # {', '.join(origins[p] for p in sub)}" if sub else ""
                    lines.append(f"{pad}- {_flow(item)}{note}")
            else:
                lines.append(f"{pad}{k}: {_flow(v)}  # {origin_of(origins, dotted)}")

    walk(config_to_dict(cfg), (), 0)
    return "\n".join(lines) + "\n"

