"""Evaluation output: printed table, JSON, traces (npz) and figures in the run folder."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np

from dvsland.report.results import atomic_write_text, write_json, write_traces_npz

from .metrics import BANDS
from .run import TARGET_SITES, EvaluationResult, target_label
from .scenario_run import format_scenario_table, scenario_traces


def _f(x, pct=False, nd=3):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{100 * x:.1f}%" if pct else f"{x:.{nd}f}"


def checkpoint_note(summary: dict) -> str:
    """``"checkpoint: learned = learned_cnn.pt sha256:1a2b3c4d5e6f"`` for the estimators of
    ``summary`` that read a trained checkpoint (several joined by ``"; "``); "" for none."""
    from dvsland.report.checkpoint import checkpoint_text

    cks = [(n, e["checkpoint"]) for n, e in summary["estimators"].items() if e.get("checkpoint")]
    if not cks:
        return ""
    return ("checkpoint" if len(cks) == 1 else "checkpoints") + ": " + \
        "; ".join(f"{n} = {checkpoint_text(c)}" for n, c in cks)


def is_recording(summary: dict) -> bool:
    """True for the summary of :func:`dvsland.evaluate.evaluate_recording`."""
    return summary.get("trajectory") == "recording"


def _source(summary: dict) -> str:
    """What was evaluated, for titles: the recording (file, intervals) or the oracle descents."""
    if is_recording(summary):
        name = Path(str(summary.get("recording", "recording"))).name
        w, h = (summary.get("sensor_size") or ["?", "?"])[:2]
        gt = "" if summary.get("has_ground_truth", True) else "; no ground truth: no error"
        f = int(summary.get("bin_factor") or 1)
        binned = f", binned {f}x{f}" if f > 1 else ""
        return f"recording {name} ({w}x{h} px{binned}, {summary.get('n_steps', '?')} intervals{gt})"
    return "closed-form oracle descents"


def _time_head(summary: dict) -> str:
    base = summary.get("time_base", "CPU")
    return ("CPU ms per update (process CPU time; wall ms beside)" if base == "CPU"
            else "wall ms per update (CUDA, device synchronised)")


def _time_lines(summary: dict) -> list:
    """The time table: per estimator, ms per update in the report's time base (median / mean),
    and the wall time beside it."""
    ests, B = summary["estimators"], len(summary["sites"])
    base = summary.get("time_base", "CPU")
    lines = [f"Time per update for the batch of B = {B} on {summary.get('device', '?')} "
             f"({summary.get('torch_threads', '?')} torch threads): {_time_head(summary)}"]
    w = _name_width(summary)
    head = f"{'estimator':<{w}} {base + ' ms med':>12} {base + ' ms mean':>13}"
    if base == "CPU":
        head += f" {'wall ms med':>12} {'wall ms mean':>13}"
    lines += [head, "-" * len(head)]
    for n, e in ests.items():
        row = f"{n:<{w}} {_f(e.get('ms_per_step_median'), nd=2):>12} {_f(e.get('ms_per_step_mean'), nd=2):>13}"
        if base == "CPU":
            row += (f" {_f(e.get('wall_ms_per_step_median'), nd=2):>12}"
                    f" {_f(e.get('wall_ms_per_step_mean'), nd=2):>13}")
        lines.append(row)
    return lines


def _name_width(summary: dict) -> int:
    """Width of the estimator column: the longest label (``dpr[baseline_steps=5]``), at least 12."""
    return max([12] + [len(n) for n in summary["estimators"]])


def _metric_row(name: str, label: str, m: dict, w: int = 12) -> str:
    return (f"{name:<{w}} {label:<9} {m['n_steps']:>6d} {_f(m['coverage'], True):>7} "
            f"{_f(m['median_abs_rel_err'], True):>9} {_f(m['rmse'], nd=4):>8} {_f(m['within_10'], True):>7} "
            f"{_f(m['within_20'], True):>7} {_f(m['bias_rel'], True):>8}")


def _error_lines(summary: dict) -> list:
    """The error table: for rendered descents one row per estimator and site, then the target sites
    (when any ran) and all sites (when more than one); for a recording one row per estimator."""
    ests, sites = summary["estimators"], summary["sites"]
    tl = summary.get("target_label") or target_label(sites)
    rec = is_recording(summary)
    what = "recording" if rec else "site"
    lines = [f"Open-loop divergence error {'of each estimator' if rec else 'per site'} on the {_source(summary)}; "
             "med|rel| and RMSE over steps with an estimate, <10%/<20% over all scored steps"]
    w = _name_width(summary)
    head = (f"{'estimator':<{w}} {'' if rec else what:<9} {'steps':>6} {'cover':>7} {'med|rel|':>9} {'RMSE':>8} "
            f"{'<10%':>7} {'<20%':>7} {'bias':>8}")
    lines += [head, "-" * len(head)]
    for name, e in ests.items():
        if rec:
            lines.append(_metric_row(name, "", e["all_sites"], w))
            continue
        for s in sites:
            lines.append(_metric_row(name, s, e["sites"][s], w))
        n_target = sum(s in TARGET_SITES for s in sites)
        if n_target > 1:  # the target sites' aggregate, when several ran (one: its own row says it)
            lines.append(_metric_row(name, tl, e["sites_A_G"], w))
        if len(sites) > 1 and n_target < len(sites):  # all sites, when it differs from that
            lines.append(_metric_row(name, "all", e["all_sites"], w))
        lines.append("")
    return lines[:-1] if lines[-1] == "" else lines


def _band_lines(summary: dict) -> list:
    """The altitude-band table over the target sites (all sites when none ran; the recording's
    ground-truth altitude), only the bands with scored steps; [] when no band has any."""
    ests, sites = summary["estimators"], summary["sites"]
    tl = summary.get("target_label") or target_label(sites)
    key, over = ("bands_A_G", f"sites {tl}") if tl != "none" else ("bands_all_sites", f"sites {','.join(sites)}")
    if is_recording(summary):
        key, over = "bands_all_sites", "the recording's ground-truth altitude"
    bands = [b[0] for b in BANDS if any(e.get(key, {}).get(b[0], {}).get("n_steps", 0) for e in ests.values())]
    if not bands:
        return []
    w = _name_width(summary)
    lines = [f"By altitude band ({over}): med|rel| / <10% / coverage",
             f"{'estimator':<{w}} " + " ".join(f"{b:>26}" for b in bands)]
    for name, e in ests.items():
        cells = [f"{_f(e[key][b]['median_abs_rel_err'], True)} / {_f(e[key][b]['within_10'], True)} / "
                 f"{_f(e[key][b]['coverage'], True)}" for b in bands]
        lines.append(f"{name:<{w}} " + " ".join(f"{c:>26}" for c in cells))
    return lines


def format_table(summary: dict) -> str:
    """Plain-text tables: the error per estimator (and site), per altitude band (when any band has
    scored steps; a recording without altitude has none), the time per update (CPU ms, wall ms
    beside) and the hard scenarios; the checkpoint of a trained estimator under the first line."""
    lines = _error_lines(summary)
    note = checkpoint_note(summary)
    if note:
        lines.insert(1, note)
    bands = _band_lines(summary)
    if bands:
        lines += [""] + bands
    elif is_recording(summary) and summary.get("has_ground_truth", True):
        lines += ["", "(no altitude band table: the recording's ground truth has no altitude)"]
    lines += [""] + _time_lines(summary)
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
    key = "all_sites" if is_recording(summary) else "sites_A_G"
    xs = []
    for k, (name, e) in enumerate(summary["estimators"].items()):
        x = e["ms_per_step_median"]
        y = e[key]["median_abs_rel_err"]
        if x is None or y is None or not math.isfinite(y):
            continue
        x = max(x, 1e-3)
        xs.append(x)
        ax.scatter([x], [100 * y], s=50, color=f"C{k % 10}", label=f"{name}: {x:.3g} {summary.get('time_base', 'CPU')} ms, {100 * y:.1f} %", zorder=3)
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
    where = "the recording" if is_recording(summary) else f"sites {tl}"
    note = checkpoint_note(summary)
    style.label(ax, f"{summary.get('time_base', 'CPU')} time per update for the batch of B = "
                    f"{len(summary['sites'])} ({summary.get('device', 'cpu')}), median [ms]",
                f"median |relative error|, {where} [%]",
                f"Divergence estimators on the {_source(summary)}: speed vs error" + (f"\n{note}" if note else ""),
                legend="outside")
    style.save(fig, path, dpi=120)


def plot_traces(res: EvaluationResult, path: Path) -> None:
    """Per site (or the recording): true D and each estimator's D_hat over time, on limits that
    show the truth and the bulk of the estimates (:func:`dvsland.report.style.robust_limits`);
    estimates beyond them sit as open triangles on the edge, counted in the panel's title. One
    legend for the figure, below the panels."""
    from matplotlib.lines import Line2D

    from dvsland.report import style

    plt = style.pyplot()
    desc = res.descents
    B = len(desc.sites)
    cols = min(3, B)
    rows = int(math.ceil(B / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(max(4.6 * cols, 9.0), 3.2 * rows + 1.2), squeeze=False,
                             layout="constrained")
    d_true = desc.divergence
    rec = is_recording(res.summary or {})
    for i, s in enumerate(desc.sites):
        ax = axes[i // cols][i % cols]
        v = desc.valid[i]
        lo, hi = style.robust_limits(d_true[i][v], [dh[i][v] for dh in res.d_hat.values()])
        out = {}
        for k, (name, dh) in enumerate(res.d_hat.items()):
            out[name] = style.plot_clipped(ax, desc.t_s[v], dh[i][v], lo, hi, name, "-", ms=0, lw=0.6,
                                           outside_label=None, color=f"C{k % 10}", alpha=0.85)
        ax.plot(desc.t_s[v], d_true[i][v], "k", lw=1.4, label="truth")
        beyond = ", ".join(f"{n}\u00a0{c}" for n, c in out.items() if c)  # a name and its count stay together
        if beyond:
            import textwrap

            beyond = "\n".join(textwrap.wrap(f"(beyond the axes: {beyond})", 48))
        title = (f"recording {s}" if rec else f"site {s}") + (f"\n{beyond}" if beyond else "")
        style.label(ax, "t [s]", "D [1/s]")
        ax.set_title(title, fontsize=8 if beyond else 10)
    for j in range(B, rows * cols):
        axes[j // cols][j % cols].axis("off")
    handles = [Line2D([], [], color=f"C{k % 10}", lw=1.5, label=n) for k, n in enumerate(res.d_hat)]
    handles += [Line2D([], [], color="k", lw=1.5, label="truth"),
                Line2D([], [], ls="", marker="^", mfc="none", mec="0.3", label="estimate beyond the axes (on the edge)")]
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 4), fontsize=8, frameon=False)
    note = checkpoint_note(res.summary) if res.summary else ""
    fig.suptitle(f"Open-loop divergence D on the {_source(res.summary or {})}: truth and estimates"
                 + (f"\n{note}" if note else ""))
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
