"""The one validation of a learned estimator's checkpoint (``snn``, ``learned``, and ``dvsland train
--resume`` / ``--init``): every loader reads the file with :func:`read_checkpoint_file`, checks the
numbers of its description with :func:`check_finite_numbers`, its weights with
:func:`check_state_dict` and, to resume, an optimizer's state with :func:`check_optimizer_state`.
Each raises one ValueError that starts with ``where`` (the parameter and the file) and says what is
wrong: nothing is loaded, trained or written from a damaged, foreign or diverged checkpoint.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch


def short_path(path) -> str:
    """``path`` as text, middle elided past 120 characters (an error message stays one short line)."""
    text = str(path)
    return text if len(text) <= 120 else f"{text[:60]}...{text[-40:]} ({len(text)} characters)"


def read_checkpoint_file(path, param: str, kind: str, hint: str = "") -> dict:
    """The dict a checkpoint file holds: ``torch.load(weights_only=True)`` on the CPU (tensors and
    plain values only; untrusted bytes never run code).

    Args:
        path: the file.
        param: the parameter that names it (``"estimator.snn.checkpoint"``, ``"--resume"``, ``"--init"``).
        kind: what it should be, e.g. ``"dvsland snn checkpoint"``.
        hint: appended to the messages (how to get a good one).

    Raises:
        ValueError: ``"<param>: ..."`` for a path the OS refuses (too long, a NUL byte), a missing
            file, a folder, bytes torch cannot read (corrupt, truncated, another kind of file) or a
            file that holds something other than a dict.
    """
    tail = f" ({hint})" if hint else ""
    if not str(path).strip():
        raise ValueError(f"{param} {str(path)!r}: empty; expected the path of a {kind} file (.pt){tail}")
    path = Path(path)
    try:
        found, folder = path.is_file(), path.is_dir()
    except (OSError, ValueError) as exc:  # ENAMETOOLONG, a NUL byte, ...
        raise ValueError(f"{param}: {short_path(path)}: {getattr(exc, 'strerror', None) or exc}; expected the path "
                         f"of a checkpoint file (at most 4096 characters, each folder or file name at most 255 "
                         f"bytes)") from None
    if folder:
        raise ValueError(f"{param}: {short_path(path)} is a folder; expected a {kind} file (.pt){tail}")
    if not found:
        raise ValueError(f"{param}: file not found: {short_path(path)}{tail}")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # untrusted bytes: the unpickler raises many kinds (KeyError, IndexError, ...)
        raise ValueError(f"{param}: {short_path(path)} is not a readable {kind} (corrupt, truncated or another kind "
                         f"of file){tail}") from None
    if not isinstance(ck, dict):
        raise ValueError(f"{param}: {short_path(path)} is not a readable {kind} (it holds a {type(ck).__name__}, "
                         f"not a checkpoint dict){tail}")
    return ck


def check_finite_numbers(value, where: str, field: str) -> None:
    """Every number in ``value`` (a checkpoint's description: nested dicts, lists, tuples) finite.

    Raises:
        ValueError: ``"<where>: <field>.<key> is nan; expected a finite number"``.
    """
    if isinstance(value, dict):
        for k, v in value.items():
            check_finite_numbers(v, where, f"{field}.{k}")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            check_finite_numbers(v, where, f"{field}[{i}]")
    elif isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{where}: {field} is {value}; expected a finite number (a damaged checkpoint)")


def check_state_dict(state, model: torch.nn.Module, where: str) -> None:
    """Every tensor of a checkpoint's ``state`` against ``model``: the same names, shapes and kinds
    of dtype (floating where the model's is), and only finite floating values.

    Args:
        state: the checkpoint's state dict.
        model: the network it must fit.
        where: how the messages start, e.g. ``"estimator.snn.checkpoint: /path/x.pt"``.

    Raises:
        ValueError: naming ``where`` and the tensor (a damaged, foreign or diverged checkpoint).
    """
    if not isinstance(state, dict):
        raise ValueError(f"{where}: its state_dict is a {type(state).__name__}, expected a mapping of tensor "
                         f"names to tensors")
    want = model.state_dict()
    missing, extra = sorted(set(want) - set(state)), sorted(set(state) - set(want))
    if missing or extra:
        raise ValueError(f"{where}: tensors missing {missing[:5]}, unexpected {extra[:5]}; expected exactly the "
                         f"tensors of the network it describes")
    for name, ref in want.items():
        t = state[name]
        if not isinstance(t, torch.Tensor) or t.is_floating_point() != ref.is_floating_point():
            what = f"a {t.dtype} tensor" if isinstance(t, torch.Tensor) else f"a {type(t).__name__}"
            kind = "floating-point" if ref.is_floating_point() else f"{ref.dtype}"
            raise ValueError(f"{where}: tensor '{name}' is {what}, expected a {kind} tensor of shape "
                             f"{tuple(ref.shape)}")
        if tuple(t.shape) != tuple(ref.shape):
            raise ValueError(f"{where}: tensor '{name}' has shape {tuple(t.shape)}, expected {tuple(ref.shape)} "
                             f"(the network its settings describe)")
        check_finite_tensor(t, where, f"tensor '{name}'")


def check_optimizer_state(state, optimizer: torch.optim.Optimizer, where: str) -> None:
    """An optimizer's saved ``state`` (``Optimizer.state_dict()``) against ``optimizer``: its parameter
    groups hold as many parameters, and every floating tensor of it (moments, steps) is finite.

    Raises:
        ValueError: naming ``where`` and the optimizer's tensor.
    """
    want = optimizer.state_dict()
    groups = state.get("param_groups") if isinstance(state, dict) else None
    per_param = state.get("state") if isinstance(state, dict) else None
    if not isinstance(groups, list) or not isinstance(per_param, dict) or \
            [len(g.get("params", ())) if isinstance(g, dict) else -1 for g in groups] != \
            [len(g["params"]) for g in want["param_groups"]]:
        raise ValueError(f"{where}: its optimizer state does not fit the network (another optimizer or model)")
    check_finite_numbers(groups, where, "optimizer.param_groups")
    for pid, entry in per_param.items():
        for key, t in (entry.items() if isinstance(entry, dict) else ()):
            if isinstance(t, torch.Tensor):
                check_finite_tensor(t, where, f"optimizer tensor '{key}' of parameter {pid}")


def check_finite_tensors(state, where: str) -> None:
    """Every floating tensor of a state dict ``state`` finite (the check that needs no network, so a
    command can make it before it makes anything; :func:`check_state_dict` makes it again)."""
    for name, t in (state.items() if isinstance(state, dict) else ()):
        if isinstance(t, torch.Tensor):
            check_finite_tensor(t, where, f"tensor '{name}'")


def check_finite_tensor(t: torch.Tensor, where: str, what: str) -> None:
    """ValueError ``"<where>: <what> holds k NaN or infinite values of n; ..."`` when ``t`` has any."""
    bad = int((~torch.isfinite(t)).sum()) if t.is_floating_point() else 0
    if bad:
        raise ValueError(f"{where}: {what} holds {bad} NaN or infinite values of {t.numel()}; expected finite "
                         f"values (a damaged or diverged training)")
