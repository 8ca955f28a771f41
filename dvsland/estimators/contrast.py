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
from typing import Optional, Tuple

import torch
import torch.nn.functional as F

from . import native_cmax


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
                   height: int, width: int, weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Accumulate events (unit weight, or ``weight`` (E, G)) into images with bilinear weights
    (one ``bincount``).

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
    if weight is not None:
        wx = wx * weight.reshape(1, -1).to(wx.dtype)
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
                    blur_sigma_px: float = 0.0, max_samples: int = 2_000_000,
                    centre_xy: Optional[Tuple[float, float]] = None) -> torch.Tensor:
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
        centre_xy: FoE (cx, cy) in sensor pixel coordinates (default the sensor centre).

    Returns:
        (B, G) float32 contrast.
    """
    B, G = candidates.shape
    H, W = int(sensor_hw[0]) + 2 * pad_px, int(sensor_hw[1]) + 2 * pad_px
    if centre_xy is None:
        centre_xy = ((sensor_hw[1] - 1) / 2.0, (sensor_hw[0] - 1) / 2.0)
    centre = (float(centre_xy[0]) + pad_px, float(centre_xy[1]) + pad_px)
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


# ---------------------------------------------------------------------- fast path of ``cmax``

def fold_seed(seed):
    """A seed folded to 31 bits, ``(s ^ (s >> 31) ^ (s >> 62)) & 0x7FFFFFFF``: any Python int (campaign
    seeds are 63-bit), or an int64 tensor of seeds (element-wise, the same values as the ints). Seeds in
    [0, 2^31) are kept as they are, so folding a folded seed changes nothing."""
    if isinstance(seed, torch.Tensor):
        s = seed.to(torch.int64)
        return (s ^ (s >> 31) ^ (s >> 62)) & 0x7FFFFFFF
    seed = int(seed)
    return (seed ^ (seed >> 31) ^ (seed >> 62)) & 0x7FFFFFFF


def seed_term(seed):
    """The seed's term of :func:`event_hash`: the seed folded to 31 bits (:func:`fold_seed`), times
    its multiplier (below 2^62). An int for an int seed, an int64 tensor for a tensor of seeds."""
    return fold_seed(seed) * 0x3C6EF372


def event_hash(b: torch.Tensor, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, seed=0) -> torch.Tensor:
    """A pseudo-random 31-bit integer per event from its fields (splitmix64-style mixing).

    Depends only on the event (b, x, y, t) and ``seed``, never on the order of the events, so
    thinning, dithering and half splits built on it give the same answer for any event order.

    Args:
        b, x, y, t: (E,) integer tensors.
        seed: any integer (folded to 31 bits; seeds below 2^31 are used as they are), or an (E,)
            int64 tensor, each event's own seed (e.g. its element's seed: the same hash as the int).

    Returns:
        (E,) int64 in [0, 2^31).
    """
    h = (b.to(torch.int64) * 0x1F1F1F1F + x.to(torch.int64) * 0x2545F491 + y.to(torch.int64) * 0x9E3779B1
         + t.to(torch.int64) * 0x6A09E667 + seed_term(seed))
    # two rounds of xorshift-multiply (int64 products wrap, which is what a hash wants)
    h = (h ^ (h >> 31)) * 0x7FB5D329728EA185
    h = (h ^ (h >> 27)) * 0x81DADEF4BC2DD44D
    h = h ^ (h >> 33)
    return h & 0x7FFFFFFF


#: corner weights of the score's splat are integers in units of 1 / WEIGHT_UNIT of an event (2^-12): the
#: image sums are then exact int64 (the same in any summation order, on any device and in the
#: compiled kernel); rounding moves a weight by at most 1.2e-4 of an event
WEIGHT_UNIT = 4096.0
#: largest canvas of one chunk of candidates of the torch path, int64 pixels: 32 MiB on the CPU,
#: 1 GiB on a GPU (the chunk is at least one candidate: B x 2 x the sensor box)
_CANVAS_MAX = 1 << 22
_CANVAS_MAX_CUDA = 1 << 27


def split_contrast(xc: torch.Tensor, yc: torch.Tensor, b: torch.Tensor, half: torch.Tensor, dt_s: torch.Tensor,
                   candidates: torch.Tensor, centre_xy: Tuple[float, float], canvas_hw: Tuple[int, int],
                   sensor_box: Tuple[float, float, float, float], half_window_s: torch.Tensor,
                   event_weight: Optional[torch.Tensor] = None, native: Optional[bool] = None) -> torch.Tensor:
    """Sharpness of the warped event image for each element and candidate D, for all events and
    for each half of them, free of the field-of-view bias.

    Events are warped radially about the focus of expansion, r_ref = r exp(D dt), and splatted
    bilinearly into one image per element, candidate and half. Only the part of the
    scene that stays in view during the whole window counts: for a candidate D that is the sensor
    box shrunk about the FoE by g = exp(|D| T / 2). (Counting everything biases the plain image
    variance towards small |D|: with the true D, the earliest events of a descent warp outside
    the latest field of view, so warps that keep every event overlapped win on event density
    alone; on the rendered sites that was a steady 5 % under-estimate of |D|.) The score is the
    index of dispersion of the counted image, sum(I^2) / sum(I) - sum(I) / area: 1 for events
    without structure whatever their density, larger when they line up. Corner weights are
    rounded to multiples of 1 / ``WEIGHT_UNIT`` of an event and the image sums are exact int64,
    so the compiled kernel (:mod:`dvsland.estimators.native_cmax`) and the torch path give the
    same score to the bit.

    Args:
        xc, yc: (E,) float32 event coordinates on the canvas, px.
        b: (E,) int64 element index in [0, B).
        half: (E,) int64 in {0, 1}, which half an event belongs to.
        dt_s: (E,) float32 event time minus its element's reference time, s.
        candidates: (B, G) candidate D, 1/s.
        centre_xy: FoE (cx, cy) on the canvas, px.
        canvas_hw: (Hc, Wc) canvas size (>= 2 each).
        sensor_box: (x_lo, x_hi, y_lo, y_hi) the sensor's outer edges on the canvas, px (inside
            the canvas with a margin of at least 1 px).
        half_window_s: (B,) half of each element's window, s.
        event_weight: (E,) float weights (default 1; the compiled kernel refuses a weight of 2^18
            or more, and a pixel above ~500 000 events would overflow the int64 sums).
        native: None = the compiled kernel where enabled (:func:`native_cmax.enabled`, CPU
            tensors), True = it where it can be loaded, False = the torch path (the reference).

    Returns:
        (B, G, 3) float64 score of all events, of half 0 and of half 1 (0 without events).
    """
    B, G = candidates.shape
    Hc, Wc = int(canvas_hw[0]), int(canvas_hw[1])
    dev = candidates.device
    out = torch.zeros(B, G, 3, dtype=torch.float64, device=dev)
    if xc.numel() == 0:
        return out
    cand_t = candidates.to(torch.float32).t().contiguous()  # (G, B)
    ginv_t = torch.exp(-cand_t.abs() * half_window_s.to(torch.float32).unsqueeze(0))  # (G, B) = 1 / g
    wt = torch.ones_like(xc, dtype=torch.float32) if event_weight is None else event_weight.to(torch.float32)
    n, s = _splat_sums(xc.to(torch.float32), yc.to(torch.float32), b, half, cand_t, dt_s.to(torch.float32), ginv_t,
                       wt, centre_xy, sensor_box, Hc, Wc, native)  # (B, G, 2), (B, G, 3) int64
    x_lo, x_hi, y_lo, y_hi = sensor_box
    area = ((x_hi - x_lo) * (y_hi - y_lo)) * (ginv_t.t().to(torch.float64) ** 2)  # (B, G) px^2
    u = WEIGHT_UNIT
    n = n.to(torch.float64) / u  # counted weight per half, events
    s = s.to(torch.float64) / (u * u)
    n0, n1 = n[..., 0], n[..., 1]
    na = n0 + n1
    out[..., 0] = (s[..., 0] + s[..., 1] + 2 * s[..., 2]) / na.clamp_min(1e-9) - na / area
    out[..., 1] = s[..., 0] / n0.clamp_min(1e-9) - n0 / area
    out[..., 2] = s[..., 1] / n1.clamp_min(1e-9) - n1 / area
    return out


def _splat_sums(xc, yc, b, half, cand_t, dt_s, ginv_t, wt, centre_xy, sensor_box, Hc: int, Wc: int, native):
    """(n (B, G, 2), s (B, G, 3)) int64: per element, candidate and half the summed integer corner
    weights, and sum I0^2, sum I1^2, sum I0 I1 over the pixels (weights in 1 / WEIGHT_UNIT).
    ``cand_t`` and ``ginv_t`` are (G, B) float32, ``dt_s`` (E,) float32."""
    mod = native_cmax.kernel_for(xc, native)
    if mod is not None:
        scale = cand_t.index_select(1, b).mul_(dt_s).exp_()  # (G, E) exp(D dt), in one buffer
        x_lo, x_hi, y_lo, y_hi = sensor_box
        return mod.splat_sums(xc.contiguous(), yc.contiguous(), b.to(torch.int64).contiguous(),
                              half.to(torch.int64).contiguous(), scale.contiguous(), ginv_t, wt.contiguous(),
                              float(centre_xy[0]), float(centre_xy[1]), float(x_lo), float(x_hi), float(y_lo),
                              float(y_hi), Hc, Wc, WEIGHT_UNIT)
    G, B = ginv_t.shape
    box = _box_canvas(sensor_box, Hc, Wc)
    cells = B * 2 * box[2] * box[3]
    cap = _CANVAS_MAX_CUDA if xc.device.type == "cuda" else _CANVAS_MAX
    chunk = max(1, min(G, cap // max(cells, 1)))
    parts = [_splat_sums_torch(xc, yc, b, half, torch.exp(cand_t[g0:g0 + chunk, b] * dt_s), ginv_t[g0:g0 + chunk],
                               wt, centre_xy, sensor_box, box) for g0 in range(0, G, chunk)]
    if len(parts) == 1:
        return parts[0]
    return torch.cat([p[0] for p in parts], 1), torch.cat([p[1] for p in parts], 1)


def _box_canvas(sensor_box, Hc: int, Wc: int) -> Tuple[int, int, int, int]:
    """(x_off, y_off, Hb, Wb): the part of the (Hc, Wc) canvas that a counted event's four corners
    can reach: the sensor box and one pixel beyond (weight outside the box is never counted, so
    the sums over this crop equal those over the whole canvas)."""
    x_lo, x_hi, y_lo, y_hi = sensor_box
    x0 = max(0, int(math.floor(x_lo)) - 1)
    y0 = max(0, int(math.floor(y_lo)) - 1)
    x1 = min(Wc, int(math.floor(x_hi)) + 3)
    y1 = min(Hc, int(math.floor(y_hi)) + 3)
    return x0, y0, y1 - y0, x1 - x0


def _splat_sums_torch(xc, yc, b, half, scale, ginv_t, wt, centre_xy, sensor_box, box):
    """The torch path of :func:`_splat_sums` for (G, E) ``scale`` and (G, B) ``ginv_t``: the
    reference of the compiled kernel, operation for operation in float32. ``box`` (x_off, y_off,
    Hb, Wb) is the crop of the canvas that the counted weight falls in (:func:`_box_canvas`)."""
    G, B = ginv_t.shape
    ox, oy, Hb, Wb = box
    P = Hb * Wb
    cx, cy = float(centre_xy[0]), float(centre_xy[1])
    x_lo, x_hi, y_lo, y_hi = sensor_box
    xw = (xc - cx) * scale  # (G, E), about the FoE
    yw = (yc - cy) * scale
    gi = ginv_t[:, b]
    inside = ((xw >= (x_lo - cx) * gi) & (xw <= (x_hi - cx) * gi)
              & (yw >= (y_lo - cy) * gi) & (yw <= (y_hi - cy) * gi))
    xs, ys = xw + cx, yw + cy
    # clamped (a non-finite coordinate too), every corner lies on the event's own image: an event
    # outside the box adds its weight 0 at a pixel near its own, never at one shared address (on a
    # GPU, the atomic adds of every outside event to one address serialised: 2/3 of cmax's time)
    x0 = torch.nan_to_num(xs.floor(), nan=float(ox)).clamp_(ox, ox + Wb - 2)
    y0 = torch.nan_to_num(ys.floor(), nan=float(oy)).clamp_(oy, oy + Hb - 2)
    fx = (xs - x0).clamp_(0, 1)
    fy = (ys - y0).clamp_(0, 1)
    wy1 = wt * fy
    wy0 = wt - wy1
    a, c = wy0 * fx, wy1 * fx
    img = (torch.arange(G, device=b.device).unsqueeze(1) * B + b) * 2 + half  # (G, E)
    base = img * P + (y0.to(torch.int64) - oy) * Wb + (x0.to(torch.int64) - ox)
    canvas = torch.zeros(G * B * 2 * P, dtype=torch.int64, device=b.device)
    zero = torch.zeros((), dtype=torch.int64, device=b.device)
    for off, wk in ((0, wy0 - a), (1, a), (Wb, wy1 - c), (Wb + 1, c)):
        q = torch.where(inside, (wk * WEIGHT_UNIT).round().to(torch.int64), zero)
        canvas.index_add_(0, (base + off).view(-1), q.view(-1))
    ims = canvas.view(G, B, 2, P)
    i0, i1 = ims[:, :, 0], ims[:, :, 1]
    n = ims.sum(-1).permute(1, 0, 2)  # (B, G, 2)
    s = torch.stack([(i0 * i0).sum(-1), (i1 * i1).sum(-1), (i0 * i1).sum(-1)], -1).permute(1, 0, 2)
    return n, s


def pixel_counts(b: torch.Tensor, px: torch.Tensor, n_elements: int, n_px: int,
                 native: Optional[bool] = None) -> torch.Tensor:
    """For each event, the number of events of its element on its pixel.

    Args:
        b: (E,) int64 element index in [0, n_elements); px: (E,) int64 pixel index in [0, n_px).
        native: as in :func:`split_contrast` (the compiled kernel counts element by element in a
            small canvas; the torch path is one ``bincount`` over n_elements x n_px cells).

    Returns:
        (E,) int64 counts (the same on both paths).
    """
    mod = native_cmax.kernel_for(b, native) if b.numel() else None
    if mod is not None:
        return mod.pixel_counts(b.to(torch.int64).contiguous(), px.to(torch.int64).contiguous(), int(n_elements),
                                int(n_px))
    cell = b * int(n_px) + px
    return torch.bincount(cell, minlength=int(n_elements) * int(n_px))[cell]
