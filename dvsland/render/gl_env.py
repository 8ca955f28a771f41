"""The one place that prepares the process for headless OpenGL (pyrender through EGL).

Import this module BEFORE ``pyrender`` or ``OpenGL`` is imported anywhere: PyOpenGL picks its
platform once, at first import, from ``PYOPENGL_PLATFORM``. Importing it:

- sets ``PYOPENGL_PLATFORM=egl`` (unless the user chose a platform already), and
  ``EGL_PLATFORM=surfaceless`` when there is no X/Wayland display, so Mesa renders off-screen
  without a window system;
- restores ``np.infty`` (removed in numpy 2; pyrender 0.1.45 still uses it).

:func:`egl_available` answers, once per process, whether a tiny off-screen pyrender context can
actually be made here; tests use it to skip with a clear reason.
"""

from __future__ import annotations

import os
import sys

import numpy as np

__all__ = ["egl_available", "egl_unavailable_reason", "import_pyrender", "delete_offscreen"]

if "OpenGL" in sys.modules and os.environ.get("PYOPENGL_PLATFORM") not in (None, "egl"):
    # Someone imported PyOpenGL first with another platform: leave it, it is their choice.
    pass
else:
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
    os.environ.setdefault("EGL_PLATFORM", "surfaceless")

if not hasattr(np, "infty"):  # numpy 2 removed the alias; pyrender 0.1.45 needs it
    np.infty = np.inf  # type: ignore[attr-defined]

_EGL_STATE: dict = {}


def import_pyrender():
    """Import and return the ``pyrender`` module with the environment above in place."""
    import pyrender  # noqa: WPS433 (import after the environment is set, on purpose)

    return pyrender


def egl_available() -> bool:
    """Whether a headless OpenGL context can be made (a 4x4 pyrender OffscreenRenderer).

    The answer is computed once per process and cached; the failure reason is kept for
    :func:`egl_unavailable_reason`.
    """
    if "ok" not in _EGL_STATE:
        try:
            pyrender = import_pyrender()
            r = pyrender.OffscreenRenderer(4, 4)
            delete_offscreen(r)
            _EGL_STATE["ok"] = True
            _EGL_STATE["reason"] = ""
        except Exception as exc:  # any failure (missing libEGL, no driver, ...) means "no"
            _EGL_STATE["ok"] = False
            _EGL_STATE["reason"] = f"{type(exc).__name__}: {exc}"
    return bool(_EGL_STATE["ok"])


def delete_offscreen(osr) -> None:
    """Free a pyrender ``OffscreenRenderer`` without ``eglTerminate``.

    pyrender's ``OffscreenRenderer.delete`` terminates the EGL display, which is shared by every
    context of the process: any other live renderer then fails with EGL_BAD_DISPLAY. This frees
    the GL objects and destroys only this context.
    """
    platform = getattr(osr, "_platform", None)
    if platform is None:
        return
    try:
        platform.make_current()
        if osr._renderer is not None:
            osr._renderer.delete()
    finally:
        display = getattr(platform, "_egl_display", None)
        context = getattr(platform, "_egl_context", None)
        if display is not None and context is not None:
            from OpenGL.EGL import EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglMakeCurrent

            eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
            eglDestroyContext(display, context)
            platform._egl_context = None
            platform._egl_display = None  # else the platform's __del__ calls eglTerminate
        elif hasattr(platform, "delete_context") and display is None:
            platform.delete_context()  # not EGL (osmesa / pyglet): its own clean-up
        osr._renderer = None
        osr._platform = None


def egl_unavailable_reason() -> str:
    """Why :func:`egl_available` said no ('' when it said yes)."""
    egl_available()
    return "no headless EGL/OpenGL context (pyrender): " + _EGL_STATE["reason"] if not _EGL_STATE["ok"] else ""
