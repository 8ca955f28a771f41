"""``run_campaign``: plan (or resume) a campaign, run its missing shards, merge and report.

Campaign folder (``logs/<name>-campaign-<UTC stamp>/`` or ``out``)::

    config.yaml        the resolved base config, written before any work
    campaign.json      the plan: base config, sweeps, seeds, shards
    shards/<id>.json   one file per finished shard, written atomically (tmp + os.replace), with
                       the config_hash of what it flew
    shards/rejected/   damaged shard files and shards of another config, moved aside on resume
    results.json       merged runs + per-group statistics (status complete / interrupted)
    runs.csv, groups.csv, table.txt, table.md, figures/campaign.png, tb/ (HParams)
    .dvsland-run, .campaign.lock   the folder's claim and the running campaign's lock

An interrupted campaign keeps its config, plan and finished shards; ``resume`` runs only the
shards without a good file (missing, damaged or of another config: reported on stderr and
re-run) and then merges all of them in plan order, so the merged runs and groups equal those of
an uninterrupted campaign. After Ctrl-C, results.json is written first, with a second Ctrl-C held
back until it is on disk.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

from dvsland import __version__
from dvsland.config import Config
from dvsland.report.stats import default_group_keys, format_group_table, group_stats
from dvsland.runs import RunDirError, RunWriteError, deferred_interrupts, lock_folder, make_run_dir

from .executors import EXECUTORS, WorkerLostError, run_local, run_ray
from .plan import CampaignPlan, Shard, auto_shard_seeds, config_digest, make_plan, shard_hash

SHARDS_DIR = "shards"
#: where damaged or foreign shard files are moved (kept, never merged)
REJECTED_DIR = "rejected"
#: the lock a running campaign holds in its folder (a second writer is refused)
LOCK_FILE = ".campaign.lock"
#: the most worker processes (local) or CPUs of a local Ray instance
MAX_WORKERS = 256


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
    """Write one shard result atomically (a kill or a full disk never leaves half a file;
    RunWriteError names the path)."""
    from dvsland.report.results import _clean, atomic_write_text

    path = shard_path(run_dir, result["id"])
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_text(path, json.dumps(_clean(result)))


def shard_problem(d, shard: Shard, expected_hash: str) -> Optional[str]:
    """None when ``d`` (a shard file's content) is a complete result of ``shard`` flown with the
    plan's config (:func:`~.plan.shard_hash` ``expected_hash``); else why it is not."""
    if not isinstance(d, dict):
        return f"holds a JSON {type(d).__name__}, not a shard result (an object)"
    if d.get("status") != "complete":
        return f"its status is {d.get('status')!r}, not 'complete'"
    if (d.get("id"), d.get("seed_offset"), d.get("n_seeds")) != (shard.id, shard.seed_offset, shard.n_seeds):
        return (f"it is shard {d.get('id')!r} of seeds {d.get('seed_offset')} + {d.get('n_seeds')}, not "
                f"{shard.id!r} of seeds {shard.seed_offset} + {shard.n_seeds}")
    runs = d.get("runs")
    if not isinstance(runs, list) or not runs:
        return "it holds no runs" if not runs else f"its runs are a JSON {type(runs).__name__}, not a list"
    if not all(isinstance(r, dict) and isinstance(r.get("outcome"), str) and "site" in r for r in runs):
        return "its runs are of the wrong type (expected objects with 'site' and 'outcome')"
    got = d.get("config_hash")
    if got != expected_hash:
        return ("it has no config hash (written by an older dvsland)" if got is None else
                f"it was flown with a different config (config hash {got}, the plan's {expected_hash})")
    return None


def read_shard_file(run_dir, shard: Shard, expected_hash: str) -> Tuple[Optional[dict], Optional[str]]:
    """(result, None) for a good shard file; (None, None) when there is none; (None, why) when
    it is unreadable, damaged or of another config."""
    path = shard_path(run_dir, shard.id)
    if not path.is_file():
        return None, None
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        return None, f"it is not readable JSON ({type(exc).__name__}: {str(exc)[:120]})"
    why = shard_problem(d, shard, expected_hash)
    return (None, why) if why else (d, None)


def read_shard(run_dir, shard_id: str, plan: Optional[CampaignPlan] = None) -> Optional[dict]:
    """A finished shard's result, or None when its file is missing, damaged or (with ``plan``) of
    another config."""
    if plan is None:
        try:
            d = json.loads(shard_path(run_dir, shard_id).read_text())
        except (OSError, ValueError):
            return None
        return d if isinstance(d, dict) and d.get("status") == "complete" else None
    sh = next((s for s in plan.shards if s.id == shard_id), None)
    return None if sh is None else read_shard_file(run_dir, sh, shard_hash(config_digest(plan.config), asdict(sh)))[0]


def reject_shard(run_dir, shard_id: str) -> Path:
    """Move a damaged or foreign shard file to ``shards/rejected/`` (kept, never merged)."""
    src = shard_path(run_dir, shard_id)
    folder = src.parent / REJECTED_DIR
    folder.mkdir(parents=True, exist_ok=True)
    dst, i = folder / src.name, 1
    while dst.exists():
        dst, i = folder / f"{shard_id}-{i}.json", i + 1
    os.replace(src, dst)
    return dst


def check_shards(plan: CampaignPlan, run_dir, quiet: bool = False) -> Tuple[List[Shard], List[dict]]:
    """(shards to run, rejected): every shard without a good file is to run; a damaged or foreign
    file is reported on stderr (naming the shard and why), moved to ``shards/rejected/`` and its
    shard re-run."""
    digest = config_digest(plan.config)
    todo, rejected = [], []
    for sh in plan.shards:
        d, why = read_shard_file(run_dir, sh, shard_hash(digest, asdict(sh)))
        if d is not None:
            continue
        todo.append(sh)
        if why:
            moved = reject_shard(run_dir, sh.id)
            rejected.append({"id": sh.id, "reason": why, "moved_to": str(moved)})
            print(f"dvsland campaign: warning: shard {sh.id} ({shard_path(run_dir, sh.id)}): {why}; moved to "
                  f"{moved}, re-running the shard", file=sys.stderr, flush=True)
    return todo, rejected


def merge(plan: CampaignPlan, run_dir) -> tuple:
    """(runs in plan order, ids of missing shards); a shard whose file is damaged or of another
    config counts as missing."""
    digest = config_digest(plan.config)
    runs, missing = [], []
    for sh in plan.shards:
        d, _ = read_shard_file(run_dir, sh, shard_hash(digest, asdict(sh)))
        if d is None:
            missing.append(sh.id)
        else:
            runs.extend(d["runs"])
    return runs, missing


def lock_campaign(run_dir):
    """Hold an exclusive lock on ``run_dir/.campaign.lock`` (:func:`dvsland.runs.lock_folder`);
    ValueError when another campaign process holds it."""
    try:
        return lock_folder(run_dir, LOCK_FILE, "dvsland campaign")
    except RunDirError as exc:
        raise RunDirError(f"{exc} with --resume") from None


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
        shard_seeds: seeds per shard (a shard flies sites x settings x shard_seeds descents); 0 =
            chosen from the memory estimate for ``workers`` (:func:`~.plan.auto_shard_seeds`).
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
    if not 1 <= int(workers) <= MAX_WORKERS:
        raise ValueError(f"--workers must be in [1, {MAX_WORKERS}] (each local worker is a process holding its "
                         f"own scenes, about 2 GB), got {workers}")
    t0 = time.perf_counter()
    if resume is None and config is not None and not shard_seeds:  # 0 / None: from the memory estimate
        shard_seeds = auto_shard_seeds(config, int(config.simulation.n_seeds if n_seeds is None else n_seeds), workers)
        if not quiet:
            print(f"campaign: {shard_seeds} seed(s) per shard, chosen from the memory estimate for {workers} "
                  "worker(s) (--shard-seeds S to choose)", file=sys.stderr)
    plan, run_dir, lock = _open_campaign(config, sweeps, n_seeds, shard_seeds, resume, out)
    session = {"executor": executor, "workers": int(workers), "t0": t0, "rejected": []}
    try:
        try:
            todo, session["rejected"] = check_shards(plan, run_dir, quiet)
            n_done_before = len(plan.shards) - len(todo)
            if max_shards is not None:
                todo = todo[:max(0, int(max_shards))]
            fly = _fly(plan, run_dir, todo, executor, workers, keep_runs, quiet, n_done_before)
        except BaseException as exc:  # noqa: BLE001 - Ctrl-C before the shards flew: report it too
            fly = {"status": "interrupted", "exc": exc, "descents": 0, "n_run": 0, "run_s": 0.0}
        return _finish(plan, run_dir, fly, session, quiet)
    finally:
        if lock is not None:
            lock.close()


def _open_campaign(config, sweeps, n_seeds, shard_seeds, resume, out):
    """(plan, folder, lock): a checked plan from ``resume``'s campaign.json, or a new plan (checked
    before its folder is made) saved in a new folder; the folder's lock held."""
    if resume is not None:
        run_dir = Path(resume)
        plan = CampaignPlan.load(run_dir)
        lock = lock_campaign(run_dir)
    else:
        if config is None:
            raise ValueError("run_campaign needs a config (or resume=FOLDER)")
        plan = make_plan(config, sweeps, n_seeds, shard_seeds)
        run_dir = make_run_dir(config, out, kind="campaign")  # claimed atomically; config.yaml first
        lock = lock_campaign(run_dir)
        plan.save(run_dir)
    try:
        (run_dir / SHARDS_DIR).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunWriteError(run_dir / SHARDS_DIR, exc) from None
    return plan, run_dir, lock


def _fly(plan: CampaignPlan, run_dir: Path, todo: List[Shard], executor: str, workers: int, keep_runs: bool,
         quiet: bool, n_done_before: int) -> dict:
    """Run the shards ``todo``, writing each result as it arrives. Returns {status, exc, descents,
    n_run, run_s}; Ctrl-C or an error ends it with status ``interrupted`` (``exc`` to re-raise)."""
    keep = [str(run_dir / SHARDS_DIR / sh.id) if keep_runs else None for sh in todo]
    shard_dicts = [asdict(sh) for sh in todo]
    bar = None if quiet else _step_bar(plan, shard_dicts, executor, workers, n_done_before)
    slot_of = {sh["id"]: i for i, sh in enumerate(shard_dicts)}
    out = {"status": "complete", "exc": None, "descents": 0, "n_run": 0}
    t_run = time.perf_counter()
    it = None
    try:
        it = (run_local(plan.config, shard_dicts, workers, keep, bar=bar) if executor == "local"
              else run_ray(plan.config, shard_dicts, workers, keep))
        for res in it:
            if res.get("status") != "complete":
                raise RuntimeError(f"shard {res['id']} ended {res.get('status')!r}")
            write_shard(run_dir, res)
            out["n_run"] += 1
            out["descents"] += len(res["runs"])
            if bar is not None:
                minutes = (time.perf_counter() - t_run) / 60
                bar.shard_done(slot_of.get(res["id"], -1),
                               f"{out['descents'] / minutes:.1f} descents/min" if minutes > 0 else "")
    except BaseException as exc:  # noqa: BLE001 - Ctrl-C too: keep what is done, report it, re-raise
        out.update(status="interrupted", exc=exc)
    finally:
        if it is not None:
            it.close()  # a failed write ends the executor too (its workers stopped)
        if bar is not None:
            bar.close()
    out["run_s"] = time.perf_counter() - t_run
    return out


def _step_bar(plan: CampaignPlan, shard_dicts: List[dict], executor: str, workers: int, n_done_before: int):
    """The campaign's bar over the loop steps of the shards to fly (:class:`~.progress.StepBar`;
    shared slots for a local pool; Ray's shards are counted when they end)."""
    from .progress import StepBar, shard_steps

    done_before = [asdict(s) for s in plan.shards if s.id not in {d["id"] for d in shard_dicts}]
    return StepBar(shard_steps(plan.config, shard_dicts), "campaign", len(plan.shards), n_done_before,
                   steps_before=sum(shard_steps(plan.config, done_before)),
                   shared=executor == "local" and workers > 1 and len(shard_dicts) > 1)


def _finish(plan: CampaignPlan, run_dir: Path, fly: dict, session: dict, quiet: bool) -> CampaignResult:
    """Merge the shard files and write the report; results.json first, with Ctrl-C / SIGTERM held
    back until it is written (:func:`~dvsland.runs.deferred_interrupts`), so a second Ctrl-C
    during an interrupted campaign's clean-up still leaves it. Re-raises ``fly["exc"]``."""
    from dvsland.report.results import write_results_json

    from .report import write_report

    with deferred_interrupts():
        runs, missing = merge(plan, run_dir)
        status = "incomplete" if fly["status"] == "complete" and missing else fly["status"]
        by = default_group_keys(runs)
        groups = group_stats(runs, by)
        wall = time.perf_counter() - session["t0"]
        dpm = fly["descents"] / (fly["run_s"] / 60) if fly["run_s"] > 0 and fly["descents"] else None
        exc = fly["exc"]
        meta = {"status": status, "n_shards": len(plan.shards), "n_shards_done": len(plan.shards) - len(missing),
                "missing_shards": missing, "rejected_shards": session["rejected"], "sweeps": plan.sweeps,
                "n_seeds": plan.n_seeds, "shard_seeds": plan.shard_seeds, "executor": session["executor"],
                "workers": session["workers"], "session": {
                    "shards_run": fly["n_run"], "descents_run": fly["descents"], "wall_time_s": wall,
                    "shards_time_s": fly["run_s"], "descents_per_min": dpm}, "dvsland_version": __version__,
                "error": None if exc is None else f"{type(exc).__name__}: {exc}"}
        write_results_json(run_dir / "results.json", runs, groups=groups, group_by=list(by), **meta)
    log = plan.config.get("logging", {})
    outputs = write_report(run_dir, runs, groups, by, meta, tensorboard=bool(log.get("tensorboard", True)),
                           figures=bool(log.get("figures", True)) and status != "interrupted", results=False)
    if not quiet:
        _print_summary(plan, run_dir, runs, groups, by, outputs, status, missing, fly, dpm)
    if isinstance(exc, WorkerLostError):
        raise WorkerLostError(str(exc).replace("RUN_DIR", str(run_dir))) from exc
    if exc is not None:
        try:
            exc.run_dir = str(run_dir)  # the command names the folder to resume
        except AttributeError:
            pass
        raise exc
    return CampaignResult(run_dir=run_dir, runs=runs, groups=groups, group_by=by, status=status,
                          n_shards=len(plan.shards), n_shards_run=fly["n_run"], wall_time_s=wall,
                          descents_per_min=dpm, outputs=outputs)


def _print_summary(plan, run_dir, runs, groups, by, outputs, status, missing, fly, dpm) -> None:
    print(format_group_table(groups, by))
    if "paper_pattern.txt" in outputs:  # the paper's nine sites: its pattern beside the pooled one
        print(outputs["paper_pattern.txt"].read_text(), end="")
    rate = f", {dpm:.1f} descents/min" if dpm else ""
    print(f"{status}: {len(plan.shards) - len(missing)}/{len(plan.shards)} shards, {len(runs)} descents "
          f"({fly['descents']} run now in {fly['run_s']:.1f} s{rate}); output in {run_dir}")
    if missing:
        print(f"{len(missing)} shards missing: dvsland campaign --resume {run_dir}")
