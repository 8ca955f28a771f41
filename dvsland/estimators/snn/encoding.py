"""Events -> log-polar event-rate tensors about the focus of expansion (the image centre).

Under a pure descent a ground point's image radius grows as r(t) ∝ 1 / z(t), so
d(log r)/dt = -v/z = -D: in log-polar coordinates (rho = log r, phi) the whole event pattern slides
along rho at the same speed |D| everywhere. Estimating D becomes estimating one global 1-D
translation speed, which suits a small convolutional network with pooling over the image.

Each pixel centre within [r_min_px, r_max_px] of the focus of expansion (the camera's principal
point) belongs to one (rho, phi) bin (precomputed); a step's events are split into ``n_sub``
equal time slices and counted per (slice, polarity, bin) with one ``bincount``, then divided by the
number of pixels in the bin (events per pixel).

Any sensor size: the motion in rho is |D| whatever the radii, so on a sensor smaller than
2 r_max_px the annulus is scaled down (both radii by min(W, H) / (2 r_max_px)), keeping the bins.
Bins that fall off the sensor (an off-centre principal point) hold no pixel and read 0.
Events outside the sensor (x not in [0, W), y not in [0, H)) or the batch are ignored and counted
in ``dropped``.
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
                 r_max_px: float = 64.0, n_sub: int = 4, device="cpu", principal_point_px=None):
        w, h = int(sensor_size[0]), int(sensor_size[1])
        for name, v in (("n_rho", n_rho), ("n_phi", n_phi), ("n_sub", n_sub)):
            if int(v) < 1:
                raise ValueError(f"{name} must be >= 1, got {v}")
        if not 0 < r_min_px < r_max_px:
            raise ValueError(f"need 0 < r_min_px < r_max_px, got {r_min_px}, {r_max_px}")
        from ..base import resolve_principal_point

        self.sensor_size = (w, h)
        self.n_rho, self.n_phi, self.n_sub = int(n_rho), int(n_phi), int(n_sub)
        #: radii as trained; the radii used are scaled by ``radius_scale`` on a small sensor
        self.r_min_px, self.r_max_px = float(r_min_px), float(r_max_px)
        self.radius_scale = min(1.0, min(w, h) / (2.0 * self.r_max_px))
        r_min_px, r_max_px = self.r_min_px * self.radius_scale, self.r_max_px * self.radius_scale
        self.principal_point_px = resolve_principal_point(principal_point_px, (w, h))
        self.device = torch.device(device)
        ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                                indexing="ij")
        dx, dy = xs - self.principal_point_px[0], ys - self.principal_point_px[1]
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
        cx, cy = self.principal_point_px
        d_edge = min(cx + 0.5, w - 0.5 - cx, cy + 0.5, h - 0.5 - cy)  # FoE to the nearest sensor edge
        r_out = r_min_px * (r_max_px / r_min_px) ** ((torch.arange(self.n_rho, dtype=torch.float64) + 1) / self.n_rho)
        whole = (r_out <= d_edge).repeat_interleave(self.n_phi)  # rings that lie on the sensor entirely
        if bool(((counts == 0) & whole).any()):
            raise ValueError(f"log-polar bins without a pixel on the {w}x{h} sensor: lower n_rho / n_phi, raise r_min_px "
                             f"or use a larger sensor "
                             f"(got n_rho={n_rho}, n_phi={n_phi}, r_min_px={r_min_px:g})")
        if not bool((counts > 0).any()):
            raise ValueError(f"no sensor pixel lies in the log-polar annulus (sensor {w}x{h}, principal point "
                             f"{self.principal_point_px}, radii {r_min_px:g}-{r_max_px:g} px)")
        #: (n_rho, n_phi) pixels per bin (0 = bin off the sensor: it reads 0)
        self.pixels_per_bin = counts.view(self.n_rho, self.n_phi).to(self.device)
        self._inv_pixels = torch.where(self.pixels_per_bin > 0, 1.0 / self.pixels_per_bin.clamp_min(1.0),
                                       torch.zeros_like(self.pixels_per_bin))
        #: events ignored by the last ``encode`` (off the sensor or the batch)
        self.dropped = 0
        #: (B,) events that fell in the annulus in the last ``encode``
        self.events_in_annulus = torch.zeros(0)

    def encode(self, events, t0_us: int, t1_us: int, batch_size: int) -> torch.Tensor:
        """(B, n_sub, 2, n_rho, n_phi) events per pixel of the events in (t0_us, t1_us]; channel 0
        ON, 1 OFF. Events outside the interval count in the nearest slice. Sets ``dropped`` and
        ``events_in_annulus`` (:meth:`encode_counts` returns them instead)."""
        x, n_ann, dropped = self.encode_counts(events, t0_us, t1_us, batch_size)
        self.dropped, self.events_in_annulus = int(dropped), n_ann
        return x

    def encode_counts(self, events, t0_us, t1_us: int, batch_size: int):
        """:meth:`encode` without side effects and without a host read: (x (B, n_sub, 2, n_rho,
        n_phi) float32 events per pixel, events_in_annulus (B,) int64, dropped () int64 events off
        the sensor or the batch). ``t0_us``: an int, or a (B,) int64 tensor per row."""
        b_n, s_n, k = int(batch_size), self.n_sub, self.n_bins
        out = torch.zeros(b_n * s_n * 2 * k, dtype=torch.float32, device=self.device)
        if events is None or not len(events):
            zero = torch.zeros(b_n, dtype=torch.int64, device=self.device)
            return out.view(b_n, s_n, 2, self.n_rho, self.n_phi) * self._inv_pixels, zero, zero.sum()
        w, h = self.sensor_size
        ev_b, ev_x, ev_y = (getattr(events, f).to(self.device, torch.int64) for f in ("b", "x", "y"))
        ok = (ev_x >= 0) & (ev_x < w) & (ev_y >= 0) & (ev_y < h) & (ev_b >= 0) & (ev_b < b_n)
        pix = torch.where(ok, ev_y * w + ev_x, torch.zeros_like(ev_x))
        bins = torch.where(ok, self.bin_of_pixel[pix], torch.full_like(pix, -1))
        ev_t = events.t.to(self.device)
        if isinstance(t0_us, torch.Tensor):  # per row (rows outside the batch: row 0's, they are dropped)
            t0 = t0_us.to(self.device).index_select(0, ev_b.clamp(0, b_n - 1))
            span = (int(t1_us) - t0).clamp_min(1)
        else:
            t0, span = int(t0_us), max(int(t1_us) - int(t0_us), 1)
        sl = ((ev_t - t0 - 1) * s_n).div(span, rounding_mode="floor").clamp(0, s_n - 1)
        pol = (events.p.to(self.device) < 0).to(torch.int64)
        keep = bins >= 0
        # events outside the annulus go to one extra bin, dropped after counting (no host read)
        n_out = out.numel()
        idx = torch.where(keep, ((ev_b * s_n + sl) * 2 + pol) * k + bins, torch.full_like(bins, n_out))
        out += torch.bincount(idx, minlength=n_out + 1)[:n_out].to(torch.float32)
        n_ann = torch.bincount(torch.where(keep, ev_b, torch.full_like(ev_b, b_n)), minlength=b_n + 1)[:b_n]
        return out.view(b_n, s_n, 2, self.n_rho, self.n_phi) * self._inv_pixels, n_ann, (~ok).sum()
