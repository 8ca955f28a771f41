"""Training batches of the recipe: samples of a :class:`~dvsland.data.Windows` -> model inputs.

Augmentations (training only; each keeps the true divergence): mirror in x and y about the
principal point (only where it is the sensor centre), a transpose on square sensors, and
dropping a random share of each window's events (a sparser sensor: higher contrast threshold).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch

from dvsland.data import Windows, gather_batch
from dvsland.estimators.learned.inputs import InputSpec, voxel_grid

#: |D| below this (1/s) is clipped in the log target (near-hover windows)
D_FLOOR = 1e-3


class Batch(NamedTuple):
    """Model inputs and targets of B samples: ``vox`` (B, n_bins, h, w) float32, ``log_count``
    (B,) float32, ``target`` (B,) float32 log|D|, ``index`` (B,) int64 rows of the Windows."""

    vox: torch.Tensor
    log_count: torch.Tensor
    target: torch.Tensor
    index: torch.Tensor


def make_batch(w: Windows, idx: torch.Tensor, spec: InputSpec, gen: Optional[torch.Generator] = None,
               max_drop: float = 0.5) -> Batch:
    """The batch of samples ``idx`` (B,) int64; augmented when ``gen`` (a torch.Generator) is given."""
    b, x, y, frac, p, n = gather_batch(w, idx)
    B = len(idx)
    W, H = spec.sensor_size
    if gen is not None and b.numel():
        flip = torch.rand(B, 3, generator=gen) < 0.5
        fx, fy = flip[b, 0], flip[b, 1]
        x = torch.where(fx, W - 1 - x, x)
        y = torch.where(fy, H - 1 - y, y)
        if W == H:
            tr = flip[b, 2]
            x, y = torch.where(tr, y, x), torch.where(tr, x, y)
        keep = torch.rand(b.shape[0], generator=gen) >= (torch.rand(B, generator=gen) * max_drop)[b]
        b, x, y, frac, p = b[keep], x[keep], y[keep], frac[keep], p[keep]
        n = torch.bincount(b, minlength=B)
    vox = voxel_grid(b, x, y, frac, p, B, spec)
    target = torch.log(w.d_true[idx].abs().clamp_min(D_FLOOR))
    return Batch(vox, torch.log1p(n.to(torch.float32)), target, idx)
