"""``dvsland bench [WHAT ...] [--quick] [--device cpu|cuda] [--threads N] [--sites A,B] [--set KEY=VALUE ...]
[--out DIR] [--docs DIR]``.

A thin command over :func:`dvsland.bench.run_bench`: speed against error, closed-loop success,
scaling with B and the economies, written to one run folder (bench.json, bench.md, pareto.png,
scaling.png); the stage benchmarks (render, events, estimators, renderers, throughput, fleet, sim) on
request.
"""

from __future__ import annotations

import sys


def register(subparsers) -> None:
    from dvsland.bench.parts import CHOICES

    from .common import add_sites_arg, add_threads_arg, ranged

    p = subparsers.add_parser(
        "bench", help="benchmarks: speed against error, closed loop, scaling, economies",
        description="Measure every registered estimator and the settings that trade speed for accuracy: "
                    "open-loop error against time per control step at B = 18, closed-loop success with a "
                    "95 % Wilson interval, time and memory per stage against the batch size, and what each "
                    "economy of the simulator buys. Writes bench.json, bench.md, pareto.png and scaling.png "
                    "into one run folder (--out), and docs/benchmarks.md with --docs docs. --quick takes "
                    "under 5 minutes on a 2-core CPU.")
    p.add_argument("what", nargs="*", metavar="WHAT",
                   help=f"parts (default: tradeoff closed_loop scaling economies); all, or any of {', '.join(CHOICES)}")
    p.add_argument("--quick", action="store_true", help="smaller samples (under 5 minutes on 2 CPU cores)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="torch device (default cpu)")
    p.add_argument("--out", default=None, metavar="DIR", help="run folder (default logs/bench-<UTC stamp>)")
    p.add_argument("--docs", default=None, metavar="DIR", help="also write benchmarks.md and its figures here")
    p.add_argument("--config", default=None, help="open-loop config (default paper)")
    p.add_argument("--closed-loop-config", default="realistic", help="closed-loop config (default realistic)")
    p.add_argument("--estimators", default=None, help="comma-separated registered names (default: all registered)")
    add_threads_arg(p, " (default 1)")
    p.add_argument("--render-threads", type=ranged(int, 0, 256, "--render-threads"), default=None, metavar="N",
                   help="fast renderer threads inside a call (0 to 256; default: --threads; 0 = all cores)")
    add_sites_arg(p, "measure only these configured sites (simulation.sites of both configs)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value of both configs (open and closed loop), e.g. --set "
                        "emulator.threshold=0.15 (repeatable)")
    p.add_argument("--campaign-preset", default="montecarlo_efference", metavar="CONFIG",
                   help="campaign part: the preset flown (default montecarlo_efference)")
    p.add_argument("--campaign-estimator", default="cmax", metavar="NAME",
                   help="campaign part: the estimator (default cmax)")
    p.add_argument("--campaign-runs", default=None, metavar="SEEDSxT_MAX,...",
                   help="campaign part: the batches measured, seeds per site and setting x timeout in s "
                        "(empty = the preset's), e.g. '7x60,1x' (the default; --quick: '1x30')")
    p.add_argument("--no-compact", action="store_true",
                   help="campaign part: simulation.compact=false (finished descents' events reach the estimator)")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.set_defaults(func=run)


def parse_campaign_runs(text):
    """``'7x60,1x'`` -> ((7, 60.0), (1, None)); None stays None.

    Raises:
        ValueError: an entry that is not SEEDSxT_MAX with SEEDS >= 1 and T_MAX > 0 (or empty).
    """
    if text is None:
        return None
    runs = []
    for part in (p.strip() for p in str(text).split(",") if p.strip()):
        seeds, _, t_max = part.partition("x")
        try:
            n, t = int(seeds), (float(t_max) if t_max.strip() else None)
        except ValueError:
            n, t = 0, None
        if n < 1 or (t is not None and not t > 0):
            raise ValueError(f"--campaign-runs: expected SEEDSxT_MAX entries with SEEDS >= 1 and T_MAX > 0 s "
                             f"or empty (e.g. '7x60,1x'), got {part!r}")
        runs.append((n, t))
    if not runs:
        raise ValueError("--campaign-runs: give at least one SEEDSxT_MAX entry, e.g. '7x60,1x'")
    return tuple(runs)


def run(args) -> int:
    from dvsland.bench import run_bench
    from dvsland.cli.common import check_device, parse_sites

    try:
        check_device(args.device, param="--device")
        runs = parse_campaign_runs(args.campaign_runs)
    except ValueError as exc:
        print(f"dvsland: error: {exc}", file=sys.stderr)
        return 2
    sites = parse_sites(args.sites)  # checked against the configs by run_bench, before its run folder
    threads = args.threads or 1
    render_threads = threads if args.render_threads is None else args.render_threads

    est = [e.strip() for e in args.estimators.split(",") if e.strip()] if args.estimators else None
    try:
        from dvsland.estimators.registry import check_estimator_names

        check_estimator_names(est)
    except ValueError as exc:
        print(f"dvsland: error: {exc}", file=sys.stderr)
        return 2
    command = "dvsland " + " ".join(sys.argv[1:]) if sys.argv and sys.argv[0].endswith("dvsland") else "dvsland bench"
    run_bench(args.what, quick=args.quick, device=args.device, out=args.out, config=args.config,
              closed_loop_config=args.closed_loop_config, docs=args.docs, threads=threads,
              render_threads=render_threads, estimators=est, command=command, overrides=args.overrides, sites=sites,
              log=(lambda *a, **k: None) if args.quiet else print,
              campaign=dict(preset=args.campaign_preset, estimator=args.campaign_estimator, runs=runs,
                            compact=not args.no_compact))
    return 0
