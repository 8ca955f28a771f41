"""Controllers by name: built-ins, ``@register_controller``, and the ``dvsland.controllers``
entry-point group for third-party packages.

A registered controller is a class (or factory) with ``from_params(params, **options)`` where
``params`` is the loop's :class:`~dvsland.control.DescentParams` and ``options`` the law's own
settings from the config (``controller.<name>`` for built-ins, ``controller.params`` otherwise).
"""

from __future__ import annotations

from typing import Callable, List

from dvsland.plugins import PluginRegistry

_PLUGINS = PluginRegistry("controller", "dvsland.controllers")
_REGISTRY = _PLUGINS.entries
_ENTRY_POINT_GROUP = _PLUGINS.group


def _check_controller(name: str, cls) -> None:
    if not hasattr(cls, "from_params"):
        raise TypeError(f"controller {name!r}: {cls!r} needs a from_params(params, **options) classmethod")
    try:
        cls.controller_name = name  # what results.json reports as the run's controller
    except (AttributeError, TypeError):
        pass


def register_controller(name: str) -> Callable:
    """Class decorator: make a controller available under ``name``.

    Example::

        @register_controller("mine")
        class Mine(Controller):
            @classmethod
            def from_params(cls, p, **options): ...
    """
    return _PLUGINS.register(name, _check_controller)


def refresh_entry_points() -> None:
    """Look for newly installed third-party controllers again."""
    _PLUGINS.refresh()


def available_controllers() -> List[str]:
    """Sorted names of every known controller (built-in, registered, entry points)."""
    return _PLUGINS.names()


def controller_class(name: str):
    """The registered class (or factory) of controller ``name``.

    Raises:
        ValueError: unknown name (the message lists the known ones).
    """
    cls = _PLUGINS.lookup(name)
    if cls is None:
        raise ValueError(f"unknown controller {name!r}; known controllers: {available_controllers()}")
    return cls


def get_controller(name: str, params, **options):
    """Build controller ``name`` for the descents described by ``params`` (a DescentParams)."""
    return controller_class(name).from_params(params, **options)
