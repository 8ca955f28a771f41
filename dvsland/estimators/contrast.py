"""Contrast maximisation for a radial (zoom) flow: warp, splat, score (after McLeod et al. 2022).

For a nadir camera descending vertically, image coordinates about the focus of expansion (FoE)
scale as r(t) = r(t_ref) z(t_ref) / z(t). With divergence D = v / z held over the window,
z(t) = z(t_ref) exp(D (t - t_ref)), so an event seen at r(t) sits at

    r(t_ref) = r(t) exp(D (t - t_ref))

at the reference time. For the true D the warped events pile up on the scene's edges and the
warped count image is sharpest (highest variance). Pure functions, batched over events and over a
per-element grid of candidate D.
"""

from __future__ import annotations

import math
from typing import Tuple

import torch
import torch.nn.functional as F


def radial_warp(x: torch.Tensor, y: torch.Tensor, dt_s: torch.Tensor, candidates: torch.Tensor,
                centre_xy: Tuple[float, float]) -> Tuple[torch.Tensor, torch.Tensor]:
    """Warp events to the reference time for every candidate divergence.

    Args:
        x, y: (E,) float, event pixel coordinates.
        dt_s: (E,) float, event time minus reference time, s.
        candidates: (E, G) float, candidate D (1/s) for each event (its element's grid).
        centre_xy: FoE (cx, cy), px.

    Returns:
        xw, yw: (E, G) float32 warped coordinates, px.
    """
    cx, cy = centre_xy
    scale = torch.exp(candidates * dt_s.unsqueeze(-1))
    xw = cx + (x.unsqueeze(-1) - cx) * scale
    yw = cy + (y.unsqueeze(-1) - cy) * scale
    return xw, yw


def splat_bilinear(xw: torch.Tensor, yw: torch.Tensor, image_index: torch.Tensor, n_images: int,
                   height: int, width: int) -> torch.Tensor:
    """Accumulate unit-weight events into images with bilinear weights (one ``bincount``).

    Args:
        xw, yw: (E, G) float, coordinates (pixel centres at integers).
        image_index: (E, G) int64, which of the ``n_images`` images each sample goes to.
        n_images, height, width: output size.

    Returns:
        (n_images, height, width) float32; weight falling outside is dropped.
    """
    x0 = torch.floor(xw)
    y0 = torch.floor(yw)
    fx = (xw - x0).reshape(1, -1)
    fy = (yw - y0).reshape(1, -1)
    x0 = x0.to(torch.int64).reshape(1, -1)
    y0 = y0.to(torch.int64).reshape(1, -1)
    base = image_index.reshape(1, -1) * (height * width)
    dev = xw.device
    dx = torch.tensor([0, 1, 0, 1], device=dev).view(4, 1)
    dy = torch.tensor([0, 0, 1, 1], device=dev).view(4, 1)
    xi = x0 + dx  # (4, S)
    yi = y0 + dy
    wx = torch.where(dx == 1, fx, 1.0 - fx)
    wy = torch.where(dy == 1, fy, 1.0 - fy)
    n = n_images * height * width
    ok = (xi >= 0) & (xi < width) & (yi >= 0) & (yi < height)
    idx = torch.where(ok, base + yi * width + xi, torch.full_like(base, n))  # n = dump bin
    out = torch.bincount(idx.reshape(-1), weights=(wx * wy).reshape(-1), minlength=n + 1)[:n]
    return out.to(torch.float32).view(n_images, height, width)


def _gaussian_kernel1d(sigma_px: float, device) -> torch.Tensor:
    r = max(1, int(math.ceil(3.0 * sigma_px)))
    k = torch.arange(-r, r + 1, dtype=torch.float32, device=device)
    g = torch.exp(-0.5 * (k / sigma_px) ** 2)
    return g / g.sum()


def image_variance(images: torch.Tensor, blur_sigma_px: float = 0.0) -> torch.Tensor:
    """Variance of each image, optionally after a separable Gaussian blur.

    The blur removes the bias of bilinear splatting towards warps that land events on integer
    pixels (the un-warped D = 0): the sum of squared Gaussian weights hardly depends on the
    sub-pixel offset.

    Args:
        images: (..., H, W) float.
        blur_sigma_px: Gaussian sigma, px; 0 = no blur.

    Returns:
        (...) float32 variance.
    """
    shape = images.shape
    img = images.reshape(-1, 1, shape[-2], shape[-1])
    if blur_sigma_px > 0:
        g = _gaussian_kernel1d(blur_sigma_px, images.device)
        r = g.numel() // 2
        img = F.conv2d(img, g.view(1, 1, 1, -1), padding=(0, r))
        img = F.conv2d(img, g.view(1, 1, -1, 1), padding=(r, 0))
    flat = img.reshape(img.shape[0], -1)
    m = flat.mean(1)
    v = (flat * flat).mean(1) - m * m
    return v.reshape(shape[:-2])


def warped_contrast(x: torch.Tensor, y: torch.Tensor, b: torch.Tensor, dt_s: torch.Tensor,
                    candidates: torch.Tensor, sensor_hw: Tuple[int, int], pad_px: int = 0,
                    blur_sigma_px: float = 0.0, max_samples: int = 2_000_000) -> torch.Tensor:
    """Contrast (variance) of the warped count image for each element and candidate D.

    Args:
        x, y: (E,) float pixel coordinates; b: (E,) int64 batch index; dt_s: (E,) event time minus
            reference time, s.
        candidates: (B, G) float, candidate D per element, 1/s.
        sensor_hw: (H, W) of the sensor; the canvas is padded by ``pad_px`` on every side so
            events warped slightly outside still count.
        blur_sigma_px: blur before the variance (see :func:`image_variance`).
        max_samples: candidates are processed in chunks of at most this many (event, candidate)
            samples, to bound memory.

    Returns:
        (B, G) float32 contrast.
    """
    B, G = candidates.shape
    H, W = int(sensor_hw[0]) + 2 * pad_px, int(sensor_hw[1]) + 2 * pad_px
    centre = ((sensor_hw[1] - 1) / 2.0 + pad_px, (sensor_hw[0] - 1) / 2.0 + pad_px)
    xs = x.to(torch.float32) + pad_px
    ys = y.to(torch.float32) + pad_px
    E = xs.numel()
    out = torch.zeros(B, G, dtype=torch.float32, device=candidates.device)
    if E == 0:
        return out
    chunk = max(1, min(G, max_samples // max(E, 1)))
    for g0 in range(0, G, chunk):
        g1 = min(G, g0 + chunk)
        cand = candidates[:, g0:g1].to(torch.float32)[b]  # (E, g)
        xw, yw = radial_warp(xs, ys, dt_s.to(torch.float32), cand, centre)
        gi = torch.arange(g1 - g0, device=b.device)
        img_idx = b.unsqueeze(-1) * (g1 - g0) + gi
        imgs = splat_bilinear(xw, yw, img_idx, B * (g1 - g0), H, W)
        out[:, g0:g1] = image_variance(imgs, blur_sigma_px).view(B, g1 - g0)
    return out
