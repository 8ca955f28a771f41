"""``dvsland dataset build CONFIG --n-seeds N --out DIR [--sites A,D] [--shard-size S]
[--estimator NAME] [--workers K] [--compression gzip|lzf|none] [--max-shards M] [--set key=value ...]
[--quiet]``, ``dvsland dataset zoom CONFIG --n-descents N --out DIR [--steps K] [--d-range LO,HI]
[--z-range LO,HI] [--seed S] [--shard-size S]`` and ``dvsland dataset info DIR``: datasets of labelled
event windows (docs/learning.md).

``build`` flies dispersed descents through the closed loop (by default with the ``oracle``
estimator: the configured law and filter flown on the true divergence) and writes one sample per
control step and descent (the events since the previous step, with the true D, tau, z, v) into
resumable HDF5 shards and a manifest; the same command again resumes an interrupted build.
``zoom`` writes the same kind of dataset from procedural textures zoomed at known divergences over
a wide range (:mod:`dvsland.data.zoom`), through the config's pixel. ``info`` prints a folder's shards, samples, bytes per sample and samples per split.
"""

from __future__ import annotations

import sys

from .common import add_config_args, config_from_args, ranged


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "dataset", help="build or inspect a dataset of labelled event windows (for learning)",
        description="Datasets of event windows labelled with the true divergence, time to contact, altitude and "
                    "velocity, flown through the closed loop (docs/learning.md).")
    sub = p.add_subparsers(dest="dataset_command", metavar="ACTION")
    b = sub.add_parser("build", help="fly dispersed descents and write their event windows as resumable shards",
                       description="Fly CONFIG's sites x controller settings for --n-seeds seeds through the closed "
                                   "loop and write one sample per step and descent into DIR/shards/*.h5 with "
                                   "DIR/dataset.json. Re-running the same command resumes (complete shards are kept).")
    add_config_args(b)
    b.add_argument("--n-seeds", type=ranged(int, 1, 1_000_000, "--n-seeds"), required=True, metavar="N", help="seeds per site")
    b.add_argument("--sites", default=None, metavar="A,D", help="subset of the configured sites (default all)")
    b.add_argument("--shard-size", type=ranged(int, 1, 100_000, "--shard-size"), default=5, metavar="S", help="seeds per shard (default 5)")
    b.add_argument("--estimator", default="oracle", metavar="NAME",
                   help="estimator that flies the loop (default oracle: the true divergence; e.g. cmax for the "
                        "estimator's own closed-loop trajectories)")
    b.add_argument("--workers", type=ranged(int, 1, 256, "--workers"), default=1, metavar="K",
                   help="shards flown at once (local processes, 1 to 256)")
    b.add_argument("--compression", default="gzip", choices=("gzip", "lzf", "none"), help="HDF5 compression")
    b.add_argument("--max-shards", type=ranged(int, 1, 1_000_000, "--max-shards"), default=None, metavar="M", help="build at most M missing shards")
    b.set_defaults(func=run_build)
    z = sub.add_parser("zoom", help="event windows of procedural textures zoomed at known divergences",
                       description="Render a new procedural texture per descent (renderer 'textures': 1/f fields and "
                                   "sharp ellipses, none of the terrains), zoom it at a divergence going linearly from "
                                   "D0 to D1 (|D| log-uniform in --d-range), turn the frames into events through "
                                   "CONFIG's emulator, and write one sample per step and descent, in the format of "
                                   "'dataset build' (train with --data DIR). The same command again resumes.")
    add_config_args(z)
    z.add_argument("--n-descents", type=ranged(int, 1, 10_000_000, "--n-descents"), required=True, metavar="N")
    z.add_argument("--steps", type=ranged(int, 2, 100_000, "--steps"), default=40, metavar="K",
                   help="control steps per descent (default 40)")
    z.add_argument("--d-range", default="0.004,0.6", metavar="LO,HI", help="|D| range, 1/s (default 0.004,0.6)")
    z.add_argument("--z-range", default="150,6000", metavar="LO,HI", help="start altitude range, m (default 150,6000)")
    z.add_argument("--seed", type=ranged(int, 0, 2 ** 31 - 1, "--seed"), default=0, metavar="S")
    z.add_argument("--shard-size", type=ranged(int, 1, 100_000, "--shard-size"), default=50, metavar="S",
                   help="descents per shard (default 50)")
    z.add_argument("--compression", default="gzip", choices=("gzip", "lzf", "none"), help="HDF5 compression")
    z.set_defaults(func=run_zoom)
    i = sub.add_parser("info", help="shards, samples, bytes per sample and split sizes of a dataset folder")
    i.add_argument("folder", metavar="DIR")
    i.set_defaults(func=run_info)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def run_build(args) -> int:
    from dvsland.data import build_dataset

    if args.out is None:
        raise ValueError("dvsland dataset build: --out DIR is required (the dataset folder; the same DIR resumes)")
    cfg = config_from_args(args)
    try:
        res = build_dataset(cfg, n_seeds=args.n_seeds, out=args.out, sites=args.sites, shard_size=args.shard_size,
                            estimator=None, quiet=args.quiet, max_shards=args.max_shards,
                            compression=None if args.compression == "none" else args.compression,
                            workers=args.workers)
    except KeyboardInterrupt:
        from pathlib import Path

        from dvsland.data.manifest import manifest_path

        print(f"dvsland: dataset build interrupted; complete shards are kept in {args.out}: run the same command "
              "again to resume" if manifest_path(Path(args.out)).is_file() else
              "dvsland: dataset build interrupted before its dataset was started; nothing was written",
              file=sys.stderr, flush=True)
        return 130
    m = res.manifest
    n_done = sum(e["status"] == "complete" for e in m["shards"])
    rate = f", {res.samples_per_s:.0f} samples/s" if res.samples_per_s else ""
    bps = f", {res.bytes_per_sample:.0f} bytes/sample" if res.bytes_per_sample else ""
    print(f"{res.status}: {n_done}/{res.n_shards} shards ({res.n_shards_built} built now: "
          f"{res.n_samples_built} samples in {res.seconds:.1f} s{rate}{bps}) -> {res.root}")
    return 0 if res.status == "complete" else 1


def _pair(text: str, param: str) -> tuple:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{param} must be two numbers LO,HI, got {text!r}") from None
    return lo, hi


def run_zoom(args) -> int:
    from dvsland.data.zoom import ZoomRequest, build_zoom_dataset

    if args.out is None:
        raise ValueError("dvsland dataset zoom: --out DIR is required (the dataset folder; the same DIR resumes)")
    (d_lo, d_hi), (z_lo, z_hi) = _pair(args.d_range, "--d-range"), _pair(args.z_range, "--z-range")
    req = ZoomRequest(n_descents=args.n_descents, steps=args.steps, d_min=d_lo, d_max=d_hi, z_min=z_lo, z_max=z_hi,
                      seed=args.seed, shard_size=args.shard_size)
    m = build_zoom_dataset(config_from_args(args), req, args.out, quiet=args.quiet,
                           compression=None if args.compression == "none" else args.compression)
    n = sum(e.get("n_samples", 0) for e in m["shards"])
    print(f"complete: {len(m['shards'])} shards, {n} samples -> {args.out}")
    return 0


def run_info(args) -> int:
    from dvsland.data.info import dataset_info, format_info

    print(format_info(dataset_info(args.folder)))
    return 0
