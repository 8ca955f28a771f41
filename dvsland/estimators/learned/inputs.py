"""The input of the learned models: a polarity-signed voxel grid, pooled, with coordinate channels.

One control step's events (the window ``(t0_us, t_us]``) become a voxel grid of ``n_bins`` time
bins (bilinear in time, an OFF event subtracts), summed over ``pool_px`` x ``pool_px`` pixel
blocks, so a 128 x 128 sensor with ``pool_px = 2`` gives (n_bins, 64, 64). Two coordinate
channels give every cell's centre relative to the principal point (the focus of expansion), in
units of ``coord_scale_px`` sensor pixels: divergence is a radial expansion about that point.

A camera other than the model's (another sensor size or lens, an off-centre principal point) is
resampled onto the model's *reference canvas* (:class:`CameraMap`, :func:`to_reference`): an event
at pixel (x, y) goes to the reference pixel ``c0 + (x - cx) f_ref / f`` (rounded), where (cx, cy) is
the camera's principal point, f its focal length in px, c0 the reference sensor's centre and f_ref
its focal length. So the principal point always lands on the canvas centre and a pixel's angle is the
reference's: the flow of a divergence D looks the same on any camera; events that fall off the
canvas are dropped (a crop about the principal point), canvas cells the sensor does not cover stay 0.

Everything is batch first and built with one ``index_put_`` over all events of all B windows
(no Python loop over the batch or the events).
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

import torch

from dvsland.config.schema import DEFAULT_FOV_DEG, focal_length_px
from dvsland.events import native

from ..base import resolve_principal_point


class InputSpec(NamedTuple):
    """How events become a model input. ``sensor_size`` (W, H) px; ``n_bins`` time bins in all;
    ``pool_px`` sensor pixels per cell side; ``coord_scale_px`` px per coordinate unit;
    ``n_windows`` control steps the input spans (the last K windows, n_bins / K bins each; with
    K > 1 an event goes to its nearest bin, so the grids of single windows concatenate exactly;
    with K = 1 bins are bilinear in time); ``focal_px`` the reference sensor's focal length, px
    (None = a 60 degree field of view across W)."""

    sensor_size: Tuple[int, int]
    n_bins: int = 4
    pool_px: int = 2
    coord_scale_px: float = 64.0
    n_windows: int = 1
    focal_px: Optional[float] = None

    @property
    def reference_focal_px(self) -> float:
        """The reference sensor's focal length, px: ``focal_px`` or that of a 60 degree field of view."""
        if self.focal_px is not None:
            return float(self.focal_px)
        return focal_length_px(self.sensor_size[0], DEFAULT_FOV_DEG)

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
    if spec.focal_px is not None and not float(spec.focal_px) > 0:
        raise ValueError(f"focal_px must be > 0 (or None), got {spec.focal_px}")
    return InputSpec((W, H), int(spec.n_bins), int(spec.pool_px), float(spec.coord_scale_px), int(spec.n_windows),
                     None if spec.focal_px is None else float(spec.focal_px))


class CameraMap(NamedTuple):
    """A camera's pixels on a model's reference canvas (module doc). ``principal_point_px`` (cx, cy)
    and ``scale`` = f_ref / f of the camera; ``identity``: the camera is the reference sensor with
    its principal point at the centre (events keep their pixels)."""

    principal_point_px: Tuple[float, float]
    scale: float
    identity: bool

    @property
    def count_scale(self) -> float:
        """scale^2: events per reference pixel per camera event (the event count the model knows)."""
        return self.scale * self.scale


def camera_map(spec: InputSpec, sensor_size, principal_point_px=None, focal_px: Optional[float] = None) -> CameraMap:
    """The :class:`CameraMap` of a camera of ``sensor_size`` (W, H) px, principal point (None = its
    centre) and focal length ``focal_px`` (None = the reference's, i.e. the same pixel angle)."""
    W, H = (int(v) for v in sensor_size)
    cx, cy = resolve_principal_point(principal_point_px, (W, H))
    if focal_px is not None and not float(focal_px) > 0:
        raise ValueError(f"focal_px must be > 0 (or None), got {focal_px}")
    scale = 1.0 if focal_px is None else spec.reference_focal_px / float(focal_px)
    W0, H0 = spec.sensor_size
    ident = (W, H) == (W0, H0) and scale == 1.0 and (cx, cy) == ((W0 - 1) / 2.0, (H0 - 1) / 2.0)
    return CameraMap((cx, cy), float(scale), bool(ident))


def to_reference(x: torch.Tensor, y: torch.Tensor, cmap: CameraMap, spec: InputSpec):
    """Camera pixels (x, y) (N,) integer -> (xi, yi) (N,) int64 reference pixels and ``keep`` (N,)
    bool (on the canvas). The identity map returns x, y as int64 and keep all True."""
    if cmap.identity:
        return x.long(), y.long(), torch.ones(x.shape, dtype=torch.bool, device=x.device)
    W0, H0 = spec.sensor_size
    cx, cy = cmap.principal_point_px
    xi = torch.floor((W0 - 1) / 2.0 + (x.to(torch.float32) - cx) * cmap.scale + 0.5).long()
    yi = torch.floor((H0 - 1) / 2.0 + (y.to(torch.float32) - cy) * cmap.scale + 0.5).long()
    keep = (xi >= 0) & (xi < W0) & (yi >= 0) & (yi < H0)
    return xi, yi, keep


def voxel_grid(b: torch.Tensor, x: torch.Tensor, y: torch.Tensor, frac: torch.Tensor, p: torch.Tensor,
               batch_size: int, spec: InputSpec, n_bins: int = None) -> torch.Tensor:
    """Signed, pooled voxel grids of B windows.

    Args:
        b: (N,) int64 window (batch row) of each event, in [0, B).
        x, y: (N,) integer pixel column and row on the sensor.
        frac: (N,) float32 event time as a fraction of its window, in [0, 1] (not read when
            ``spec.n_windows`` > 1 and the grid has one bin: any tensor).
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
    size = batch_size * nb * h * w
    if b.numel() == 0:
        return torch.zeros(size, dtype=torch.float32, device=b.device).view(batch_size, nb, h, w)
    P = spec.pool_px
    if spec.n_windows > 1 and nb == 1 and b.device.type == "cpu" and not p.is_floating_point():
        # one bin: the compiled signed counts per cell (events.native), the same whole numbers in one pass
        mod = native.kernels()
        out = None if mod is None else mod.cell_counts(b.long().contiguous(), x.long().contiguous(),
                                                         y.long().contiguous(), p.to(torch.int8).contiguous(),
                                                         batch_size, h, w, P)
        if out is not None:
            return out.view(batch_size, 1, h, w)
    if P & (P - 1) == 0:  # a power of two: shifts (integer division is several times slower)
        sh = P.bit_length() - 1
        cx, cy = x.long() >> sh, y.long() >> sh
    else:
        cx, cy = x.long() // P, y.long() // P
    pol = p.to(torch.float32)
    # b (nb h w) + cy w + cx, as two fused multiply-adds
    base = torch.add(torch.add(cx, cy, alpha=w), b.long(), alpha=nb * h * w)
    if spec.n_windows > 1:
        if nb > 1:
            base = base + (frac.to(torch.float32) * nb).long().clamp(0, nb - 1) * (h * w)
        # sums of +-1: exact in any order, and bincount is faster than index_put_(accumulate=True)
        return torch.bincount(base, weights=pol, minlength=size).to(torch.float32).view(batch_size, nb, h, w)
    out = torch.zeros(size, dtype=torch.float32, device=b.device)
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


class PixelCells(NamedTuple):
    """``table`` (H W,) int64: the canvas cell (index in the (h, w) grid, row-major) of every camera
    pixel y W + x, h w for a pixel off the canvas; ``width`` W."""

    table: torch.Tensor
    width: int


def pixel_cells(cmap: CameraMap, spec: InputSpec, sensor_size, device=None) -> PixelCells:
    """The :class:`PixelCells` of a camera of ``sensor_size`` (W, H) on ``spec``'s canvas: one
    look-up per event instead of the float mapping of :func:`to_reference`."""
    W, H = (int(v) for v in sensor_size)
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    xi, yi, keep = to_reference(xs.flatten(), ys.flatten(), cmap, spec)
    h, w = spec.grid_hw
    cell = (yi // spec.pool_px) * w + (xi // spec.pool_px)
    return PixelCells(torch.where(keep, cell, torch.full_like(cell, h * w)).to(device), W)


def _grid_by_table(events, frac, batch_size: int, spec: InputSpec, cells: PixelCells):
    """(grid (B, bins_per_window, h, w) float32, counts (B,) int64 on the canvas) with the look-up
    ``cells``; one bincount over (row, bin, cell or off-canvas slot, polarity)."""
    h, w = spec.grid_hw
    hw1, nb = h * w + 1, spec.bins_per_window
    base = events.b * (nb * hw1) + cells.table[events.y * cells.width + events.x]
    if nb > 1:
        base = base + (frac * nb).long().clamp(0, nb - 1) * hw1
    c = torch.bincount(base * 2 + (events.p > 0), minlength=batch_size * nb * hw1 * 2)
    c = c.view(batch_size, nb, hw1, 2)[:, :, :h * w]
    grid = (c[..., 1] - c[..., 0]).to(torch.float32).view(batch_size, nb, h, w)
    return grid, c.sum(dim=(1, 2, 3))


def _window_fraction(events, t0_us, t_us: int) -> torch.Tensor:
    """(N,) float32 (t - t0) / (t_us - t0) of each event (span at least 1 µs); ``t0_us`` an int
    or a (B,) int64 tensor per row (the same float64 arithmetic either way)."""
    if isinstance(t0_us, torch.Tensor):
        t0 = t0_us.to(events.t.device).index_select(0, events.b)
        span = (int(t_us) - t0).clamp_min(1)
        return (events.t - t0).to(torch.float64).div_(span).to(torch.float32)
    span = max(int(t_us) - int(t0_us), 1)
    return (events.t - int(t0_us)).to(torch.float64).div_(span).to(torch.float32)


def events_voxel_grid(events, t0_us, t_us: int, batch_size: int, spec: InputSpec,
                      cmap: Optional[CameraMap] = None, cells: Optional[PixelCells] = None):
    """:func:`voxel_grid` of one :class:`dvsland.events.Events` window (t0_us, t_us], µs int, on
    the reference canvas (``cmap``: the camera's :class:`CameraMap`; None = the identity).
    ``t0_us``: an int, or a (B,) int64 tensor, the window's start per row (no host read).

    ``cells``: the camera's :func:`pixel_cells` (a faster path for another camera with inputs of
    K > 1 windows, the same grid as ``cmap``'s).

    Returns:
        (grid (B, spec.bins_per_window, h, w) float32, counts (B,) int64 events on the canvas).
    """
    if spec.n_windows > 1 and spec.bins_per_window == 1:
        frac = events.t  # one bin per window: every event goes to it, its time is not needed
    else:
        frac = _window_fraction(events, t0_us, t_us)
    if cells is not None and spec.n_windows > 1:
        return _grid_by_table(events, frac, batch_size, spec, cells)
    b, p = events.b, events.p
    if cmap is None or cmap.identity:
        x, y = events.x, events.y
    else:
        x, y, keep = to_reference(events.x, events.y, cmap, spec)
        b, x, y, frac, p = b[keep], x[keep], y[keep], frac[keep], p[keep]
    return voxel_grid(b, x, y, frac, p, batch_size, spec, spec.bins_per_window), row_counts(b, batch_size)


def row_counts(b: torch.Tensor, batch_size: int) -> torch.Tensor:
    """(B,) int64 events per row of a batch index ``b`` (N,) int64 sorted ascending (as every
    estimator's events are: the estimators' input check sorts them), by binary search."""
    edges = torch.searchsorted(b, torch.arange(batch_size + 1, device=b.device, dtype=b.dtype))
    return edges[1:] - edges[:-1]
