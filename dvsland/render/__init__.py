"""Renderers of the landing sites (docs/render.md, docs/render_reference.md).

Public names: :class:`Renderer` (interface), :func:`get_renderer`, :func:`available_renderers`,
:func:`register_renderer`, :class:`FastRenderer`.

``"fast"``: batched torch renderer over prepared levels of detail (:mod:`dvsland.render.fast`).
``"textures"``: procedural scale-free ground that is none of the terrains (:mod:`dvsland.render.textures`).
``"pyrender"``: the 3-D reference (:mod:`dvsland.render.pyrender_ref`), imported lazily because
importing pyrender sets OpenGL environment variables.
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Sequence

from dvsland.config import CameraConfig, RenderConfig

from .base import Renderer
from .fast import FastRenderer
from .textures import TextureRenderer

_REGISTRY: Dict[str, Callable] = {"fast": FastRenderer, "textures": TextureRenderer}
_LAZY = {"pyrender": ("dvsland.render.pyrender_ref", "PyrenderRenderer")}


def register_renderer(name: str, cls: Callable) -> None:
    """Register a renderer class (same constructor signature as :class:`Renderer`)."""
    _REGISTRY[name] = cls


def available_renderers() -> list:
    """Names accepted by :func:`get_renderer`."""
    return sorted(set(_REGISTRY) | set(_LAZY))


def get_renderer(name: str, site_names: Sequence[str], camera: Optional[CameraConfig] = None,
                 render: Optional[RenderConfig] = None, device="cpu", **kwargs) -> Renderer:
    """Build renderer ``name`` ("fast" or "pyrender") for ``site_names``.

    Extra keyword arguments go to the renderer class (e.g. ``level_size`` for "fast").
    """
    if name not in _REGISTRY and name in _LAZY:
        import importlib

        mod, attr = _LAZY[name]
        _REGISTRY[name] = getattr(importlib.import_module(mod), attr)
    if name not in _REGISTRY:
        raise ValueError(f"unknown renderer {name!r}: expected one of {available_renderers()}")
    camera = camera if camera is not None else CameraConfig()
    return _REGISTRY[name](site_names, camera, render, device=device, **kwargs)


__all__ = ["Renderer", "FastRenderer", "TextureRenderer", "get_renderer", "available_renderers", "register_renderer"]
