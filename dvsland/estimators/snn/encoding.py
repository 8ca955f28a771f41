"""Events -> log-polar event-rate tensors about the focus of expansion (the image centre).

Under a pure descent a ground point's image radius grows as r(t) ∝ 1 / z(t), so
d(log r)/dt = -v/z = -D: in log-polar coordinates (rho = log r, phi) the whole event pattern slides
along rho at the same speed |D| everywhere. Estimating D becomes estimating one global 1-D
translation speed, which suits a small convolutional network with pooling over the image.

Each pixel centre within [r_min_px, r_max_px] of the centre belongs to one (rho, phi) bin
(precomputed); a step's events are split into ``n_sub`` equal time slices and counted per
(slice, polarity, bin) with one ``bincount``, then divided by the number of pixels in the bin
(events per pixel).
"""

from __future__ import annotations

import math

import torch


class LogPolarEncoder:
    """Events of one control step -> (B, n_sub, 2, n_rho, n_phi) float32 events per pixel.

    Args:
        sensor_size: (W, H) pixels; the centre is the focus of expansion of a nadir camera.
        n_rho, n_phi: bins in log radius and angle.
        r_min_px, r_max_px: radii covered (pixels nearer the centre carry little flow).
        n_sub: time slices per step.
        device: torch device of the output.
    """

    def __init__(self, sensor_size, n_rho: int = 24, n_phi: int = 24, r_min_px: float = 16.0,
                 r_max_px: float = 64.0, n_sub: int = 4, device="cpu"):
        w, h = int(sensor_size[0]), int(sensor_size[1])
        for name, v in (("n_rho", n_rho), ("n_phi", n_phi), ("n_sub", n_sub)):
            if int(v) < 1:
                raise ValueError(f"{name} must be >= 1, got {v}")
        if not 0 < r_min_px < r_max_px:
            raise ValueError(f"need 0 < r_min_px < r_max_px, got {r_min_px}, {r_max_px}")
        self.sensor_size = (w, h)
        self.n_rho, self.n_phi, self.n_sub = int(n_rho), int(n_phi), int(n_sub)
        self.r_min_px, self.r_max_px = float(r_min_px), float(r_max_px)
        self.device = torch.device(device)
        ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                                indexing="ij")
        dx, dy = xs + 0.5 - w / 2, ys + 0.5 - h / 2
        r = torch.sqrt(dx * dx + dy * dy)
        rho = (torch.log(r.clamp(min=1e-9)) - math.log(r_min_px)) / (math.log(r_max_px) - math.log(r_min_px))
        phi = (torch.atan2(dy, dx) + math.pi) / (2 * math.pi)
        ir = torch.floor(rho * self.n_rho).to(torch.int64)
        ip = torch.floor(phi * self.n_phi).to(torch.int64).clamp(max=self.n_phi - 1)
        inside = (ir >= 0) & (ir < self.n_rho)
        bin_of_px = torch.where(inside, ir * self.n_phi + ip, torch.full_like(ir, -1))
        self.n_bins = self.n_rho * self.n_phi
        #: (H * W,) int64 bin of each pixel, -1 outside the annulus
        self.bin_of_pixel = bin_of_px.flatten().to(self.device)
        counts = torch.bincount(bin_of_px[inside].flatten(), minlength=self.n_bins).to(torch.float32)
        if bool((counts == 0).any()):
            raise ValueError(f"log-polar bins without a pixel: lower n_rho / n_phi or raise r_min_px "
                             f"(got n_rho={n_rho}, n_phi={n_phi}, r_min_px={r_min_px})")
        #: (n_rho, n_phi) pixels per bin
        self.pixels_per_bin = counts.view(self.n_rho, self.n_phi).to(self.device)

    def encode(self, events, t0_us: int, t1_us: int, batch_size: int) -> torch.Tensor:
        """(B, n_sub, 2, n_rho, n_phi) events per pixel of the events in (t0_us, t1_us]; channel 0
        ON, 1 OFF. Events outside the interval count in the nearest slice."""
        b_n, s_n, k = int(batch_size), self.n_sub, self.n_bins
        out = torch.zeros(b_n * s_n * 2 * k, dtype=torch.float32, device=self.device)
        if events is not None and len(events):
            w = self.sensor_size[0]
            bins = self.bin_of_pixel[events.y * w + events.x]
            span = max(int(t1_us) - int(t0_us), 1)
            sl = ((events.t - int(t0_us) - 1) * s_n).div(span, rounding_mode="floor").clamp(0, s_n - 1)
            pol = (events.p < 0).to(torch.int64)
            keep = bins >= 0
            idx = ((events.b * s_n + sl) * 2 + pol) * k + bins
            out += torch.bincount(idx[keep], minlength=out.numel()).to(torch.float32)
        return out.view(b_n, s_n, 2, self.n_rho, self.n_phi) / self.pixels_per_bin
