"""The merged report of a campaign: results.json, runs.csv, groups.csv (+ Parquet with pyarrow),
the printed table, a figure and a TensorBoard HParams table."""

from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional, Sequence

from dvsland.report.checkpoint import checkpoint_text
from dvsland.report.results import RunWriteError, atomic_write_text, write_results_json
from dvsland.report.stats import format_group_table, write_csv
from dvsland.report.style import save_atomic

#: flat columns of runs.csv (nested dicts are flattened as sweep.<k> and dispersion.<k>)
RUN_COLUMNS = ("run", "site", "scene", "label", "estimator", "seed_index", "seed", "outcome", "t_end_s",
               "lowest_altitude_m", "v_at_50m_mps", "v_end_mps", "fuel_used_kg", "max_thrust_n", "z0_m", "v0_mps",
               "held_steps", "missing_estimates")


def flat_runs(runs: List[dict]) -> List[dict]:
    """Runs as flat rows (one column per field; ``sweep.<key>`` and ``dispersion.<name>``)."""
    out = []
    for r in runs:
        row = {k: r.get(k) for k in RUN_COLUMNS}
        for k, v in (r.get("sweep") or {}).items():
            row[f"sweep.{k}"] = v
        for k, v in (r.get("dispersion") or {}).items():
            row[f"dispersion.{k}"] = v
        out.append(row)
    return out


def write_tables(folder, runs: List[dict], groups: List[dict]) -> List[Path]:
    """runs.csv and groups.csv (and .parquet files when pyarrow is installed)."""
    folder = Path(folder)
    rows = flat_runs(runs)
    paths = [folder / "runs.csv", folder / "groups.csv"]
    for path, data in zip(paths, (rows, groups)):
        try:
            write_csv(path, data)
        except OSError as exc:  # a full disk: one error naming the file
            raise RunWriteError(path, exc) from None
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return paths
    for name, data in (("runs", rows), ("groups", groups)):
        cols = sorted({k for r in data for k in r}, key=lambda k: list(data[0]).index(k) if k in data[0] else 1e9)
        table = pa.table({c: [r.get(c) for r in data] for c in cols})
        try:
            pq.write_table(table, folder / f"{name}.parquet")
        except OSError as exc:
            raise RunWriteError(folder / f"{name}.parquet", exc) from None
        paths.append(folder / f"{name}.parquet")
    return paths


def _label(g: dict, by: Sequence[str], skip=("site",)) -> str:
    return " ".join(str(g.get(k)) for k in by if k not in skip)


def figure_title(runs: List[dict], meta: Optional[dict] = None) -> str:
    """Campaign figure title: preset (or controller settings), estimators, seeds and descents."""
    meta = meta or {}

    def names(key):
        return ", ".join(dict.fromkeys(str(r[key]) for r in runs if r.get(key) is not None))

    preset = f"preset {meta['preset']}" if meta.get("preset") else f"settings {names('label') or '?'}"
    ests = names("estimator") or "?"
    cks = ", ".join(dict.fromkeys(checkpoint_text(r["checkpoint"]) for r in runs if r.get("checkpoint")))
    if cks:  # a trained estimator: which weights flew
        ests += f" ({cks})"
    n_seeds = meta.get("n_seeds")
    if n_seeds is None:
        n_seeds = len({r.get("seed_index", r.get("seed")) for r in runs})
    return f"Campaign, {preset}: estimator {ests}, {n_seeds} seed{'s' if n_seeds != 1 else ''}, {len(runs)} descents"


def campaign_figure(path, runs: List[dict], groups: List[dict], by: Sequence[str],
                    title: Optional[str] = None, meta: Optional[dict] = None) -> Path:
    """Two panels: success rate with its 95 % Wilson interval per site (one marker per series =
    the group keys other than the site), and the velocity at the success altitude of the
    successful descents per site and series (dots, median bar). A title names the preset (or
    controller settings), estimators and seeds; both panels carry a legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dvsland.report.stats import group_key, median

    sites = list(dict.fromkeys(g["site"] for g in groups))
    series = list(dict.fromkeys(_label(g, by) for g in groups))
    n_s = max(1, len(series))
    width = 0.8 / n_s
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.0), dpi=90)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for j, s in enumerate(series):
        c = colors[j % len(colors)]
        xs, ys, lo, hi = [], [], [], []
        for g in groups:
            if _label(g, by) != s:
                continue
            x = sites.index(g["site"]) - 0.4 + width * (j + 0.5)
            xs.append(x)
            ys.append(100 * g["success_rate"])
            # Wilson bounds at k = 0 or n equal the rate up to rounding: clip the tiny negative rest
            lo.append(max(0.0, 100 * (g["success_rate"] - g["success_lo"])))
            hi.append(max(0.0, 100 * (g["success_hi"] - g["success_rate"])))
        ax1.errorbar(xs, ys, yerr=[lo, hi], fmt="o", color=c, capsize=3, ms=4, label=s or "all")
        for i, site in enumerate(sites):
            v = [abs(r["v_at_50m_mps"]) for r in runs
                 if r.get("site") == site and r.get("outcome") == "success" and r.get("v_at_50m_mps") is not None
                 and _label(dict(zip(by, group_key(r, by))), by) == s]
            if not v:
                continue
            x = i - 0.4 + width * (j + 0.5)
            jitter = [x + width * 0.3 * (((k * 7919) % 13) / 12 - 0.5) for k in range(len(v))]
            ax2.plot(jitter, v, ".", color=c, ms=3, alpha=0.6)
            med = median(v)  # the table's median (an even count: the mean of the middle two)
            ax2.plot([x - width * 0.4, x + width * 0.4], [med, med], "-", color=c, lw=2)
    for ax in (ax1, ax2):
        ax.set_xticks(range(len(sites)))
        ax.set_xticklabels(sites)
        ax.set_xlabel("site")
        ax.grid(alpha=0.3)
    ax1.set_ylim(-3, 103)
    ax1.set_ylabel("success rate, % (95 % Wilson interval)")
    ax1.legend(fontsize=7, loc="best")
    ax2.set_ylabel("|v| at the success altitude, m/s (successes)")
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="", marker="o", ms=5, color=colors[j % len(colors)], label=s or "all")
               for j, s in enumerate(series)] if n_s > 1 else []
    handles += [Line2D([], [], ls="", marker=".", ms=7, color="0.35", label="one successful descent"),
                Line2D([], [], ls="-", lw=2, color="0.35", label="median")]
    ax2.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    fig.suptitle(title or figure_title(runs, meta), fontsize=11)
    fig.tight_layout()
    try:
        return save_atomic(fig, path)
    finally:
        plt.close(fig)


def write_hparams(folder, groups: List[dict], by: Sequence[str]) -> Path:
    """One TensorBoard HParams entry per group (hparams: the group keys; metrics: n, success rate
    and interval, medians), under ``<folder>/tb``: compare groups in TensorBoard's HParams view."""
    import shutil

    from torch.utils.tensorboard import SummaryWriter

    folder = Path(folder) / "tb"
    if folder.is_dir():  # a resumed campaign rewrites its table, never appends a second one
        shutil.rmtree(folder)
    with SummaryWriter(str(folder)) as w:
        for i, g in enumerate(groups):
            hp = {k.replace("sweep.", ""): str(g.get(k)) for k in by}
            metrics = {}
            for k in ("n", "success_rate", "success_lo", "success_hi", "n_crash", "n_ascent", "n_timeout",
                      "lowest_m_median", "v50_mps_median", "fuel_kg_median"):
                v = g.get(k)
                metrics[f"campaign/{k}"] = float("nan") if v is None else float(v)
            w.add_hparams(hp, metrics, run_name=f"group{i:03d}")
    return folder


def write_paper_pattern(folder, runs: List[dict], by: Sequence[str], figures: bool = True) -> dict:
    """When the runs fly the paper's nine sites: its reported pattern beside the flown one pooled
    over seeds and settings (``dvsland.report.paper_pattern``), one per series (the group keys
    other than site and setting, e.g. the estimator): ``paper_pattern.txt`` / ``.md`` /
    ``.json`` and ``figures/paper_pattern.png`` (``paper_pattern-<series>.png`` for several
    series; not with ``figures=False``). Reads c2 and the success altitude from the campaign's ``config.yaml`` (a swept
    ``controller.c2`` from the runs). Returns {name: path}; empty when the sites are not the paper's."""
    import json

    import yaml

    from dvsland.report import paper_pattern as pp
    from dvsland.report.stats import group_key

    folder = Path(folder)
    if not runs or not pp.applies(runs):
        return {}
    cfg = yaml.safe_load((folder / "config.yaml").read_text()) if (folder / "config.yaml").is_file() else {}
    c2 = float((cfg.get("controller") or {}).get("c2", 0.25))
    alt = float((cfg.get("simulation") or {}).get("success_altitude_m", 50.0))
    keys = [k for k in by if k not in ("site", "label")]
    series: dict = {}
    for r in runs:
        series.setdefault(_label(dict(zip(keys, group_key(r, keys))), keys), []).append(r)
    texts, mds, data, out = [], [], {}, {}
    for i, (name, rs) in enumerate(series.items()):
        c2_s = float((rs[0].get("sweep") or {}).get("controller.c2", c2))
        head = f"[{name}] " if name else ""
        texts.append(head + pp.format_comparison(rs, c2_s, alt))
        mds.append((f"**{name}**\n\n" if name else "") + pp.format_pooled_comparison(rs, c2_s, alt, markdown=True))
        data[name or "all"] = {"c2": c2_s, "success_altitude_m": alt, "sites": pp.pooled_pattern(rs, c2_s, alt)}
        if figures:
            fig = "paper_pattern.png" if len(series) == 1 else f"paper_pattern-{i}.png"
            (folder / "figures").mkdir(parents=True, exist_ok=True)
            out[fig] = pp.paper_pattern_chart(rs, folder / "figures" / fig, c2_s, alt, pooled=True)
    for ext, body in (("txt", "\n\n".join(texts)), ("md", "\n\n".join(mds))):
        out[f"paper_pattern.{ext}"] = atomic_write_text(folder / f"paper_pattern.{ext}", body + "\n")
    text = json.dumps({"paper": pp.load_paper_pattern(), "flown": data}, indent=1)
    out["paper_pattern.json"] = atomic_write_text(folder / "paper_pattern.json", text)
    return out


def write_report(folder, runs: List[dict], groups: List[dict], by: Sequence[str], meta: dict,
                 figures: bool = True, tensorboard: bool = True, results: bool = True) -> dict:
    """Write every merged output of a campaign into ``folder`` (``results``: results.json too;
    the campaign writes it first itself); returns {name: path}. Text files are written
    atomically; a full disk is one RunWriteError naming the file."""
    folder = Path(folder)
    out = {"results": folder / "results.json"}
    if results:
        write_results_json(folder / "results.json", runs, groups=groups, group_by=list(by), **meta)
    for p in write_tables(folder, runs, groups):
        out[p.name] = p
    atomic_write_text(folder / "table.txt", format_group_table(groups, by) + "\n")
    atomic_write_text(folder / "table.md", format_group_table(groups, by, markdown=True) + "\n")
    if figures and runs:
        out["figure"] = campaign_figure(folder / "figures" / "campaign.png", runs, groups, by, meta=meta)
    if tensorboard and groups:
        out["tb"] = write_hparams(folder, groups, by)
    if runs:  # the paper's nine sites: its reported pattern beside the pooled flown one
        out.update(write_paper_pattern(folder, runs, by, figures=figures))
    return out

