"""Evaluation output: printed table, JSON, traces (npz) and figures in the run folder."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np

from dvsland.report.results import atomic_write_text, write_json, write_traces_npz

from .metrics import BANDS
from .run import EvaluationResult, target_label
from .scenario_run import format_scenario_table, scenario_traces


def _f(x, pct=False, nd=3):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{100 * x:.1f}%" if pct else f"{x:.{nd}f}"


def format_table(summary: dict) -> str:
    """Plain-text tables: per estimator and site, then per altitude band (sites A-G), then speed."""
    ests = summary["estimators"]
    sites = summary["sites"]
    tl = summary.get("target_label") or target_label(sites)
    lines = []
    head = (f"{'estimator':<10} {'site':<5} {'steps':>6} {'cover':>7} {'med|rel|':>9} {'RMSE':>8} "
            f"{'<10%':>7} {'<20%':>7} {'bias':>8}")
    lines.append("Open-loop divergence error per site (closed-form oracle descents; med|rel| and RMSE over "
                 "steps with an estimate, <10%/<20% over all steps)")
    lines.append(head)
    lines.append("-" * len(head))

    def row(name, label, m):
        return (f"{name:<10} {label:<5} {m['n_steps']:>6d} {_f(m['coverage'], True):>7} "
                f"{_f(m['median_abs_rel_err'], True):>9} {_f(m['rmse'], nd=4):>8} {_f(m['within_10'], True):>7} "
                f"{_f(m['within_20'], True):>7} {_f(m['bias_rel'], True):>8}")

    for name, e in ests.items():
        for s in sites:
            lines.append(row(name, s, e["sites"][s]))
        lines.append(row(name, tl, e["sites_A_G"]))
        lines.append(row(name, "all", e["all_sites"]))
        lines.append("")
    lines.append(f"By altitude band (sites {tl}): med|rel| / <10% / coverage")
    lines.append(f"{'estimator':<10} " + " ".join(f"{b[0]:>26}" for b in BANDS))
    for name, e in ests.items():
        cells = []
        for b in BANDS:
            m = e["bands_A_G"][b[0]]
            cells.append(f"{_f(m['median_abs_rel_err'], True)} / {_f(m['within_10'], True)} / "
                         f"{_f(m['coverage'], True)}")
        lines.append(f"{name:<10} " + " ".join(f"{c:>26}" for c in cells))
    lines.append("")
    lines.append(f"Time per update for the batch of B = {len(sites)} on {summary.get('device', '?')} "
                 f"({summary.get('torch_threads', '?')} torch threads): "
                 + ", ".join(f"{n} {_f(e['ms_per_step_median'], nd=2)} ms (median) / "
                             f"{_f(e['ms_per_step_mean'], nd=2)} ms (mean)" for n, e in ests.items()))
    scen = format_scenario_table(summary)
    if scen:
        lines += ["", scen]
    return "\n".join(lines)


def plot_speed_vs_error(summary: dict, path: Path) -> None:
    """Scatter: median ms per update vs median |relative error| (sites A-G), one labelled point per
    estimator, the 10 % target as a labelled dashed line, log time axis with 1-2-5 ticks."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    from dvsland.report import style

    plt = style.pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    xs = []
    for k, (name, e) in enumerate(summary["estimators"].items()):
        x = e["ms_per_step_median"]
        y = e["sites_A_G"]["median_abs_rel_err"]
        if x is None or y is None or not math.isfinite(y):
            continue
        x = max(x, 1e-3)
        xs.append(x)
        ax.scatter([x], [100 * y], s=50, color=f"C{k % 10}", label=f"{name}: {x:.3g} ms, {100 * y:.1f} %", zorder=3)
        ax.annotate(name, (x, 100 * y), textcoords="offset points", xytext=(6, 4), fontsize=8)
    ax.axhline(10, color="grey", lw=0.8, ls="--", label="target: 10 % median error")
    ax.set_xscale("log")
    if xs:
        lo, hi = min(xs), max(xs)
        ax.set_xlim(lo / 2.5, hi * 2.5)
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_ylim(bottom=0)
    tl = summary.get("target_label") or target_label(summary["sites"])
    style.label(ax, f"time per update for the batch of B = {len(summary['sites'])} "
                    f"({summary.get('device', 'cpu')}) [ms]",
                f"median |relative error|, sites {tl} [%]", "Divergence estimators: speed vs error",
                legend="outside")
    style.save(fig, path, dpi=120)


def plot_traces(res: EvaluationResult, path: Path) -> None:
    """Per site: true D and each estimator's D_hat over time."""
    from dvsland.report import style

    plt = style.pyplot()
    desc = res.descents
    B = len(desc.sites)
    cols = min(3, B)
    rows = int(math.ceil(B / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 2.8 * rows), squeeze=False)
    d_true = desc.divergence
    for i, s in enumerate(desc.sites):
        ax = axes[i // cols][i % cols]
        v = desc.valid[i]
        for name, dh in res.d_hat.items():
            ax.plot(desc.t_s[v], dh[i][v], lw=0.7, label=name)
        ax.plot(desc.t_s[v], d_true[i][v], "k", lw=1.2, label="truth")
        lo = np.nanmin(d_true[i][v]) if v.any() else -1.0
        ax.set_ylim(1.6 * lo, 0.3 * abs(lo))
        ax.set_title(f"site {s}")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("D [1/s]")
    for j in range(B, rows * cols):
        axes[j // cols][j % cols].axis("off")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("Open-loop divergence D along the ideal descents: truth and estimates")
    fig.tight_layout()
    style.save(fig, path, dpi=110)


def write_outputs(res: EvaluationResult, run_dir: Path, figures: bool = True) -> dict:
    """Write evaluation.json, table.txt, traces.npz and (figures) speed_vs_error.png, traces.png.

    Returns {kind: path}.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": run_dir / "evaluation.json", "table": run_dir / "table.txt",
             "traces": run_dir / "traces.npz"}
    # each file atomically: a full disk leaves the previous file or none (RunWriteError names it)
    write_json(paths["json"], res.summary)  # strict JSON: NaN / inf -> null
    atomic_write_text(paths["table"], format_table(res.summary) + "\n")
    write_traces_npz(paths["traces"], dict(t_s=res.descents.t_s, altitude_m=res.descents.altitude_m,
                                           d_true=res.descents.divergence, scored=res.scored, n_events=res.n_events,
                                           sites=np.array(res.descents.sites),
                                           **{f"d_hat_{n}": v for n, v in res.d_hat.items()},
                                           **scenario_traces(getattr(res, "scenarios", {}))))
    if figures:
        paths["speed_vs_error"] = run_dir / "speed_vs_error.png"
        plot_speed_vs_error(res.summary, paths["speed_vs_error"])
        paths["traces_png"] = run_dir / "traces.png"
        plot_traces(res, paths["traces_png"])
    return paths
