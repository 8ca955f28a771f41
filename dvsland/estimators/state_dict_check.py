"""The one check of a learned estimator's weights before they are loaded (``snn``, ``learned``)."""

from __future__ import annotations

import torch


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
        bad = int((~torch.isfinite(t)).sum()) if t.is_floating_point() else 0
        if bad:
            raise ValueError(f"{where}: tensor '{name}' holds {bad} NaN or infinite values of {t.numel()}; "
                             f"expected finite weights (a damaged or diverged training)")
