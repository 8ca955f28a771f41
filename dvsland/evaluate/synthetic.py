"""Synthetic event streams with a known divergence, for tests and development.

:func:`zoom_blob_events` draws events around point features (blobs) that spread radially about the
image centre as a camera descending with constant divergence D would see them:
``r(t) = r(0) exp(-D t)`` (D < 0 while descending, so features move outwards).
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from dvsland.events import Events


def blob_layout(batch_size: int, n_blobs: int, sensor_size: Tuple[int, int], extent: float = 0.85,
                seed: int = 0) -> torch.Tensor:
    """Random blob offsets from the image centre at t = 0, (B, n_blobs, 2) float64 px (x, y).

    Offsets are uniform within ``extent`` times the half-size of the sensor.
    """
    g = torch.Generator().manual_seed(int(seed))
    W, H = sensor_size
    half = torch.tensor([W / 2.0, H / 2.0], dtype=torch.float64) * extent
    return (torch.rand(batch_size, n_blobs, 2, generator=g, dtype=torch.float64) * 2 - 1) * half


def zoom_blob_events(offsets: torch.Tensor, divergence: torch.Tensor, t0_us: int, t1_us: int,
                     sensor_size: Tuple[int, int], events_per_blob: int = 40, sigma_px: float = 0.7,
                     seed: int = 0, active: Optional[torch.Tensor] = None, device="cpu") -> Events:
    """Events in (t0_us, t1_us] around blobs zooming with constant divergence.

    Args:
        offsets: (B, K, 2) float blob offsets from the centre at t = 0, px.
        divergence: (B,) float D, 1/s (negative = features spread outwards).
        t0_us, t1_us: the interval, int µs.
        sensor_size: (W, H).
        events_per_blob: events per blob in the interval.
        sigma_px: Gaussian spread of the events about the blob centre, px.
        seed: seed of the draw (combine with the interval to get a new draw each step).
        active: (B,) bool, elements that get events (default all).

    Returns:
        :class:`Events` sorted by (b, t), polarity alternating; events off the sensor dropped.
    """
    B, K, _ = offsets.shape
    W, H = sensor_size
    g = torch.Generator().manual_seed(int(seed))
    n = K * events_per_blob
    t_us = torch.randint(int(t0_us) + 1, int(t1_us) + 1, (B, n), generator=g)
    k = torch.arange(n) % K
    scale = torch.exp(-divergence.to(torch.float64).view(B, 1) * t_us.to(torch.float64) * 1e-6)
    centre = torch.tensor([(W - 1) / 2.0, (H - 1) / 2.0], dtype=torch.float64)
    pos = offsets.to(torch.float64)[:, k] * scale.unsqueeze(-1) + centre
    pos = pos + torch.randn(B, n, 2, generator=g, dtype=torch.float64) * sigma_px
    xy = torch.round(pos).to(torch.int64)
    b = torch.arange(B).view(B, 1).expand(B, n)
    ok = (xy[..., 0] >= 0) & (xy[..., 0] < W) & (xy[..., 1] >= 0) & (xy[..., 1] < H)
    if active is not None:
        ok = ok & active.view(B, 1).cpu()
    p = torch.where(torch.arange(n) % 2 == 0, 1, -1).to(torch.int8).expand(B, n)
    ev = Events(b[ok], xy[..., 0][ok], xy[..., 1][ok], t_us[ok], p[ok], sort=True)
    return ev.to(device)
