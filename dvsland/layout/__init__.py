"""The batch layout: which descent each batch element is (site, controller setting, seed, dispersed
scene and sensor values), expanded from a config.

It sits just above ``dvsland.config`` and below every stage, so the renderer (scene labels), the
stages layer and the loop all read the same layout without importing upwards.

Public names: :class:`BatchLayout`, :func:`build_layout`, :func:`expand_seeds`, :func:`setting_label`,
:func:`scene_label`.
"""

from .batch import BatchLayout, build_layout, expand_seeds, scene_label, setting_label

__all__ = ["BatchLayout", "build_layout", "expand_seeds", "scene_label", "setting_label"]
