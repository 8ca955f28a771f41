"""``dvsland simulate [CONFIG] [--estimator NAME] [--controller NAME] [--renderer fast|pyrender] [--sites A,B,...]
[--device cpu|cuda] [--threads N] [--out DIR] [--set key=value ...] [--quiet]``: fly the batched closed loop."""

from __future__ import annotations

from .common import (add_config_args, add_sites_arg, add_threads_arg, check_configured_sites, config_from_args,
                     parse_sites)


def _estimator_names() -> str:
    """The estimators to name in --help: the registry's when it is already loaded (plug-ins
    registered in this process), else the built-ins (loading the registry would load torch)."""
    import sys

    if "dvsland.estimators.registry" in sys.modules:
        try:
            from dvsland.estimators import available_estimators

            return ", ".join(available_estimators())
        except Exception:  # a broken plug-in must not break --help
            pass
    return "dpr, cmax, oracle, snn, learned or another registered name (an unknown name's error lists them)"


def register(subparsers) -> None:
    p = subparsers.add_parser("simulate", help="fly every site x controller setting as one batched closed loop",
                              description="Fly the configured experiment (default: the shipped 'paper' config, "
                                          "9 sites x 2 settings) as one batch and write config.yaml, "
                                          "results.json, traces.npz, TensorBoard files (tb/) and figures into "
                                          "the run folder.")
    add_config_args(p)
    p.add_argument("--estimator", default=None, metavar="NAME",
                   help=f"divergence estimator: {_estimator_names()}; or a class by import path, "
                        "'package.module:Class' or 'path/to/file.py:Class'; 'ALIAS=...' shows it as ALIAS in "
                        "tables and figures (default: estimator.name)")
    p.add_argument("--controller", default=None, metavar="NAME",
                   help="thrust law (tau_p, div_p, div_gs, policy, or a registered name); sets controller.name")
    p.add_argument("--renderer", default=None, metavar="NAME",
                   help="scene renderer: fast, pyrender or a registered one (default: render.renderer)")
    add_sites_arg(p, "fly only these configured sites (simulation.sites)")
    p.add_argument("--device", default=None, metavar="DEVICE",
                   help="torch device: cpu, cuda, cuda:0, ... (checked against this machine)")
    add_threads_arg(p)
    p.set_defaults(func=run_simulate)


def run_simulate(args) -> int:
    from dvsland.sim import simulate

    sites = parse_sites(args.sites)  # before anything is loaded or written
    cfg = config_from_args(args, [f"controller.name={args.controller}"] if args.controller else [])
    check_configured_sites(cfg, sites)
    try:
        result = simulate(cfg, sites=sites, out=args.out)
    except KeyboardInterrupt:
        print("dvsland: interrupted; results gathered so far were written", flush=True)
        return 130
    if cfg.logging.quiet:
        print(f"run folder: {result.run_dir}")
    return 0 if result.status == "complete" else 1
