"""Add compact features (craters, boulders) onto a regular grid by patches (no per-feature loop).

Features are grouped by patch size (a geometric ladder in texels) and processed in chunks: for each
chunk a (M, P, P) block of texel indices is evaluated and scattered with ``index_add_`` (CPU,
float64: the summation order is fixed, so the result is reproducible bit for bit).
"""

from __future__ import annotations

from typing import Callable, Sequence

import torch

from .grid import Grid


def stamp(outs: Sequence[torch.Tensor], grid: Grid, x_m: torch.Tensor, y_m: torch.Tensor, d_m: torch.Tensor,
          fresh: torch.Tensor, weight: torch.Tensor, reach: float, fn: Callable,
          max_elems: int = 1 << 22) -> None:
    """Accumulate features into flat fields.

    Args:
        outs: flat (n_rows * n_cols,) float64 fields, updated in place.
        grid: the sampling grid.
        x_m, y_m, d_m, fresh, weight: (M,) float64 feature centre, diameter, freshness, weight.
        reach: influence radius in units of the radius D/2 (the profile is 0 beyond it).
        fn: ``fn(r, d_m, fresh) -> tuple of tensors`` (one per field), elementwise: r = distance /
            (D/2) (K,) float64 at the K texels within ``reach``, with each one's feature's d_m and
            fresh (K,).
    """
    if d_m.numel() == 0:
        return
    s = grid.spacing_m
    nr, nc = grid.n_rows, grid.n_cols
    ci, cj = grid.texel(x_m, y_m)
    rad = reach * 0.5 * d_m / s
    keep = ((weight > 0) & (ci + rad >= -1) & (ci - rad <= nr) & (cj + rad >= -1) & (cj - rad <= nc))
    if not bool(keep.any()):
        return
    ci, cj, d_m, fresh, weight, rad = (t[keep] for t in (ci, cj, d_m, fresh, weight, rad))
    # a patch never needs to be larger than the grid (the window is clipped to it below): a
    # feature much larger than a fine grid (narrow field of view) gets a grid-sized patch
    half = (torch.ceil(rad).to(torch.int64) + 1).clamp_(max=max(nr, nc) + 1)
    # patch half-sizes rounded up on a geometric ladder (ratio ~1.25) to batch similar features
    ladder = torch.unique(torch.round(1.25 ** torch.arange(0, 64, dtype=torch.float64)).to(torch.int64))
    pos = torch.searchsorted(ladder, half).clamp_(max=ladder.numel() - 1)
    bins = torch.maximum(ladder[pos], half)
    for b in torch.unique(bins).tolist():
        sel = torch.nonzero(bins == b).squeeze(1)
        wr, wc = min(2 * b + 1, nr), min(2 * b + 1, nc)
        chunk = max(1, max_elems // (wr * wc))
        ar_r = torch.arange(wr, dtype=torch.int64)
        ar_c = torch.arange(wc, dtype=torch.int64)
        for start in range(0, sel.numel(), chunk):
            idx = sel[start:start + chunk]
            fi, fj = ci[idx], cj[idx]
            i0 = (torch.round(fi).to(torch.int64) - b).clamp(0, nr - wr)
            j0 = (torch.round(fj).to(torch.int64) - b).clamp(0, nc - wc)
            ii = i0[:, None, None] + ar_r[None, :, None]
            jj = j0[:, None, None] + ar_c[None, None, :]
            dist = s * torch.sqrt((ii - fi[:, None, None]) ** 2 + (jj - fj[:, None, None]) ** 2)
            r = dist / (0.5 * d_m[idx][:, None, None])
            _stamp_inside(outs, fn, r, reach, idx, i0, j0, nc, d_m, fresh, weight)


def _stamp_inside(outs, fn, r: torch.Tensor, reach: float, idx, i0, j0, n_cols: int, d_m, fresh, weight) -> None:
    """Evaluate ``fn`` only at the texels of the patches ``r`` (M, wr, wc) float64 that lie within
    ``reach`` and add them into ``outs`` (the same values, element by element, as evaluating the whole
    patches and masking). idx (M,): the features' entries in d_m, fresh, weight; i0, j0 (M,) int64:
    the patches' first row and column."""
    _, wr, wc = r.shape
    sel = (r < reach).view(-1).nonzero().squeeze(1)  # flat (feature, row, col) of the texels inside
    feat = sel // (wr * wc)
    rem = sel - feat * (wr * wc)
    row = rem // wc
    flat = (i0.index_select(0, feat) + row) * n_cols + j0.index_select(0, feat) + (rem - row * wc)
    f_idx = idx.index_select(0, feat)
    vals = fn(r.view(-1).index_select(0, sel), d_m.index_select(0, f_idx), fresh.index_select(0, f_idx))
    w = weight.index_select(0, f_idx)
    for out, v in zip(outs, vals):
        out.index_add_(0, flat, v * w)
