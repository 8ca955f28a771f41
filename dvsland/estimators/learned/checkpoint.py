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
ValueError naming ``estimator.learned.checkpoint`` (or the option that named the file) and what is
wrong: the one checkpoint validation of :mod:`dvsland.estimators.state_dict_check`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Tuple

import torch

from ..state_dict_check import (check_finite_numbers, check_finite_tensors, check_state_dict, read_checkpoint_file,
                                short_path)
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


def read_checkpoint(path, param: str = PARAM) -> dict:
    """The raw dict of a checkpoint file, its format and fields checked and every number of its
    description finite (:mod:`~dvsland.estimators.state_dict_check`, the one checkpoint validation).

    Raises:
        ValueError: starting with ``param`` (default :data:`PARAM`; ``"--resume"``, ``"--init"`` for
            ``dvsland train``) and the file: missing, unreadable, of another kind or version, or damaged.
    """
    hint = "train one with `dvsland train CONFIG --model cnn --data DIR --out PATH`"
    ck = read_checkpoint_file(path, param, "dvsland learned checkpoint", hint)
    where = f"{param}: {short_path(path)}"
    if ck.get("format") != FORMAT:
        raise ValueError(f"{where} is not a dvsland learned checkpoint (format {ck.get('format')!r}, expected "
                         f"{FORMAT!r}; {hint})")
    if ck.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{where} has format_version {ck.get('format_version')!r}; this dvsland reads "
                         f"{FORMAT_VERSION}")
    missing = [k for k in ("model", "input", "state_dict") if k not in ck]
    if missing:
        raise ValueError(f"{where} lacks the fields {missing}")
    for field in ("model", "input"):
        check_finite_numbers(ck[field], where, field)
    check_finite_tensors(ck["state_dict"], where)
    return ck


def load_checkpoint(path, sensor_size=None, param: str = PARAM) -> Tuple[torch.nn.Module, InputSpec, dict]:
    """(network in eval mode on CPU, its InputSpec, the whole checkpoint dict) of ``path``, every
    part checked (:func:`read_checkpoint`, then its weights against the network it describes).

    ``sensor_size`` (W, H): when given, must equal the checkpoint's (ValueError otherwise). The
    ``learned`` estimator passes none: it resamples any camera onto the checkpoint's canvas.
    ``param``: what the messages name (default :data:`PARAM`).
    """
    ck = read_checkpoint(path, param)
    where = f"{param}: {short_path(path)}"
    m, i = ck["model"], ck["input"]
    try:
        spec = check_input_spec(InputSpec(tuple(i["sensor_size"]), i["n_bins"], i["pool_px"], i["coord_scale_px"],
                                          i.get("n_windows", 1), i.get("focal_px")))
        net, _ = build_model(m["name"] if ":" not in m.get("class", "") or m["name"] in ("cnn", "spiking")
                             else m["class"], dict(m["settings"]))
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: its model or input description does not make a network "
                         f"({type(exc).__name__}: {exc})") from None
    if sensor_size is not None and tuple(int(v) for v in sensor_size) != spec.sensor_size:
        raise ValueError(f"{where} was trained for a {spec.sensor_size[0]} x {spec.sensor_size[1]} sensor, "
                         f"the camera is {sensor_size[0]} x {sensor_size[1]} (camera.sensor / width_px, height_px)")
    check_state_dict(ck["state_dict"], net, where)
    net.load_state_dict(ck["state_dict"])
    return net.eval(), spec, ck
