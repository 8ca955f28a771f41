"""The renderer interface shared by every backend (nadir pinhole camera, linear irradiance; see below).

A renderer is built for a list of site names, a camera and a render config; ``render`` takes a
batch of altitudes (m above the landing point) and site indices and returns frames
``(B, H, W) float32`` of linear irradiance (relative units: an albedo-1 Lambertian plate facing
the sun gives 1), finite and > 0 (ambient floor).

Camera: nadir pinhole at (0, 0, h0 + altitude) (h0 = terrain height of the landing point),
square pixels, ``fov_deg`` across the width. Image orientation is the map view: row 0 at the
north edge (rows go south), columns go east.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import torch

from dvsland.config import CameraConfig, RenderConfig
from dvsland.terrain.spec import split_site_name


class Renderer:
    """Base class: argument checks and camera geometry. Subclasses implement :meth:`_render`."""

    name = "base"

    def __init__(self, site_names: Sequence[str], camera: CameraConfig, render: Optional[RenderConfig] = None,
                 device="cpu"):
        site_names = [site_names] if isinstance(site_names, str) else list(site_names)
        if not site_names:
            raise ValueError("site_names must name at least one site (A-I)")
        for s in site_names:
            split_site_name(s)  # A-I or a variant such as "A~1"; ValueError naming the forms
        self.site_names = site_names
        self.camera = camera
        self.render_config = render if render is not None else RenderConfig()
        self.device = torch.device(device)
        if not (self.render_config.min_altitude_m < self.render_config.max_altitude_m):
            raise ValueError("render.min_altitude_m must be below render.max_altitude_m")

    # ------------------------------------------------------------ geometry
    @property
    def height_px(self) -> int:
        return int(self.camera.height_px)

    @property
    def width_px(self) -> int:
        return int(self.camera.width_px)

    @property
    def tan_half_fov(self) -> float:
        """tan(fov / 2), fov across the width."""
        return math.tan(math.radians(self.camera.fov_deg) / 2)

    def pixel_m_per_m(self) -> float:
        """Ground size of the central pixel per metre of altitude (m/m)."""
        return 2 * self.tan_half_fov / self.width_px

    def footprint_m(self, altitude_m: float) -> float:
        """Ground width (m) seen across the image at ``altitude_m`` over flat ground."""
        return 2 * altitude_m * self.tan_half_fov

    def ray_tangents(self, dtype=torch.float32):
        """Per-pixel ray slopes (tx east, ty north), each (H, W): the ray of pixel (i, j) meets
        flat ground at depth z below the camera at (tx * z, ty * z)."""
        h, w = self.height_px, self.width_px
        pitch = self.pixel_m_per_m()
        j = (torch.arange(w, dtype=torch.float64) + 0.5 - w / 2) * pitch
        i = (torch.arange(h, dtype=torch.float64) + 0.5 - h / 2) * pitch
        ty, tx = torch.meshgrid(-i, j, indexing="ij")
        return tx.to(device=self.device, dtype=dtype), ty.to(device=self.device, dtype=dtype)

    # ------------------------------------------------------------ checks
    def check_inputs(self, altitude_m: torch.Tensor, site_idx: torch.Tensor):
        """Validate and move inputs. Returns (altitude_m float32 (B,), site_idx int64 (B,))."""
        if not isinstance(altitude_m, torch.Tensor):
            altitude_m = torch.as_tensor(altitude_m, dtype=torch.float32)
        if not isinstance(site_idx, torch.Tensor):
            site_idx = torch.as_tensor(site_idx, dtype=torch.int64)
        if altitude_m.dim() != 1:
            raise ValueError(f"altitude_m must have shape (B,), got {tuple(altitude_m.shape)}")
        if site_idx.shape != altitude_m.shape:
            raise ValueError(f"site_idx must have shape {tuple(altitude_m.shape)} like altitude_m, "
                             f"got {tuple(site_idx.shape)}")
        if site_idx.dtype.is_floating_point or site_idx.dtype == torch.bool:
            raise ValueError(f"site_idx must be an integer tensor, got {site_idx.dtype}")
        lo, hi = self.render_config.min_altitude_m, self.render_config.max_altitude_m
        n = len(self.site_names)
        if altitude_m.numel():
            alt_ok = torch.isfinite(altitude_m) & (altitude_m >= lo) & (altitude_m <= hi)
            site_ok = (site_idx >= 0) & (site_idx < n)
            ok = torch.stack([alt_ok.all(), site_ok.all()]).cpu()  # one sync for both checks
            if not bool(ok[0]):
                bad = altitude_m[~alt_ok][0].item()
                raise ValueError(f"altitude_m must be in [render.min_altitude_m, render.max_altitude_m] = "
                                 f"[{lo}, {hi}] m, got {bad}")
            if not bool(ok[1]):
                bad = site_idx[~site_ok][0].item()
                raise ValueError(f"site_idx must be in [0, {n - 1}] (sites {self.site_names}), got {bad}")
        return (altitude_m.to(device=self.device, dtype=torch.float32),
                site_idx.to(device=self.device, dtype=torch.int64))

    # ------------------------------------------------------------ rendering
    def render(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        """Frames for a batch of descents.

        Args:
            altitude_m: (B,) altitude above the landing point, m, in
                [render.min_altitude_m, render.max_altitude_m].
            site_idx: (B,) int64 index into ``site_names``.

        Returns:
            (B, H, W) float32 linear irradiance on the renderer's device, finite, > 0.
        """
        altitude_m, site_idx = self.check_inputs(altitude_m, site_idx)
        return self._render(altitude_m, site_idx)

    def render_in_range(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        """:meth:`render` for inputs the caller guarantees: (B,) altitudes finite and within
        [render.min_altitude_m, render.max_altitude_m], (B,) integer site indices in range (the
        loop clamps its altitudes and takes its indices from the layout). No value is checked, so
        no host sync: a value out of range gives wrong frames, not an error."""
        return self._render(altitude_m.to(device=self.device, dtype=torch.float32),
                            site_idx.to(device=self.device, dtype=torch.int64))

    __call__ = render

    def _render(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError
