"""PNG figures of a simulation: per-run descent plots (like the paper's Fig. 6) and the
lowest-altitude chart per site and setting (like Fig. 7). Matplotlib, Agg backend."""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from dvsland.dynamics import closed_form_state

from .checkpoint import checkpoint_text
from .style import label, save_atomic
from .tensorboard import _estimator_label, run_folder_name


def _plt():
    from .style import pyplot

    return pyplot()


def _run_rows(traces: Dict[str, np.ndarray], b: int) -> np.ndarray:
    """Row indices of run ``b`` while it flew, plus its final row."""
    act = traces["active"][:, b]
    rows = np.nonzero(act)[0]
    if rows.size and rows[-1] + 1 < act.shape[0] and np.isfinite(traces["z_m"][rows[-1] + 1, b]):
        rows = np.append(rows, rows[-1] + 1)
    return rows


def _descent_axes():
    """(figure, 4 axes) of a descent figure, 9 x 9 in at 80 dpi (its PNG's resolution), shared
    time axis, legends to the right. Drawn to be cheap: at most 6 y ticks, 1, 2, 2.5 or 5 x 10^k
    apart; axis labels at fixed places (aligned, not placed from the tick labels' extents
    at every draw); no tick marks (the grid shows the ticks); the axes' white background patches
    left to the figure's."""
    plt = _plt()
    fig, ax = plt.subplots(4, 1, figsize=(9, 9), dpi=80, sharex=True)
    fig.subplots_adjust(left=0.1, right=0.74, top=0.95, bottom=0.06, hspace=0.12)  # legends to the right
    from matplotlib.ticker import MaxNLocator

    for a in ax:
        a.yaxis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10]))
        a.yaxis.set_label_coords(-0.115, 0.5)
        a.xaxis.set_label_coords(0.5, -0.16)
        a.tick_params(left=False, bottom=False)
        a.patch.set_visible(False)  # white on the white figure: the same pixels undrawn (still the clip path)
    return fig, ax


def _reset_axes(ax) -> None:
    """Empty a reused descent panel for the next run, as ``ax.cla()`` would for what the descent
    figures draw: remove the data artists and the legend, restart the colour cycle (C0 first) and
    autoscale both axes from no data (null data limits). Unlike ``cla()`` it keeps the axes' Tick
    objects: rebuilding them on the next draw was about 40 % of a figure's CPU. The axis labels,
    the grid and the figure title are set again by every figure."""
    for artist in (*ax.lines, *ax.collections, *ax.patches, *ax.texts, *ax.images, *ax.artists, *ax.tables):
        artist.remove()
    ax.containers.clear()  # bar / errorbar groups: they would keep their legend entries
    if ax.get_legend() is not None:
        ax.get_legend().remove()
    ax.set_prop_cycle(None)
    ax.relim()
    ax.set_autoscale_on(True)  # the D panel's set_ylim turned y autoscaling off


def _divergence_panel(ax, t, d_true, d_est, d_filtered) -> None:
    """The D panel: the true D (black), every raw estimate (dots), the filtered D the law used
    (a line drawn above the dots) on limits that show the truth and the bulk of both series
    (:func:`~.style.robust_limits`); estimates beyond them sit as open triangles on the edge
    (:func:`~.style.plot_clipped`), counted in the legend. Arrays: (N,) float, 1/s, NaN = none."""
    from .style import plot_clipped, robust_limits

    lo, hi = robust_limits(d_true, (d_est, d_filtered))
    hi = max(hi, 0.0 + 0.05 * (hi - lo))  # D = 0 (no closing speed) always in view
    ax.plot(t, d_true, "k", lw=1.2, label="D true", zorder=3)
    edge = "{n} beyond the axes,\nmarked on the edge"
    plot_clipped(ax, t, d_est, lo, hi, "D estimated (raw)", ".", ms=2.5, outside_label="raw: " + edge,
                 color="C0", alpha=0.7, zorder=2)
    plot_clipped(ax, t, d_filtered, lo, hi, "D filtered\n(the law's input)", "-", ms=0,
                 outside_label="filtered: " + edge, lw=1.3, color="C3", zorder=4)
    label(ax, ylabel="divergence D [1/s]", legend="outside")


def _save_descent(fig, path) -> None:
    """Save a descent figure to ``path``: PNG at 80 dpi, glyphs unhinted (cheaper to lay out, as
    legible at this size)."""
    with _plt().rc_context({"text.hinting": "no_hinting"}):
        save_atomic(fig, path, dpi=80)


def descent_figure(traces: Dict[str, np.ndarray], b: int, run: dict, path, c2: float = 0.5, _fig=None):
    """Four panels for run ``b``: altitude, velocity (with the closed form), D true / estimated /
    filtered, thrust. Saved to ``path``; returns the path."""
    plt = _plt()
    rows = _run_rows(traces, b)
    t = traces["t_s"][rows, b]
    fig, ax = _fig if _fig is not None else _descent_axes()
    for a in ax:
        _reset_axes(a)
    est = _estimator_label(run["estimator"])
    if run.get("checkpoint"):
        est += f", {checkpoint_text(run['checkpoint'])}"
    title = f"{run.get('run', b)}  ({est}): {run['outcome']} at {run['t_end_s']:.1f} s, " \
            f"lowest {run['lowest_altitude_m']:.0f} m, loop gain λ = " \
            f"{'-' if run.get('loop_gain') is None else format(run['loop_gain'], '.3g')} 1/s"
    fig.suptitle(title, fontsize=9)
    zc = vc = None
    if run.get("z0_m") and run.get("v0_mps", 0) < 0:
        zc, vc = closed_form_state(t, run["z0_m"], run["v0_mps"], c2)
    ax[0].plot(t, traces["z_m"][rows, b], label="altitude")
    if zc is not None:
        ax[0].plot(t, zc, "k--", lw=0.8, label="closed form")
    label(ax[0], ylabel="altitude z [m]", legend="outside")
    ax[1].plot(t, traces["v_mps"][rows, b], label="velocity")
    if vc is not None:
        ax[1].plot(t, vc, "k--", lw=0.8, label="closed form")
    label(ax[1], ylabel="velocity v [m/s]", legend="outside")
    _divergence_panel(ax[2], t, traces["d_true"][rows, b], traces["d_est"][rows, b], traces["d_filtered"][rows, b])
    thrust = traces["thrust_n"][rows, b]
    big = np.isfinite(thrust).any() and np.nanmax(np.abs(thrust)) >= 1e6
    ax[3].step(t, thrust / (1e6 if big else 1e3), where="post", lw=0.8, label="commanded thrust")
    label(ax[3], "flight time t [s]", "thrust [MN]" if big else "thrust [kN]", legend="outside")
    _save_descent(fig, path)
    if _fig is None:
        plt.close(fig)
    return Path(path)


def lowest_altitude_chart(runs: List[dict], path, success_altitude_m: float = 50.0):
    """Grouped bars: lowest altitude reached per site (x) and setting (colour), log scale; the
    success altitude dashed. Saved to ``path``."""
    plt = _plt()
    sites = list(dict.fromkeys(r["site"] for r in runs))
    labels = list(dict.fromkeys(r["label"] for r in runs))
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / max(len(labels), 1)
    lowest = []
    for j, lab in enumerate(labels):
        vals = []
        for s in sites:
            sel = [r["lowest_altitude_m"] for r in runs if r["site"] == s and r["label"] == lab]
            vals.append(np.mean(sel) if sel else np.nan)
        vals = np.maximum(np.asarray(vals, dtype=float), 1.0)
        lowest.append(np.nanmin(vals) if np.isfinite(vals).any() else success_altitude_m)
        x = np.arange(len(sites)) + (j - (len(labels) - 1) / 2) * width
        ax.bar(x, vals, width, label=lab)
    ax.axhline(success_altitude_m, color="k", ls="--", lw=0.8, label=f"success ({success_altitude_m:g} m)")
    ax.set_yscale("log")
    top = max([r.get("z0_m", 1e4) for r in runs] + [success_altitude_m * 2])
    bottom = max(1.0, min(lowest + [success_altitude_m]) / 2)
    ax.set_ylim(bottom, top * 1.2)
    ticks = [t for t in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000, 20000, 50000, 100000)
             if bottom <= t <= top * 1.2]
    ax.set_yticks(ticks)
    ax.set_yticklabels([f"{t:g}" for t in ticks])
    ax.minorticks_off()  # log minor ticks are most of this chart's drawing time
    ax.set_xticks(np.arange(len(sites)))
    ax.set_xticklabels(sites)
    ax.set_xlabel("site")  # categorical: no unit
    ests = ", ".join(dict.fromkeys(_estimator_label(str(r.get("estimator", "?")))
                                   + (f" ({checkpoint_text(r['checkpoint'])})" if r.get("checkpoint") else "")
                                   for r in runs))
    label(ax, None, "lowest altitude reached [m]", "Lowest altitude per site and controller setting "
          f"(log scale); estimator {ests}", legend="outside", grid=False)
    ax.grid(True, axis="y", alpha=0.3)
    ax.set_title(ax.get_title(), y=1.0)  # placed, not searched for: nothing is drawn above the axes
    from .style import save

    return save(fig, path, dpi=90)


def write_figures(run_dir, runs: List[dict], traces: Dict[str, np.ndarray], c2: float = 0.5,
                  success_altitude_m: float = 50.0, max_descent_plots: Optional[int] = 64) -> List[Path]:
    """All figures into ``<run_dir>/figures/``: ``descent_<run>.png`` per run (at most
    ``max_descent_plots``) and ``lowest_altitude.png``. Returns the paths written."""
    out = Path(run_dir) / "figures"
    out.mkdir(parents=True, exist_ok=True)
    paths = [lowest_altitude_chart(runs, out / "lowest_altitude.png", success_altitude_m)]
    fig = _descent_axes()
    try:
        for b, run in enumerate(runs[:max_descent_plots] if max_descent_plots else runs):
            paths.append(descent_figure(traces, b, run, out / f"descent_{run_folder_name(run['run'])}.png", c2,
                                        _fig=fig))
    finally:
        _plt().close(fig[0])
    return paths
