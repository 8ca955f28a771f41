"""dvsland: event-camera-guided spacecraft landing with time-to-contact.

The loop, one subpackage per stage: :mod:`dvsland.terrain` -> :mod:`dvsland.render` ->
:mod:`dvsland.events` -> :mod:`dvsland.estimators` -> :mod:`dvsland.control` ->
:mod:`dvsland.dynamics`, driven by :mod:`dvsland.sim`; configured by :mod:`dvsland.config`.
"""

from ._version import __version__

__all__ = ["__version__", "simulate"]


def __getattr__(name):  # lazy: importing dvsland stays cheap
    if name == "simulate":
        from dvsland.sim import simulate

        return simulate
    raise AttributeError(f"module 'dvsland' has no attribute {name!r}")
