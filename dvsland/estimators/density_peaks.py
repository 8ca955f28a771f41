"""Density Peaks Ranking (DPR): the paper's initialisation of the tracked centroids (section 4).

count image -> Gaussian blur (kornia) -> morphological local maxima (max-pool NMS) -> ranked by
blurred density -> top ``n_max``. Pure functions, batched over B.

The blur is one depthwise convolution over the images, and a single image is blurred as the first of
two: an image's blur, and so its peaks, do not depend on how many images are blurred with it (a plain
convolution of one image sums in another order, which differs between CPUs).

On a CPU with the compiled ``dpr`` kernels (:mod:`.native_dpr`), the blur, the local maxima and the
scores run as one pass per image, with the same bits as the torch path: the blur's sums as the
fused multiply-add chain oneDNN's depthwise convolution computes. This is checked once per process
on a small sample against the torch path; where it does not hold, the torch path runs.
"""

from __future__ import annotations

import functools
import math
from typing import Tuple

import kornia
import torch
import torch.nn.functional as F

from . import native_dpr


def _check_image(image: torch.Tensor) -> None:
    if not isinstance(image, torch.Tensor) or image.dim() != 3:
        raise ValueError(f"image must be a (B, H, W) tensor, got "
                         f"{getattr(image, 'shape', type(image))}")


@functools.lru_cache(maxsize=8)
def _gaussian_kernels(k: int, sigma_px: float, device: str, dtype: torch.dtype):
    """(kernel_x, kernel_y), each (1, k): the kernels kornia's gaussian_blur2d makes per call."""
    sigma = torch.tensor([[sigma_px, sigma_px]], dtype=dtype, device=device)
    return (kornia.filters.get_gaussian_kernel1d(k, sigma[:, 1].view(1, 1)),
            kornia.filters.get_gaussian_kernel1d(k, sigma[:, 0].view(1, 1)))


def _blur_depthwise(img: torch.Tensor, kx: torch.Tensor, ky: torch.Tensor) -> torch.Tensor:
    """Separable blur of ``img`` (B, H, W) float32 with 1-d kernels kx, ky (1, k), zero border:
    rows then columns, the B images as the B channels of a grouped convolution -> (B, H, W). One image
    is blurred as the first of two, so that its sums run as those of any batch's images."""
    B = img.shape[0]
    if B == 1:
        return _blur_depthwise(img.expand(2, -1, -1), kx, ky)[:1]
    k = kx.shape[-1]
    x = img.unsqueeze(0)
    h = F.conv2d(x, kx.view(1, 1, 1, k).expand(B, 1, 1, k), padding=(0, k // 2), groups=B)
    return F.conv2d(h, ky.view(1, 1, k, 1).expand(B, 1, k, 1), padding=(k // 2, 0), groups=B)[0]


def _peak_scores(blurred: torch.Tensor, nms_px: int, min_density: float) -> torch.Tensor:
    """(B, H, W) the blurred density ``blurred`` (B, H, W) at its ``nms_px`` local maxima above
    ``min_density``, -1 elsewhere."""
    is_peak = (blurred >= _max_filter(blurred, int(nms_px))) & (blurred > min_density)
    return torch.where(is_peak, blurred, torch.full_like(blurred, -1.0))


def _torch_scores(img: torch.Tensor, kx: torch.Tensor, ky: torch.Tensor, nms_px: int,
                  min_density: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """(blurred, score) (B, H, W) float32 of count images ``img`` (B, H, W) float32: the depthwise
    blur, and :func:`_peak_scores` of it."""
    blurred = _blur_depthwise(img, kx, ky)
    return blurred, _peak_scores(blurred, nms_px, min_density)


@functools.lru_cache(maxsize=8)
def compiled_scores_match(kernels) -> bool:
    """Whether ``kernels`` (a loaded :class:`~.native_dpr.Kernels`) give this machine's torch path's
    blur and scores bit for bit, on a sample of three sparse count images (checked once per process)."""
    g = torch.Generator().manual_seed(1)
    img = torch.poisson(torch.rand(3, 37, 53, generator=g) * 1.5, generator=g)
    img[:, :, :20] = 0.0
    for sigma, nms in ((2.0, 3), (1.0, 5)):
        kx, ky = _gaussian_kernels(2 * int(math.ceil(3.0 * sigma)) + 1, sigma, "cpu", torch.float32)
        got = kernels.peak_scores(img, kx, ky, nms, 0.0)
        if not all(torch.equal(a, b) for a, b in zip(got, _torch_scores(img, kx, ky, nms, 0.0))):
            return False
    return True


def _max_filter(x: torch.Tensor, k: int) -> torch.Tensor:
    """k x k running maximum of x (B, H, W), -inf outside: the same values as
    ``F.max_pool2d(x, k, stride=1, padding=k // 2)`` (max is exact), as separable shifted
    maxima (10-20x faster than max_pool2d on CPU for 128 x 128 images)."""
    if k == 1:
        return x
    B, H, W = x.shape
    r = k // 2
    xp = F.pad(x, (r, r, r, r), value=float("-inf"))
    m = xp[:, :, 0:W]
    for i in range(1, k):
        m = torch.maximum(m, xp[:, :, i:i + W])
    out = m[:, 0:H]
    for i in range(1, k):
        out = torch.maximum(out, m[:, i:i + H])
    return out


def density_peaks(image: torch.Tensor, n_max: int, sigma_px: float = 2.0, nms_px: int = 3,
                  min_density: float = 0.0) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Top ``n_max`` local maxima of the blurred event count image, ranked by density.

    Args:
        image: (B, H, W) float, event counts per pixel (ON + OFF).
        n_max: number of peaks kept, >= 1.
        sigma_px: Gaussian blur sigma, px (> 0). The kernel is 2*ceil(3 sigma)+1 wide.
        nms_px: odd size of the max-pool window that defines a local maximum (>= 1).
        min_density: a peak must have blurred density > this (0 = any event nearby).

    Returns:
        peaks: (B, n_max, 2) float32 pixel coordinates (x, y) of the peaks, rank order
            (densest first); NaN in unused slots.
        density: (B, n_max) float32 blurred density at each peak (0 in unused slots).
        valid: (B, n_max) bool, True where a peak exists.
    """
    _check_image(image)
    if int(n_max) < 1:
        raise ValueError(f"n_max must be >= 1, got {n_max}")
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    if int(nms_px) < 1 or int(nms_px) % 2 == 0:
        raise ValueError(f"nms_px must be an odd integer >= 1, got {nms_px}")
    B, H, W = image.shape
    img = image.to(torch.float32).unsqueeze(1)
    k = 2 * int(math.ceil(3.0 * sigma_px)) + 1
    if H * W < 256 * 256:
        # kornia's gaussian_blur2d (filter2d_separable, zero border), with the 1-d kernels made once
        # and the images as the channels of one depthwise convolution: the same values up to the
        # sums' rounding, 3-5x cheaper on a CPU than a batch of one-channel images; compiled where it
        # gives the same bits
        kx, ky = _gaussian_kernels(k, float(sigma_px), str(img.device), img.dtype)
        kern = native_dpr.kernel_for(img)
        if kern is not None and compiled_scores_match(kern):
            _, score = kern.peak_scores(img[:, 0].contiguous(), kx, ky, int(nms_px), float(min_density))
        else:
            _, score = _torch_scores(img[:, 0], kx, ky, int(nms_px), float(min_density))
    else:
        blurred = kornia.filters.gaussian_blur2d(img, (k, k), (float(sigma_px), float(sigma_px)),
                                                 border_type="constant")[:, 0]
        score = _peak_scores(blurred, nms_px, min_density)
    score = score.reshape(B, H * W)
    n = min(int(n_max), H * W)
    top, idx = torch.topk(score, n, dim=1)  # sorted, densest first
    valid = top > min_density
    xy = torch.stack([(idx % W).to(torch.float32), (idx // W).to(torch.float32)], dim=-1)
    peaks = torch.where(valid.unsqueeze(-1), xy, torch.full_like(xy, float("nan")))
    density = torch.where(valid, top, torch.zeros_like(top))
    if n < n_max:  # tiny images: pad to n_max slots
        pad = int(n_max) - n
        peaks = torch.cat([peaks, peaks.new_full((B, pad, 2), float("nan"))], 1)
        density = torch.cat([density, density.new_zeros(B, pad)], 1)
        valid = torch.cat([valid, valid.new_zeros(B, pad)], 1)
    return peaks, density, valid
