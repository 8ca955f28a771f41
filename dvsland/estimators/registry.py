"""Estimators by name: built-ins, ``@register_estimator``, the ``dvsland.estimators``
entry-point group for third-party packages, and import paths ``package.module:Class`` or
``path/to/file.py:Class`` for a user's class that is neither registered nor installed.

Any of these may carry a short name, an alias: ``mine=pkg.mod:Class`` (or ``fast=dpr``). The
alias is what tables, JSON keys, figures and TensorBoard show (:func:`estimator_label`); the part
after ``=`` is what is built.
"""

from __future__ import annotations

import inspect
import re
from typing import Any, Callable, Dict, List, Optional, Tuple

from dvsland.checks import check_keys
from dvsland.plugins import PluginRegistry

_PLUGINS = PluginRegistry("estimator", "dvsland.estimators")
_REGISTRY = _PLUGINS.entries
_ENTRY_POINT_GROUP = _PLUGINS.group


def register_estimator(name: str) -> Callable:
    """Class decorator: make an estimator available under ``name``.

    Example::

        @register_estimator("mine")
        class Mine(DivergenceEstimator): ...
    """
    return _PLUGINS.register(name)


def refresh_entry_points() -> None:
    """Look for newly installed third-party estimators again."""
    _PLUGINS.refresh()


def available_estimators() -> List[str]:
    """Sorted names of every known estimator (built-in, registered, entry points)."""
    return _PLUGINS.names()


_ALIAS = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*")


def split_alias(name: str) -> Tuple[Optional[str], str]:
    """``"mine=pkg.mod:Class"`` -> ``("mine", "pkg.mod:Class")``; a name without an alias ->
    ``(None, name)``. Only an ``=`` before any ``[`` separates an alias (``cmax[window_ms=300]``
    has none).

    Raises:
        ValueError: an alias that is not a plain name (letters, digits, ``_ . -``; not starting
            with a digit), an empty estimator after ``=``, or an alias that is itself a known
            estimator other than the one it names.
    """
    if not isinstance(name, str) or "=" not in name.split("[", 1)[0]:
        return None, name
    alias, spec = (x.strip() for x in name.split("=", 1))
    if not _ALIAS.fullmatch(alias):
        raise ValueError(f"estimator {name!r}: the alias {alias!r} before '=' must be a plain name (letters, digits, "
                         f"'_', '.', '-'), e.g. 'mine=package.module:Class'")
    if not spec:
        raise ValueError(f"estimator {name!r}: nothing after '=': write ALIAS=NAME or ALIAS=package.module:Class")
    base = spec.split("[", 1)[0].strip()
    if alias != base and _PLUGINS.lookup(alias) is not None:
        raise ValueError(f"estimator {name!r}: the alias {alias!r} is already a registered estimator; choose another")
    return alias, spec


def estimator_label(name) -> str:
    """The name an estimator is shown by: its alias (``mine`` for ``mine=pkg.mod:Class``), else
    the name as given. Never raises (display only)."""
    try:
        alias, _ = split_alias(name)
    except ValueError:
        return str(name)
    return alias if alias is not None else str(name)


def _import_path(name: str):
    """The class named by ``package.module:Class`` or ``path/to/file.py:Class``.

    A module is imported from ``sys.path``, then from the current directory; a ``.py`` file is
    loaded from its path (once; its ``@register_estimator`` names are registered too).
    """
    import importlib
    import importlib.util
    import os
    import sys

    mod_name, _, attr = name.rpartition(":")
    if not mod_name or not attr:
        raise ValueError(f"estimator import path must look like 'package.module:Class' or 'file.py:Class', got {name!r}")
    try:
        if mod_name.endswith(".py"):
            path = os.path.abspath(mod_name)
            if not os.path.isfile(path):
                raise ValueError(f"estimator {name!r}: file {mod_name!r} not found")
            key = "dvsland_user_estimator_" + "".join(c if c.isalnum() else "_" for c in path)
            module = sys.modules.get(key)
            if module is None:
                spec = importlib.util.spec_from_file_location(key, path)
                module = importlib.util.module_from_spec(spec)
                sys.modules[key] = module
                try:
                    spec.loader.exec_module(module)
                except BaseException:
                    del sys.modules[key]
                    raise
        else:
            try:
                module = importlib.import_module(mod_name)
            except ModuleNotFoundError as exc:
                if exc.name != mod_name.split(".")[0] or os.getcwd() in sys.path:
                    raise
                sys.path.append(os.getcwd())
                module = importlib.import_module(mod_name)
    except ValueError:
        raise
    except Exception as exc:
        raise ValueError(f"estimator {name!r}: cannot import {mod_name!r}: {type(exc).__name__}: {exc}") from exc
    cls = getattr(module, attr, None)
    if cls is None or not callable(cls):
        raise ValueError(f"estimator {name!r}: {mod_name!r} has no class {attr!r}")
    return cls


def estimator_class(name: str) -> Callable:
    """The class (or factory) of estimator ``name``: a registered name, an entry point, or an
    import path ``package.module:Class`` / ``path/to/file.py:Class``, each optionally behind an
    alias ``ALIAS=...`` (:func:`split_alias`).

    Raises:
        ValueError: unknown name (the message lists the known ones) or an import path that fails.
    """
    _, name = split_alias(name)
    cls = _PLUGINS.lookup(name)
    if cls is not None:
        return cls
    if isinstance(name, str) and ":" in name:
        return _import_path(name)
    raise ValueError(f"unknown estimator {name!r}; known: {available_estimators()}, "
                     f"or an import path 'package.module:Class' (optionally named: 'alias=package.module:Class')")


def get_estimator(name: str, batch_size: int, sensor_size: Tuple[int, int], device: Any = "cpu",
                  **params):
    """Build estimator ``name`` (see :func:`estimator_class`) for B = ``batch_size`` descents.

    ``params`` must be keyword parameters of the estimator's constructor (a misspelt one is a
    ValueError listing the allowed ones), except ``dt_s``, ``seed`` and ``principal_point_px``, which are passed only
    where the constructor takes them. A constructor with ``**kwargs`` gets everything.

    Raises:
        ValueError: unknown name (the message lists the known ones), or unknown parameters.
    """
    if not isinstance(name, str):
        raise ValueError(f"unknown estimator {name!r}; known estimators: {available_estimators()}")
    cls = estimator_class(name)
    accepted, takes_any = _parameters(cls)
    if not takes_any:
        params = {k: v for k, v in params.items() if k in accepted or k not in CONTEXT_PARAMS}
        check_keys(f"estimator {name!r}", params, accepted)
    return cls(batch_size=batch_size, sensor_size=sensor_size, device=device, **params)


#: offered to every estimator by the factory; passed only to those whose constructor takes them
CONTEXT_PARAMS = ("dt_s", "seed", "principal_point_px")


def _parameters(cls) -> Tuple[List[str], bool]:
    """(keyword parameters of ``cls`` besides batch_size, sensor_size and device; whether it takes
    ``**kwargs``)."""
    try:
        sig = inspect.signature(cls)
    except (TypeError, ValueError):  # not introspectable: pass everything
        return [], True
    names = [p.name for p in sig.parameters.values()
             if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
             and p.name not in ("self", "batch_size", "sensor_size", "device")]
    return names, any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())


def check_estimator_names(names, param: str = "--estimators") -> None:
    """ValueError naming ``param`` for names no registry knows (an import path ``pkg.mod:Class``, an
    alias ``A=...`` and options ``name[k=v]`` are read by their name)."""
    known = available_estimators()
    unknown = [n for n in (names or ()) if ":" not in n and split_alias(n)[1].split("[", 1)[0].strip() not in known]
    if unknown:
        raise ValueError(f"{param}: unknown estimator(s) {unknown}; known: {known}")
