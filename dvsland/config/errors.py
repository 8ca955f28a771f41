"""The config error, at the bottom of :mod:`dvsland.config` so that every config module (the
schema's sensor presets, the validation, the loader) raises the same class without importing
each other."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration value, key or file is not acceptable."""


__all__ = ["ConfigError"]
