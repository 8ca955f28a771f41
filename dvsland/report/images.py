"""Images of frames and events: display mapping, labelled montages (shared stretch, colorbar),
captioned GIFs, event frames (ON red, OFF blue with a legend, as the paper's Figure 1) and x-y-t
scatters (as its Figure 3), drawn through :mod:`dvsland.report.style`. Used by ``dvsland render`` and
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


def montage(frames: np.ndarray, alts: Sequence[float], sites: Sequence[str], path: Path, scale: int = 2,
            renderer: str = "") -> np.ndarray:
    """Save the labelled montage of linear irradiance ``frames`` (altitudes, sites, H, W) to ``path``:
    rows = altitudes, columns = sites, one shared log stretch (1st-99.5th percentile over all
    tiles) and its colorbar. Returns the image as (H, W, 3) uint8 (for TensorBoard)."""
    from . import style

    log, lo, hi = style.log_stretch(frames)
    fig = style.image_grid(log, [f"{a:g} m" for a in alts], [f"site {s}" for s in sites],
                           title=f"{renderer + ' renderer: ' if renderer else ''}log irradiance, one stretch "
                                 "for all tiles (1st-99.5th percentile)",
                           colorbar_label="ln(irradiance) [-]", tile_inches=0.8 * max(1, scale), vmin=lo, vmax=hi)
    img = style.figure_to_array(fig)
    style.save(fig, path)
    return img


def annotated_gif(frames_u8: np.ndarray, captions: Sequence[str], path: Path, min_size: int = 256,
                  duration_ms: int = 100) -> Path:
    """Save uint8 frames (N, H, W) as a looping GIF, each enlarged (nearest) to at least
    ``min_size`` px and captioned (e.g. the altitude) in its top-left corner."""
    from PIL import Image

    from .style import annotate_image

    n, h, w = frames_u8.shape
    k = max(1, -(-min_size // max(h, w)))
    ims = [annotate_image(Image.fromarray(f).resize((w * k, h * k), Image.NEAREST), c, size=13)
           for f, c in zip(frames_u8, captions)]
    ims[0].save(path, save_all=True, append_images=ims[1:], duration=duration_ms, loop=0)
    return Path(path)


def save_frame_png(frame: torch.Tensor, path: Path) -> None:
    """One frame (H, W) of linear irradiance as a PNG through :func:`to_display`."""
    from PIL import Image

    Image.fromarray(to_display(frame[None])[0]).save(path)


def event_frame_rgb(events, H: int, W: int, t0_us: int, t1_us: int) -> np.ndarray:
    """(H, W, 3) uint8: white, ON-dominated pixels red, OFF-dominated blue (b = 0 events in
    [t0_us, t1_us))."""
    from .style import OFF_RGB, ON_RGB

    ev = events.time_window(t0_us, t1_us).select_batch(0)
    img = np.full((H, W, 3), 255, np.uint8)
    if len(ev):
        cnt = ev.to_count_image(1, H, W)[0].cpu().numpy()  # (2, H, W)
        net = cnt[0] - cnt[1]
        img[net > 0] = ON_RGB
        img[net < 0] = OFF_RGB
    return img


def draw_event_frame(events, H, W, t0_us, t1_us, path: Path, title: str = "") -> None:
    """Save the event frame of [t0_us, t1_us) (see :func:`event_frame_rgb`) with axes in px and
    the ON/OFF legend."""
    from . import style

    img = event_frame_rgb(events, H, W, t0_us, t1_us)
    fig, ax = style.pyplot().subplots(figsize=(5, 5))
    ax.imshow(img, interpolation="nearest")
    style.label(ax, "x [px]", "y [px]", title, grid=False)
    style.polarity_legend(ax)
    style.save(fig, path, dpi=120)


def draw_xyt_scatter(events, H, W, t0_us, t1_us, path: Path, max_points: int = 30000, seed: int = 0,
                     title: str = "") -> None:
    """Save a 3-D x-y-t scatter of the events of [t0_us, t1_us) (at most ``max_points``, drawn
    at random), ON red, OFF blue."""
    from . import style

    plt = style.pyplot()
    ev = events.time_window(t0_us, t1_us).select_batch(0)
    n = len(ev)
    if n > max_points:
        idx = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:max_points]
        ev = ev[torch.sort(idx).values]
    fig = plt.figure(figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    if len(ev):
        t_ms = (ev.t - t0_us).cpu().numpy() * 1e-3
        x, y, p = ev.x.cpu().numpy(), ev.y.cpu().numpy(), ev.p.cpu().numpy()
        for pol, rgb, lab in ((1, style.ON_RGB, "ON (brighter)"), (-1, style.OFF_RGB, "OFF (darker)")):
            m = p == pol
            ax.scatter(x[m], t_ms[m], y[m], s=0.3, color=tuple(np.asarray(rgb) / 255), label=lab, depthshade=False)
        ax.legend(loc="upper left", markerscale=15, fontsize=8)
    ax.set_xlim(0, W)
    ax.set_zlim(H, 0)
    ax.set_xlabel("x [px]")
    ax.set_ylabel("t [ms]")
    ax.set_zlabel("y [px]")
    ax.set_title(title + (f" ({len(ev)} of {n} shown)" if n > len(ev) else ""), fontsize=9)
    style.save(fig, path, dpi=120)


__all__ = ["to_display", "montage", "annotated_gif", "save_frame_png", "event_frame_rgb", "draw_event_frame",
           "draw_xyt_scatter"]
