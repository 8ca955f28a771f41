"""Datasets of a camera whose principal point is off the sensor centre, recorded as a crop.

The renderers always put the landing point (the focus of expansion of the nadir descent) at the
sensor centre. A sensor whose principal point ``(cx, cy)`` (``camera.principal_point_px``) lies
elsewhere sees what a larger, centred sensor of the same pixels and lens sees in a window: the
W x H window whose pixel ``(cx, cy)`` falls on the larger sensor's centre. So the build renders and
emulates a centred sensor of ``(W + 2 |dx|) x (H + 2 |dy|)`` pixels (``dx = cx - (W - 1) / 2``,
likewise dy; same pitch and focal length, so the same pixel angle) and keeps the events of that
window, shifted to its own pixel coordinates. The emulator is per pixel, so the kept events are
exactly those of the off-centre sensor.
"""

from __future__ import annotations

import copy
import math
from typing import NamedTuple, Optional, Tuple

from dvsland.config.schema import focal_length_px
from dvsland.estimators.base import resolve_principal_point


class Crop(NamedTuple):
    """The window ``x0 <= x < x0 + width``, ``y0 <= y < y0 + height`` of the rendered sensor, px."""

    x0: int
    y0: int
    width: int
    height: int


def focal_px(camera) -> float:
    """Focal length of ``camera`` (a :class:`dvsland.config.CameraConfig`) in pixels:
    (W / 2) / tan(fov_deg / 2)."""
    return focal_length_px(camera.width_px, camera.fov_deg)


def principal_point(camera) -> Tuple[float, float]:
    """(cx, cy) px of ``camera``: ``principal_point_px`` or the sensor centre."""
    return resolve_principal_point(camera.principal_point_px, (camera.width_px, camera.height_px))


def recording_camera(camera) -> Tuple[object, Optional[Crop]]:
    """(the camera to render, the crop of its events) for ``camera``; ``(camera, None)`` when its
    principal point is the sensor centre.

    Raises:
        ValueError: naming ``camera.principal_point_px`` when its offset from the centre is not a
            whole number of pixels (the crop shifts by whole pixels).
    """
    W, H = int(camera.width_px), int(camera.height_px)
    cx, cy = principal_point(camera)
    dx, dy = cx - (W - 1) / 2.0, cy - (H - 1) / 2.0
    if dx == 0 and dy == 0:
        return camera, None
    if dx != round(dx) or dy != round(dy):
        raise ValueError(f"camera.principal_point_px: [{cx}, {cy}] must be a whole number of pixels from the sensor "
                         f"centre [{(W - 1) / 2}, {(H - 1) / 2}] for a recorded dataset (the build crops a larger "
                         f"centred sensor)")
    ax, ay = abs(int(round(dx))), abs(int(round(dy)))
    cam = copy.deepcopy(camera)
    cam.sensor, cam.principal_point_px = "custom", None
    cam.width_px, cam.height_px = W + 2 * ax, H + 2 * ay
    # the same angle per pixel: widen the field of view with the width (tan grows linearly)
    cam.fov_deg = math.degrees(2.0 * math.atan(math.tan(math.radians(camera.fov_deg) / 2.0) * cam.width_px / W))
    if cam.pixel_pitch_um is not None and cam.focal_length_mm is not None:
        cam.pixel_pitch_um, cam.focal_length_mm = None, None  # fov_deg says it all (no lens/fov contradiction)
    return cam, Crop(ax - int(round(dx)), ay - int(round(dy)), W, H)
