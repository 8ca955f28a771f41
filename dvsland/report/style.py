"""One look for every dvsland figure: labelled axes with units, legends that are not clipped,
titles, colorbars, one contrast stretch shared by the images it says it is shared by.

Every figure function in dvsland goes through these helpers (matplotlib, Agg backend):

- :func:`pyplot` – matplotlib.pyplot on the Agg backend, with dvsland's rc style;
- :func:`label` – axis labels (a unit is required: ``"altitude [m]"``), title, legend;
- :func:`log_stretch` – log irradiance and the percentile bounds of a display stretch;
- :func:`image_grid` – a labelled grid of grey images (rows × columns) with one colorbar;
- :func:`polarity_legend` – the ON red / OFF blue legend of event images;
- :func:`save` – ``bbox_inches="tight"`` (legends and labels never clipped), then close;
- :func:`annotate_image` – a text line drawn onto a PIL image (GIF overlays), in DejaVu Sans.
"""

from __future__ import annotations

import io
import re
from pathlib import Path
from typing import Optional, Sequence, Tuple

import numpy as np

#: colours of event polarities everywhere (RGB 0-255): ON red, OFF blue
ON_RGB = (220, 30, 30)
OFF_RGB = (30, 60, 220)

RC = {
    "figure.dpi": 100, "savefig.dpi": 110, "font.size": 9, "axes.titlesize": 10, "axes.labelsize": 9,
    "legend.fontsize": 8, "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.grid": False,
    "grid.alpha": 0.3, "image.cmap": "gray",
}

_UNIT = re.compile(r"\[[^\]]+\]")


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (no display needed), with dvsland's style."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    plt.rcParams.update(RC)
    return plt


def has_unit(text: str) -> bool:
    """True if an axis label states a unit in brackets: ``[m]``, ``[1/s]``, ``[-]`` (dimensionless)."""
    return bool(_UNIT.search(text or ""))


def label(ax, xlabel: Optional[str] = None, ylabel: Optional[str] = None, title: Optional[str] = None,
          legend: bool | str = False, grid: bool = True):
    """Label ``ax``: axis labels must carry a unit in brackets (``"t [s]"``, ``"error [%]"``,
    ``"count [-]"``); a title; a legend (``legend=True``: best place, or a matplotlib ``loc``
    string; ``"outside"``: right of the axes, kept in the saved file by :func:`save`).

    Raises:
        ValueError: an axis label without a unit.
    """
    for name, text in (("xlabel", xlabel), ("ylabel", ylabel)):
        if text is not None and not has_unit(text):
            raise ValueError(f"{name} {text!r} has no unit: write it as 'quantity [unit]' ('[-]' if none)")
    if xlabel is not None:
        ax.set_xlabel(xlabel)
    if ylabel is not None:
        ax.set_ylabel(ylabel)
    if title is not None:
        ax.set_title(title)
    if grid:
        ax.grid(True, alpha=0.3)
    if legend:
        handles, _ = ax.get_legend_handles_labels()
        if handles:
            if legend == "outside":
                ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
            else:
                ax.legend(loc=legend if isinstance(legend, str) else "best")
    return ax


def robust_limits(truth, estimates=(), q: float = 2.0, pad: float = 0.15, floor: float = 0.02) -> Tuple[float, float]:
    """(low, high) y limits that show all of ``truth`` and the central ``100 - 2 q`` % of every
    series in ``estimates`` (percentiles ``q`` and ``100 - q`` of its finite values), padded by
    ``pad`` of the span (at least ``floor``): a few wild estimates cannot flatten the truth, and
    the estimates' bulk stays in view. Non-finite values are ignored; (-1, 1) when nothing is finite.

    Args:
        truth: (N,) values always shown. estimates: sequence of (M,) series.
    """
    vals = []
    t = np.asarray(truth, dtype=np.float64).ravel()
    t = t[np.isfinite(t)]
    if t.size:
        vals += [t.min(), t.max()]
    for e in estimates:
        e = np.asarray(e, dtype=np.float64).ravel()
        e = e[np.isfinite(e)]
        if e.size:
            vals += list(np.percentile(e, [q, 100.0 - q]))
    if not vals:
        return (-1.0, 1.0)
    lo, hi = float(min(vals)), float(max(vals))
    span = max(hi - lo, floor)
    return (lo - pad * span, hi + pad * span)


def plot_clipped(ax, x, y, lo: float, hi: float, label: str, style: str = ".", ms: float = 2.5,
                 outside_label: Optional[str] = "{label}: {n} outside the axes (on the edge)", **kw) -> int:
    """Plot the points of ``y`` (against ``x``) inside [lo, hi] with ``style`` (a line breaks where
    it leaves them), and the ones outside as open triangles on the edge they passed (up at ``hi``,
    down at ``lo``), in the same colour, so that nothing is silently clipped. The legend reads
    ``label`` and, when some were outside, ``outside_label`` formatted with ``label`` and ``n``
    (None: no legend entry for them). Returns the number outside.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ok = np.isfinite(y)
    inside = ok & (y >= lo) & (y <= hi)
    (line,) = ax.plot(x, np.where(inside, y, np.nan), style, ms=ms, label=label, **kw)  # a line breaks there
    above, below = ok & (y > hi), ok & (y < lo)
    n_out = int(above.sum() + below.sum())
    if n_out:
        c = line.get_color()
        edge = dict(ls="", mfc="none", mec=c, ms=4, mew=0.8, clip_on=False)
        text = "_nolegend_" if outside_label is None else outside_label.format(label=label, n=n_out)
        # only non-empty lines: an empty line drawn unclipped would stretch the layout to the origin
        if above.any():
            ax.plot(x[above], np.full(int(above.sum()), hi), marker="^", **edge, label=text)
        if below.any():
            ax.plot(x[below], np.full(int(below.sum()), lo), marker="v", **edge,
                    label="_nolegend_" if above.any() else text)
    ax.set_ylim(lo, hi)
    return n_out


def save_atomic(fig, path, **savefig_kwargs) -> Path:
    """``fig.savefig`` into memory, then one atomic write to ``path`` (format from its suffix): a
    full disk or a read-only folder leaves the previous figure or none, never half a PNG.

    Raises:
        RunWriteError: the folder or the file could not be written; the message names the path.
    """
    from dvsland.report.results import atomic_write_bytes, writes_under

    path = Path(path)
    buf = io.BytesIO()
    fmt = path.suffix.lstrip(".").lower() or "png"
    if fmt == "png":  # zlib level 1: the same pixels, cheaper to encode (~10 % larger files)
        savefig_kwargs.setdefault("pil_kwargs", {"compress_level": 1})
    fig.savefig(buf, format=fmt, **savefig_kwargs)
    with writes_under(path.parent):
        path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_bytes(path, buf.getbuffer())


def save(fig, path, dpi: Optional[int] = None) -> Path:
    """Save ``fig`` to ``path`` with a tight bounding box (nothing outside the axes is clipped,
    legends placed outside included), atomically (:func:`save_atomic`), and close it. Returns the path."""
    plt = pyplot()
    try:
        return save_atomic(fig, path, dpi=dpi, bbox_inches="tight", pad_inches=0.08)
    finally:
        plt.close(fig)


def log_stretch(images, lo_q: float = 0.01, hi_q: float = 0.995) -> Tuple[np.ndarray, float, float]:
    """Natural log of linear irradiance ``images`` (any shape, > 0) and one display range over
    all of them: the ``lo_q`` and ``hi_q`` quantiles. Returns (log images, lo, hi)."""
    log = np.log(np.clip(np.asarray(images, dtype=np.float64), 1e-12, None))
    lo, hi = (float(v) for v in np.quantile(log, [lo_q, hi_q])) if log.size else (0.0, 1.0)
    if not hi > lo:
        hi = lo + 1e-6
    return log, lo, hi


def image_grid(tiles, row_labels: Sequence[str], col_labels: Sequence[str], title: str = "",
               colorbar_label: Optional[str] = "log irradiance [-]", row_title: str = "", col_title: str = "",
               tile_inches: float = 1.6, vmin: Optional[float] = None, vmax: Optional[float] = None):
    """A labelled grid of grey images and one colorbar, all tiles on one display range.

    Args:
        tiles: (R, C, H, W) array; shown with ``vmin``/``vmax`` (default: its own min / max), so
            equal values look equal in every tile. Pass log irradiance with the bounds of
            :func:`log_stretch` for a shared contrast stretch.
        row_labels, col_labels: R and C labels (``"1000 m"``, ``"site A"``). A column label with a
            second line (``"site H\\nflat, dusty, few features"``) is headed by its first line and
            the rest is written as a note on every tile of that column (for tiles that are nearly
            uniform by nature and would otherwise read as a failed render).
        title: figure title (say what the stretch is).
        colorbar_label: the colorbar's label (with its unit); None: no colorbar.
        row_title, col_title: what the rows and columns are (``"altitude"``, ``"site"``).
        tile_inches: size of one tile.

    Returns:
        The matplotlib figure (save it with :func:`save`).
    """
    plt = pyplot()
    tiles = np.asarray(tiles)
    if tiles.ndim != 4:
        raise ValueError(f"tiles must be (R, C, H, W), got shape {tiles.shape}")
    r, c = tiles.shape[:2]
    if len(row_labels) != r or len(col_labels) != c:
        raise ValueError(f"row_labels/col_labels must have {r}/{c} entries, got {len(row_labels)}/{len(col_labels)}")
    vmin = float(np.nanmin(tiles)) if vmin is None else vmin
    vmax = float(np.nanmax(tiles)) if vmax is None else vmax
    fig, axes = plt.subplots(r, c, figsize=(c * tile_inches + 1.3, r * tile_inches + 0.9), squeeze=False)
    im = None
    for i in range(r):
        for j in range(c):
            ax = axes[i][j]
            im = ax.imshow(tiles[i, j], cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            head, _, note = str(col_labels[j]).partition("\n")
            if i == 0:
                ax.set_title(head, fontsize=9)
            if note:
                ax.text(0.5, 0.06, note, transform=ax.transAxes, ha="center", va="bottom", fontsize=8,
                        wrap=True, bbox=dict(boxstyle="round,pad=0.25", fc="white", ec="0.4", alpha=0.85))
            if j == 0:
                ax.set_ylabel(row_labels[i], fontsize=9)
    if col_title:
        fig.supxlabel(col_title, fontsize=9)
    if row_title:
        fig.supylabel(row_title, fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    if colorbar_label and im is not None:
        cb = fig.colorbar(im, ax=axes.ravel().tolist(), fraction=0.04, pad=0.02)
        cb.set_label(colorbar_label)
    return fig


def polarity_legend(ax, loc: str = "upper right"):
    """Legend of event polarities on ``ax``: ON (brightness up) red, OFF (down) blue."""
    from matplotlib.patches import Patch

    handles = [Patch(color=np.asarray(ON_RGB) / 255, label="ON (brighter)"),
               Patch(color=np.asarray(OFF_RGB) / 255, label="OFF (darker)")]
    return ax.legend(handles=handles, loc=loc, framealpha=0.85)


def _font(size: int):
    from PIL import ImageFont

    try:
        from matplotlib import font_manager

        return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)
    except Exception:  # no FreeType: PIL's own default font
        return ImageFont.load_default()


def annotate_image(img, text: str, size: int = 14, xy: Tuple[int, int] = (4, 3)):
    """Draw ``text`` (one line, white on a dark box) at ``xy`` on a PIL image, in place; returns it."""
    from PIL import ImageDraw

    if img.mode not in ("RGB", "L"):
        img = img.convert("RGB")
    draw = ImageDraw.Draw(img)
    font = _font(size)
    box = draw.textbbox(xy, text, font=font)
    dark = 0 if img.mode == "L" else (0, 0, 0)
    white = 255 if img.mode == "L" else (255, 255, 255)
    draw.rectangle((box[0] - 2, box[1] - 2, box[2] + 2, box[3] + 2), fill=dark)
    draw.text(xy, text, fill=white, font=font)
    return img


def figure_to_array(fig) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a drawn matplotlib figure (for TensorBoard images)."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def renderer_pairs_figure(pairs, sites: Sequence[str], altitudes_m: Sequence[float], path,
                          names: Tuple[str, str] = ("fast", "pyrender")) -> Path:
    """Side-by-side renderer comparison: rows = sites; per altitude two columns, ``names[0]`` then
    ``names[1]``, each pair on its own shared log stretch (1st-99.5th percentile of both).

    Args:
        pairs: per site (row), per altitude, a pair (a, b) of (H, W) linear irradiance.
        sites, altitudes_m: row and altitude labels.
        path: PNG to write.
    """
    r, c = len(pairs), len(pairs[0]) if pairs else 0
    if len(sites) != r or len(altitudes_m) != c:
        raise ValueError(f"need {r} sites and {c} altitudes for the pairs, got {len(sites)} and {len(altitudes_m)}")
    h, w = np.asarray(pairs[0][0][0]).shape
    tiles = np.zeros((r, 2 * c, h, w))
    for i, row in enumerate(pairs):
        for j, (a, b) in enumerate(row):
            log, lo, hi = log_stretch(np.stack([a, b]))
            tiles[i, 2 * j: 2 * j + 2] = np.clip((log - lo) / (hi - lo), 0.0, 1.0)
    cols = [f"{alt:.0f} m\n{n}" for alt in altitudes_m for n in names]
    fig = image_grid(tiles, [f"site {s}" for s in sites], cols,
                     title=f"{names[0]} vs {names[1]} renderer: ln(irradiance), each {names[0]} | {names[1]} "
                           "pair on one stretch (1st-99.5th percentile of the pair)",
                     colorbar_label="stretched ln(irradiance) [-]", vmin=0.0, vmax=1.0, tile_inches=1.3)
    return save(fig, path)
