"""Datasets of several cameras in one training set: every folder's events on the model's canvas.

The model's input is the reference canvas of :mod:`dvsland.estimators.learned.inputs`: the first
``--data`` folder's sensor, centred on the principal point, at its pixel angle. Each folder's
events are moved there as the estimator moves a camera's events at run time
(:func:`~dvsland.estimators.learned.inputs.to_reference`: about the folder's recorded principal
point, scaled by f_ref / f), events off the canvas are dropped, and a camera with finer pixels is
thinned to the reference's event density (each event kept with probability (f_ref / f)^2, when
read; the estimator instead keeps every event and scales the count it gives the model by the same
factor). A folder of the reference camera is left as it is, bit for bit.
"""

from __future__ import annotations

from typing import List

import torch

from dvsland.config.schema import DEFAULT_FOV_DEG, focal_length_px
from dvsland.data import Windows, concat_windows, load_manifest_info, load_windows
from dvsland.estimators.learned.inputs import InputSpec, camera_map, to_reference


def reference_camera(infos: List[dict]) -> dict:
    """{"sensor_size": (W, H), "focal_px": float or None} of the first folder's manifest info."""
    return {"sensor_size": tuple(int(v) for v in infos[0]["sensor_size"]), "focal_px": infos[0].get("focal_px")}


def folder_map(spec: InputSpec, info: dict):
    """The :class:`~dvsland.estimators.learned.inputs.CameraMap` of a folder (its manifest info)."""
    focal = info.get("focal_px")
    if focal is None and tuple(info["sensor_size"]) == spec.sensor_size:
        focal = spec.reference_focal_px
    elif focal is None:
        focal = focal_length_px(info["sensor_size"][0], DEFAULT_FOV_DEG)  # as the older builds flew
    return camera_map(spec, info["sensor_size"], info.get("principal_point_px"), focal)


def on_canvas(w: Windows, spec: InputSpec, cmap) -> Windows:
    """``w`` with its events on the reference canvas (int16 reference pixels), those off it dropped."""
    if cmap.identity:
        return w
    xi, yi, keep = to_reference(w.x, w.y, cmap, spec)
    n = w.offset[1:] - w.offset[:-1]
    owner = torch.repeat_interleave(torch.arange(len(n)), n)
    counts = torch.bincount(owner[keep], minlength=len(n))
    offset = torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(counts, 0)])
    return w._replace(x=xi[keep].to(torch.int16), y=yi[keep].to(torch.int16), frac=w.frac[keep], p=w.p[keep],
                      offset=offset, sensor_size=tuple(spec.sensor_size))


def load_canvas_split(dirs, split: str, spec: InputSpec, infos: List[dict], seed: int = 0) -> Windows:
    """The ``split`` of every folder in ``dirs`` on ``spec``'s canvas, in one Windows (empty
    splits of some folders are skipped; ValueError when all are empty)."""
    parts, errors = [], []
    for d, info in zip(dirs, infos):
        cmap = folder_map(spec, info)
        try:
            w = load_windows(d, split, keep_share=min(1.0, cmap.count_scale), seed=seed)
        except ValueError as exc:
            if "no sample" not in str(exc):
                raise
            errors.append(str(exc))  # this folder has no sample in the split
            continue
        parts.append(on_canvas(w, spec, cmap))
    if not parts:
        raise ValueError("; ".join(errors))
    return concat_windows(parts, param="--data")
