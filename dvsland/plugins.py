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
