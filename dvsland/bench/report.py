"""The benchmark report: bench.json (every figure), bench.md (tables), pareto.png and scaling.png."""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from dvsland.report.results import write_json

from .stages import STAGE_NAMES
from .tradeoff import pareto_front

FAMILY_MARKERS = {"dpr": "o", "cmax": "s", "snn": "^", "oracle": "D", "setting": "v", "renderer": "P"}


def _pct(x, nd: int = 1) -> str:
    return "-" if x is None or not isinstance(x, (int, float)) or not math.isfinite(x) else f"{100 * x:.{nd}f} %"


def _num(x, nd: int = 2) -> str:
    return "-" if x is None or not isinstance(x, (int, float)) or not math.isfinite(x) else f"{x:.{nd}f}"


def stage_ms(timing: dict):
    """({stage: ms}, total ms, kind) of a :func:`time_stages` result: process CPU time on the CPU
    (one torch thread: the uncontended cost on a shared machine), wall time on CUDA."""
    if str(timing.get("device", "cpu")).startswith("cpu") and "cpu_ms" in timing:
        return timing["cpu_ms"], float(timing["cpu_ms_total"]), "CPU"
    return timing.get("ms", {}), float(timing.get("ms_total", math.nan)), "wall"


def _point(row: dict):
    e = row.get("error") or {}
    t = row.get("timing") or {}
    return (stage_ms(t)[1] if t else math.nan, float(e.get("median_abs_rel_err", math.nan)))


def _on_front_candidates(rows: List[dict]) -> List[int]:
    """Rows that estimate from events on all sites: the ``oracle`` presets read the true state
    (references for controller studies) and the renderer pair is measured on a subset of sites, so
    they are drawn but never part of the front."""
    return [i for i, r in enumerate(rows) if (r.get("timing") or {}).get("needs_events", True)
            and r.get("family") not in ("oracle", "renderer")]


def front_indices(rows: List[dict]) -> List[int]:
    """Indices of the rows on the Pareto front of (ms per step, median |relative error|), fastest first."""
    cand = _on_front_candidates(rows)
    pts = [_point(rows[i]) for i in cand]
    return [cand[j] for j in pareto_front(pts)]


def front_rows(rows: List[dict]) -> List[dict]:
    """The rows on the Pareto front (see :func:`front_indices`)."""
    return [rows[i] for i in front_indices(rows)]


def plot_pareto(rows: List[dict], path: Path, title: str) -> None:
    """Median |relative error| of D against ms per control step (log x), one labelled marker per
    configuration, the Pareto front as a step line, legend outside the axes (never clipped)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 6))
    pts = [_point(r) for r in rows]
    cmap = plt.get_cmap("tab20")
    for i, (r, (x, y)) in enumerate(zip(rows, pts)):
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        ref = r.get("family") == "oracle"
        ax.scatter([max(x, 1e-3)], [100 * y], marker=FAMILY_MARKERS.get(r["family"], "o"), s=60,
                   color="none" if ref else cmap(i % 20), edgecolor=cmap(i % 20) if ref else "k",
                   linewidth=1.2 if ref else 0.5,
                   label=f"{i + 1}: {r['label']}" + (" (reads the truth)" if ref else ""), zorder=3)
        ax.annotate(str(i + 1), (max(x, 1e-3), 100 * y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    front = front_indices(rows)
    if front:
        xs = [max(pts[i][0], 1e-3) for i in front]
        ys = [100 * pts[i][1] for i in front]
        sx, sy = [xs[0]], [ys[0]]
        for x, y in zip(xs[1:], ys[1:]):
            sx += [x, x]
            sy += [sy[-1], y]
        ax.plot(sx, sy, "k--", lw=1.0, label="Pareto front (event-based configurations)", zorder=2)
    ax.set_xscale("log")
    ax.set_ylim(bottom=0)
    kind = next((stage_ms(r["timing"])[2] for r in rows if r.get("timing")), "wall")
    ax.set_xlabel(f"{kind} time per control step at B = 18 (render + emulate + estimate + control), ms")
    ax.set_ylabel("median |relative error| of D, % (sites A-G)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7.5, frameon=False)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _batch_ticks(ax, bs) -> None:
    """Log batch axis ticked at the batch sizes measured, plain numbers, no minor labels."""
    from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator, ScalarFormatter

    ticks = sorted(set(int(b) for b in bs))
    if not ticks:
        return
    ax.xaxis.set_major_locator(FixedLocator(ticks))
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_locator(NullLocator())
    ax.xaxis.set_minor_formatter(NullFormatter())
    lo, hi = ticks[0], ticks[-1]
    ax.set_xlim(lo / 1.4, hi * 1.4)


def plot_scaling(rows: Sequence[Dict], path, title: str) -> None:
    """Two panels: ms per step of each stage against B (log-log), and peak memory against B
    (the rows of :func:`dvsland.bench.scaling.run_scaling`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bs = [r["batch_size"] for r in rows]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    per = [stage_ms(r) for r in rows]
    kind = per[0][2] if per else "wall"
    for k in STAGE_NAMES:
        ys = [max(p[0][k], 1e-3) for p in per]
        if any(p[0][k] > 0 for p in per):
            a1.plot(bs, ys, "o-", label=k.replace("_", " + "))
    a1.plot(bs, [p[1] for p in per], "k--", marker="s", ms=5, label="total")
    if kind == "CPU":
        a1.plot(bs, [r["ms_total"] for r in rows], "k:", marker="^", ms=5, mfc="white",
                label="total, wall (loaded machine)")
    a1.set_xscale("log")
    a1.set_yscale("log")
    _batch_ticks(a1, bs)
    a1.set_xlabel("batch size B (descents)")
    a1.set_ylabel(f"{kind} time per control step, ms")
    a1.set_title(title, fontsize=9)
    a1.legend(fontsize=8)
    a1.grid(True, which="both", alpha=0.3)
    mem = [(r["batch_size"], r["peak_memory_mib"]) for r in rows if r.get("peak_memory_mib") is not None]
    if mem:
        mx, my = [m[0] for m in mem], [max(m[1], 1e-1) for m in mem]
        a2.plot(mx, my, "o-", color="tab:purple", ms=6, label="peak resident memory")
        for x, y in zip(mx, my):
            a2.annotate(f"{y:.0f}", (x, y), textcoords="offset points", xytext=(5, -12), fontsize=8)
        # a log memory axis only when the values span a decade or more and there are enough
        # points to read it; else linear with plain ticks (two points on a log axis clash)
        if len(mem) >= 3 and max(my) / min(my) >= 10:
            a2.set_yscale("log")
            from matplotlib.ticker import FuncFormatter, NullFormatter

            a2.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            a2.yaxis.set_minor_formatter(NullFormatter())
        else:
            a2.set_ylim(0, max(my) * 1.15)
        a2.legend(fontsize=8, loc="lower right")
        a2.set_xscale("log")
        _batch_ticks(a2, mx)
    else:
        a2.text(0.5, 0.5, "no memory measured", ha="center", va="center", transform=a2.transAxes)
    a2.set_xlabel("batch size B (descents)")
    a2.set_ylabel("peak resident memory above the imports, MiB")
    a2.set_title("CPU: fresh process, renderer atlas of 9 sites included", fontsize=9)
    a2.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(report: dict, figures: Dict[str, str]) -> str:
    """The tables of ``report`` as markdown (figures: {kind: relative path})."""
    m = report["machine"]
    lines = []
    lines.append(f"Command: `{report['command']}`  ")
    lines.append(f"Run: {report['started_utc']}, {report['wall_s']:.0f} s wall, {report.get('cpu_s', 0):.0f} s of "
                 f"CPU (this process and its children); machine: {m['cpu_model']} "
                 f"({m['cpu_count']} cores), load average {m['load_average']} at the start and "
                 f"{report.get('load_average_end')} at the end; torch {m['torch_version']}, device {m['device']}, "
                 f"{m['torch_threads']} torch thread(s), renderer threads {report['render_threads']}; "
                 f"git {m['git_commit']}.")
    if report.get("overrides") or (report.get("sites") and len(report["sites"]) < 9):
        lines.append(f"Sites {', '.join(report.get('sites') or [])}; overrides: "
                     f"{', '.join(report.get('overrides') or []) or 'none'} (the method texts below describe "
                     "the default run).")
    lines.append("")
    tr = report.get("tradeoff")
    if tr:
        lines.append("## Speed against error")
        lines.append("")
        lines.append(tr["method"])
        lines.append("")
        kind = next((stage_ms(r["timing"])[2] for r in tr["rows"] if r.get("timing")), "wall")
        lines.append(f"Times per control step at B = 18, ms ({kind} time by stage; the wall time beside it):")
        lines.append("")
        lines.append("| # | configuration | median \\|rel. err.\\| | p90 \\|rel. err.\\| | coverage A-G "
                     "| coverage H, I "
                     f"| {kind} ms/step | wall ms/step | render | emulate | estimate | control + dynamics |")
        lines.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for i, r in enumerate(tr["rows"]):
            e, t = r.get("error") or {}, r.get("timing") or {}
            ms, tot, _ = stage_ms(t) if t else ({}, None, kind)
            hi = r.get("coverage_H_I")
            lines.append(f"| {i + 1} | {r['label']}{' (failed: ' + r['failed'] + ')' if r.get('failed') else ''} | "
                         f"{_pct(e.get('median_abs_rel_err'))} | {_pct(e.get('p90_abs_rel_err'))} | "
                         f"{_pct(e.get('coverage'), 0)} | {_pct(hi, 0)} | {_num(tot)} | {_num(t.get('ms_total'))} | "
                         + " | ".join(_num(ms.get(k)) for k in STAGE_NAMES) + " |")
        lines.append("")
        if "pareto" in figures:
            lines.append(f"![speed against error]({figures['pareto']})")
            lines.append("")
        lines.append("Pareto front (no other configuration is both faster and more accurate; the `oracle` rows read "
                     "the true state, so they are references, and the renderer pair is measured on sites A and E only: "
                     "neither is on the front):")
        lines.append("")
        lines.append(f"| configuration | median \\|rel. err.\\| | {kind} ms/step | wall ms/step |")
        lines.append("|---|---|---|---|")
        for r in front_rows(tr["rows"]):
            lines.append(f"| {r['label']} | {_pct(r['error']['median_abs_rel_err'])} | "
                         f"{_num(stage_ms(r['timing'])[1])} "
                         f"| {_num(r['timing']['ms_total'])} |")
        lines.append("")
    cl = report.get("closed_loop")
    if cl:
        lines.append("## Closed loop")
        lines.append("")
        lines.append(cl["method"])
        lines.append("")
        lines.append("| estimator | landed | success rate | 95 % Wilson interval | outcomes | sanitised estimates "
                     "| wall s |")
        lines.append("|---|---|---|---|---|---|---|")
        for r in cl["rows"]:
            if r.get("failed"):
                lines.append(f"| {r['estimator']} | failed: {r['failed']} | | | | | |")
                continue
            oc = ", ".join(f"{k} {v}" for k, v in sorted(r["outcomes"].items()))
            lines.append(f"| {r['estimator']} | {r['successes']}/{r['n']} | {_pct(r['success_rate'], 0)} | "
                         f"{_pct(r['wilson95'][0], 0)} - {_pct(r['wilson95'][1], 0)} | {oc} | "
                         f"{r['sanitised_estimates']} | {r['wall_s']:.1f} |")
        lines.append("")
    sc = report.get("scaling")
    if sc:
        lines.append("## Scaling with the batch size")
        lines.append("")
        lines.append(sc["method"])
        lines.append("")
        kind = stage_ms(sc["rows"][0])[2] if sc["rows"] else "wall"
        lines.append(f"{kind} ms per control step by stage, then the totals:")
        lines.append("")
        lines.append("| B | " + " | ".join(k.replace("_", " + ") for k in STAGE_NAMES)
                     + f" | {kind} ms/step | wall ms/step | {kind} ms per descent | events/step | peak memory, MiB |")
        lines.append("|---" * (len(STAGE_NAMES) + 6) + "|")
        for r in sc["rows"]:
            ms, tot, _ = stage_ms(r)
            lines.append(f"| {r['batch_size']} | " + " | ".join(_num(ms[k]) for k in STAGE_NAMES)
                         + f" | {_num(tot)} | {_num(r['ms_total'])} | {_num(tot / r['batch_size'], 3)} | "
                         f"{r['events_per_step']:.0f} | {_num(r['peak_memory_mib'], 0)} |")
        lines.append("")
        if "scaling" in figures:
            lines.append(f"![time per stage and memory against B]({figures['scaling']})")
            lines.append("")
    ec = report.get("economies")
    if ec:
        lines.append("## What modelling only what the scene needs buys")
        lines.append("")
        lines.extend(economy_lines(ec))
        lines.append("")
    cp = report.get("campaign")
    if cp:
        lines.extend(campaign_section(cp))
    st = report.get("stage_benchmarks")
    if st:
        lines.append("## Stage benchmarks")
        lines.append("")
        for name, r in st.items():
            lines.append(f"- `{name}`: exit status {r['rc']}, {r['seconds']:.1f} s, JSON `{r.get('json')}`")
        lines.append("")
    return "\n".join(lines)


def economy_lines(ec: dict) -> List[str]:
    out = []
    lod = ec.get("lod")
    if lod and not lod.get("failed"):
        w = lod["whole_footprint_finest"]
        ext = w.get("prep_cpu_s_extrapolated")
        out += [
            f"**Footprint-only levels of detail** (sites {', '.join(lod['sites'])}, B = {lod['batch_size']}, "
            "altitudes 60 m - 8 km):",
            "",
            "| render | CPU ms per call | texels held per site | MiB per site | RMS of log I difference "
            "| correlation |",
            "|---|---|---|---|---|---|",
            f"| LOD footprint, 128 px | {_num(lod['lod']['ms_per_call'])} | {lod['lod']['texels_per_site']:,} | "
            f"{_num(lod['lod']['mib_per_site'], 1)} | {_num(lod['lod_vs_2x']['rms_log_diff_median'], 3)} (median), "
            f"{_num(lod['lod_vs_2x']['rms_log_diff_max'], 3)} (max) | {_num(lod['lod_vs_2x']['corr_median'], 3)} "
            f"(median), {_num(lod['lod_vs_2x']['corr_min'], 3)} (min) |",
            f"| 2x supersampled from 2x finer levels, 256 px box-filtered to 128 | "
            f"{_num(lod['supersampled_2x']['ms_per_call'])} | {lod['supersampled_2x']['texels_per_site']:,} | "
            f"{_num(lod['supersampled_2x']['mib_per_site'], 1)} | reference | reference |",
            f"| whole {w['altitude_m'] / 1000:g} km footprint at the finest texel ({w['texel_m']:.3f} m), counted, "
            f"not run | - | {w['texels']:.3g} | {w['mib_float32']:,.0f} (float32) | - | - |",
            "",
        ]
        if ext:
            out += [f"Preparing that whole footprint at the measured {w['prep_cpu_s_per_texel_measured']:.3g} CPU s "
                    f"per texel (shading a 256 x 256 window) would take about {ext / 3600:.1f} CPU hours "
                    "(extrapolated), against the level set's one-off preparation of a few seconds per site.", ""]
    ring = ec.get("ring")
    if ring and not ring.get("failed"):
        out += [
            f"**Count-image ring against raw events** (`dpr` window of {ring['window_steps']} steps, "
            f"B = {ring['batch_size']}, {ring['events_in_window_mean']:,.0f} events in the window):",
            "",
            "| window kept as | CPU ms per step | bytes held | window identical |",
            "|---|---|---|---|",
            f"| ring of pixel indices + running count image | {_num(ring['ring']['ms_per_step'], 3)} | "
            f"{ring['ring']['bytes_held']:,} | {'yes' if ring['windows_identical'] else 'NO'} |",
            f"| raw events, count image rebuilt each step | {_num(ring['raw_events']['ms_per_step'], 3)} | "
            f"{ring['raw_events']['bytes_held']:,} | reference |",
            "",
        ]
    ch = ec.get("changed")
    if ch and not ch.get("failed"):
        hf = ch["half_finished"]
        out += [
            f"**Emulating only pixels that changed** (B = {ch['batch_size']}, {ch['steps']} steps at "
            f"{', '.join(f'{100 * f:.0f} %' for f in ch['fractions'])} of the descents): "
            f"{_pct(ch['changed_pixel_fraction_mean'])} of pixels change between frames (a zooming scene: "
            f"almost all), {_pct(ch['candidate_pixel_fraction_mean'])} cross a threshold. The emulator already "
            f"does per-event work only for those; the dense pass over every pixel (log, difference, candidate "
            f"search) takes {_num(ch['dense_pass_ms_median'])} ms of the {_num(ch['step_ms_median'])} ms (CPU) step, "
            "the most that skipping unchanged pixels could still save.",
            "",
            f"With half the batch finished (frozen frames), a step over all {ch['batch_size']} elements takes "
            f"{_num(hf['cpu_ms_all_elements'])} ms of CPU, over only the running half "
            f"{_num(hf['cpu_ms_running_only'])} ms; the finished elements emit {hf['events_from_frozen_elements']} "
            "events, so emulating only the running elements would be exact.",
            "",
        ]
    for k, v in ec.items():
        if isinstance(v, dict) and v.get("failed"):
            out.append(f"- {k}: failed: {v['failed']}")
    return out


CAMPAIGN_BEGIN, CAMPAIGN_END = "<!-- bench campaign: begin -->", "<!-- bench campaign: end -->"


def campaign_section(cp: dict) -> List[str]:
    """The campaign part as markdown, between markers (a campaign-only run replaces just this
    block of an existing benchmarks.md)."""
    from .campaign import campaign_lines

    return [CAMPAIGN_BEGIN, "## Campaign cost", "", cp["method"], "", *campaign_lines(cp["rows"]), "",
            CAMPAIGN_END, ""]


def _merge_campaign(old: str, report: dict, header: str) -> str:
    """``old`` benchmarks.md with its campaign block replaced (or appended) by this run's."""
    block = "\n".join([*campaign_section(report["campaign"])[:-1]])
    block = block.replace("## Campaign cost\n", "## Campaign cost\n\n" + header + "\n", 1)
    if CAMPAIGN_BEGIN in old and CAMPAIGN_END in old:
        a, b = old.index(CAMPAIGN_BEGIN), old.index(CAMPAIGN_END) + len(CAMPAIGN_END)
        return old[:a] + block + old[b:]
    return old.rstrip("\n") + "\n\n" + block + "\n"


def write_report(report: dict, run_dir: Path, docs_dir: Optional[Path] = None) -> Dict[str, Path]:
    """Write bench.json, bench.md and the figures into ``run_dir``; with ``docs_dir`` also
    ``benchmarks.md`` and its figures there. Returns {kind: path}."""
    run_dir = Path(run_dir)
    paths = {"json": run_dir / "bench.json", "md": run_dir / "bench.md"}
    figs = {}
    m = report["machine"]
    tag = f"{m['device']}, {m['cpu_model']}, load {m['load_average']}"
    if report.get("tradeoff"):
        paths["pareto"] = run_dir / "pareto.png"
        plot_pareto(report["tradeoff"]["rows"], paths["pareto"], f"speed against error ({tag})")
        figs["pareto"] = "pareto.png"
    if report.get("scaling"):
        paths["scaling"] = run_dir / "scaling.png"
        plot_scaling(report["scaling"]["rows"], paths["scaling"], f"estimator dpr ({tag})")
        figs["scaling"] = "scaling.png"
    write_json(paths["json"], report)  # strict JSON: NaN / inf -> null
    paths["md"].write_text("# dvsland benchmark\n\n" + markdown(report, figs) + "\n")
    if docs_dir is not None:
        docs_dir = Path(docs_dir)
        docs_dir.mkdir(parents=True, exist_ok=True)
        dfigs = {}
        for k, name in figs.items():
            shutil.copyfile(run_dir / name, docs_dir / f"benchmarks_{name}")
            dfigs[k] = f"benchmarks_{name}"
        intro = ("# Benchmarks: speed against error, scaling, and what each economy buys\n\n"
                 "Everything on this page was written by one run of `dvsland bench` (the command is below); "
                 "run it again to regenerate the page (`--docs docs`) and its figures. Timings are wall "
                 "clock on the machine named below; on a shared machine they are inflated by the load it "
                 "reports.\n\n")
        paths["docs"] = docs_dir / "benchmarks.md"
        only_campaign = report.get("campaign") and not any(report.get(k) for k in
                                                             ("tradeoff", "closed_loop", "scaling", "economies"))
        if only_campaign and paths["docs"].is_file():  # keep the other parts' tables of the page
            header = markdown({**report, "campaign": None, "stage_benchmarks": None}, {}).strip()
            paths["docs"].write_text(_merge_campaign(paths["docs"].read_text(), report, header))
        else:
            paths["docs"].write_text(intro + markdown(report, dfigs) + "\n")
    return paths
