"""``dvsland campaign CONFIG [--sweep key=v1,v2 ...] [--n-seeds N] [--sites A,B] [--executor local|ray]
[--workers K] [--threads N] [--shard-seeds S] [--resume DIR] [--out DIR] [--set key=value ...] [--quiet]``:
a Monte Carlo campaign (grid x seeds in shards, merged report with success-rate intervals)."""

from __future__ import annotations

import sys

from .common import (add_config_args, add_sites_arg, add_threads_arg, config_from_args, parse_sites, ranged,
                     restrict_sites)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "campaign", help="Monte Carlo campaign: grid x seeds in resumable shards, success rates with intervals",
        description="Fly the config's sites x controller settings for many seeds (and every combination of "
                    "--sweep values), one batch per shard, locally or on Ray; merge into results.json, "
                    "runs.csv / groups.csv, a figure and a TensorBoard HParams table. Turn dispersions on with "
                    "--set dispersion.enabled=true (see docs/campaigns.md).")
    add_config_args(p)
    p.add_argument("--sweep", action="append", default=[], metavar="KEY=V1,V2",
                   help="sweep a config value, e.g. --sweep estimator.name=dpr,oracle (repeatable: cartesian grid)")
    p.add_argument("--n-seeds", type=ranged(int, 1, 10**9, "--n-seeds"), default=None, metavar="N",
                   help="seeds per grid point "
                   "(default simulation.n_seeds)")
    p.add_argument("--shard-seeds", type=int, default=0, metavar="S",
                   help="seeds per shard (default 0: chosen from the memory estimate, simulation.max_memory_gb "
                        "shared by the workers, at most n_seeds / workers; docs/campaigns.md)")
    p.add_argument("--executor", default="local", choices=("local", "ray"),
                   help="local: here (--workers > 1: a process pool); ray: Ray tasks (local instance, or the "
                        "cluster at $RAY_ADDRESS)")
    p.add_argument("--workers", type=int, default=1, metavar="K", help="processes (local) or CPUs of a local Ray")
    add_threads_arg(p, " (each worker)")
    add_sites_arg(p, "fly only these configured sites (simulation.sites)")
    p.add_argument("--resume", default=None, metavar="DIR", help="resume the campaign in DIR (its plan and "
                   "config rule): run only the missing shards, then merge")
    p.add_argument("--estimator", default=None, metavar="NAME", help="divergence estimator (dpr, oracle, ...)")
    p.add_argument("--keep-runs", action="store_true", help="keep each shard's run folder (traces.npz) under shards/")
    p.set_defaults(func=run_campaign_cmd)


def run_campaign_cmd(args) -> int:
    from dvsland.campaign import run_campaign
    from dvsland.campaign.executors import WorkerLostError

    cfg = None
    if args.resume is not None and not str(args.resume).strip():
        raise ValueError("--resume: give the campaign folder to resume (it is empty)")
    sites = parse_sites(args.sites)  # before anything is loaded or written
    if args.resume is None:
        cfg = restrict_sites(config_from_args(args), sites)
    elif args.config or args.sweep or args.overrides or sites or args.threads:
        print("dvsland campaign: resuming: the config (sites and threads too), sweeps and seeds come from the "
              "campaign folder")
    try:
        res = run_campaign(cfg, sweeps=args.sweep, n_seeds=args.n_seeds, executor=args.executor,
                           workers=args.workers, resume=args.resume, out=args.out, quiet=args.quiet,
                           shard_seeds=args.shard_seeds, keep_runs=args.keep_runs)
    except KeyboardInterrupt as exc:
        run_dir = getattr(exc, "run_dir", None)  # set once the campaign's folder exists
        print("dvsland: campaign interrupted before its folder was made; nothing was written" if run_dir is None
              else f"dvsland: campaign interrupted; finished shards are kept: dvsland campaign --resume {run_dir}",
              file=sys.stderr, flush=True)
        return 130
    except WorkerLostError as exc:
        print(f"dvsland: error: {exc}", file=sys.stderr, flush=True)
        return 1
    return 0 if res.status == "complete" else 1
