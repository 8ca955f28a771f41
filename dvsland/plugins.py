"""One registry mechanism for every extension point (estimators, controllers): built-ins and
``@register_...`` decorators fill a name -> class table, and third-party packages add theirs
through an entry-point group, loaded once on first use (a broken plug-in warns, never breaks
dvsland). ``dvsland.estimators.registry`` and ``dvsland.control.registry`` are thin fronts.
"""

from __future__ import annotations

import warnings
from importlib import metadata
from typing import Callable, Dict, List, Optional


class PluginRegistry:
    """Name -> class (or factory) table of one kind of stage, with an entry-point group.

    Args:
        kind: what the entries are, for messages (``"estimator"``, ``"controller"``).
        group: entry-point group third-party packages declare (``"dvsland.estimators"``).
    """

    def __init__(self, kind: str, group: str):
        self.kind, self.group = kind, group
        self.entries: Dict[str, Callable] = {}
        self._entry_points_loaded = False

    def register(self, name: str, on_register: Optional[Callable[[str, Callable], None]] = None) -> Callable:
        """Class decorator putting the class under ``name``; ``on_register(name, cls)`` may check
        or annotate it first (raising keeps it out). A non-string or empty name is a ValueError."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"{self.kind} name must be a non-empty string, got {name!r}")

        def deco(cls):
            if on_register is not None:
                on_register(name, cls)
            self.entries[name] = cls
            return cls

        return deco

    def load_entry_points(self) -> None:
        """Load the group's entry points once (names already registered win)."""
        if self._entry_points_loaded:
            return
        self._entry_points_loaded = True
        try:
            eps = metadata.entry_points(group=self.group)
        except TypeError:  # Python < 3.10 API
            eps = metadata.entry_points().get(self.group, [])
        for ep in eps:
            if ep.name in self.entries:
                continue
            try:
                obj = ep.load()
            except Exception as exc:  # a broken plug-in must not break dvsland
                warnings.warn(f"{self.kind} entry point {ep.name!r} ({ep.value}) failed to load: {exc}")
                continue
            self.entries.setdefault(ep.name, obj)

    def refresh(self) -> None:
        """Look for newly installed third-party entries again."""
        self._entry_points_loaded = False
        self.load_entry_points()

    def names(self) -> List[str]:
        """Sorted names of every known entry (built-in, registered, entry points)."""
        self.load_entry_points()
        return sorted(self.entries)

    def lookup(self, name: str) -> Optional[Callable]:
        """The entry registered as ``name``, or None."""
        self.load_entry_points()
        return self.entries.get(name)


# ------------------------------------------------------------------ the contract at the boundary
class PluginError(ValueError):
    """A stage plug-in (estimator, controller, filter) broke its contract or raised.

    Attributes:
        plugin: the plug-in's name as configured (``estimator.name``, ``controller.name``).
        call: the call that failed (``__init__``, ``reset``, ``update``, ``confidence``, ``__call__``).
        plugin_traceback: the plug-in's own traceback text when it raised, else "".
    """

    def __init__(self, plugin: str, call: str, message: str, plugin_traceback: str = ""):
        self.plugin, self.call, self.plugin_traceback = str(plugin), str(call), plugin_traceback
        super().__init__(f"plug-in {self.plugin!r}, call {self.call}: {message}")


def call_plugin(plugin: str, call: str, fn: Callable, *args, **kwargs):
    """``fn(*args, **kwargs)``; anything it raises (``SystemExit``, ``RecursionError`` and
    ``MemoryError`` included; not Ctrl-C) becomes one :class:`PluginError` naming the plug-in and the
    call, with the plug-in's traceback kept in ``plugin_traceback``."""
    import traceback

    try:
        return fn(*args, **kwargs)
    except PluginError:
        raise
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - every failure of user code, one error
        raise PluginError(plugin, call, f"raised {type(exc).__name__}: {_short(exc)}",
                          traceback.format_exc(limit=-20)) from None


def _short(exc: BaseException, limit: int = 300) -> str:
    text = str(exc)
    return text if len(text) <= limit else text[:limit] + " ..."


def check_batch_tensor(value, batch_size: int, device, plugin: str, call: str, allow_none: bool = False,
                       detach: bool = True):
    """The (B,) floating tensor a plug-in returned, detached, or a :class:`PluginError` saying what
    was expected and what came back (type, shape, dtype, device).

    Args:
        value: what the plug-in returned.
        batch_size: B.
        device: the loop's torch device (a CPU result for a CUDA loop and the reverse are errors).
        plugin, call: for the message.
        allow_none: None is accepted (returned as None), e.g. for ``confidence()``.
        detach: return it detached from any autograd graph (the default); False keeps the graph
            (the loop's differentiable mode).
    """
    import torch

    if value is None and allow_none:
        return None
    want = f"a torch.Tensor of shape ({batch_size},) with a floating dtype on {torch.device(device)}"
    if not isinstance(value, torch.Tensor):
        raise PluginError(plugin, call, f"expected {want}, got {type(value).__name__} {_short(repr(value), 80)}")
    got = f"shape {tuple(value.shape)}, dtype {value.dtype}, device {value.device}"
    if tuple(value.shape) != (batch_size,):
        raise PluginError(plugin, call, f"expected {want}, got {got}")
    if not value.dtype.is_floating_point:  # bool, int and complex are not divergences
        raise PluginError(plugin, call, f"expected {want}, got {got}")
    dev = torch.device(device)
    if value.device.type != dev.type or None not in (value.device.index, dev.index) and value.device.index != dev.index:
        raise PluginError(plugin, call, f"expected {want}, got {got}")
    return value.detach() if detach else value
