"""Images of frames and events: display mapping, labelled montages, event frames (ON red, OFF
blue, as the paper's Figure 1) and x-y-t scatters (as its Figure 3). Used by ``dvsland render`` and
``dvsland events``; matplotlib and PIL are imported only when drawing."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch


def to_display(frames: torch.Tensor, lo_q: float = 0.01, hi_q: float = 0.995, shared: bool = False) -> np.ndarray:
    """Linear irradiance (B, H, W) -> uint8 (B, H, W): log, then a percentile stretch per image
    (or one stretch for all images when ``shared``)."""
    log = torch.log(frames.detach().float().cpu().clamp(min=1e-12))
    flat = log.reshape(1, -1) if shared else log.flatten(1)
    lo = torch.quantile(flat, lo_q, dim=1)
    hi = torch.quantile(flat, hi_q, dim=1)
    if shared:
        lo, hi = lo.expand(log.shape[0]), hi.expand(log.shape[0])
    span = (hi - lo).clamp(min=1e-6)[:, None, None]
    out = ((log - lo[:, None, None]) / span).clamp(0, 1) * 255.0
    return out.round().to(torch.uint8).numpy()


def montage(tiles: np.ndarray, row_labels: Sequence[str], col_labels: Sequence[str], scale: int = 2,
            gap: int = 4):
    """Grid image of uint8 tiles (R, C, H, W) with row and column labels -> PIL.Image (L)."""
    from PIL import Image, ImageDraw

    r, c, h, w = tiles.shape
    h2, w2 = h * scale, w * scale
    left, top = 70, 22
    canvas = Image.new("L", (left + c * (w2 + gap), top + r * (h2 + gap)), color=0)
    draw = ImageDraw.Draw(canvas)
    for j, lab in enumerate(col_labels):
        draw.text((left + j * (w2 + gap) + w2 // 2 - 4 * len(lab), 5), lab, fill=255)
    for i, lab in enumerate(row_labels):
        draw.text((5, top + i * (h2 + gap) + h2 // 2 - 5), lab, fill=255)
        for j in range(c):
            tile = Image.fromarray(tiles[i, j]).resize((w2, h2), Image.NEAREST)
            canvas.paste(tile, (left + j * (w2 + gap), top + i * (h2 + gap)))
    return canvas


def save_frame_png(frame: torch.Tensor, path: Path) -> None:
    """One frame (H, W) of linear irradiance as a PNG through :func:`to_display`."""
    from PIL import Image

    Image.fromarray(to_display(frame[None])[0]).save(path)


def event_frame_rgb(events, H: int, W: int, t0_us: int, t1_us: int) -> np.ndarray:
    """(H, W, 3) uint8: white, ON-dominated pixels red, OFF-dominated blue (b = 0 events in
    [t0_us, t1_us))."""
    ev = events.time_window(t0_us, t1_us).select_batch(0)
    img = np.full((H, W, 3), 255, np.uint8)
    if len(ev):
        cnt = ev.to_count_image(1, H, W)[0].cpu().numpy()  # (2, H, W)
        net = cnt[0] - cnt[1]
        img[net > 0] = (220, 30, 30)
        img[net < 0] = (30, 60, 220)
    return img


def draw_event_frame(events, H, W, t0_us, t1_us, path: Path, title: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = event_frame_rgb(events, H, W, t0_us, t1_us)
    fig, ax = plt.subplots(figsize=(5, 5), dpi=120)
    ax.imshow(img, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px]")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def draw_xyt_scatter(events, H, W, t0_us, t1_us, path: Path, max_points: int = 30000, seed: int = 0,
                     title: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ev = events.time_window(t0_us, t1_us).select_batch(0)
    n = len(ev)
    if n > max_points:
        idx = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:max_points]
        ev = ev[torch.sort(idx).values]
    fig = plt.figure(figsize=(6, 5), dpi=120)
    ax = fig.add_subplot(projection="3d")
    if len(ev):
        t_ms = (ev.t - t0_us).cpu().numpy() * 1e-3
        x, y, p = ev.x.cpu().numpy(), ev.y.cpu().numpy(), ev.p.cpu().numpy()
        for pol, color, lab in ((1, "tab:red", "ON"), (-1, "tab:blue", "OFF")):
            m = p == pol
            ax.scatter(x[m], t_ms[m], y[m], s=0.3, c=color, label=lab, depthshade=False)
        ax.legend(loc="upper left", markerscale=15, fontsize=8)
    ax.set_xlim(0, W)
    ax.set_zlim(H, 0)
    ax.set_xlabel("x [px]")
    ax.set_ylabel("t [ms]")
    ax.set_zlabel("y [px]")
    ax.set_title(title + (f" ({len(ev)} of {n} shown)" if n > len(ev) else ""), fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


__all__ = ["to_display", "montage", "save_frame_png", "event_frame_rgb", "draw_event_frame", "draw_xyt_scatter"]
