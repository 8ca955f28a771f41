"""``dvsland train-loop [CONFIG] --what policy|law|filter|estimator [--params NAME,...] [--sites D,E,...]
[--cpu-minutes M] [--window N] [--lr LR] [--loss track=1,...] [--seed S] [--val-seed S] [--out DIR | --resume DIR]
[--set ...] [--quiet]``: train a law's constants, the ``efference_fit`` filter's constants, a policy network or the
``learned`` estimator's network by gradients through the closed loop (:mod:`dvsland.learn.loop_run`)."""

from __future__ import annotations

import json
from pathlib import Path

from .common import add_config_args, add_sites_arg, add_threads_arg, apply_threads, config_from_args, parse_sites

#: defaults that differ by what is trained: (window, loss weights)
WHAT_DEFAULTS = {"policy": (40, "track=1,landing=1,fail=25,fuel=0"),
                 "law": (0, "track=0,landing=1,fail=25,fuel=0.05"),
                 "filter": (40, "track=0,landing=1,fail=25,fuel=0,filter=1"),
                 "estimator": (40, "track=0,landing=1,fail=25,fuel=0,filter=1")}
#: Adam's default learning rate by what is trained
WHAT_LR = {"policy": 3e-3, "law": 2e-2, "filter": 2e-2, "estimator": 1e-4}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train-loop", help="train a law's or the efference_fit filter's constants, or a policy network, by "
                           "gradients through the closed loop",
        description="Fly the config's descents as one batch with loop_step(grad=True) and train, from the loss "
                    "of the flight itself (landing speed, failures, fuel, tracking of the TTC profile), either "
                    "the constants of the configured law (--what law: div_gs lambda_per_s and d_final_per_s, "
                    "tau_p / div_p kp_scale), the constants of the efference_fit filter (--what filter: "
                    "meas_sigma_rel, meas_sigma_abs, cauchy_c, prior_rel_sigma, prior_rel_sigma_v; needs "
                    "controller.filter=efference_fit) or the network of the 'policy' law (--what policy: add --set "
                    "controller.name=policy). The budget is process CPU time. Writes checkpoint.pt, trained.yaml "
                    "(fly it: dvsland simulate RUN/trained.yaml), train_loop.json and TensorBoard scalars (tb/) "
                    "into the run folder. Use an estimator whose estimate depends on the state (oracle): "
                    "frames and events carry no gradient. --what estimator fine-tunes the learned estimator's "
                    "network (estimator.name=learned) on the same loss, the events fixed along the flown "
                    "trajectory; trained.yaml then names its checkpoint as estimator.learned.checkpoint.")
    add_config_args(p)
    p.add_argument("--what", required=True, choices=("policy", "law", "filter", "estimator"),
                   help="what is trained (estimator: the learned estimator's network, estimator.name=learned)")
    p.add_argument("--params", default="", metavar="NAME,...",
                   help="--what law or filter: the constants to train (default: the law's set; the filter's "
                        "meas_sigma_rel,meas_sigma_abs,cauchy_c,prior_rel_sigma)")
    add_sites_arg(p, "train on these configured sites (simulation.sites)")
    p.add_argument("--cpu-minutes", type=float, default=1.0, metavar="M",
                   help="budget of process CPU time, minutes (not wall time; default 1)")
    p.add_argument("--max-windows", type=int, default=0, metavar="N", help="stop after N windows (0 = no cap)")
    p.add_argument("--window", type=int, default=None, metavar="N",
                   help="steps per truncated-backpropagation window, 0 = whole descents (default: policy 40, law 0, "
                        "filter 40, estimator 40)")
    p.add_argument("--lr", type=float, default=None,
                   help="Adam learning rate (default: policy 3e-3, law and filter 2e-2, estimator 1e-4)")
    p.add_argument("--loss", default="", metavar="NAME=W,...",
                   help="loss weights over the defaults: policy " + WHAT_DEFAULTS["policy"][1] + "; law "
                        + WHAT_DEFAULTS["law"][1] + "; filter and estimator " + WHAT_DEFAULTS["filter"][1]
                        + "; track_gs (div_gs's target at the true altitude, docs/train_loop.md) and residual "
                        "(a residual policy's correction squared) are 0 unless given")
    p.add_argument("--seed", type=int, default=0, help="seed of the training's dispersed restarts")
    p.add_argument("--val-seed", type=int, default=999, help="simulation.seed of the validation descents")
    p.add_argument("--val-seeds", type=int, default=None, metavar="N",
                   help="seeds per site and setting of the validation descents (default: simulation.n_seeds)")
    p.add_argument("--val-every", type=int, default=50, metavar="N", help="validate every N windows (0 = at the end)")
    p.add_argument("--resume", default=None, metavar="DIR",
                   help="go on with the training in DIR (its config.yaml and checkpoint.pt; --cpu-minutes more)")
    add_threads_arg(p)
    p.set_defaults(func=run_train_loop)


def loop_settings(args):
    """The :class:`~dvsland.learn.loop_train.TrainLoopSettings` of the command line (checked)."""
    from dvsland.learn.loop_loss import LossWeights
    from dvsland.learn.loop_train import TrainLoopSettings

    window, loss = WHAT_DEFAULTS[args.what]
    return TrainLoopSettings(
        what=args.what, params=tuple(n.strip() for n in args.params.split(",") if n.strip()),
        window=window if args.window is None else args.window,
        lr=WHAT_LR[args.what] if args.lr is None else args.lr, seed=args.seed,
        cpu_minutes=args.cpu_minutes, max_windows=args.max_windows, val_every=args.val_every,
        loss=LossWeights.parse(args.loss, LossWeights.parse(loss))).check()


def _resume_dir(args) -> Path:
    from dvsland.learn.loop_run import CHECKPOINT

    if args.out is not None:
        raise ValueError("--resume and --out: give one (--resume DIR goes on writing into DIR)")
    d = Path(args.resume)
    if not (d / CHECKPOINT).is_file() or not (d / "config.yaml").is_file():
        raise ValueError(f"--resume {args.resume}: no train-loop run folder (expected {CHECKPOINT} and config.yaml "
                         f"in it)")
    if args.config is not None:
        raise ValueError("--resume DIR: leave CONFIG out (the run folder's config.yaml is used)")
    args.config = str(d / "config.yaml")
    return d


def run_train_loop(args) -> int:
    sites = parse_sites(args.sites)
    if args.val_seeds is not None and not 1 <= args.val_seeds <= 10000:
        raise ValueError(f"--val-seeds must be an integer in [1, 10000], got {args.val_seeds}")
    run_dir = _resume_dir(args) if args.resume else None
    cfg = config_from_args(args)
    settings = loop_settings(args)  # every option checked before a folder is made
    from dvsland.learn.loop_run import train_loop
    from dvsland.runs import make_run_dir

    apply_threads(cfg)
    if run_dir is None:
        run_dir = make_run_dir(cfg, args.out, kind="train-loop")
    quiet = bool(cfg.logging.quiet)
    summary = train_loop(cfg, run_dir, settings, sites=sites, val_seed=args.val_seed, val_seeds=args.val_seeds,
                         resume=bool(args.resume),
                         progress=not quiet)
    v = summary["validation"]
    if not quiet:
        print(json.dumps({"values": summary["values"], "windows": summary["windows"],
                          "simulated_steps": summary["simulated_steps"], "cpu_s": summary["cpu_s"],
                          "validation": {k: v[k] for k in ("n", "landed", "median_landing_speed_mps",
                                                           "median_fuel_kg")}}))
    print(f"run folder: {run_dir}")
    return 0
