"""The paper's reported closed-loop pattern beside the one just flown (text and a Fig. 7-style chart).

The paper's pattern is transcribed in ``paper_pattern.yaml`` (package data): per site a coarse
pattern (``best``, ``late`` = fails only near the end, ``early`` = fails early, ``jittery``), the
number of descents that reached 50 m, and "unknown" wherever the paper gives no figure. A flown
descent is classed the same way from its summary: ``reached`` (success), ``late`` (it failed
after half of the closed-form time to the success altitude) or ``early`` (before it). Single
descents flip with tiny changes (the integrator alone flips some), so compare patterns, pooled
over seeds where ``simulation.n_seeds`` > 1, not one descent against one figure.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Dict, List

import numpy as np
import yaml

from dvsland.config.schema import SITE_NAMES

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
    lowest altitude, class); then the coarse checks."""
    paper = load_paper_pattern()
    flown = flown_pattern(runs, c2, success_altitude_m)
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


def paper_pattern_chart(runs: List[dict], path, c2: float, success_altitude_m: float = 50.0):
    """Fig. 7-style chart: the lowest altitude per site and setting (bars, log scale) with the
    paper's reported pattern written above each site (its altitudes are not transcribed)."""
    from .figures import _plt

    plt = _plt()
    paper = load_paper_pattern()
    sites = [s for s in SITE_NAMES if any(r["site"] == s for r in runs)]
    labels = list(dict.fromkeys(r["label"] for r in runs))
    fig, ax = plt.subplots(figsize=(10, 4.5))
    width = 0.8 / max(len(labels), 1)
    colours = {"reached": "tab:green", "late": "tab:orange", "early": "tab:red", "running": "tab:gray"}
    for j, lab in enumerate(labels):
        x = np.arange(len(sites)) + (j - (len(labels) - 1) / 2) * width
        for i, s in enumerate(sites):
            sel = [r for r in runs if r["site"] == s and r["label"] == lab]
            if not sel:
                continue
            lows = np.array([r["lowest_altitude_m"] for r in sel], dtype=float)
            cls = [classify_run(r, c2, success_altitude_m) for r in sel]
            main = max(set(cls), key=cls.count)
            ax.bar(x[i], max(float(np.median(lows)), 1.0), width, color=colours[main],
                   edgecolor="k", lw=0.4, hatch="" if j == 0 else "//")
    top = max([r.get("z0_m", 1e4) for r in runs] + [success_altitude_m * 2])
    ax.axhline(success_altitude_m, color="k", ls="--", lw=0.8)
    ax.set_yscale("log")
    ax.set_ylim(max(1.0, success_altitude_m / 5), top * 3)
    for i, s in enumerate(sites):
        p = paper["sites"].get(s, {})
        ax.text(i, top * 1.3, f"paper:\n{p.get('pattern', '?')}", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(np.arange(len(sites)))
    ax.set_xticklabels(sites)
    ax.set_xlabel("site")
    ax.set_ylabel("lowest altitude reached [m]")
    flown_ok = sum(1 for r in runs if r["outcome"] == "success")
    ax.set_title(f"reached {success_altitude_m:g} m: paper {paper['reached_50m']} of {paper['descents']}, "
                 f"this run {flown_ok} of {len(runs)}   (bars: this run; hatched: 2nd setting)", fontsize=9)
    from matplotlib.patches import Patch

    handles = [Patch(color=c, label=k) for k, c in colours.items() if k != "running"]
    handles.append(Patch(facecolor="w", edgecolor="k", label=" / ".join(labels)))
    ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.005, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)


__all__ = ["load_paper_pattern", "applies", "classify_run", "flown_pattern", "checks", "format_comparison",
           "paper_pattern_chart"]
