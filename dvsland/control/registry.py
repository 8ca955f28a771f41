"""Controllers by name: built-ins, ``@register_controller``, and the ``dvsland.controllers``
entry-point group for third-party packages.

A registered controller is a class (or factory) with ``from_params(params, **options)`` where
``params`` is the loop's :class:`~dvsland.control.DescentParams` and ``options`` the law's own
settings from the config (``controller.<name>`` for built-ins, ``controller.params`` otherwise).
"""

from __future__ import annotations

from importlib import metadata
from typing import Callable, Dict, List

_REGISTRY: Dict[str, Callable] = {}
_ENTRY_POINT_GROUP = "dvsland.controllers"
_entry_points_loaded = False


def register_controller(name: str) -> Callable:
    """Class decorator: make a controller available under ``name``.

    Example::

        @register_controller("mine")
        class Mine(Controller):
            @classmethod
            def from_params(cls, p, **options): ...
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"controller name must be a non-empty string, got {name!r}")

    def deco(cls):
        if not hasattr(cls, "from_params"):
            raise TypeError(f"controller {name!r}: {cls!r} needs a from_params(params, **options) classmethod")
        _REGISTRY[name] = cls
        try:
            cls.controller_name = name  # what results.json reports as the run's controller
        except (AttributeError, TypeError):
            pass
        return cls

    return deco


def _load_entry_points() -> None:
    global _entry_points_loaded
    if _entry_points_loaded:
        return
    _entry_points_loaded = True
    try:
        eps = metadata.entry_points(group=_ENTRY_POINT_GROUP)
    except TypeError:  # Python < 3.10 API
        eps = metadata.entry_points().get(_ENTRY_POINT_GROUP, [])
    for ep in eps:
        if ep.name in _REGISTRY:
            continue
        try:
            obj = ep.load()
        except Exception as exc:  # a broken plug-in must not break dvsland
            import warnings

            warnings.warn(f"controller entry point {ep.name!r} ({ep.value}) failed to load: {exc}")
            continue
        _REGISTRY.setdefault(ep.name, obj)


def refresh_entry_points() -> None:
    """Look for newly installed third-party controllers again."""
    global _entry_points_loaded
    _entry_points_loaded = False
    _load_entry_points()


def available_controllers() -> List[str]:
    """Sorted names of every known controller (built-in, registered, entry points)."""
    _load_entry_points()
    return sorted(_REGISTRY)


def controller_class(name: str):
    """The registered class (or factory) of controller ``name``.

    Raises:
        ValueError: unknown name (the message lists the known ones).
    """
    _load_entry_points()
    if name not in _REGISTRY:
        raise ValueError(f"unknown controller {name!r}; known controllers: {available_controllers()}")
    return _REGISTRY[name]


def get_controller(name: str, params, **options):
    """Build controller ``name`` for the descents described by ``params`` (a DescentParams)."""
    return controller_class(name).from_params(params, **options)
