"""Flat-kernel mean-shift on a count image, batched over (B, N) seeds with gathered patches.

Each seed moves to the count-weighted mean of the pixels within ``radius_px`` of it, until it
moves less than ``tol_px`` or ``iters`` iterations have run. Only a loop over iterations; the
patches of all (B, N) seeds are gathered at once.
"""

from __future__ import annotations

import functools
import math
from typing import Tuple

import torch
import torch.nn.functional as F

from . import native_dpr


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
    if native_dpr.fits(radius_px, image_pad_px):
        mod = native_dpr.kernel_for(image)
        if mod is not None:  # the same iterations seed by seed, where the sums are exact (module doc there)
            q = int(image_pad_px)
            out = mod.meanshift(image, q, image.shape[2] - 2 * q, image.shape[1] - 2 * q, seeds, valid, radius_px,
                                int(iters), tol_px)
            if out is not None:
                return out[0], out[1], torch.tensor(out[2])
    r_int = int(math.ceil(radius_px))
    P = 2 * r_int + 2  # patch side: covers [floor(c) - r_int, floor(c) + r_int + 1]
    q = r_int + 1  # zero border needed so that every patch lies inside the padded image
    img = image.to(torch.float32)
    have = int(image_pad_px)
    H, W = img.shape[1] - 2 * have, img.shape[2] - 2 * have
    if have < q:
        img = F.pad(img, (q - have,) * 4)
        have = q
    img = img.contiguous()
    Hp, Wp = img.shape[1], img.shape[2]
    off, moments_t, hi, zero = _constants(str(dev), P, r_int, W, H)
    # thresholds as float32 0-dim tensors (a Python scalar is cast to float32 all the same, but
    # costs a tensor conversion per op)
    r2 = torch.tensor(float(radius_px) ** 2, dtype=torch.float32, device=dev)
    tol = torch.tensor(float(tol_px), dtype=torch.float32, device=dev)
    # patches[i] = the P x P patch whose top-left pixel is flat index i of the padded images: an
    # overlapping strided view (one index_select per gather, no (A, P*P) index arithmetic)
    n_flat = B * Hp * Wp
    patches = img.reshape(-1).as_strided((max(n_flat - (P - 1) * (Wp + 1), 0), P, P), (1, Wp, 1))
    # flat index of the patch of a seed = lin_b + Wp * floor(y) + floor(x), computed by one addmv
    # in float (exact: integers below 2**24, else float64)
    ldt = torch.float32 if n_flat < 2 ** 24 else torch.float64
    wv = torch.tensor([1.0, float(Wp)], dtype=ldt, device=dev)
    s0 = have - r_int
    lin_all = torch.arange(B, device=dev, dtype=ldt).mul_(Hp * Wp).add_(s0 * Wp + s0).repeat_interleave(N)

    def window(cc, lb):
        """Kernel weights around cc (A, 2) with patch offsets lb (A,): (w (A, P*P), base (A, 2))."""
        base = cc.floor()
        lin = torch.addmv(lb, base.to(ldt), wv).to(torch.int64)
        w = patches.index_select(0, lin)  # (A, P, P) copy
        d2 = (off - (cc - base).unsqueeze(-1)).pow(2)  # (A, 2, P): (dx^2, dy^2) per column / row
        inside = (d2[:, 0].unsqueeze(1) + d2[:, 1].unsqueeze(2)) <= r2
        return torch.where(inside, w, zero).reshape(-1, P * P), base

    c = torch.where(valid.unsqueeze(-1), seeds.to(torch.float32), zero)
    c = torch.clamp(c, zero, hi).reshape(B * N, 2)
    valid_f = valid.reshape(-1)
    # iterate only the centroids still moving (compacted whenever some froze). A seed whose
    # kernel holds no counts stops (it does not move) and is found lost by the final count.
    ia = valid_f.nonzero().squeeze(1)
    ca, la = c.index_select(0, ia), lin_all.index_select(0, ia)
    n_iter = 0
    for _ in range(int(iters)):
        if ia.numel() == 0:
            break
        n_iter += 1
        w, base = window(ca, la)
        m = moments_t @ w.t()  # (3, A): sum, sum dx, sum dy
        s = m[0]
        empty = s <= zero
        mean = torch.clamp(base + m[1:].t() / s.clamp_min(1e-12).unsqueeze(-1), zero, hi)
        new = torch.where(empty.unsqueeze(-1), ca, mean)
        still = torch.linalg.vector_norm(new - ca, dim=-1) >= tol  # = Tensor.norm, less Python
        if not tol_px > 0:
            still = still & ~empty
        c.index_copy_(0, ia, new)
        sel = still.nonzero().squeeze(1)
        if sel.numel() < ia.numel():
            ia, ca, la = ia.index_select(0, sel), new.index_select(0, sel), la.index_select(0, sel)
        else:
            ca = new
    w, _ = window(c, lin_all)
    counts = torch.where(valid_f, w.sum(-1), zero)
    alive = valid_f & (counts > 0)
    c = torch.where(alive.unsqueeze(-1), c, torch.full((), float("nan"), device=dev))
    return c.reshape(B, N, 2), counts.reshape(B, N), torch.tensor(n_iter)


@functools.lru_cache(maxsize=32)
def _constants(device: str, P: int, r_int: int, W: int, H: int):
    """Cached per-shape constants: pixel offsets (P,) -r..r+1, moments (3, P*P) = (1, dx, dy)
    per patch pixel (row-major, y outer), the upper clamp (W-1, H-1) and a zero, all float32."""
    off = torch.arange(P, device=device, dtype=torch.float32) - r_int
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    moments = torch.stack([torch.ones(P * P, device=device), ox.reshape(-1), oy.reshape(-1)], 0)
    hi = torch.tensor([W - 1.0, H - 1.0], device=device)
    return off, moments, hi, torch.zeros((), device=device)
