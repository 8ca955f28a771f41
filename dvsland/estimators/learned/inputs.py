"""The input of the learned models: a polarity-signed voxel grid, pooled, with coordinate channels.

One control step's events (the window ``(t0_us, t_us]``) become a voxel grid of ``n_bins`` time
bins (bilinear in time, an OFF event subtracts), summed over ``pool_px`` x ``pool_px`` pixel
blocks, so a 128 x 128 sensor with ``pool_px = 2`` gives (n_bins, 64, 64). Two coordinate
channels give every cell's centre relative to the principal point (the focus of expansion), in
units of ``coord_scale_px`` sensor pixels: divergence is a radial expansion about that point.

Everything is batch first and built with one ``index_put_`` over all events of all B windows
(no Python loop over the batch or the events).
"""

from __future__ import annotations

from typing import NamedTuple, Tuple

import torch


class InputSpec(NamedTuple):
    """How events become a model input. ``sensor_size`` (W, H) px; ``n_bins`` time bins in all;
    ``pool_px`` sensor pixels per cell side; ``coord_scale_px`` px per coordinate unit;
    ``n_windows`` control steps the input spans (the last K windows, n_bins / K bins each; with
    K > 1 an event goes to its nearest bin, so the grids of single windows concatenate exactly;
    with K = 1 bins are bilinear in time)."""

    sensor_size: Tuple[int, int]
    n_bins: int = 4
    pool_px: int = 2
    coord_scale_px: float = 64.0
    n_windows: int = 1

    @property
    def bins_per_window(self) -> int:
        """n_bins / n_windows."""
        return self.n_bins // self.n_windows

    @property
    def grid_hw(self) -> Tuple[int, int]:
        """(h, w) cells of the pooled grid (ceil of H / pool_px, W / pool_px)."""
        W, H = self.sensor_size
        return (-(-H // self.pool_px), -(-W // self.pool_px))


def check_input_spec(spec: InputSpec) -> InputSpec:
    """ValueError naming the field for values outside their ranges."""
    W, H = (int(v) for v in spec.sensor_size)
    if W < 8 or H < 8:
        raise ValueError(f"sensor_size must be (W, H) with W, H >= 8 px, got {spec.sensor_size}")
    if not 1 <= int(spec.n_bins) <= 32:
        raise ValueError(f"n_bins must be in [1, 32], got {spec.n_bins}")
    if not 1 <= int(spec.pool_px) <= 16:
        raise ValueError(f"pool_px must be in [1, 16], got {spec.pool_px}")
    if not float(spec.coord_scale_px) > 0:
        raise ValueError(f"coord_scale_px must be > 0, got {spec.coord_scale_px}")
    if not 1 <= int(spec.n_windows) <= 32 or int(spec.n_bins) % int(spec.n_windows):
        raise ValueError(f"n_windows must be in [1, 32] and divide n_bins = {spec.n_bins}, got {spec.n_windows}")
    return InputSpec((W, H), int(spec.n_bins), int(spec.pool_px), float(spec.coord_scale_px), int(spec.n_windows))


def voxel_grid(b: torch.Tensor, x: torch.Tensor, y: torch.Tensor, frac: torch.Tensor, p: torch.Tensor,
               batch_size: int, spec: InputSpec, n_bins: int = None) -> torch.Tensor:
    """Signed, pooled voxel grids of B windows.

    Args:
        b: (N,) int64 window (batch row) of each event, in [0, B).
        x, y: (N,) integer pixel column and row on the sensor.
        frac: (N,) float32 event time as a fraction of its window, in [0, 1].
        p: (N,) polarity, +1 ON / -1 OFF (any integer or float dtype).
        batch_size: B.
        spec: the :class:`InputSpec`.
        n_bins: bins of this grid (default ``spec.n_bins``; one window's: ``spec.bins_per_window``).

    Returns:
        (B, n_bins, h, w) float32: per cell and bin, ON minus OFF events; with
        ``spec.n_windows`` = 1 each split linearly between its two nearest bins (bin centres at
        k / (n_bins - 1)), else in the bin it falls in (bin k = [k, k + 1) / n_bins).
    """
    h, w = spec.grid_hw
    nb = spec.n_bins if n_bins is None else int(n_bins)
    out = torch.zeros(batch_size * nb * h * w, dtype=torch.float32, device=b.device)
    if b.numel() == 0:
        return out.view(batch_size, nb, h, w)
    cell = (y.long() // spec.pool_px) * w + (x.long() // spec.pool_px)
    pol = p.to(torch.float32)
    base = b.long() * (nb * h * w) + cell
    if spec.n_windows > 1:
        k = (frac.to(torch.float32) * nb).long().clamp(0, nb - 1)
        out.index_put_((base + k * (h * w),), pol, accumulate=True)
        return out.view(batch_size, nb, h, w)
    tb = frac.to(torch.float32).clamp(0.0, 1.0) * (nb - 1)
    lo = tb.floor().long().clamp(max=nb - 1)
    wt_hi = tb - lo.to(torch.float32)
    hi = (lo + 1).clamp(max=nb - 1)
    out.index_put_((base + lo * (h * w),), pol * (1.0 - wt_hi), accumulate=True)
    out.index_put_((base + hi * (h * w),), pol * wt_hi, accumulate=True)
    return out.view(batch_size, nb, h, w)


def coord_channels(spec: InputSpec, principal_point_px: Tuple[float, float], device=None) -> torch.Tensor:
    """(1, 2, h, w) float32: each cell centre's (x - cx, y - cy) / coord_scale_px, sensor pixels."""
    h, w = spec.grid_hw
    cx, cy = (float(v) for v in principal_point_px)
    P = spec.pool_px
    xs = (torch.arange(w, dtype=torch.float32) * P + (P - 1) / 2.0 - cx) / spec.coord_scale_px
    ys = (torch.arange(h, dtype=torch.float32) * P + (P - 1) / 2.0 - cy) / spec.coord_scale_px
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy])[None].to(device)


def events_voxel_grid(events, t0_us: int, t_us: int, batch_size: int, spec: InputSpec) -> torch.Tensor:
    """:func:`voxel_grid` of one :class:`dvsland.events.Events` window (t0_us, t_us], µs int:
    (B, spec.bins_per_window, h, w)."""
    span = max(int(t_us) - int(t0_us), 1)
    frac = (events.t - int(t0_us)).to(torch.float64).div_(span).to(torch.float32)
    return voxel_grid(events.b, events.x, events.y, frac, events.p, batch_size, spec, spec.bins_per_window)
