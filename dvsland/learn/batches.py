"""Training batches of the recipe: samples of a :class:`~dvsland.data.Windows` -> model inputs.

Augmentations (training only):

- *time scale* (changes the divergence, so that it is no longer tied to the altitude, the scene's
  scale and the law that flew the descent): a window's events up to a share s of the window,
  stretched over the whole window, are what a camera with divergence s D would see (displacement
  and event count both scale by s); two consecutive windows of a descent squeezed into one are a
  divergence 2 D. ``time_scale`` = (probability of a merge, lowest s): the target becomes
  f |D| with f in [s_min, 2].
- with inputs spanning K > 1 control steps (``InputSpec.n_windows``) the same idea on the span:
  a real span of u K steps (u in [s_min, 2], the windows before the sample, cut inside the oldest
  one) squeezed into the input's K steps is a divergence u D.
- mirror in x and y about the principal point (the sensor centre in the datasets), a transpose
  on square sensors, and dropping a random share of each window's events (a sparser sensor).
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


def _time_scale(w: Windows, idx, cols, gen, p_merge: float, s_min: float):
    """Time-scale augmentation (module doc): (columns b, x, y, frac, p; |D| (B,) float32 targets)."""
    b, x, y, frac, p = cols
    B = len(idx)
    nxt = w.next[idx]
    merge = (torch.rand(B, generator=gen) < p_merge) & (nxt >= 0)
    d = w.d_true[idx].abs()
    if bool(merge.any()):
        rows = torch.nonzero(merge).squeeze(1)
        b2, x2, y2, f2, p2, _ = gather_batch(w, nxt[rows])
        frac = torch.where(merge[b], frac * 0.5, frac)
        b, x, y, p = torch.cat([b, rows[b2]]), torch.cat([x, x2]), torch.cat([y, y2]), torch.cat([p, p2])
        frac = torch.cat([frac, 0.5 + 0.5 * f2])
        d = torch.where(merge, 2.0 * w.d_true[nxt.clamp_min(0)].abs(), d)
    u = torch.rand(B, generator=gen)
    lo = torch.where(merge, torch.full_like(u, 0.5), torch.full_like(u, s_min))
    stretch = merge | (torch.rand(B, generator=gen) < 0.5)
    s = torch.where(stretch, lo + (1.0 - lo) * u, torch.ones_like(u))
    keep = frac <= s[b]
    b, x, y, p = b[keep], x[keep], y[keep], p[keep]
    frac = frac[keep] / s[b]
    return (b, x, y, frac, p), d * s


def _span(w: Windows, idx, K: int, gen, time_scale):
    """Events of the last u K control steps before each sample mapped onto [0, 1] (module doc):
    (columns b, x, y, frac, p; |D| (B,) float32 targets u |D|). u = 1 without ``gen``."""
    B = len(idx)
    if gen is None or time_scale is None:
        u = torch.ones(B)
    else:
        u = time_scale[1] + (2.0 - time_scale[1]) * torch.rand(B, generator=gen)
    M = torch.ceil(u * K - 1e-6).long().clamp(1, 2 * K)
    chain = [idx]
    for _ in range(2 * K - 1):  # the windows before: a few steps, each over the whole batch
        c = chain[-1]
        chain.append(torch.where(c >= 0, w.prev[c.clamp_min(0)], torch.full_like(c, -1)))
    chain = torch.stack(chain, 1)  # (B, 2K), column j = j steps back
    use = (chain >= 0) & (torch.arange(2 * K)[None] < M[:, None])
    rb, rj = torch.nonzero(use, as_tuple=True)
    b2, x, y, frac, p, _ = gather_batch(w, chain[rb, rj])
    b, j = rb[b2], rj[b2]
    Mf = M[b].to(torch.float32)
    ft = (Mf - 1 - j.to(torch.float32) + frac.clamp(max=1.0 - 1e-6)) / Mf  # an event stays in its window
    cut = 1.0 - u[b] * K / Mf
    keep = ft >= cut
    f_in = ((ft - cut) / (1.0 - cut))[keep]
    return (b[keep], x[keep], y[keep], f_in.clamp(0.0, 1.0), p[keep]), w.d_true[idx].abs() * u


def make_batch(w: Windows, idx: torch.Tensor, spec: InputSpec, gen: Optional[torch.Generator] = None,
               max_drop: float = 0.5, time_scale=(0.35, 0.4)) -> Batch:
    """The batch of samples ``idx`` (B,) int64; augmented when ``gen`` (a torch.Generator) is given.
    ``time_scale``: (merge probability, lowest stretch) or None (module doc)."""
    B = len(idx)
    W, H = spec.sensor_size
    if spec.n_windows > 1:
        (b, x, y, frac, p), d_abs = _span(w, idx, spec.n_windows, gen, time_scale)
        n = torch.bincount(b, minlength=B)
    else:
        b, x, y, frac, p, n = gather_batch(w, idx)
        d_abs = w.d_true[idx].abs()
        if gen is not None and time_scale is not None:
            (b, x, y, frac, p), d_abs = _time_scale(w, idx, (b, x, y, frac, p), gen, *time_scale)
            n = torch.bincount(b, minlength=B)
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
    target = torch.log(d_abs.clamp_min(D_FLOOR))
    return Batch(vox, torch.log1p(n.to(torch.float32)), target, idx)
