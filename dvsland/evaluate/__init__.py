"""Open-loop evaluation of divergence estimators (and synthetic event streams with known D)."""

from .synthetic import blob_layout, zoom_blob_events

__all__ = ["blob_layout", "zoom_blob_events"]
