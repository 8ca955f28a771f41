"""``dvsland train CONFIG --model NAME|pkg.mod:Class --data DIR [--recipe quick] [--epochs E]
[--max-minutes M] [--max-cpu-minutes M] [--out CKPT] [--resume | --init CKPT]``: the training
recipe of the ``learned`` estimator (:mod:`dvsland.learn`, :mod:`.train_recipe`) on dataset
folders of ``dvsland dataset build``; ``--recipe quick`` names a ready set of recipe settings
(:data:`dvsland.learn.RECIPES`). The checkpoint is flown with ``--estimator learned --set
estimator.learned.checkpoint=PATH``.

Without ``--model`` and ``--data`` (the older mode): ``dvsland train [CONFIG] [--out PATH]
[--overwrite-shipped] [--sites A~1,...] [--n-seq N] [--steps K] [--epochs E] [--init CKPT]
[--threads N] [--set key=value ...] [--quiet]`` trains the log-polar spiking estimator ``snn``
(:mod:`dvsland.estimators.snn`) on constant-divergence descents and climbs over held-out terrain
(site variants A~1 ... I~2 unless ``--sites`` names others), rendered by the fast renderer and
turned into events by the config's emulator (:func:`dvsland.estimators.snn.train.train`); its
checkpoint is flown with ``--set estimator.snn.checkpoint=PATH``.

Where it goes: ``--out PATH`` (a ``.pt`` file), or by default a new run folder
``<logging.root>/<name>-train-<UTC stamp>/`` (``<model>.pt`` for the recipe; ``snn.pt``,
``train.json`` and ``config.yaml`` for the snn). A path inside the installed package (the shipped
checkpoints) is refused unless ``--overwrite-shipped`` is given, and any other existing file unless
``--overwrite``: both are checked before any data is read or made.

Time caps: ``--max-minutes`` is wall-clock time, ``--max-cpu-minutes`` CPU time of the process
(all its threads; what a shared machine gives a run is CPU time).

Every checkpoint it reads (``--init``, ``--resume``, ``--data-cache``) goes through the one checkpoint
validation (:mod:`dvsland.estimators.state_dict_check`) before any data are made or any file is
written: a missing, foreign, damaged or diverged file is one error naming the option and the file.

The options are added by :func:`add_train_arguments` in groups (recipe, output, data, model,
training), the one place to extend them.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from .common import add_config_args, add_threads_arg, apply_threads, config_from_args, parse_sites, ranged

#: checkpoint file name in a default run folder
CHECKPOINT_NAME = "snn.pt"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train", help="train a learned estimator on a dataset folder (--model cnn --data DIR; --recipe quick)",
        description="Train a model of the learned estimator on dataset folders of `dvsland dataset build` "
                    "(--model cnn|spiking|pkg.mod:Class --data DIR) and write its checkpoint: to --out PATH, or "
                    "into a new run folder under logs/ (<model>.pt, with TensorBoard curves beside it). "
                    "--recipe quick: a small, fast model and schedule capped at 9 CPU-minutes (docs/learning.md, "
                    "'Your first model in 15 minutes'). Fly the result with --estimator learned --set "
                    "estimator.learned.checkpoint=PATH. Without --model and --data: the older log-polar spiking "
                    "estimator snn on generated descents (snn.pt; --set estimator.snn.checkpoint=PATH). The "
                    "shipped checkpoints inside the package are only replaced with --overwrite-shipped.")
    add_config_args(p, out=False)
    add_train_arguments(p)
    p.set_defaults(func=run_train)


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    """Every option of ``dvsland train`` (besides CONFIG and --set): output, data, model, training."""
    rec = p.add_argument_group("recipe (any learned model on a dataset folder; chosen by --model or --recipe)")
    rec.add_argument("--model", default=None, metavar="NAME|pkg.mod:Class",
                     help="train this model of the learned estimator's zoo (cnn, spiking) or any class with the "
                          "same forward(vox, coords, log_count) on --data with the recipe (default with --data: "
                          "cnn); without --model and --data: the older spiking snn")
    rec.add_argument("--recipe", default=None, metavar="NAME",
                     help="a named set of recipe settings (model, input, schedule, time cap): quick = a first "
                          "model in about 9 CPU-minutes of training; options given beside it win")
    rec.add_argument("--data", default=None, metavar="DIR[,DIR]",
                     help="dataset folder(s) of `dvsland dataset build`, of one sensor")
    rec.add_argument("--model-set", action="append", default=[], metavar="KEY=VALUE",
                     help="a model constructor setting, e.g. width=16 (repeatable)")
    rec.add_argument("--n-bins", type=ranged(int, 1, 64, "--n-bins"), default=None,
                     help="time bins of the voxel grid (default 4; spiking 6; quick 8)")
    rec.add_argument("--n-windows", type=ranged(int, 1, 64, "--n-windows"), default=None,
                     help="control steps the input spans (the last K windows; n_bins must be a multiple of K; "
                          "default 1, quick 8)")
    rec.add_argument("--pool-px", type=ranged(int, 1, 64, "--pool-px"), default=None,
                     help="sensor pixels per input cell side (default 2; spiking 4; quick 4)")
    rec.add_argument("--patience", type=ranged(int, 1, 10_000, "--patience"), default=None,
                     help="early stopping: epochs without a better val error (default 6)")
    rec.add_argument("--resume", action="store_true", help="continue the training stored in --out")
    rec.add_argument("--tensorboard", default=None, metavar="DIR",
                     help="TensorBoard folder (default: beside --out, <out>.tb)")
    out = p.add_argument_group("output")
    out.add_argument("--out", default=None, metavar="PATH",
                     help="checkpoint file to write (.pt); default: logs/<name>-train-<UTC stamp>/<model>.pt "
                          "(snn.pt without --model)")
    out.add_argument("--overwrite-shipped", action="store_true",
                     help="allow --out inside the installed dvsland package (the shipped checkpoints)")
    out.add_argument("--overwrite", action="store_true", help="allow --out to replace an existing file of yours")
    out.add_argument("--quiet", action="store_true", help="print only the checkpoint path")
    add_threads_arg(out)

    data = p.add_argument_group("data", "the older snn mode's generated descents (without --model and --data)")
    data.add_argument("--sites", default=None, metavar="A~1,B~2,...",
                      help="training terrains (sites or variants; default: the variants ~1 and ~2 of A-I, "
                           "never the evaluation sites themselves)")
    data.add_argument("--hold-out-type", default=None, choices=("craters", "craters_rocks", "rocky", "featureless"),
                      help="leave every site of this type out of the default training terrains")
    data.add_argument("--n-seq", type=ranged(int, 1, 1_000_000, "--n-seq"), default=1280, metavar="N",
                      help="sequences (default 1280)")
    data.add_argument("--steps", type=ranged(int, 1, 10_000, "--steps"), default=20, metavar="K",
                      help="control steps per sequence (default 20)")
    data.add_argument("--c2-max", type=ranged(float, 0.0, 10.0, "--c2-max"), default=0.0,
                      help="descents follow tau = tau0 - c2 t with c2 in [0, C2_MAX] (0 = constant D)")
    data.add_argument("--dispersion", default=None, metavar="CONFIG",
                      help="draw each sequence's sun elevation and sensor from this config's dispersion section, "
                           "e.g. montecarlo")
    data.add_argument("--sun-step", type=ranged(float, 0.01, 90.0, "--sun-step"), default=None,
                      help="round dispersed sun elevations to this step, deg (default: the config's sun_step_deg)")
    data.add_argument("--seed", type=ranged(int, 0, 2 ** 63 - 1, "--seed"), default=0,
                      help="seed of the data (and of the weights unless --train-seed); the recipe: of the weights, "
                           "the batch order and the augmentation")
    data.add_argument("--data-cache", default=None, metavar="PATH",
                      help="torch file of the generated sequences: loaded when it exists and matches, else written")

    model = p.add_argument_group("model", "the older snn mode's network; --init also for the recipe")
    model.add_argument("--channels", default="16,32", help="LIF channels of the two layers (new networks only)")
    model.add_argument("--n-sub", type=ranged(int, 1, 64, "--n-sub"), default=4,
                       help="network steps (time slices) per control step")
    model.add_argument("--init", default=None, metavar="CKPT",
                       help="start from this checkpoint's weights (fine-tuning): an snn checkpoint, or with --model a "
                            "learned one of the same model, settings, bins and windows (its cells may differ: --pool-px refines "
                            "it onto finer ones); checked like every checkpoint")

    tr = p.add_argument_group("training", "both modes unless marked (recipe defaults: epochs 30, batch 64, lr 2e-3)")
    tr.add_argument("--epochs", type=ranged(int, 1, 100_000, "--epochs"), default=None,
                    help="epochs (default 14 for snn, 30 for the recipe)")
    tr.add_argument("--batch", type=ranged(int, 1, 65_536, "--batch"), default=None,
                    help="batch size (default 32 for snn, 64 for the recipe)")
    tr.add_argument("--lr", type=ranged(float, 1e-08, 10.0, "--lr"), default=None,
                    help="learning rate (default 3e-3 for snn, 2e-3 for the recipe)")
    tr.add_argument("--crop-steps", type=ranged(int, 1, 10_000, "--crop-steps"), default=None,
                    help="snn: train on random windows of this many steps (validation on whole sequences)")
    tr.add_argument("--warmup-steps", type=ranged(int, 0, 10_000, "--warmup-steps"), default=5,
                    help="snn: steps at the start of a sequence not scored")
    tr.add_argument("--train-seed", type=ranged(int, 0, 2 ** 63 - 1, "--train-seed"), default=None,
                    help="seed of the weights and the batch order (default --seed; the data keep --seed)")
    tr.add_argument("--max-minutes", type=ranged(float, 0.01, 100000.0, "--max-minutes"), default=None,
                    help="stop training after this many wall-clock minutes (the time on the clock; on a shared "
                         "machine it buys less training than the same CPU time)")
    tr.add_argument("--ema", type=ranged(float, 0.0, 0.99999, "--ema"), default=None, metavar="DECAY",
                    help="recipe: validate, keep and ship an exponential moving average of the weights, updated "
                         "after every optimizer step with this decay (e.g. 0.999: about the last 1,000 steps; "
                         "default 0: the weights as trained)")
    tr.add_argument("--max-cpu-minutes", type=ranged(float, 0.01, 100000.0, "--max-cpu-minutes"), default=None,
                    help="recipe: stop training after this many CPU-minutes of this process (all threads; reading "
                         "the data before the first epoch not counted); quick: 9")


def package_dir() -> Path:
    """The installed ``dvsland`` package folder (what ``--overwrite-shipped`` guards)."""
    import dvsland

    return Path(dvsland.__file__).resolve().parent


def check_out_path(out, overwrite_shipped: bool = False, overwrite: bool = False, name: str = CHECKPOINT_NAME) -> Path:
    """The checkpoint path ``--out`` names, checked before any work (``name``: the file a folder is told to hold).

    Raises:
        ValueError: a path inside the installed package without ``overwrite_shipped``, an existing
            file without ``overwrite``, a folder, or a parent that is a file.
    """
    path = Path(out).expanduser()
    if str(out).strip() == "":
        raise ValueError("--out: empty path")
    resolved = path.resolve()
    pkg = package_dir()
    if (resolved == pkg or pkg in resolved.parents) and not overwrite_shipped:
        raise ValueError(f"--out {out}: this is inside the installed dvsland package ({pkg}); training would "
                         f"replace a shipped file. Write elsewhere (default: a run folder under logs/), or pass "
                         f"--overwrite-shipped to replace it on purpose")
    if path.is_dir():
        raise ValueError(f"--out {out}: is a folder; give the checkpoint file, e.g. {path / name}")
    if path.exists() and not overwrite and not (overwrite_shipped and pkg in resolved.parents):
        raise ValueError(f"--out {out}: the file exists; pass --overwrite to replace it")
    for parent in path.parents:
        if parent.exists() and not parent.is_dir():
            raise ValueError(f"--out {out}: {parent} is a file, not a folder")
    return path


def _check_numbers(args) -> None:
    for name, v, lo in (("--n-seq", args.n_seq, 2), ("--steps", args.steps, 2), ("--epochs", args.epochs, 1),
                        ("--batch", args.batch, 1), ("--n-sub", args.n_sub, 1)):
        if v < lo:
            raise ValueError(f"{name} must be >= {lo}, got {v}")
    if not 0 <= args.warmup_steps < args.steps:
        raise ValueError(f"--warmup-steps must be in [0, --steps), got {args.warmup_steps} with --steps {args.steps}")
    if not args.lr > 0:
        raise ValueError(f"--lr must be > 0, got {args.lr}")
    try:
        channels = tuple(int(c) for c in args.channels.split(","))
    except ValueError:
        channels = ()
    if len(channels) != 2 or min(channels) < 1:
        raise ValueError(f"--channels must be two positive integers, e.g. 16,32; got {args.channels!r}")


def _start_from(args, cfg):
    """(network or None, encoder, the prior training's meta) of ``--init``: its checkpoint loaded by
    the snn loader with the one checkpoint validation (ValueError naming ``--init`` and the file for
    a missing, foreign, damaged or diverged one), else (None, a new encoder with ``--n-sub``, {})."""
    from dvsland.estimators.snn import LogPolarEncoder, load_checkpoint

    sensor = (cfg.camera.width_px, cfg.camera.height_px)
    if args.init is None:
        return None, LogPolarEncoder(sensor, n_sub=args.n_sub), {}
    if not args.init.strip():
        raise ValueError(f"--init {args.init!r}: empty; expected an snn checkpoint file (.pt) to start from")
    model, enc, meta = load_checkpoint(args.init, sensor, cfg.dt_s, param="--init")
    return model, enc, meta if isinstance(meta, dict) else {}


def _read_cache(path):
    """The ``--data-cache`` file ``path`` read (``{"key": settings, "data": sequences}``), or None
    when there is none yet (it is made and written then). Read by the one checkpoint reader
    (tensors and plain values only), before any data are made.

    Raises:
        ValueError: naming ``--data-cache`` for a file that is unreadable or not such a cache (it is
            never overwritten: it may be a file of yours).
    """
    from dvsland.estimators.state_dict_check import read_checkpoint_file, short_path

    if path is None:
        return None
    try:
        missing = bool(str(path).strip()) and not Path(path).exists()
    except (OSError, ValueError):  # a name the OS refuses: read_checkpoint_file names it
        missing = False
    if missing:
        if not Path(path).parent.is_dir():
            raise ValueError(f"--data-cache: {short_path(path)}: the folder {short_path(Path(path).parent)} does "
                             f"not exist; the cache would be written there after the data are made")
        return None
    cached = read_checkpoint_file(path, "--data-cache", "dvsland training-data cache",
                                  "delete it, or name another file for the cache")
    p = Path(path)
    if not isinstance(cached.get("key"), dict) or not isinstance(cached.get("data"), dict):
        raise ValueError(f"--data-cache: {short_path(p)} is not a dvsland training-data cache (no 'key' and 'data'); "
                         f"it is left as it is: name another file for the cache")
    return cached


def _cached_data(cached, key: dict, path, log):
    """The sequences of the cache ``cached`` (:func:`_read_cache`) when made with ``key``, else None."""
    if cached is None:
        return None
    if cached["key"] != key:
        log(f"data: {path} was made with other settings; regenerating")
        return None
    log(f"data: loaded {path}")
    return cached["data"]


def _write_cache(path, key: dict, data: dict) -> None:
    """Write the ``--data-cache`` atomically (a temporary file renamed: no half-written cache)."""
    import torch

    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    torch.save({"key": key, "data": data}, tmp)
    tmp.replace(p)


def _sequences():
    """The module that makes the training sequences (``make_sequences``, ``training_sites``)."""
    from dvsland.data import snn_sequences

    return snn_sequences


def run_train(args) -> int:
    if args.model is not None or args.data is not None or args.recipe is not None:
        from .train_recipe import run_recipe

        return run_recipe(args, check_out_path)
    for flag, value in (("--max-cpu-minutes", args.max_cpu_minutes), ("--n-windows", args.n_windows),
                        ("--patience", args.patience), ("--ema", args.ema)):
        if value is not None:
            raise ValueError(f"{flag} is an option of the recipe (--model NAME --data DIR); the snn (no --model) "
                             f"takes --max-minutes, --epochs and --steps")
    if args.resume:
        raise ValueError("--resume continues a recipe training (--model NAME --data DIR --out CKPT); the snn "
                         "starts from a checkpoint's weights with --init CKPT")
    args.epochs = 14 if args.epochs is None else args.epochs
    args.batch = 32 if args.batch is None else args.batch
    args.lr = 3e-3 if args.lr is None else args.lr
    import torch

    from dvsland.config import load_config
    from dvsland.estimators.snn import SpikingDivergenceNet, save_checkpoint
    from dvsland.estimators.snn.train import train
    from dvsland.runs import make_run_dir

    # ---- every check before any data is made or any file is written
    _check_numbers(args)
    sites = parse_sites(args.sites)
    out = check_out_path(args.out, args.overwrite_shipped, args.overwrite) if args.out is not None else None
    cfg = config_from_args(args)
    dispersion = load_config(args.dispersion).dispersion if args.dispersion else None
    log = (lambda *a, **k: None) if args.quiet else print
    apply_threads(cfg)
    init_model, enc, prior = _start_from(args, cfg)  # --init checked before any data or folder
    cached = _read_cache(args.data_cache)  # so is --data-cache
    seqs = _sequences()
    if sites is None:
        sites = seqs.training_sites(hold_out_type=args.hold_out_type)
    elif args.hold_out_type:
        raise ValueError("--hold-out-type picks from the default training terrains; leave it out with --sites")
    t0 = time.perf_counter()
    key = {"n_seq": args.n_seq, "steps": args.steps, "seed": args.seed, "c2_max": args.c2_max, "sites": sites,
           "dispersion": args.dispersion, "sun_step": args.sun_step, "n_sub": enc.n_sub,
           "camera": [cfg.camera.width_px, cfg.camera.height_px]}
    data = _cached_data(cached, key, args.data_cache, log)
    if out is None:
        run_dir = make_run_dir(cfg, None, kind="train")
        out = run_dir / CHECKPOINT_NAME
    else:
        run_dir = None

    train_seed = args.seed if args.train_seed is None else args.train_seed
    torch.manual_seed(train_seed)
    if data is None:
        data = seqs.make_sequences(cfg, enc, sites, args.n_seq, args.steps, seed=args.seed, c2_max=args.c2_max,
                                   dispersion=dispersion, sun_step_deg=args.sun_step, progress=not args.quiet)
        if args.data_cache:
            _write_cache(args.data_cache, key, data)
    t_data = time.perf_counter() - t0
    log(f"data: {args.n_seq} sequences x {args.steps} steps on {', '.join(sites)} in {t_data:.0f} s; "
        f"mean events/px/step {float(data['x'].float().mean()) * enc.n_sub:.3f}")
    if init_model is not None:
        model = init_model
        log(f"starting from {args.init} ({prior.get('epochs_run', '?')} epochs)")
    else:
        channels = tuple(int(c) for c in args.channels.split(","))
        model = SpikingDivergenceNet(enc.n_rho, enc.n_phi, dt_s=cfg.dt_s / enc.n_sub, channels=channels)
    hist = train(model, data, epochs=args.epochs, batch=args.batch, lr=args.lr, warmup_steps=args.warmup_steps,
                 seed=train_seed, max_minutes=args.max_minutes, crop_steps=args.crop_steps, log=log)
    meta = {"sites": sites, "hold_out_type": args.hold_out_type, "dispersion": args.dispersion,
            "sun_step": args.sun_step, "n_seq": args.n_seq, "steps": args.steps, "crop_steps": args.crop_steps,
            "c2_max": args.c2_max, "epochs_run": len(hist["epoch"]), "batch": args.batch, "lr": args.lr,
            "warmup_steps": args.warmup_steps, "seed": args.seed, "train_seed": train_seed,
            "data_seconds": t_data, "train_seconds": hist["seconds"][-1] if hist["seconds"] else 0.0,
            "history": hist, "init": args.init, "prior": {k: v for k, v in prior.items() if k != "prior"},
            "config": cfg.name, "command": "dvsland " + " ".join(sys.argv[1:]) if sys.argv else "dvsland train"}
    tmp = out.with_name(out.name + ".tmp")  # the old file stays until the new one is complete
    save_checkpoint(tmp, model, enc, meta)
    tmp.replace(out)
    _report(args, out, run_dir, meta)
    return 0


def _report(args, out: Path, run_dir, meta: dict) -> None:
    """``train.json`` in the run folder (if any) and the lines of the command's output."""
    from dvsland.report.results import write_json

    if run_dir is not None:
        write_json(run_dir / "train.json", {k: v for k, v in meta.items()})
    if args.quiet:
        print(out)
    else:
        print(f"wrote {out}")
        print(json.dumps({k: v for k, v in meta.items() if k != "history"}))
        print(f"use it: dvsland evaluate --estimators snn --set estimator.snn.checkpoint={out}")
