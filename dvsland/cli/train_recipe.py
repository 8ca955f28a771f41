"""``dvsland train CONFIG --model NAME --data DIR``: the recipe path of ``dvsland train`` (:mod:`dvsland.learn`)."""

from __future__ import annotations

import json
from pathlib import Path

from .common import apply_threads, config_from_args

#: defaults of the recipe that differ by model: (n_bins, pool_px)
MODEL_INPUT_DEFAULTS = {"cnn": (4, 2), "spiking": (6, 4)}


def _parse_model_set(items) -> dict:
    """``["width=16", ...]`` -> {"width": 16}: values read as JSON (numbers, lists), else strings."""
    out = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--model-set {item!r}: expected KEY=VALUE, e.g. width=16")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = json.loads(v)
        except ValueError:
            out[k.strip()] = v
    return out


def check_model_name(model) -> None:
    """A ``--model`` that is neither a zoo name (:data:`MODEL_INPUT_DEFAULTS`) nor an import path
    ``pkg.mod:Class`` is a ValueError naming it; checked without importing torch."""
    name = "cnn" if model is None else str(model).strip()
    if not name:
        raise ValueError(f"--model {model!r}: empty; expected a model of the zoo (cnn, spiking) or "
                         f"pkg.mod:Class (leave --model out for the cnn)")
    if name not in MODEL_INPUT_DEFAULTS and ":" not in name:
        raise ValueError(f"--model {model!r}: unknown model; choose one of {sorted(MODEL_INPUT_DEFAULTS)} or "
                         f"'package.module:Class'")


def recipe_settings(args, cfg):
    """The :class:`~dvsland.learn.RecipeSettings` of the command line: the defaults, or the named
    ``--recipe``'s settings, with every option given on top (ValueError naming the option)."""
    from dvsland.learn import RECIPES, RecipeSettings

    check_model_name(args.model)
    base = {}
    if getattr(args, "recipe", None) is not None:
        if args.recipe not in RECIPES:
            raise ValueError(f"--recipe {args.recipe!r}: unknown recipe; choose one of {', '.join(sorted(RECIPES))}")
        base = dict(RECIPES[args.recipe])
    name = args.model.strip() if args.model is not None else base.get("model", "cnn")
    nb, pool = (base["n_bins"], base["pool_px"]) if "n_bins" in base else MODEL_INPUT_DEFAULTS.get(name, (4, 2))
    ms = {**base.get("model_settings", {}), **_parse_model_set(args.model_set)}
    nb = args.n_bins if args.n_bins is not None else nb
    n_windows = args.n_windows if args.n_windows is not None else base.get("n_windows", 1)
    if name == "spiking":
        ms.setdefault("slice_dt_s", cfg.dt_s * n_windows / nb)
    given = {"epochs": args.epochs, "max_minutes": args.max_minutes, "batch_size": args.batch, "lr": args.lr,
             "patience": args.patience, "max_cpu_minutes": getattr(args, "max_cpu_minutes", None),
             "ema": getattr(args, "ema", None)}
    defaults = {"epochs": 30, "batch_size": 64, "lr": 2e-3, "patience": 6, "ema": 0.0}
    over = {k: v if v is not None else base.get(k, defaults.get(k)) for k, v in given.items()}
    rest = {k: v for k, v in base.items() if k in ("schedule", "val_max_samples", "echo")}
    return RecipeSettings(model=name, model_settings=ms, n_bins=nb,
                          pool_px=args.pool_px if args.pool_px is not None else pool, n_windows=n_windows,
                          seed=args.seed if args.train_seed is None else args.train_seed, **over, **rest).check()


def run_recipe(args, check_out_path) -> int:
    """Check the arguments, train, write the checkpoint and print where it is and how it scored.
    ``check_out_path(out, overwrite_shipped, overwrite, name)``: the --out guard of ``dvsland train``."""
    check_model_name(args.model)  # before torch loads: a typo is answered at once
    from dvsland.estimators.learned import read_checkpoint
    from dvsland.learn import train
    from dvsland.data import load_manifest_info
    from dvsland.learn.recipe import data_dirs

    if args.data is None:
        raise ValueError("--data DIR: the recipe (--model) trains on a dataset folder of `dvsland dataset build`")
    for d in data_dirs(args.data):  # ValueError naming --data: no folder named, or one that is no dataset
        try:
            load_manifest_info(d)
        except ValueError as exc:
            raise ValueError(f"--data {d}: {exc}") from None
    cfg = config_from_args(args)
    apply_threads(cfg)
    s = recipe_settings(args, cfg)
    if args.resume and args.init is not None:
        raise ValueError("--init and --resume: give one (--resume goes on with the training in --out, --init starts "
                         "a new training from another checkpoint's weights)")
    if args.resume and args.out is None:
        raise ValueError("--resume: continues the training stored in --out; give --out PATH")
    if args.init is not None:
        read_checkpoint(args.init, "--init")  # the file and its numbers checked before a run folder is made
    if args.out is None:
        from dvsland.runs import make_run_dir

        out = make_run_dir(cfg, None, kind="train") / f"{s.model.replace(':', '_').replace('.', '_')}.pt"
    elif args.resume:
        out = Path(args.out)
    else:
        out = check_out_path(args.out, args.overwrite_shipped, args.overwrite,
                             name=f"{'cnn' if args.model is None else args.model.strip().split(':')[-1]}.pt")
    tb = Path(args.tensorboard) if args.tensorboard else out.with_name(out.stem + ".tb")
    log = (lambda *a, **k: None) if args.quiet else print
    ck = train(args.data, out, s, resume=args.resume, progress=not args.quiet, tb_dir=tb, log=log, init=args.init)
    if args.quiet:
        print(out)
        return 0
    fin = ck["final"]
    print(f"wrote {out} ({ck['epoch']} epochs, {fin['train_seconds']:.0f} s wall, "
          f"{fin.get('train_cpu_seconds', float('nan')):.0f} s CPU; TensorBoard: {tb})")
    print(f"use it: dvsland evaluate --estimators learned --set estimator.learned.checkpoint={out}")
    return 0
