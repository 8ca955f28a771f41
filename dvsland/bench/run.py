"""``run_bench``: measure the chosen parts and write one run folder (bench.json, bench.md, figures).

Parts of the report (default: all four): ``tradeoff`` (speed against error per configuration),
``closed_loop`` (success rate with its 95 % Wilson interval), ``scaling`` (stages and memory
against B), ``economies`` (what each economy buys). The stage benchmarks of the individual
subsystems (``render``, ``events``, ``estimators``, ``renderers``, ``sim``) run on request, in
process, each writing its JSON into the run folder.
"""

from __future__ import annotations

import contextlib
import io
import os
import time
import traceback
from datetime import datetime, timezone
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import torch

from dvsland.config import Config, load_config
from dvsland.runs import make_run_dir

from .machine import load_average, machine_info

from .parts import ALIASES, CHOICES, EXTRA_PARTS, REPORT_PARTS, STAGE_BENCHES, parse_what  # noqa: F401 - re-exported

#: campaign part: (seeds per site and setting, t_max_s or None = the preset's) of each measured batch
CAMPAIGN_RUNS_FULL = ((7, 60.0), (1, None))
CAMPAIGN_RUNS_QUICK = ((1, 30.0),)

#: closed-loop estimators: quick / full
CLOSED_LOOP_QUICK = ["oracle", "oracle[noise_rel=0.3]", "dpr"]
CLOSED_LOOP_FULL = ["oracle", "oracle[noise_rel=0.1]", "oracle[noise_rel=0.3]", "oracle[noise_rel=0.1;delay_steps=3]",
                    "dpr", "dpr[pair_weighting=length]", "snn", "cmax"]


def run_bench(what: Sequence[str] = (), quick: bool = False, device="cpu", out: Optional[Path] = None,
              config=None, closed_loop_config="realistic", docs: Optional[Path] = None, threads: int = 1,
              render_threads: int = 1, estimators: Optional[Sequence[str]] = None, command: str = "",
              closed_loop_estimators: Optional[Sequence[str]] = None, log=print,
              overrides: Sequence[str] = (), sites: Optional[Sequence[str]] = None,
              campaign: Optional[Dict] = None) -> Dict:
    """Run the benchmark and write its run folder; returns the report dict (``report['run_dir']``).

    Args:
        what: parts (see :data:`CHOICES`); empty = the four report parts.
        quick: smaller samples (see docs/benchmarks.md for what is reduced).
        device: ``cpu`` or ``cuda``.
        out: run folder (default ``logs/bench-<UTC stamp>/``).
        config: open-loop config (default ``paper``); ``closed_loop_config``: closed-loop config
            (default ``realistic``, 100 kN engine).
        docs: also write ``benchmarks.md`` and its figures into this folder.
        threads: torch threads; ``render_threads``: the fast renderer's threads inside a call.
        estimators: restrict the speed/error part to these registered names.
        closed_loop_estimators: specs flown in the closed loop (default: a set per mode).
        overrides: ``section.key=value`` strings applied to both configs (``--set``).
        sites: measure only these sites of both configs' ``simulation.sites`` (checked before the
            run folder is made).
        campaign: the ``campaign`` part's ``preset`` (default montecarlo_efference), ``estimator``
            (default cmax), ``runs`` ((n_seeds, t_max_s or None), ...) and ``compact`` (default True).
    """
    parts = parse_what(what)
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device='cuda' but CUDA is not available; use --device cpu")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'cpu' or 'cuda', got {device!r}")
    if int(threads) < 1 or int(render_threads) < 0:
        raise ValueError(f"threads must be >= 1 and render_threads >= 0, got {threads}, {render_threads}")
    from dvsland.config.sites import restrict_sites

    overrides = list(overrides or ())
    if isinstance(config, Config):
        cfg = config
        if overrides:
            raise ValueError("overrides apply to a config by name or path; edit a Config object directly")
    else:
        cfg = load_config(config, overrides)
    cfg = restrict_sites(cfg, sites)
    ccfg = restrict_sites(load_config(closed_loop_config, overrides), sites) if "closed_loop" in parts else None
    torch.set_num_threads(int(threads))
    cfg.render.threads = int(render_threads)
    cfg.simulation.device = str(dev)
    cfg.logging.quiet = True
    cfg.name = "bench"
    run_dir = make_run_dir(cfg, out)
    t_start = time.perf_counter()
    report = dict(command=command or "dvsland bench", quick=bool(quick), parts=parts,
                  sites=[s.name for s in cfg.simulation.sites], overrides=overrides,
                  started_utc=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
                  machine=machine_info(dev), render_threads=int(render_threads), run_dir=str(run_dir))
    from .report import write_report

    cpu0 = os.times()

    def save():
        report["wall_s"] = time.perf_counter() - t_start
        c = os.times()
        report["cpu_s"] = (c.user + c.system + c.children_user + c.children_system
                           - cpu0.user - cpu0.system - cpu0.children_user - cpu0.children_system)
        report["load_average_end"] = load_average()
        return write_report(report, run_dir, docs)

    report["status"] = "running"
    try:
        if "tradeoff" in parts:
            _part_tradeoff(report, cfg, dev, quick, estimators, log)
            save()
        if "closed_loop" in parts:
            _part_closed_loop(report, closed_loop_config, dev, quick, run_dir, render_threads, log,
                              closed_loop_estimators, ccfg)
            save()
        if "scaling" in parts:
            _part_scaling(report, cfg, dev, quick, log, "" if isinstance(config, Config) else (config or ""))
            save()
        if "economies" in parts:
            _part_economies(report, cfg, quick, log)
            save()
        if "campaign" in parts:
            _part_campaign(report, dict(campaign or {}), dev, quick, overrides, sites, log)
            save()
        stage = [p for p in parts if p in STAGE_BENCHES]
        if stage:
            report["stage_benchmarks"] = {}
            for name in stage:
                report["stage_benchmarks"][name] = _stage_bench(name, quick, run_dir, log, str(dev))
                save()
    except BaseException as exc:  # Ctrl-C too: keep what was measured, then re-raise
        report["status"] = f"interrupted: {type(exc).__name__}: {exc}"
        save()
        raise
    report["status"] = "complete"
    paths = save()
    log(f"bench: {report['wall_s']:.0f} s; wrote " + ", ".join(str(p) for p in paths.values()))
    return report


def _part_tradeoff(report, cfg, dev, quick, estimators, log):
    from .tradeoff import configurations, run_tradeoff

    log("== speed against error (open loop; B = 18 timing)")
    confs = configurations(quick, estimators)
    configured = [s.name for s in cfg.simulation.sites]
    for c in confs:  # rows on a fixed pair of sites (pyrender) keep those of them that are configured
        if c.sites:
            c.sites = [s for s in c.sites if s in configured] or configured[:2]
    rows = run_tradeoff(cfg, confs, dev, quick=quick, log=log)
    seg = "segments of 12 steps, every 12th" if quick else "segments of 30 steps, every 4th"
    report["tradeoff"] = dict(rows=rows, method=(
        f"Open-loop error of D along the closed-form oracle descents of sites A-I (`dvsland.evaluate`, "
        f"{seg}, the first 5 steps of each segment not scored), over sites A-G; coverage = scored steps "
        f"with an estimate. Time per control step: B = 18 descents (sites x 2) flown on `loop_step` "
        f"(the stages of `build_stages`, the configured controller), median over "
        f"{'4' if quick else '10'} timed steps from 30 % and 80 % of the descents, by the loop's stage "
        f"timer: render + emulate + estimate + control/dynamics; `oracle` needs no events, so it pays no "
        f"render or emulation. Settings rows change one thing against `dpr` (row `dpr`: threshold 0.1, 128x128, fast "
        f"renderer; at 64x64 the pixel-based dpr parameters are left as they are); the two renderer rows "
        f"use sites A and E only (pyrender renders frame by frame: in --quick "
        f"its time is one timed step, its error a short sample). Times come from a few steps: differences "
        f"under about 10 % are within their noise."))


def _part_closed_loop(report, cl_config, dev, quick, run_dir, render_threads, log, ests=None, ccfg=None):
    from .closed_loop import run_closed_loop

    log("== closed loop (fixed seeds)")
    ccfg = load_config(cl_config) if ccfg is None else ccfg
    ccfg.render.threads = int(render_threads)
    ests = list(ests) if ests else (CLOSED_LOOP_QUICK if quick else CLOSED_LOOP_FULL)
    rows = run_closed_loop(ccfg, ests, Path(run_dir), device=dev, quick=quick, log=log)
    report["closed_loop"] = dict(config=str(cl_config), rows=rows, method=(
        f"`dvsland.simulate` with config `{cl_config}` (100 kN engine), all nine sites x both controller "
        f"settings x {1 if quick else 2} seed(s) = {18 if quick else 36} descents per estimator, seed "
        f"{ccfg.simulation.seed} (fixed); success = reached {ccfg.simulation.success_altitude_m:g} m. The "
        "interval is the 95 % Wilson score interval of that small sample. Each run folder is kept in the "
        "benchmark's folder."))


def _part_scaling(report, cfg, dev, quick, log, config_name=""):
    from .scaling import BATCHES_FULL, BATCHES_QUICK, MEMORY_QUICK, run_scaling

    log("== scaling with B (dpr)")
    batches = BATCHES_QUICK if quick else BATCHES_FULL
    mem_b = MEMORY_QUICK if quick else batches
    rows = run_scaling(cfg, batches, dev, "dpr", quick=quick, log=log, memory_batches=mem_b, config_name=config_name)
    report["scaling"] = dict(rows=rows, batches=list(batches), method=(
        f"`dpr` on B descents (element b flies site b mod 9), B = {', '.join(map(str, batches))}"
        f"; median ms per control step of each stage of `loop_step` (the configured controller) over "
        f"{'1 (B >= 256) or 4' if quick else '4 (B >= 256) or 10'} timed steps after a warm-up, at "
        f"{'50 %' if quick else '30 % and 80 %'} of the descents. Peak memory: on the CPU, the peak resident "
        f"set of a fresh process flying B descents for two steps minus its resident set after the imports "
        f"(renderer atlas of the nine sites included; measured for B = {', '.join(map(str, mem_b))}); on CUDA "
        "the allocator's peak over the measurement."))


def _part_economies(report, cfg, quick, log):
    from . import economies as E

    log("== economies")
    sites = [s.name for s in cfg.simulation.sites]
    ec = {}
    for key, fn, kw in (("lod", E.lod_economy, dict(sites=["E"] if quick else ["A", "E", "H"])),
                        ("ring", E.ring_economy, dict(sites=sites)),
                        ("changed", E.changed_pixels_economy, dict(sites=sites))):
        t0 = time.perf_counter()
        try:
            ec[key] = fn(cfg, kw.pop("sites"), **kw)
        except Exception as exc:  # noqa: BLE001 - one failing measurement must not end the report
            traceback.print_exc()
            ec[key] = dict(failed=f"{type(exc).__name__}: {exc}")
        ec[key]["seconds"] = time.perf_counter() - t0
        log(f"  {key}: {time.perf_counter() - t0:.1f} s")
    report["economies"] = ec


def _part_campaign(report, spec: dict, dev, quick, overrides, sites, log):
    from .campaign import bench_campaign

    preset, est = spec.get("preset") or "montecarlo_efference", spec.get("estimator") or "cmax"
    runs = spec.get("runs") or (CAMPAIGN_RUNS_QUICK if quick else CAMPAIGN_RUNS_FULL)
    compact = bool(spec.get("compact", True))
    log(f"== campaign cost ({preset} + {est})")
    rows = []
    for n_seeds, t_max in runs:
        try:
            rows.append(bench_campaign(preset, est, int(n_seeds), t_max, sites, dev, overrides, compact, log))
        except Exception as exc:  # noqa: BLE001 - one failing batch must not end the report
            traceback.print_exc()
            rows.append(dict(preset=preset, estimator=est, failed=f"{type(exc).__name__}: {exc}"))
        report["campaign"] = dict(rows=rows, method=(
            f"One batch per row, as one campaign shard: `{preset}` with estimator `{est}`, every configured site "
            "and controller setting times the row's seeds, flown in one process on `loop_step` (one torch "
            "thread, `render.threads=1`, simulation.compact "
            f"{'on' if compact else 'off'}). Set-up: `build_stages` (terrain and scene preparation or their "
            "cache, atlas, estimator), CPU s per descent (wall in brackets); scenes: where the renderer's "
            "scenes came from. Stage columns: process CPU ms per descent-step (steps x B: finished "
            "descents count, so the figure includes what they still cost); per flying step: the same total "
            "over the descent-steps still flying. Descents per CPU-minute include the set-up."))
    report["campaign"]["rows"] = rows


def _stage_bench(name: str, quick: bool, run_dir: Path, log, device: str = "cpu") -> Dict:
    import importlib

    mod, full, qargs = STAGE_BENCHES[name]
    path = Path(run_dir) / f"stage_{name}.json"
    sim_dir = Path(run_dir) / f"stage_{name}_run"
    argv = [a.replace("{json}", str(path)).replace("{dir}", str(sim_dir)).replace("{device}", device)
            for a in (qargs if quick else full)]
    log(f"== stage benchmark {name}: python -m dvsland.bench.{mod} {' '.join(argv)}")
    t0 = time.perf_counter()
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            rc = importlib.import_module(f"dvsland.bench.{mod}").main(argv)
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else 1
    except Exception:  # noqa: BLE001
        traceback.print_exc()
        rc = 1
    text = buf.getvalue()
    log(text)
    (Path(run_dir) / f"stage_{name}.txt").write_text(text)
    return dict(rc=int(rc or 0), seconds=time.perf_counter() - t0, json=path.name if path.exists() else None)
