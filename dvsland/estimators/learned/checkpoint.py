"""Checkpoints of the training recipe (``dvsland train --model ...``): write, read and check.

A checkpoint is a ``torch.save`` dict:

- ``format`` = ``"dvsland-learned"``, ``format_version`` = 1;
- ``model``: ``{"name": "cnn" | "spiking" | "pkg.mod:Class", "class": import path, "settings": kwargs}``;
- ``input``: the :class:`~.inputs.InputSpec` fields (``sensor_size``, ``n_bins``, ``pool_px``, ``coord_scale_px``,
  ``n_windows``, ``focal_px``: the reference canvas; a checkpoint without ``focal_px`` has a 60 degree field of view);
- ``state_dict``: the weights;
- ``data``: provenance (dataset folder, its config hash, sensor, samples per split);
- ``history``: one dict per epoch (losses, validation errors, calibration);
- ``train``: the recipe's settings; for resuming also ``epoch``, ``optimizer``, ``best_val``, ``bad_epochs``.

:func:`load_checkpoint` reads only tensors and plain values (``weights_only``) and raises
ValueError naming ``estimator.learned.checkpoint`` and what is wrong.
"""

from __future__ import annotations

from pathlib import Path
from typing import Tuple

import torch

from ..state_dict_check import check_state_dict
from .inputs import InputSpec, check_input_spec
from .models import build_model

FORMAT, FORMAT_VERSION = "dvsland-learned", 1
PARAM = "estimator.learned.checkpoint"


def save_checkpoint(path, blob: dict) -> Path:
    """Write ``blob`` (the fields above) atomically (a temporary file renamed). Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": FORMAT, "format_version": FORMAT_VERSION, **blob}, tmp)
    tmp.replace(path)
    return path


def read_checkpoint(path) -> dict:
    """The raw dict of a checkpoint file; ValueError naming :data:`PARAM` if missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{PARAM}: file not found: {path} (train one with `dvsland train CONFIG --model cnn "
                         f"--data DIR --out PATH`)")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # untrusted bytes: the unpickler raises many kinds
        raise ValueError(f"{PARAM}: {path} is not a readable dvsland learned checkpoint (corrupt, truncated or "
                         f"another kind of file)") from None
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        fmt = ck.get("format") if isinstance(ck, dict) else type(ck).__name__
        raise ValueError(f"{PARAM}: {path} is not a dvsland learned checkpoint (format {fmt!r}, expected {FORMAT!r})")
    if ck.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{PARAM}: {path} has format_version {ck.get('format_version')!r}; this dvsland reads "
                         f"{FORMAT_VERSION}")
    missing = [k for k in ("model", "input", "state_dict") if k not in ck]
    if missing:
        raise ValueError(f"{PARAM}: {path} lacks the fields {missing}")
    return ck


def load_checkpoint(path, sensor_size=None) -> Tuple[torch.nn.Module, InputSpec, dict]:
    """(network in eval mode on CPU, its InputSpec, the whole checkpoint dict) of ``path``.

    ``sensor_size`` (W, H): when given, must equal the checkpoint's (ValueError otherwise). The
    ``learned`` estimator passes none: it resamples any camera onto the checkpoint's canvas.
    """
    ck = read_checkpoint(path)
    m, i = ck["model"], ck["input"]
    try:
        spec = check_input_spec(InputSpec(tuple(i["sensor_size"]), i["n_bins"], i["pool_px"], i["coord_scale_px"],
                                          i.get("n_windows", 1), i.get("focal_px")))
        net, _ = build_model(m["name"] if ":" not in m.get("class", "") or m["name"] in ("cnn", "spiking")
                             else m["class"], dict(m["settings"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{PARAM}: {path}: its model or input description does not make a network "
                         f"({type(exc).__name__}: {exc})") from None
    if sensor_size is not None and tuple(int(v) for v in sensor_size) != spec.sensor_size:
        raise ValueError(f"{PARAM}: {path} was trained for a {spec.sensor_size[0]} x {spec.sensor_size[1]} sensor, "
                         f"the camera is {sensor_size[0]} x {sensor_size[1]} (camera.sensor / width_px, height_px)")
    check_state_dict(ck["state_dict"], net, f"{PARAM}: {path}")
    net.load_state_dict(ck["state_dict"])
    return net.eval(), spec, ck
