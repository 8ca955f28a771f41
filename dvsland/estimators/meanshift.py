"""Flat-kernel mean-shift on a count image, batched over (B, N) seeds with gathered patches.

Each seed moves to the count-weighted mean of the pixels within ``radius_px`` of it, until it
moves less than ``tol_px`` or ``iters`` iterations have run. Only a loop over iterations; the
patches of all (B, N) seeds are gathered at once.
"""

from __future__ import annotations

import math
from typing import Tuple

import torch


def meanshift_flat(image: torch.Tensor, seeds: torch.Tensor, valid: torch.Tensor, radius_px: float,
                   iters: int = 20, tol_px: float = 0.01) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mean-shift with a flat (uniform disk) kernel, seeded at ``seeds``.

    Pixel (x, y) has its centre at integer coordinates; the kernel covers the pixels whose centre
    lies within ``radius_px`` (inclusive) of the current centroid.

    Args:
        image: (B, H, W) float, event counts per pixel.
        seeds: (B, N, 2) float, start positions (x, y) in pixels; ignored where not ``valid``.
        valid: (B, N) bool, which seeds exist.
        radius_px: kernel radius R, px (> 0).
        iters: maximum iterations (>= 1).
        tol_px: a seed that moves less than this is converged (frozen).

    Returns:
        centroids: (B, N, 2) float32 (x, y); NaN where not valid or where the kernel held no
            counts at some iteration (the seed is lost).
        counts: (B, N) float32, counts within R of the final centroid (0 where not valid).
        n_iter: int tensor (), the iterations run.
    """
    if image.dim() != 3:
        raise ValueError(f"image must be (B, H, W), got {tuple(image.shape)}")
    B, H, W = image.shape
    if seeds.shape[:2] != valid.shape or seeds.shape[0] != B or seeds.shape[-1] != 2:
        raise ValueError(f"seeds must be (B, N, 2) = ({B}, N, 2) and valid (B, N), got "
                         f"{tuple(seeds.shape)} and {tuple(valid.shape)}")
    if not radius_px > 0:
        raise ValueError(f"radius_px must be > 0, got {radius_px}")
    if int(iters) < 1:
        raise ValueError(f"iters must be >= 1, got {iters}")
    N = seeds.shape[1]
    dev = image.device
    r_int = int(math.ceil(radius_px))
    P = 2 * r_int + 2  # patch side: covers [floor(c) - r_int, floor(c) + r_int + 1]
    flat = image.to(torch.float32).reshape(B, H * W)
    off = torch.arange(P, device=dev, dtype=torch.float32) - r_int  # -r .. r+1
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    ox = ox.reshape(1, 1, P * P)
    oy = oy.reshape(1, 1, P * P)
    r2 = float(radius_px) ** 2

    c = torch.where(valid.unsqueeze(-1), seeds.to(torch.float32), torch.zeros((), device=dev))
    c = c.clamp(min=torch.zeros(2, device=dev), max=torch.tensor([W - 1.0, H - 1.0], device=dev))
    alive = valid.clone()
    active = valid.clone()
    counts = torch.zeros(B, N, dtype=torch.float32, device=dev)
    n_iter = 0

    def window(cc):
        base = cc.floor()
        px = base[..., :1] + ox  # (B, N, P*P) pixel x
        py = base[..., 1:] + oy
        # in the kernel and on the sensor (outside the sensor counts are zero)
        inside = (((px - cc[..., :1]) ** 2 + (py - cc[..., 1:]) ** 2) <= r2) & \
            (px >= 0) & (px <= W - 1) & (py >= 0) & (py <= H - 1)
        lin = (py.clamp(0, H - 1) * W + px.clamp(0, W - 1)).long()
        w = torch.gather(flat, 1, lin.reshape(B, N * P * P)).reshape(B, N, P * P)
        w = w * inside
        return px, py, w

    for _ in range(int(iters)):
        n_iter += 1
        px, py, w = window(c)
        s = w.sum(-1)
        empty = s <= 0
        mean = torch.stack([(w * px).sum(-1), (w * py).sum(-1)], -1) / s.clamp_min(1e-12).unsqueeze(-1)
        new = torch.where((active & ~empty).unsqueeze(-1), mean, c)
        shift = (new - c).norm(dim=-1)
        alive = alive & ~(active & empty)
        c = new
        active = active & ~empty & (shift >= tol_px)
        if not bool(active.any()):
            break
    _, _, w = window(c)
    counts = torch.where(alive, w.sum(-1), torch.zeros((), device=dev))
    alive = alive & (counts > 0)
    c = torch.where(alive.unsqueeze(-1), c, torch.full_like(c, float("nan")))
    return c, counts, torch.tensor(n_iter)
