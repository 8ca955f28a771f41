"""Build validated config dataclasses from plain dicts (as read from YAML).

Errors are :class:`ConfigError` and name the parameter (dotted path), the file, and the
allowed range or choices.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, Optional

from dvsland.checks import check_choice, check_range

from .schema import LIST_ITEM_TYPES, Config


class ConfigError(ValueError):
    """A configuration value, key or file is not acceptable."""


def _where(source: Optional[str]) -> str:
    return f" (in {source})" if source else ""


def _field_types(cls) -> dict:
    return typing.get_type_hints(cls)


def _strip_optional(tp):
    """Return (inner_type, is_optional) for Optional[X]."""
    if typing.get_origin(tp) is typing.Union:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def coerce_scalar(value: Any, tp, path: str, source: Optional[str]) -> Any:
    """Convert ``value`` to the scalar type ``tp`` (int, float, bool, str) or raise ConfigError."""
    def bad(expected: str):
        return ConfigError(f"{path}{_where(source)}: expected {expected}, got {value!r}")

    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "yes", "no", "1", "0"):
            return value.lower() in ("true", "yes", "1")
        raise bad("true or false")
    if tp is int:
        if isinstance(value, bool):
            raise bad("an integer")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                f = float(value)
            except ValueError:
                raise bad("an integer") from None
            if f.is_integer():
                return int(f)
        raise bad("an integer")
    if tp is float:
        if isinstance(value, bool):
            raise bad("a number")
        if isinstance(value, (int, float)):
            return float(value)
        if isinstance(value, str):  # YAML 1.1 reads "5e6" as a string
            try:
                return float(value)
            except ValueError:
                raise bad("a number") from None
        raise bad("a number")
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)
        raise bad("a string")
    if tp is dict:
        if isinstance(value, dict):
            return dict(value)
        raise bad("a mapping")
    raise bad(str(tp))


def _check_field(value: Any, md: dict, path: str, source: Optional[str]) -> None:
    if value is None:
        return
    if md.get("choices") is not None:
        check_choice(path, value, md["choices"], where=_where(source), error=ConfigError)
    rng = md.get("rng")
    if rng is not None and isinstance(value, (int, float)):
        check_range(path, value, rng[0], rng[1], open_lo=bool(md.get("open_lo")), open_hi=bool(md.get("open_hi")),
                    where=_where(source), error=ConfigError)


def build(cls, data: Any, path: str = "", source: Optional[str] = None):
    """Build dataclass ``cls`` from a dict, validating keys, types and ranges.

    Args:
        cls: a config dataclass (e.g. :class:`~dvsland.config.schema.Config`).
        data: mapping of field name to value (missing fields take their default).
        path: dotted prefix of this section for error messages.
        source: file name for error messages.
    """
    if data is None:
        data = {}
    if dataclasses.is_dataclass(data) and isinstance(data, cls):
        data = dataclasses.asdict(data)
    if not isinstance(data, dict):
        raise ConfigError(f"{path or 'config'}{_where(source)}: expected a mapping, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = [k for k in data if k not in fields]
    if unknown:
        where = f"{path}." if path else ""
        raise ConfigError(f"unknown key '{where}{unknown[0]}'{_where(source)}; "
                          f"known keys here: {sorted(fields)}")
    types = _field_types(cls)
    kwargs = {}
    for name, f in fields.items():
        fpath = f"{path}.{name}" if path else name
        if name not in data:
            continue
        kwargs[name] = convert(data[name], types[name], fpath, source, owner=cls, name=name)
        _check_field(kwargs[name], f.metadata, fpath, source)
    obj = cls(**kwargs)
    return obj


def convert(value: Any, tp, path: str, source: Optional[str], owner=None, name: str = ""):
    """Convert a raw value to field type ``tp`` (dataclass, list of dataclasses, scalar)."""
    tp, optional = _strip_optional(tp)
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{path}{_where(source)}: must not be null")
    if dataclasses.is_dataclass(tp):
        return build(tp, value, path, source)
    if tp is list or typing.get_origin(tp) is list:
        item_tp = LIST_ITEM_TYPES.get((owner, name))
        if isinstance(value, str):  # "A,B,C" from the command line
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}{_where(source)}: expected a list, got {value!r}")
        if item_tp is None:
            return list(value)
        return [build(item_tp, v, f"{path}[{i}]", source) for i, v in enumerate(value)]
    return coerce_scalar(value, tp, path, source)


def check_config(cfg: Config, source: Optional[str] = None) -> Config:
    """Cross-field checks that no single field can make. Returns ``cfg``.

    Names of stage implementations (``estimator.name``, ``render.renderer``,
    ``controller.name``) are checked where the stages are built, against their registries
    (:func:`dvsland.stages.check_names`), so that loading a config imports no stage.
    """
    if cfg.dynamics.dry_mass_kg >= cfg.dynamics.mass_kg:
        raise ConfigError(f"dynamics.dry_mass_kg{_where(source)}: {cfg.dynamics.dry_mass_kg} must be "
                          f"below dynamics.mass_kg = {cfg.dynamics.mass_kg}")
    if cfg.controller.thrust_max_n is not None and cfg.controller.thrust_max_n < cfg.controller.thrust_min_n:
        raise ConfigError(f"controller.thrust_max_n{_where(source)}: {cfg.controller.thrust_max_n} must be "
                          f">= controller.thrust_min_n = {cfg.controller.thrust_min_n}")
    if cfg.render.min_altitude_m >= cfg.render.max_altitude_m:
        raise ConfigError(f"render.min_altitude_m{_where(source)}: must be below render.max_altitude_m")
    if not cfg.controller.settings:
        raise ConfigError(f"controller.settings{_where(source)}: needs at least one setting")
    names = [s.name for s in cfg.simulation.sites]
    if len(set(names)) != len(names):
        raise ConfigError(f"simulation.sites{_where(source)}: site names must be unique, got {names}")
    for i, s in enumerate(cfg.simulation.sites):
        if s.z0_m > cfg.render.max_altitude_m:
            raise ConfigError(f"simulation.sites[{i}].z0_m{_where(source)}: {s.z0_m} is above "
                              f"render.max_altitude_m = {cfg.render.max_altitude_m}")
    if not cfg.simulation.device.startswith(("cpu", "cuda", "mps")):
        raise ConfigError(f"simulation.device{_where(source)}: {cfg.simulation.device!r} is not a torch "
                          f"device; use 'cpu' or 'cuda[:N]'")
    return cfg
