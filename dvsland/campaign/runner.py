"""``run_campaign``: plan (or resume) a campaign, run its missing shards, merge and report.

Campaign folder (``logs/<name>-campaign-<UTC stamp>/`` or ``out``)::

    config.yaml        the resolved base config, written before any work
    campaign.json      the plan: base config, sweeps, seeds, shards
    shards/<id>.json   one file per finished shard, written atomically (tmp + os.replace)
    results.json       merged runs + per-group statistics (status complete / interrupted)
    runs.csv, groups.csv, table.txt, table.md, figures/campaign.png, tb/ (HParams)

An interrupted campaign keeps its config, plan and finished shards; ``resume`` runs only the
shards without a file and then merges all of them in plan order, so the merged runs and groups
equal those of an uninterrupted campaign.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence

from dvsland import __version__
from dvsland.config import Config
from dvsland.report.stats import default_group_keys, format_group_table, group_stats
from dvsland.runs import make_run_dir

from .executors import EXECUTORS, run_local, run_ray
from .plan import CampaignPlan, make_plan

SHARDS_DIR = "shards"


@dataclass
class CampaignResult:
    """What a campaign produced: its folder, merged runs, group rows, status and timings."""

    run_dir: Path
    runs: List[dict]
    groups: List[dict]
    group_by: List[str]
    status: str
    n_shards: int
    n_shards_run: int
    wall_time_s: float
    descents_per_min: Optional[float]
    outputs: dict = field(default_factory=dict)


def shard_path(run_dir, shard_id: str) -> Path:
    return Path(run_dir) / SHARDS_DIR / f"{shard_id}.json"


def write_shard(run_dir, result: dict) -> Path:
    """Write one shard result atomically (a kill never leaves half a file)."""
    from dvsland.report.results import _clean

    path = shard_path(run_dir, result["id"])
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".json.tmp{os.getpid()}")
    tmp.write_text(json.dumps(_clean(result)))
    os.replace(tmp, path)
    return path


def read_shard(run_dir, shard_id: str) -> Optional[dict]:
    """A finished shard's result, or None when its file is missing or unreadable."""
    path = shard_path(run_dir, shard_id)
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return d if d.get("status") == "complete" else None


def merge(plan: CampaignPlan, run_dir) -> tuple:
    """(runs in plan order, ids of missing shards)."""
    runs, missing = [], []
    for sh in plan.shards:
        d = read_shard(run_dir, sh.id)
        if d is None:
            missing.append(sh.id)
        else:
            runs.extend(d["runs"])
    return runs, missing


def run_campaign(config: Optional[Config] = None, sweeps: Sequence[str] = (), n_seeds: Optional[int] = None,
                 executor: str = "local", workers: int = 1, resume=None, out=None, quiet: bool = False,
                 shard_seeds: int = 5, keep_runs: bool = False, max_shards: Optional[int] = None) -> CampaignResult:
    """Run a Monte Carlo campaign (see module doc).

    Args:
        config: the base config (ignored with ``resume``: the folder's plan rules).
        sweeps: ``key=v1,v2`` strings; the grid is their cartesian product.
        n_seeds: seeds per grid point (default ``simulation.n_seeds``).
        executor: ``local`` (sequential, or a process pool when ``workers > 1``) or ``ray``.
        workers: processes (local) or CPUs of a local Ray instance.
        resume: a campaign folder: run only its missing shards, then merge.
        out: campaign folder (default ``logs/<name>-campaign-<stamp>/``).
        quiet: no progress bar and no printed table.
        shard_seeds: seeds per shard (a shard flies sites x settings x shard_seeds descents).
        keep_runs: keep each shard's run folder (config.yaml, results.json, traces.npz) under
            ``shards/<id>/``.
        max_shards: run at most this many of the missing shards, then stop (status
            ``incomplete``; resume later). For tests and time-boxed runs.

    Returns:
        :class:`CampaignResult`. Ctrl-C / an exception: the finished shards stay on disk, a
        partial report is written (status ``interrupted``) and the exception is re-raised.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"executor must be one of {list(EXECUTORS)}, got {executor!r}")
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    t0 = time.perf_counter()
    if resume is not None:
        run_dir = Path(resume)
        plan = CampaignPlan.load(run_dir)
    else:
        if config is None:
            raise ValueError("run_campaign needs a config (or resume=FOLDER)")
        plan = make_plan(config, sweeps, n_seeds, shard_seeds)
        run_dir = make_run_dir(config, out, kind="campaign")  # config.yaml first
        plan.save(run_dir)
    (run_dir / SHARDS_DIR).mkdir(parents=True, exist_ok=True)
    todo = [sh for sh in plan.shards if read_shard(run_dir, sh.id) is None]
    n_done_before = len(plan.shards) - len(todo)
    if max_shards is not None:
        todo = todo[:max(0, int(max_shards))]
    keep = [str(run_dir / SHARDS_DIR / sh.id) if keep_runs else None for sh in todo]
    shard_dicts = [asdict(sh) for sh in todo]
    pbar = None
    if not quiet:
        from tqdm.auto import tqdm

        pbar = tqdm(total=len(plan.shards), initial=n_done_before, unit="shard", desc="campaign", file=sys.stderr)
    status, exc_to_raise, descents, n_run = "complete", None, 0, 0
    t_run = time.perf_counter()
    try:
        it = (run_local(plan.config, shard_dicts, workers, keep) if executor == "local"
              else run_ray(plan.config, shard_dicts, workers, keep))
        for res in it:
            if res.get("status") != "complete":
                raise RuntimeError(f"shard {res['id']} ended {res.get('status')!r}")
            write_shard(run_dir, res)
            n_run += 1
            descents += len(res["runs"])
            if pbar is not None:
                pbar.update(1)
                minutes = (time.perf_counter() - t_run) / 60
                pbar.set_postfix(descents_per_min=f"{descents / minutes:.1f}" if minutes > 0 else "-")
    except BaseException as exc:  # noqa: BLE001 - Ctrl-C too: keep what is done, report it, re-raise
        status, exc_to_raise = "interrupted", exc
    finally:
        if pbar is not None:
            pbar.close()
    run_s = time.perf_counter() - t_run
    runs, missing = merge(plan, run_dir)
    if status == "complete" and missing:
        status = "incomplete"
    by = default_group_keys(runs)
    groups = group_stats(runs, by)
    wall = time.perf_counter() - t0
    dpm = descents / (run_s / 60) if run_s > 0 and descents else None
    meta = {"status": status, "n_shards": len(plan.shards), "n_shards_done": len(plan.shards) - len(missing),
            "missing_shards": missing, "sweeps": plan.sweeps, "n_seeds": plan.n_seeds, "shard_seeds": plan.shard_seeds,
            "executor": executor, "workers": int(workers), "session": {
                "shards_run": n_run, "descents_run": descents, "wall_time_s": wall, "shards_time_s": run_s,
                "descents_per_min": dpm}, "dvsland_version": __version__,
            "error": None if exc_to_raise is None else f"{type(exc_to_raise).__name__}: {exc_to_raise}"}
    from .report import write_report

    log = plan.config.get("logging", {})
    outputs = write_report(run_dir, runs, groups, by, meta, figures=bool(log.get("figures", True)) and status != "interrupted",
                           tensorboard=bool(log.get("tensorboard", True)))
    if not quiet:
        print(format_group_table(groups, by))
        if "paper_pattern.txt" in outputs:  # the paper's nine sites: its pattern beside the pooled one
            print(outputs["paper_pattern.txt"].read_text(), end="")
        rate = f", {dpm:.1f} descents/min" if dpm else ""
        print(f"{status}: {len(plan.shards) - len(missing)}/{len(plan.shards)} shards, {len(runs)} descents "
              f"({descents} run now in {run_s:.1f} s{rate}); output in {run_dir}")
        if missing:
            print(f"{len(missing)} shards missing: dvsland campaign --resume {run_dir}")
    if exc_to_raise is not None:
        raise exc_to_raise
    return CampaignResult(run_dir=run_dir, runs=runs, groups=groups, group_by=by, status=status,
                          n_shards=len(plan.shards), n_shards_run=n_run, wall_time_s=wall, descents_per_min=dpm,
                          outputs=outputs)
