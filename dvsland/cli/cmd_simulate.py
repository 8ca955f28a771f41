"""``dvsland simulate [CONFIG] [--estimator NAME] [--controller NAME] [--renderer fast|pyrender] [--sites A,B,...]
[--device cpu|cuda] [--out DIR] [--set key=value ...] [--quiet]``: fly the batched closed loop."""

from __future__ import annotations

from .common import add_config_args, config_from_args


def register(subparsers) -> None:
    p = subparsers.add_parser("simulate", help="fly every site x controller setting as one batched closed loop",
                              description="Fly the configured experiment (default configs/paper.yaml: 9 sites x "
                                          "2 settings) and write results.json, traces.npz, TensorBoard files "
                                          "and figures into the run folder.")
    add_config_args(p)
    p.add_argument("--estimator", default=None, metavar="NAME", help="divergence estimator (dpr, oracle, cmax, ...)")
    p.add_argument("--controller", default=None, metavar="NAME",
                   help="thrust law (tau_p, div_p, div_gs, or a registered name); sets controller.name")
    p.add_argument("--renderer", default=None, metavar="NAME",
                   help="scene renderer: fast, pyrender or a registered one (dvsland.render.available_renderers())")
    p.add_argument("--sites", default=None, metavar="A,B,...", help="fly only these configured sites")
    p.add_argument("--device", default=None, metavar="DEVICE", help="torch device: cpu, cuda, cuda:0, ...")
    p.set_defaults(func=run_simulate)


def run_simulate(args) -> int:
    from dvsland.sim import simulate

    cfg = config_from_args(args, [f"controller.name={args.controller}"] if args.controller else [])
    try:
        result = simulate(cfg, sites=args.sites, out=args.out)
    except KeyboardInterrupt:
        print("dvsland: interrupted; results gathered so far were written", flush=True)
        return 130
    return 0 if result.status == "complete" else 1
