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
        :class:`Events` on ``device``, sorted by (b, t), polarity alternating; events off the
        sensor dropped. Inputs may live on any device: the draw is made on the CPU generator
        (the same events on every device) and the result moved to ``device`` at the end.
    """
    # everything is computed on the CPU, where the generator draws, then moved once
    offsets = offsets.detach().cpu()
    divergence = torch.as_tensor(divergence).detach().cpu()
    if active is not None:
        active = torch.as_tensor(active).detach().cpu()
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
        ok = ok & active.view(B, 1)
    p = torch.where(torch.arange(n) % 2 == 0, 1, -1).to(torch.int8).expand(B, n)
    ev = Events(b[ok], xy[..., 0][ok], xy[..., 1][ok], t_us[ok], p[ok], sort=True)
    return ev.to(device)


class ZoomTextureFrames:
    """A stand-in renderer: a seeded random texture per site seen from a nadir camera.

    The ground texture is smooth noise blobs; at altitude z the image shows a footprint of width
    ``2 z tan(fov/2)`` about the landing point, so frames zoom exactly as in a vertical descent
    (features in px scale as 1/z). For tests and development without the terrain renderer.

    Args:
        n_sites: number of textures.
        sensor_size: (W, H).
        fov_deg: field of view across the width.
        texture_px: texture side, texels; ``ground_m``: its ground width, m.
        seed: texture seed.

    Call with (altitude_m (B,), site_idx (B,)) -> (B, H, W) float32 irradiance in [0.05, 1.05].
    """

    def __init__(self, n_sites: int, sensor_size=(128, 128), fov_deg: float = 60.0, texture_px: int = 1024,
                 ground_m: float = 12000.0, seed: int = 0, device="cpu"):
        import math

        import torch.nn.functional as F

        g = torch.Generator().manual_seed(int(seed))
        tex = torch.rand(n_sites, 1, texture_px // 8, texture_px // 8, generator=g)
        tex = F.interpolate(tex, size=(texture_px, texture_px), mode="bicubic", align_corners=False)
        fine = torch.rand(n_sites, 1, texture_px // 2, texture_px // 2, generator=g)
        tex = tex + 0.5 * F.interpolate(fine, size=(texture_px, texture_px), mode="bilinear", align_corners=False)
        tex = (tex - tex.amin((2, 3), keepdim=True)) / (tex.amax((2, 3), keepdim=True)
                                                         - tex.amin((2, 3), keepdim=True))
        self.texture = (0.05 + tex).to(device)
        self.W, self.H = int(sensor_size[0]), int(sensor_size[1])
        self.tan_half = math.tan(math.radians(fov_deg) / 2)
        self.ground_m = float(ground_m)
        self.device = torch.device(device)

    def __call__(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        import torch.nn.functional as F

        B = altitude_m.shape[0]
        half_w = altitude_m.to(torch.float32).to(self.device) * self.tan_half  # m
        u = (torch.arange(self.W, device=self.device, dtype=torch.float32) + 0.5) / self.W * 2 - 1
        v = (torch.arange(self.H, device=self.device, dtype=torch.float32) + 0.5) / self.H * 2 - 1
        vv, uu = torch.meshgrid(v * self.H / self.W, u, indexing="ij")
        s = (half_w / (self.ground_m / 2)).view(B, 1, 1)
        grid = torch.stack([uu.unsqueeze(0) * s, vv.unsqueeze(0) * s], -1)
        tex = self.texture.index_select(0, site_idx.to(device=self.device, dtype=torch.long))
        return F.grid_sample(tex, grid, mode="bilinear", padding_mode="reflection", align_corners=False)[:, 0]
