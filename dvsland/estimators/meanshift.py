"""Flat-kernel mean-shift on a count image, batched over (B, N) seeds with gathered patches.

Each seed moves to the count-weighted mean of the pixels within ``radius_px`` of it, until it
moves less than ``tol_px`` or ``iters`` iterations have run. Only a loop over iterations; the
patches of all (B, N) seeds are gathered at once.
"""

from __future__ import annotations

import math
from typing import Tuple

import torch
import torch.nn.functional as F


def meanshift_flat(image: torch.Tensor, seeds: torch.Tensor, valid: torch.Tensor, radius_px: float,
                   iters: int = 20, tol_px: float = 0.01,
                   image_pad_px: int = 0) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mean-shift with a flat (uniform disk) kernel, seeded at ``seeds``.

    Pixel (x, y) has its centre at integer coordinates; the kernel covers the pixels whose centre
    lies within ``radius_px`` (inclusive) of the current centroid. Pixels off the sensor count 0.

    Args:
        image: (B, H, W) float, event counts per pixel; or, with ``image_pad_px`` = q > 0, the
            counts already surrounded by q zero pixels on every side, (B, H + 2q, W + 2q)
            (saves a padding copy per call; coordinates stay those of the sensor).
        seeds: (B, N, 2) float, start positions (x, y) in pixels; ignored where not ``valid``.
        valid: (B, N) bool, which seeds exist.
        radius_px: kernel radius R, px (> 0).
        iters: maximum iterations (>= 1).
        tol_px: a seed that moves less than this is converged (frozen).
        image_pad_px: zero border already around ``image``, px.

    Returns:
        centroids: (B, N, 2) float32 (x, y); NaN where not valid or where the kernel held no
            counts at some iteration (the seed is lost).
        counts: (B, N) float32, counts within R of the final centroid (0 where not valid).
        n_iter: int tensor (), the iterations run.
    """
    if image.dim() != 3:
        raise ValueError(f"image must be (B, H, W), got {tuple(image.shape)}")
    if int(image_pad_px) < 0:
        raise ValueError(f"image_pad_px must be >= 0, got {image_pad_px}")
    B = image.shape[0]
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
    q = r_int + 1  # zero border needed so that every patch lies inside the padded image
    img = image.to(torch.float32)
    have = int(image_pad_px)
    H, W = img.shape[1] - 2 * have, img.shape[2] - 2 * have
    if have < q:
        img = F.pad(img, (q - have,) * 4)
        have = q
    Hp, Wp = img.shape[1], img.shape[2]
    flat = img.reshape(B, Hp * Wp)
    off = torch.arange(P, device=dev, dtype=torch.float32) - r_int  # -r .. r+1
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    ox = ox.reshape(1, 1, P * P)
    oy = oy.reshape(1, 1, P * P)
    off_lin = (oy * Wp + ox).to(torch.int64)  # (1, 1, K) offsets from the patch's base pixel
    moments = torch.stack([torch.ones(P * P, device=dev), ox.reshape(-1), oy.reshape(-1)], 1)  # (K, 3)
    r2 = float(radius_px) ** 2
    hi = torch.tensor([W - 1.0, H - 1.0], device=dev)

    c = torch.where(valid.unsqueeze(-1), seeds.to(torch.float32), torch.zeros((), device=dev))
    c = torch.minimum(c.clamp_min(0.0), hi).reshape(B * N, 2)
    flat_all = img.reshape(-1)
    row_base = (torch.arange(B, device=dev) * (Hp * Wp)).repeat_interleave(N)  # (B*N,) image offsets
    alive = valid.reshape(-1).clone()
    active = alive.clone()
    n_iter = 0

    def window(cc, rb):
        """Kernel weights around cc (A, 2) in images at offsets rb (A,): (w (A, K), base (A, 2))."""
        base = cc.floor()
        f = cc - base  # in [0, 1)
        lin0 = rb + ((base[:, 1] + have) * Wp + (base[:, 0] + have)).to(torch.int64)  # (A,)
        w = flat_all[lin0.unsqueeze(-1) + off_lin[0]]  # (A, K)
        inside = ((ox[0] - f[:, :1]) ** 2 + (oy[0] - f[:, 1:]) ** 2) <= r2
        return w * inside, base

    # iterate only the centroids still moving (compacted each iteration)
    for _ in range(int(iters)):
        ia = active.nonzero().squeeze(1)
        if ia.numel() == 0:
            break
        n_iter += 1
        ca = c[ia]
        w, base = window(ca, row_base[ia])
        m = w @ moments  # (A, 3): sum, sum dx, sum dy
        s = m[:, 0]
        empty = s <= 0
        mean = torch.minimum((base + m[:, 1:] / s.clamp_min(1e-12).unsqueeze(-1)).clamp_min(0.0), hi)
        new = torch.where(empty.unsqueeze(-1), ca, mean)
        shift = (new - ca).norm(dim=-1)
        c[ia] = new
        alive[ia] = ~empty
        active[ia] = ~empty & (shift >= tol_px)
    w, _ = window(c, row_base)
    counts = torch.where(alive, w.sum(-1), torch.zeros((), device=dev))
    alive = alive & (counts > 0)
    c = torch.where(alive.unsqueeze(-1), c, torch.full_like(c, float("nan")))
    return c.reshape(B, N, 2), counts.reshape(B, N), torch.tensor(n_iter)
