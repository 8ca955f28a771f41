"""The calibration report of an evaluation (``dvsland evaluate --calibration``): calibration.json,
calibration.txt (the coverage table, also printed) and calibration.png (reliability diagram and
risk-coverage curve per estimator) in the run folder. The numbers: :mod:`.calibration`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

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


# ---------------------------------------------------------------------------------------------- fitting a map
#: the sample of an evaluation that a calibration table is fitted from (written with --calibration)
SAMPLE_FILE = "calibration_sample.npz"


def calibration_sample(res) -> dict:
    """The scored steps of an evaluation as flat arrays: ``d_true``, ``site``, ``n_events`` (events
    of the step's window) and, per estimator i (``labels[i]``), ``d_hat_i``, ``confidence_i`` and,
    for an estimator whose diagnostics give it (``cmax``), ``structure_i``."""
    conf = getattr(res, "confidence", None) or {}
    if not conf:
        raise ValueError("--calibration: this evaluation recorded no per-step confidence")
    sc = np.asarray(res.scored, dtype=bool)
    sites = np.broadcast_to(np.array([str(s) for s in res.descents.sites])[:, None], sc.shape)
    out = {"d_true": np.asarray(res.descents.divergence, dtype=np.float64)[sc], "site": sites[sc],
           "n_events": np.asarray(res.n_events, dtype=np.int64)[sc], "labels": np.array(list(res.d_hat))}
    for i, name in enumerate(res.d_hat):
        out[f"d_hat_{i}"] = np.asarray(res.d_hat[name], dtype=np.float64)[sc]
        out[f"confidence_{i}"] = np.asarray(conf[name], dtype=np.float64)[sc]
        st = (getattr(res, "structure", None) or {}).get(name)
        if st is not None:
            out[f"structure_{i}"] = np.asarray(st, dtype=np.float64)[sc]
    return out


def write_calibration_sample(res, run_dir: Path, meta: dict) -> Path:
    """Write :func:`calibration_sample` and ``meta`` (config name, seed, overrides, checkpoints as
    JSON text) to ``run_dir / calibration_sample.npz``."""
    import io
    import json

    from dvsland.report.results import atomic_write_bytes, to_json

    path = Path(run_dir) / SAMPLE_FILE
    buf = io.BytesIO()
    np.savez_compressed(buf, meta=np.array(to_json(meta, indent=None)), **calibration_sample(res))
    atomic_write_bytes(path, buf.getbuffer())  # a full disk: one clear error, no temporary file left
    with np.load(path) as z:
        json.loads(str(z["meta"]))  # a file that reads back
    return path


def read_calibration_sample(path) -> dict:
    """A ``calibration_sample.npz`` (or the run folder holding one) as {arrays..., "meta": dict}."""
    import json

    p = Path(path)
    if p.is_dir():
        p = p / SAMPLE_FILE
    if not p.is_file():
        raise ValueError(f"no calibration sample at {str(path)!r}: run `dvsland evaluate ... --calibration` "
                         f"(it writes {SAMPLE_FILE} into its run folder)")
    with np.load(p) as z:
        out = {k: z[k] for k in z.files}
    out["meta"] = json.loads(str(out.get("meta", np.array("{}"))))
    cfg_file = p.parent / "config.yaml"
    if "estimator_params" not in out["meta"] and cfg_file.is_file():  # a sample written without them
        from dvsland.config import load_config
        from dvsland.estimators.factory import estimator_params

        cfg = load_config(cfg_file)
        names = out["meta"].get("estimators") or {}
        out["meta"]["estimator_params"] = {lab: estimator_params(cfg, n) for lab, n in names.items()}
    return out


def _coverage_rows(d_true, d_hat, conf, sites) -> dict:
    from .calibration import coverage_table, site_type

    t = coverage_table(d_true, d_hat, conf, [site_type(s) for s in sites])
    return {k: {"n_estimates": r["n_estimates"], "cover_1sigma": r["cover_1sigma"], "cover_2sigma": r["cover_2sigma"],
                "within_5_points": r["within_5_points"]} for k, r in t.items()}


def fit_from_samples(samples, label: str, estimator: Optional[str] = None, feature: str = "events",
                     sigma_bins: int = 8, feature_bins: int = 6, min_count: int = 40) -> dict:
    """Fit one estimator's calibration table on one or several evaluation samples (pooled) and
    return its JSON object (:func:`dvsland.estimators.calibrate.calibration_to_json`), its ``fit``
    naming the configs, seeds, overrides and checkpoint of the samples and the coverage per site
    type before and after on the fitting sample itself (judge it on other seeds).

    Args:
        samples: dicts of :func:`read_calibration_sample`.
        label: the estimator's label in those evaluations (``cmax``, ``mine=pkg.mod:Class``'s ``mine``).
        estimator: the estimator the table is for (default: the label's name in the first sample).
        feature, sigma_bins, feature_bins, min_count: :func:`~dvsland.estimators.calibrate.fit_calibration`.
    """
    import json

    from dvsland.estimators.calibrate import apply_calibration_np, calibration_off, calibration_to_json, fit_calibration

    parts, metas = [], []
    for s in samples:
        labels = [str(x) for x in np.asarray(s["labels"]).tolist()]
        if label not in labels:
            raise ValueError(f"estimator {label!r} is not in this calibration sample (it has {', '.join(labels)})")
        i = labels.index(label)
        meta = dict(s.get("meta") or {})
        if not calibration_off(meta.get("calibration", "none")):
            raise ValueError(f"this sample was evaluated with estimator.calibration={meta['calibration']!r}: fit on "
                             f"raw confidences (estimator.calibration=none)")
        if feature == "structure" and f"structure_{i}" not in s:
            raise ValueError(f"the 'structure' feature: this calibration sample holds no structure for {label!r} "
                             f"(its estimator gives none, or the sample predates it)")
        st = s.get(f"structure_{i}", np.full(np.shape(s["d_true"]), np.nan))
        parts.append((s["d_true"], s[f"d_hat_{i}"], s[f"confidence_{i}"], s["n_events"], s["site"], st))
        metas.append(meta)
    dt, dh, c, ne, site, st = (np.concatenate([p[k] for p in parts]) for k in range(6))
    params, info = fit_calibration(dt, dh, c, feature, ne, structure=st, sigma_bins=sigma_bins,
                                   feature_bins=feature_bins, min_count=min_count)
    after = apply_calibration_np(params, dh, c, ne, st)
    names = [m.get("estimators", {}).get(label, label) for m in metas]
    est = estimator or names[0]
    ck = [m.get("checkpoints", {}).get(label) for m in metas]
    prm = [json.dumps((m.get("estimator_params") or {}).get(label), sort_keys=True) for m in metas]
    if len(set(prm)) > 1:
        raise ValueError(f"the samples ran {label!r} with different parameters: fit one table per setting")
    fit = {"configs": sorted({str(m.get("config", "?")) for m in metas}),
           "seeds": sorted({int(m["seed"]) for m in metas if m.get("seed") is not None}),
           "overrides": [m.get("overrides", []) for m in metas], "estimator_label": label,
           "checkpoint": next((x for x in ck if x), None),
           "estimator_params": (metas[0].get("estimator_params") or {}).get(label), "feature": feature, "sigma_bins": sigma_bins,
           "feature_bins": feature_bins if feature != "none" else 1, "min_count": min_count,
           "n_estimates": info["n_estimates"], "cell_counts": info["cell_counts"],
           "coverage_before": _coverage_rows(dt, dh, c, site), "coverage_after_in_sample": _coverage_rows(dt, dh, after, site)}
    return calibration_to_json(params, est, fit)


def format_fit(obj: dict) -> str:
    """Two lines per site type: the fitting sample's coverage before / after a fitted table."""
    fit = obj["fit"]
    lines = [f"calibration table for {obj['estimator']} (feature {obj['feature']}, fitted on {', '.join(fit['configs'])} "
             f"seeds {fit['seeds']}, {fit['n_estimates']} estimates); in-sample 1 sigma / 2 sigma before -> after:"]
    for grp, b in fit["coverage_before"].items():
        a = fit["coverage_after_in_sample"][grp]
        lines.append(f"  {grp:<14} {_pct(b['cover_1sigma']):>7} / {_pct(b['cover_2sigma']):>7} -> "
                     f"{_pct(a['cover_1sigma']):>7} / {_pct(a['cover_2sigma']):>7}")
    return "\n".join(lines)
