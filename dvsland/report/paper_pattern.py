"""The paper's reported closed-loop pattern beside the one just flown (text and a Fig. 7-style chart).

The paper's pattern is transcribed in ``paper_pattern.yaml`` (package data): per site a coarse
pattern (``best``, ``late`` = fails only near the end, ``early`` = fails early, ``jittery``), the
number of descents that reached 50 m, and "unknown" wherever the paper gives no figure. A flown
descent is classed the same way from its summary: ``reached`` (success), ``late`` (it failed
after half of the closed-form time to the success altitude) or ``early`` (before it). Single
descents flip with tiny changes (the integrator alone flips some), so compare patterns, pooled
over seeds where ``simulation.n_seeds`` > 1, not one descent against one figure.

Pooled over many runs (:func:`pooled_pattern`, :func:`format_pooled_comparison`; a campaign's
report uses them): per site the fraction of descents that reached the success altitude, failed
late and failed early, each with its 95 % Wilson interval, and the ascents in the first 30 s.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Dict, List

import numpy as np
import yaml

from dvsland.config.schema import SITE_NAMES
from dvsland.report.stats import wilson_interval
from dvsland.report.style import save_atomic

#: Seconds within which an ascent counts as "ascends early" in the check list.
EARLY_ASCENT_S = 30.0


def load_paper_pattern() -> dict:
    """The transcription of the paper's section 6 / Fig. 7 (``paper_pattern.yaml``) as a dict."""
    text = resources.files("dvsland.report").joinpath("paper_pattern.yaml").read_text()
    return yaml.safe_load(text)


def applies(runs: List[dict]) -> bool:
    """True when the runs fly all nine of the paper's sites (the comparison is then meaningful)."""
    return set(SITE_NAMES) <= {r["site"] for r in runs}


def _nominal_time_s(run: dict, c2: float, success_altitude_m: float) -> float:
    # closed form of the constant-TTC-decrease descent: tau = tau0 (z/z0)^c2, t = (tau0 - tau) / c2
    z0, v0 = run.get("z0_m"), run.get("v0_mps")
    if not z0 or not v0 or v0 >= 0 or not 0 < success_altitude_m < z0:
        return float("nan")
    tau0 = z0 / abs(v0)
    return tau0 * (1.0 - (success_altitude_m / z0) ** c2) / c2


def classify_run(run: dict, c2: float, success_altitude_m: float = 50.0) -> str:
    """``reached`` / ``late`` / ``early`` / ``running`` for one run summary (see module doc)."""
    if run["outcome"] == "success":
        return "reached"
    if run["outcome"] in ("running", "interrupted"):
        return "running"
    t_nom = _nominal_time_s(run, c2, success_altitude_m)
    return "late" if np.isfinite(t_nom) and run["t_end_s"] >= 0.5 * t_nom else "early"


def flown_pattern(runs: List[dict], c2: float, success_altitude_m: float = 50.0) -> Dict[str, dict]:
    """Per site: the classes of its runs, counts, and the lowest altitudes (m)."""
    out: Dict[str, dict] = {}
    for r in runs:
        s = out.setdefault(r["site"], {"classes": [], "outcomes": [], "lowest_m": [], "t_end_s": []})
        s["classes"].append(classify_run(r, c2, success_altitude_m))
        s["outcomes"].append(r["outcome"])
        s["lowest_m"].append(float(r["lowest_altitude_m"]))
        s["t_end_s"].append(float(r["t_end_s"]))
    return out


#: the classes a pooled pattern counts (a run still ``running`` is counted apart)
CLASSES = ("reached", "late", "early")


def pooled_pattern(runs: List[dict], c2: float, success_altitude_m: float = 50.0,
                   confidence: float = 0.95) -> Dict[str, dict]:
    """The flown pattern pooled over every run of a site (all seeds and controller settings).

    Args:
        runs: run summaries (``site``, ``outcome``, ``t_end_s``, ``z0_m``, ``v0_mps``); any number
            per site.
        c2: the controller's TTC decrease rate (classifies late / early, :func:`classify_run`).
        success_altitude_m: the success altitude, m.
        confidence: level of the Wilson intervals.

    Returns:
        ``{site: {"n", "n_reached", "n_late", "n_early", "n_running", "early_ascents",
        "<cls>_rate", "<cls>_lo", "<cls>_hi" for cls in CLASSES}}`` in the order of SITE_NAMES, then
        any other site, plus ``"all"`` pooling every site. Rates are fractions of the finished runs
        (``n``, running runs excluded); ``early_ascents`` counts ascents ending before
        :data:`EARLY_ASCENT_S` s.
    """
    by_site: Dict[str, List[dict]] = {}
    for r in runs:
        by_site.setdefault(r["site"], []).append(r)
    order = [s for s in SITE_NAMES if s in by_site] + [s for s in by_site if s not in SITE_NAMES]

    def summary(rs: List[dict]) -> dict:
        cls = [classify_run(r, c2, success_altitude_m) for r in rs]
        n = sum(1 for c in cls if c != "running")
        row = {"n": n, "n_running": cls.count("running"),
               "early_ascents": sum(1 for r in rs if r["outcome"] == "ascent" and r["t_end_s"] < EARLY_ASCENT_S)}
        for c in CLASSES:
            k = cls.count(c)
            lo, hi = wilson_interval(k, n, confidence)
            row.update({f"n_{c}": k, f"{c}_rate": k / n if n else float("nan"), f"{c}_lo": lo, f"{c}_hi": hi})
        return row

    out = {s: summary(by_site[s]) for s in order}
    out["all"] = summary(list(runs))
    return out


def _p(x: float) -> str:
    # whole percents, one decimal near 0 and 100 where rounding would hide the interval's width
    x = round(x, 6)  # a Wilson bound of k = 0 or k = n is 0 or 1 up to rounding
    return f"{x:.1f}" if (0 < x < 1 or 99 < x < 100) else f"{x:.0f}"


def _pct(row: dict, c: str) -> str:
    if not row["n"]:
        return "-"
    return f"{_p(100 * row[c + '_rate'])} % [{_p(100 * row[c + '_lo'])}-{_p(100 * row[c + '_hi'])}]"


def format_pooled_comparison(runs: List[dict], c2: float, success_altitude_m: float = 50.0,
                             markdown: bool = False, confidence: float = 0.95) -> str:
    """Table of the paper's pattern per site beside the pooled flown one (:func:`pooled_pattern`):
    reached / late / early as percentages with their Wilson intervals, the descents counted and
    the ascents in the first 30 s; a last row pools every site against the paper's 2 of 18."""
    paper = load_paper_pattern()
    pooled = pooled_pattern(runs, c2, success_altitude_m, confidence)
    alt = f"{success_altitude_m:g} m"
    head = ["site", "paper", "paper says", f"reached {alt}", "failed late", "failed early", "n",
            f"ascents < {EARLY_ASCENT_S:g} s"]
    rows = []
    for site, row in pooled.items():
        if site == "all":
            p = {"pattern": f"{paper['reached_50m']}/{paper['descents']} reached", "note": "A, C late; B early"}
        else:
            p = paper["sites"].get(site, {})
        rows.append([site, str(p.get("pattern", "unknown")), str(p.get("note", "unknown")), _pct(row, "reached"),
                     _pct(row, "late"), _pct(row, "early"), str(row["n"]), str(row["early_ascents"])])
    ci = f"{100 * confidence:g} % Wilson intervals in brackets"
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines + ["", f"({ci}; n: finished descents, all seeds and controller settings.)"])
    widths = [max(len(h), *(len(r[i]) for r in rows)) + 2 for i, h in enumerate(head)]
    fmt = lambda cells: "".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip()  # noqa: E731
    lines = [f"paper (section 6 / Fig. 7) vs flown, pooled over seeds and settings ({ci}):", fmt(head)]
    return "\n".join(lines + [fmt(r) for r in rows])


def checks(runs: List[dict], c2: float, success_altitude_m: float = 50.0) -> List[tuple]:
    """The pattern's coarse checks: (what, paper, flown) rows."""
    paper = load_paper_pattern()
    cls = [classify_run(r, c2, success_altitude_m) for r in runs]
    fails = [r for r, c in zip(runs, cls) if c in ("late", "early")]
    early_ascents = sum(1 for r in runs if r["outcome"] == "ascent" and r["t_end_s"] < EARLY_ASCENT_S)
    late = sum(1 for c in cls if c == "late")
    low = [r["lowest_altitude_m"] for r in fails]
    return [
        ("reached 50 m", f"{paper['reached_50m']} of {paper['descents']}", f"{cls.count('reached')} of {len(runs)}"),
        (f"ascents in the first {EARLY_ASCENT_S:g} s", "none reported", str(early_ascents)),
        ("failures that came late (after half the nominal time)", "A, C late; B early",
         f"{late} of {len(fails)}"),
        ("median lowest altitude of the failures", "unknown (Fig. 7)",
         f"{np.median(low):.0f} m" if low else "-"),
    ]


def format_comparison(runs: List[dict], c2: float, success_altitude_m: float = 50.0) -> str:
    """Text table: per site the paper's pattern and note, then each flown run (outcome, time,
    lowest altitude, class), or, when a site has more than two runs (several seeds), the pattern
    pooled over them (:func:`format_pooled_comparison`); then the coarse checks."""
    paper = load_paper_pattern()
    flown = flown_pattern(runs, c2, success_altitude_m)
    if max((len(f["classes"]) for f in flown.values()), default=0) > 2:
        lines = [format_pooled_comparison(runs, c2, success_altitude_m)]
    else:
        lines = ["paper (section 6 / Fig. 7) vs this run:",
                 f"{'site':<5}{'paper':<9}{'paper says':<34}flown (outcome t_end lowest -> class)"]
        for site in SITE_NAMES:
            if site not in flown:
                continue
            p = paper["sites"].get(site, {})
            f = flown[site]
            cells = [f"{o} {t:.0f}s {lo:.0f}m->{c}" for o, t, lo, c in
                     zip(f["outcomes"], f["t_end_s"], f["lowest_m"], f["classes"])]
            lines.append(f"{site:<5}{str(p.get('pattern', 'unknown')):<9}{str(p.get('note', 'unknown')):<34}"
                         + " | ".join(cells))
        lines.append(f"{'':<5}{'':<9}{'which 2 reached 50 m: ' + str(paper['reached_50m_runs']):<34}")
    for what, p, f in checks(runs, c2, success_altitude_m):
        lines.append(f"  {what}: paper {p}; flown {f}")
    return "\n".join(lines)


_COLOURS = {"reached": "tab:green", "late": "tab:orange", "early": "tab:red", "running": "tab:gray"}
#: smallest font in the chart, points at the saved size (the figure is saved at :data:`DPI`)
FONT_PT = 10
DPI = 100


def class_words(success_altitude_m: float = 50.0) -> Dict[str, str]:
    """The printed table's column words for each class (:func:`format_pooled_comparison`)."""
    return {"reached": f"reached {success_altitude_m:g} m", "late": "failed late", "early": "failed early",
            "running": "still running"}


def _lowest_altitude_panel(ax, runs: List[dict], sites: List[str], c2: float, success_altitude_m: float):
    """Bars: the median lowest altitude per site and setting (log scale), coloured by the most
    common class; with several runs per bar a 10th-90th percentile whisker; the paper's pattern
    is written above each site."""
    paper = load_paper_pattern()
    labels = list(dict.fromkeys(r["label"] for r in runs))
    width = 0.8 / max(len(labels), 1)
    for j, lab in enumerate(labels):
        x = np.arange(len(sites)) + (j - (len(labels) - 1) / 2) * width
        for i, s in enumerate(sites):
            sel = [r for r in runs if r["site"] == s and r["label"] == lab]
            if not sel:
                continue
            lows = np.array([r["lowest_altitude_m"] for r in sel], dtype=float)
            cls = [classify_run(r, c2, success_altitude_m) for r in sel]
            main = max(set(cls), key=cls.count)
            med = max(float(np.median(lows)), 1.0)
            ax.bar(x[i], med, width, color=_COLOURS[main], edgecolor="k", lw=0.4, hatch="" if j == 0 else "//")
            if len(sel) > 1:
                p10, p90 = np.maximum(np.percentile(lows, [10, 90]), 1.0)
                ax.errorbar(x[i], med, yerr=[[max(med - p10, 0.0)], [max(p90 - med, 0.0)]], fmt="none", ecolor="k",
                            lw=0.8, capsize=2)
    top = max([r.get("z0_m") or 1e4 for r in runs] + [success_altitude_m * 2])
    ax.axhline(success_altitude_m, color="k", ls="--", lw=0.8)
    ax.set_yscale("log")
    ax.set_ylim(max(1.0, success_altitude_m / 5), top * 3)
    for i, s in enumerate(sites):
        p = paper["sites"].get(s, {})
        ax.text(i, top * 1.3, str(p.get("pattern", "?")), ha="center", va="bottom", fontsize=FONT_PT)
    ax.text(-0.55, top * 1.3, "paper:", ha="right", va="bottom", fontsize=FONT_PT, style="italic")
    ax.set_xticks(np.arange(len(sites)))
    ax.set_xticklabels(sites)
    ax.set_xlabel("site")
    ax.set_ylabel("lowest altitude reached [m]")
    return labels


def _pooled_panel(ax, runs: List[dict], sites: List[str], c2: float, success_altitude_m: float):
    """Stacked bars per site: the fractions reached / failed late / failed early pooled over every
    run of the site, with the 95 % Wilson interval of the reached fraction; the paper's pattern
    above each site."""
    paper = load_paper_pattern()
    pooled = pooled_pattern(runs, c2, success_altitude_m)
    x = np.arange(len(sites))
    bottom = np.zeros(len(sites))
    for c in CLASSES:
        frac = np.array([100 * pooled[s][f"{c}_rate"] if pooled[s]["n"] else 0.0 for s in sites])
        ax.bar(x, frac, 0.6, bottom=bottom, color=_COLOURS[c], edgecolor="k", lw=0.4,
               label=class_words(success_altitude_m)[c])
        bottom += frac
    rate = np.array([100 * pooled[s]["reached_rate"] for s in sites])
    # clipped: a Wilson bound at k = 0 or k = n may sit a rounding error past the rate
    lo = np.maximum(rate - np.array([100 * pooled[s]["reached_lo"] for s in sites]), 0.0)
    hi = np.maximum(np.array([100 * pooled[s]["reached_hi"] for s in sites]) - rate, 0.0)
    ax.errorbar(x, rate, yerr=[lo, hi], fmt="o", color="k", ms=3, capsize=3, lw=0.9,
                label=f"{class_words(success_altitude_m)['reached']}: 95 % CI")
    for i, s in enumerate(sites):
        ax.text(i, 103, f"{paper['sites'].get(s, {}).get('pattern', '?')}\nn={pooled[s]['n']}",
                ha="center", va="bottom", fontsize=FONT_PT)
    ax.text(-0.55, 103, "paper:\nflown:", ha="right", va="bottom", fontsize=FONT_PT, style="italic")
    ax.set_ylim(0, 132)
    ax.set_yticks([0, 25, 50, 75, 100])
    ax.set_xticks(x)
    ax.set_xticklabels(sites)
    ax.set_xlabel("site")
    ax.set_ylabel("share of descents, % (pooled)")
    return pooled


def paper_pattern_chart(runs: List[dict], path, c2: float, success_altitude_m: float = 50.0,
                        pooled: bool | None = None):
    """Fig. 7-style chart: the lowest altitude per site and setting (bars, log scale; the median
    and a 10th-90th percentile whisker over seeds) with the paper's reported pattern written above
    each site (its altitudes are not transcribed). ``pooled`` (default: when some site and setting
    has more than one run) adds a panel of the reached / late / early shares pooled over seeds and
    settings with the Wilson interval of the reached share."""
    from .figures import _plt

    plt = _plt()
    paper = load_paper_pattern()
    sites = [s for s in SITE_NAMES if any(r["site"] == s for r in runs)]
    if pooled is None:
        keys = [(r["site"], r["label"]) for r in runs]
        pooled = len(keys) > len(set(keys))
    if pooled:
        fig, (ax, ax2) = plt.subplots(1, 2, figsize=(15, 5))
    else:
        fig, ax = plt.subplots(figsize=(11, 5))
    labels = _lowest_altitude_panel(ax, runs, sites, c2, success_altitude_m)
    flown_ok = sum(1 for r in runs if r["outcome"] == "success")
    title = (f"reached {success_altitude_m:g} m: paper {paper['reached_50m']} of {paper['descents']}, "
             f"{'pooled' if pooled else 'this run'} {flown_ok} of {len(runs)}")
    from matplotlib.patches import Patch

    words = class_words(success_altitude_m)
    handles = [Patch(color=c, label=words[k]) for k, c in _COLOURS.items() if k != "running"]
    handles.append(Patch(facecolor="w", edgecolor="k", label=" / ".join(labels)))
    if pooled:
        fig.suptitle(title, fontsize=FONT_PT + 2)
        ax.set_title("lowest altitude: median over seeds,\n10-90 % whisker (hatched: 2nd setting)", fontsize=FONT_PT)
        _pooled_panel(ax2, runs, sites, c2, success_altitude_m)
        ax2.set_title(f"{words['reached']} / failed late / failed early,\npooled over seeds and settings",
                      fontsize=FONT_PT)
        ax2.legend(handles=handles + ax2.get_legend_handles_labels()[0][-1:], fontsize=FONT_PT, loc="upper left",
                   bbox_to_anchor=(1.005, 1.0))
    else:
        ax.set_title(title + "\n(bars: this run; hatched: 2nd setting)", fontsize=FONT_PT)
        ax.legend(handles=handles, fontsize=FONT_PT, loc="upper left", bbox_to_anchor=(1.005, 1.0))
    for a in fig.axes:
        a.tick_params(labelsize=FONT_PT)
        a.xaxis.label.set_size(FONT_PT + 1)
        a.yaxis.label.set_size(FONT_PT + 1)
    fig.tight_layout()
    try:
        save_atomic(fig, path, dpi=DPI)
    finally:
        plt.close(fig)
    return Path(path)


__all__ = ["load_paper_pattern", "applies", "classify_run", "flown_pattern", "pooled_pattern", "checks",
           "format_comparison", "format_pooled_comparison", "paper_pattern_chart"]
