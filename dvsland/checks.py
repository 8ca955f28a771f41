"""Argument checks with messages that name the parameter and what is allowed (in the spirit of
kornia's ``KORNIA_CHECK``). Used by the config validation, the site specs and the stage classes,
so that one range is written once (in the config schema) and read everywhere. Also the content
hash that names a checkpoint file in every report (:func:`file_sha256`).

Example::

    check_range("radius_px", radius_px, 0.5, 64.0)   # ValueError: radius_px: 0.1 is out of range; allowed [0.5, 64.0]
    check_keys("estimator 'dpr'", params, ["n_max", "radius_px"])
    check_fields(DPRConfig, n_max=n_max, radius_px=radius_px)   # the ranges of the schema's fields
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from pathlib import Path
from typing import Any, Dict, Iterable, List, Optional, Tuple, Type


def range_text(lo: Optional[float], hi: Optional[float], open_lo: bool = False, open_hi: bool = False) -> str:
    """``[lo, hi]`` / ``(lo, hi]`` ...; a missing bound is written as -inf / inf."""
    lo = -math.inf if lo is None else lo
    hi = math.inf if hi is None else hi
    return f"{'(' if open_lo else '['}{lo}, {hi}{')' if open_hi else ']'}"


def in_range(value: Any, lo: Optional[float] = None, hi: Optional[float] = None, open_lo: bool = False,
             open_hi: bool = False) -> bool:
    """True if ``value`` is a number, not NaN, within the bounds (inf only where a bound is infinite)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        try:
            value = float(value)
        except (TypeError, ValueError):
            return False
    f = float(value)
    lo_f = -math.inf if lo is None else float(lo)
    hi_f = math.inf if hi is None else float(hi)
    if math.isnan(f) or (math.isinf(f) and not (math.isinf(lo_f) or math.isinf(hi_f))):
        return False
    ok_lo = f > lo_f if open_lo else f >= lo_f
    ok_hi = f < hi_f if open_hi else f <= hi_f
    return ok_lo and ok_hi


def check_range(name: str, value: Any, lo: Optional[float] = None, hi: Optional[float] = None, *,
                open_lo: bool = False, open_hi: bool = False, where: str = "", error: Type[Exception] = ValueError):
    """Return ``value`` if it lies in [lo, hi] (open ends as asked); else raise ``error`` with
    ``"<name><where>: <value> is out of range; allowed [lo, hi]"``."""
    if not in_range(value, lo, hi, open_lo, open_hi):
        raise error(f"{name}{where}: {value!r} is out of range; allowed {range_text(lo, hi, open_lo, open_hi)}")
    return value


def check_choice(name: str, value: Any, choices: Iterable, *, where: str = "", error: Type[Exception] = ValueError):
    """Return ``value`` if it is one of ``choices``; else raise ``error`` listing them."""
    choices = list(choices)
    if value not in choices:
        raise error(f"{name}{where}: {value!r} is not allowed; choose one of {choices}")
    return value


def check_keys(what: str, given: Iterable[str], allowed: Iterable[str], *, error: Type[Exception] = ValueError) -> None:
    """Raise ``error`` naming the unknown keys of ``given`` and listing ``allowed`` (sorted)."""
    allowed = sorted(set(allowed))
    unknown = sorted(k for k in given if k not in allowed)
    if unknown:
        raise error(f"{what}: unknown key{'s' if len(unknown) > 1 else ''} {unknown}; allowed: {allowed}")


def field_bounds(cls, name: str) -> dict:
    """The range metadata of field ``name`` of a config dataclass ``cls``: ``{"lo", "hi", "open_lo",
    "open_hi", "choices"}`` (None where the field declares none)."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            md = f.metadata
            rng = md.get("rng") or (None, None)
            return {"lo": rng[0], "hi": rng[1], "open_lo": bool(md.get("open_lo")),
                    "open_hi": bool(md.get("open_hi")), "choices": md.get("choices")}
    raise KeyError(f"{cls.__name__} has no field {name!r}")


def check_fields(cls, prefix: str = "", error: Type[Exception] = ValueError, **values) -> None:
    """Check keyword ``values`` against the ranges and choices that config dataclass ``cls``
    declares for the fields of the same names (the schema is the one place a range is written)."""
    for name, value in values.items():
        b = field_bounds(cls, name)
        label = f"{prefix}{name}"
        if b["choices"] is not None:
            check_choice(label, value, b["choices"], error=error)
        elif b["lo"] is not None or b["hi"] is not None:
            check_range(label, value, b["lo"], b["hi"], open_lo=b["open_lo"], open_hi=b["open_hi"], error=error)




# ------------------------------------------------------------------ devices (torch imported when called)
def available_devices() -> List[str]:
    """The torch devices this machine can run on: ``cpu``, then ``cuda:0``... and ``mps`` when present."""
    import torch

    devs = ["cpu"]
    if torch.cuda.is_available():
        devs += [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        devs.append("mps")
    return devs


def check_device(name, param: str = "simulation.device"):
    """Validate a torch device name against this machine before any work (or run folder) starts.

    Args:
        name: ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"``, ...
        param: how the user set it (``--device`` or ``simulation.device``), named in the error.

    Returns:
        The :class:`torch.device`.

    Raises:
        ValueError: naming ``param``, the value, and the devices available here.
    """
    import torch

    avail = available_devices()
    try:
        dev = torch.device(str(name))
    except (RuntimeError, ValueError, TypeError):
        raise ValueError(f"{param}={name!r} is not a torch device; available on this machine: "
                         f"{', '.join(avail)}") from None
    if dev.type == "cpu":
        return dev
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "torch was built without CUDA" if torch.version.cuda is None else "no CUDA device is visible"
            raise ValueError(f"{param}={name!r}: CUDA is not available ({why}, torch {torch.__version__}); "
                             f"available on this machine: {', '.join(avail)}")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{param}={name!r}: only {torch.cuda.device_count()} CUDA device(s) here; "
                             f"available on this machine: {', '.join(avail)}")
        return dev
    if dev.type == "mps" and "mps" in avail:
        return dev
    raise ValueError(f"{param}={name!r}: device type {dev.type!r} is not available or not supported by dvsland; "
                     f"available on this machine: {', '.join(avail)}")


#: hex digits of a checkpoint's SHA-256 kept in reports (``learned_cnn.pt sha256:1a2b3c4d5e6f``)
HASH_DIGITS = 12

_SHA_CACHE: Dict[Tuple[str, int, int], str] = {}


def file_sha256(path, digits: int = HASH_DIGITS) -> str:
    """The first ``digits`` hex digits of the SHA-256 of the file's bytes (read in 1 MiB blocks;
    cached per path, size and modification time).

    Raises:
        ValueError: the file cannot be read (the message names it).
    """
    path = Path(path)
    try:
        st = os.stat(path)
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
        if key not in _SHA_CACHE:
            h = hashlib.sha256()
            with open(path, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
            _SHA_CACHE[key] = h.hexdigest()
    except OSError as exc:
        raise ValueError(f"cannot read the checkpoint {path}: {exc.strerror or exc}") from None
    return _SHA_CACHE[key][:digits]


__all__ = ["check_range", "check_choice", "check_keys", "check_fields", "field_bounds", "in_range", "range_text",
           "available_devices", "check_device", "HASH_DIGITS", "file_sha256"]
