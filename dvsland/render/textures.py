"""Renderer ``textures``: procedural ground that is none of the terrains, for generalisation.

Each site name gets its own seeded texture, flat and scale-free, built from two families of
features that the terrains do not have:

- a **1/f^beta field**: ``n_waves`` plane waves whose spatial frequencies are log-uniform over the
  scales the camera can see, orientations and phases uniform, and per-wave amplitude
  f^((2 - beta) / 2), so that the power spectrum falls as 1/f^beta (beta per texture in
  [1.6, 2.4]; natural photographs sit near 2). It looks alike at every altitude;
- **sharp-edged ellipses** (``n_shapes``) of log-uniform size, brighter or darker than the field,
  placed about the landing point at every scale.

Frames are exact pixel integrals of the waves (each wave times the pixel's box response
sinc(f_x p) sinc(f_y p), p the pixel's ground size; waves beyond the Nyquist limit fade to 0 over
the last third of the band) and of the ellipses' edges (a one-pixel linear ramp), so nothing
aliases and a frame depends only on the altitude and the texture. The field's contrast, its mean
brightness and the ellipses' strength are drawn per texture. Site names are only texture keys:
``"A"`` and ``"A~3"`` are two textures; the texture of a name depends on the name and
``seed`` only.

Cost: O(H W (n_waves + n_shapes)) per frame, about 10-20x the ``fast`` renderer; meant for
datasets and generalisation checks, not for campaigns.
"""

from __future__ import annotations

import hashlib
import math
from typing import Optional, Sequence, Tuple

import torch

from dvsland.config import CameraConfig, RenderConfig

from .base import Renderer

#: largest and smallest ground scale the features cover, as multiples of the view (the footprint at
#: the highest altitude) and of the pixel (at the lowest)
_VIEW_MULT, _PIXEL_MULT = 2.0, 1.0
#: (frames x pixels x features) float32 values rendered at once (~64 MB)
_CHUNK_VALUES = 1 << 24


def texture_seed(name: str, seed: int) -> int:
    """A 63-bit seed of (site name, seed): the same on every machine and run."""
    h = hashlib.sha256(f"dvsland-textures:{int(seed)}:{name}".encode()).digest()
    return int.from_bytes(h[:8], "little") & ((1 << 63) - 1)


def texture_params(name: str, seed: int, f_lo: float, f_hi: float, n_waves: int, n_shapes: int) -> dict:
    """The random parameters of one texture (float64 tensors; frequencies in cycles/m, sizes in m).

    Returns a dict: ``fx``, ``fy``, ``phase``, ``amp`` (n_waves,); ``cx``, ``cy``, ``ca``, ``sa``,
    ``inv_a``, ``inv_b``, ``r_min``, ``gain`` (n_shapes,); ``mean``, ``contrast``, ``beta`` floats.
    """
    g = torch.Generator().manual_seed(texture_seed(name, seed))

    def u(n, lo=0.0, hi=1.0):
        return lo + (hi - lo) * torch.rand(n, generator=g, dtype=torch.float64)

    beta = float(u(1, 1.6, 2.4))
    f = torch.exp(u(n_waves, math.log(f_lo), math.log(f_hi)))
    ang = u(n_waves, 0.0, 2 * math.pi)
    amp = f ** ((2.0 - beta) / 2.0)
    amp = amp * math.sqrt(2.0 / float((amp ** 2).sum()))  # the whole field: unit variance
    r = torch.exp(u(n_shapes, math.log(0.5 / f_hi), math.log(0.5 / f_lo)))  # semi-major axes, m
    spread = r * 8.0  # centres within +-8 sizes of the landing point: every scale in view
    rot = u(n_shapes, 0.0, math.pi)
    aspect = u(n_shapes, 0.4, 1.0)
    sign = torch.where(u(n_shapes) < 0.5, -1.0, 1.0)
    return {"fx": f * torch.cos(ang), "fy": f * torch.sin(ang), "phase": u(n_waves, 0.0, 2 * math.pi), "amp": amp,
            "cx": u(n_shapes, -1.0, 1.0) * spread, "cy": u(n_shapes, -1.0, 1.0) * spread,
            "ca": torch.cos(rot), "sa": torch.sin(rot), "inv_a": 1.0 / r, "inv_b": 1.0 / (r * aspect),
            "r_min": r * aspect, "gain": sign * u(n_shapes, 0.15, 0.6),
            "mean": float(u(1, 0.3, 1.0)), "contrast": float(u(1, 0.12, 0.45)), "beta": beta}


class TextureRenderer(Renderer):
    """Procedural scale-free textures (module doc), one per site name.

    Args:
        site_names, camera, render, device: as :class:`~dvsland.render.base.Renderer`.
        seed: texture seed (with the site name).
        n_waves: plane waves of the 1/f^beta field per texture.
        n_shapes: ellipses per texture.
        altitude_range_m: (lo, hi) altitudes the features are laid out for (default the render
            config's ``min_altitude_m`` / ``max_altitude_m``); a narrower range puts every feature
            where it is seen.
    """

    name = "textures"

    def __init__(self, site_names: Sequence[str], camera: CameraConfig, render: Optional[RenderConfig] = None,
                 device="cpu", seed: int = 0, n_waves: int = 96, n_shapes: int = 96,
                 altitude_range_m: Optional[Tuple[float, float]] = None):
        super().__init__(site_names, camera, render, device)
        for key, v in (("n_waves", n_waves), ("n_shapes", n_shapes)):
            if not (isinstance(v, int) and 1 <= v <= 4096):
                raise ValueError(f"{key} must be an integer in [1, 4096], got {v!r}")
        lo, hi = altitude_range_m if altitude_range_m is not None else (self.render_config.min_altitude_m,
                                                                        self.render_config.max_altitude_m)
        if not (0 < float(lo) < float(hi)):
            raise ValueError(f"altitude_range_m must be (lo, hi) with 0 < lo < hi, got {altitude_range_m!r}")
        f_lo = 1.0 / (_VIEW_MULT * self.footprint_m(float(hi)))
        f_hi = 0.5 / (_PIXEL_MULT * self.pixel_m_per_m() * float(lo))
        ps = [texture_params(n, seed, f_lo, f_hi, int(n_waves), int(n_shapes)) for n in self.site_names]
        keys = [k for k in ps[0] if isinstance(ps[0][k], torch.Tensor)]
        #: per texture and feature, (S, n) float32 on the device; scalars (S,)
        self.tables = {k: torch.stack([p[k] for p in ps]).to(device=self.device, dtype=torch.float32) for k in keys}
        for k in ("mean", "contrast"):
            self.tables[k] = torch.tensor([p[k] for p in ps], dtype=torch.float32, device=self.device)
        tx, ty = self.ray_tangents(torch.float32)
        self._tx, self._ty = tx.reshape(-1), ty.reshape(-1)  # (P,) ground offset per metre of altitude

    def _render(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        B, H, W = altitude_m.shape[0], self.height_px, self.width_px
        out = torch.empty(B, H, W, dtype=torch.float32, device=self.device)
        n = max(1, _CHUNK_VALUES // (H * W * max(self.tables["fx"].shape[1], self.tables["cx"].shape[1])))
        for i in range(0, B, n):  # frames in groups: the (frames, pixels, features) terms stay ~64 MB
            out[i:i + n] = self._render_group(altitude_m[i:i + n], site_idx[i:i + n])
        return out

    def _render_group(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        B, H, W = altitude_m.shape[0], self.height_px, self.width_px
        t = {k: v.index_select(0, site_idx) for k, v in self.tables.items()}
        z = altitude_m.view(B, 1)
        p = z * self.pixel_m_per_m()  # (B, 1) pixel ground size, m
        ones = torch.ones_like(self._tx)
        # (B, P, 3): ground east, north (m) and 1 per pixel; every feature is then a matmul away
        xy1 = torch.stack([self._tx.unsqueeze(0) * z, self._ty.unsqueeze(0) * z, ones.expand(B, -1)], 2)
        out = self._field(t, xy1, p) + self._shapes(t, xy1, p)
        return out.view(B, H, W).clamp_min(0.02)

    def _field(self, t: dict, xy1: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """(B, P) the 1/f^beta field, pixel-integrated, times contrast, plus the mean."""
        fx, fy = t["fx"], t["fy"]  # (B, K)
        fxp, fyp = (fx * p).abs(), (fy * p).abs()
        fade = ((0.5 - torch.maximum(fxp, fyp)) / (0.5 / 3.0)).clamp(0.0, 1.0)  # 0 beyond Nyquist
        w = t["amp"] * torch.sinc(fxp) * torch.sinc(fyp) * fade  # (B, K)
        coef = torch.stack([2 * math.pi * fx, 2 * math.pi * fy, t["phase"]], 1)  # (B, 3, K)
        s = torch.bmm(torch.bmm(xy1, coef).cos_(), w.unsqueeze(2)).squeeze(2)  # (B, P)
        return t["mean"].view(-1, 1) * (1.0 + t["contrast"].view(-1, 1) * s)

    def _shapes(self, t: dict, xy1: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """(B, P) the ellipses' brightness offsets (edges a one-pixel ramp)."""
        ca, sa, ia, ib = t["ca"], t["sa"], t["inv_a"], t["inv_b"]  # (B, M)
        cx, cy = t["cx"], t["cy"]
        # the ellipse's own axes, in semi-axes: u = ((x - cx) ca + (y - cy) sa) / a, v likewise / b
        U = torch.stack([ca * ia, sa * ia, -(cx * ca + cy * sa) * ia], 1)  # (B, 3, M)
        V = torch.stack([-sa * ib, ca * ib, (cx * sa - cy * ca) * ib], 1)
        u, v = torch.bmm(xy1, U), torch.bmm(xy1, V)  # (B, P, M)
        rho = u.mul_(u).addcmul_(v, v).sqrt_()  # 1 on the edge
        k = (t["r_min"] / p).unsqueeze(1)  # (B, 1, M) semi-minor axis in pixels: the ramp's slope
        inside = rho.mul_(-k).add_(k + 0.5).clamp_(0.0, 1.0)  # 0.5 - (rho - 1) r_min / p
        # an ellipse narrower than two pixels fades with its area (no one-pixel speckle)
        gain = t["gain"] * (2.0 * t["r_min"] / p).clamp(max=1.0) ** 2  # (B, M)
        return t["mean"].view(-1, 1) * torch.bmm(inside, gain.unsqueeze(2)).squeeze(2)


__all__ = ["TextureRenderer", "texture_params", "texture_seed"]
