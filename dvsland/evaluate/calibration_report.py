"""The calibration report of an evaluation (``dvsland evaluate --calibration``): calibration.json,
calibration.txt (the coverage table, also printed) and calibration.png (reliability diagram and
risk-coverage curve per estimator) in the run folder. The numbers: :mod:`.calibration`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dvsland.report.results import atomic_write_text, write_json

from .calibration import TARGET_1S, TARGET_2S, calibration_summary


def calibration_of(res) -> dict:
    """:func:`~.calibration.calibration_summary` of an :class:`~.run.EvaluationResult` (its scored
    steps); ValueError when the evaluation recorded no confidence."""
    conf = getattr(res, "confidence", None) or {}
    if not conf:
        raise ValueError("--calibration: this evaluation recorded no per-step confidence")
    return calibration_summary(res.descents.divergence, res.d_hat, conf, res.scored, res.descents.sites)


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


def format_calibration_table(cal: dict) -> str:
    """Plain-text coverage table: per estimator and site type (then all), the estimates, the
    abstentions (NaN / confidence 0), the 1 sigma and 2 sigma coverage and whether both are
    within 5 points of 68.3 % / 95.4 %."""
    w = max([12] + [len(n) for n in cal["estimators"]])
    lines = [f"Calibration: share of estimates with |D_hat - D| inside the predicted 1 sigma / 2 sigma "
             f"(target {100 * TARGET_1S:.1f}% / {100 * TARGET_2S:.1f}% +- 5 points)",
             "sigma = 0.1 sqrt(1/c - 1) max(|D_hat|, |D|), at least 1e-6 of the scale; abstentions (NaN, c = 0) apart"]
    head = (f"{'estimator':<{w}} {'site type':<14} {'steps':>6} {'estim.':>6} {'NaN':>5} {'c=0':>5} "
            f"{'<=1sig':>7} {'<=2sig':>7} {'ok':>3}")
    lines += [head, "-" * len(head)]
    for name, e in cal["estimators"].items():
        for grp, r in e["coverage"].items():
            ok = "-" if r["within_5_points"] is None else ("yes" if r["within_5_points"] else "no")
            lines.append(f"{name:<{w}} {grp:<14} {r['n_steps']:>6d} {r['n_estimates']:>6d} {r['n_nan']:>5d} "
                         f"{r['n_zero_confidence']:>5d} {_pct(r['cover_1sigma']):>7} {_pct(r['cover_2sigma']):>7} "
                         f"{ok:>3}")
        lines.append("")
    return "\n".join(lines[:-1])


def plot_calibration(cal: dict, path: Path) -> None:
    """Two panels: the reliability diagram (RMS predicted vs observed relative error per bin,
    log-log, the diagonal = calibrated; point size ~ steps) and the risk-coverage curve (median
    |relative error| of the steps kept, most confident first, vs the share kept)."""
    from dvsland.report import style

    plt = style.pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.4), layout="constrained")
    lo, hi = 1e-3, 1.0
    for k, (name, e) in enumerate(cal["estimators"].items()):
        col = f"C{k % 10}"
        rb = e["reliability"]
        if rb:
            x = np.array([b["pred_rms_rel_sigma"] for b in rb])
            y = np.array([b["obs_rms_rel_err"] for b in rb])
            n = np.array([b["n"] for b in rb], dtype=float)
            pos = (x > 0) & (y > 0)
            a1.plot(x[pos], y[pos], "-", color=col, lw=1, alpha=0.7)
            a1.scatter(x[pos], y[pos], s=10 + 60 * n[pos] / n.max(), color=col, label=name, zorder=3)
            if pos.any():
                lo, hi = min(lo, x[pos].min(), y[pos].min()), max(hi, x[pos].max(), y[pos].max())
        rc = e["risk_coverage"]
        xs = [s for s, m in zip(rc["share_kept"], rc["median_abs_rel_err"]) if m is not None]
        ys = [100 * m for m in rc["median_abs_rel_err"] if m is not None]
        a2.plot([100 * s for s in xs], ys, "o-", ms=3, color=col, label=f"{name} (answers {_pct(rc['answered_share'])})")
    a1.plot([lo, hi], [lo, hi], "k--", lw=0.8, label="calibrated")
    a1.set_xscale("log")
    a1.set_yscale("log")
    style.label(a1, "predicted relative sigma, RMS per bin [-]", "observed |relative error|, RMS per bin [-]",
                "Reliability (above the diagonal = over-confident)", legend="best")
    a2.set_ylim(bottom=0)
    style.label(a2, "steps kept, most confident first [%]", "median |relative error| of kept steps [%]",
                "Risk-coverage", legend="best")
    style.save(fig, path, dpi=110)


def write_calibration(res, run_dir: Path, figures: bool = True) -> dict:
    """Write calibration.json, calibration.txt and (figures) calibration.png into ``run_dir``.

    Returns ({kind: path}, the table text)."""
    run_dir = Path(run_dir)
    cal = calibration_of(res)
    table = format_calibration_table(cal)
    paths = {"calibration_json": run_dir / "calibration.json", "calibration_table": run_dir / "calibration.txt"}
    write_json(paths["calibration_json"], cal)
    atomic_write_text(paths["calibration_table"], table + "\n")
    if figures:
        paths["calibration_png"] = run_dir / "calibration.png"
        plot_calibration(cal, paths["calibration_png"])
    return paths, table
