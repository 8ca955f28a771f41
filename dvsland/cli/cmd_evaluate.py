"""``dvsland evaluate [CONFIG] [--estimators dpr,cmax] [--sites A,B,...] [--segment-steps N --stride S]
[--max-steps N] [--device cpu|cuda] [--threads N] [--calibration [--fit-calibration]] [--out DIR] [--set key=value ...]
[--quiet]``:
open-loop evaluation of divergence estimators on the evaluation event streams."""

from __future__ import annotations

from .common import (add_config_args, add_sites_arg, add_threads_arg, apply_threads, check_configured_sites,
                     config_from_args, parse_sites, ranged)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "evaluate", help="open-loop error and speed of divergence estimators on all sites",
        description="Render the closed-form oracle descent of every site, emulate its events, run the "
                    "estimators side by side and write evaluation.json, table.txt, traces.npz, "
                    "speed_vs_error.png, traces.png and TensorBoard files (tb/) into the run folder. Time per "
                    "update is process CPU ms (as dvsland bench; wall ms beside it; wall on CUDA); a trained "
                    "estimator (learned, snn) is named with its checkpoint file and SHA-256 everywhere. A full "
                    "run (9 sites, ~930 steps) takes minutes; --segment-steps 20 --stride 10 is a ~10x quicker "
                    "sample.")
    add_config_args(p)
    p.add_argument("--estimators", default="dpr,cmax", metavar="NAME,NAME",
                   help="estimators to compare (default dpr,cmax); a name may carry its own parameter "
                        "values to compare variants side by side, e.g. 'cmax[window_ms=300;n_grid=21]' = that "
                        "estimator with --set estimator.cmax.window_ms=300 --set estimator.cmax.n_grid=21 "
                        "(same typing and range checks; separate them with ';'); 'ALIAS=NAME' shows NAME (a "
                        "registered name, a spec or an import path 'package.module:Class') as ALIAS everywhere")
    add_sites_arg(p, "only these configured sites (simulation.sites)")
    p.add_argument("--segment-steps", type=ranged(int, 0, 100_000, "--segment-steps"), default=0, metavar="N",
                   help="split the descents into segments of N steps (0 = whole descents)")
    p.add_argument("--stride", type=ranged(int, 1, 100_000, "--stride"), default=1, metavar="S",
                   help="run every S-th segment (quick runs)")
    p.add_argument("--max-steps", type=ranged(int, 1, 10_000_000, "--max-steps"), default=None, metavar="N",
                   help="truncate the descents")
    p.add_argument("--warmup-steps", type=ranged(int, 0, 100_000, "--warmup-steps"), default=10, metavar="N",
                   help="steps at the start of each segment left out of the metrics (default 10)")
    p.add_argument("--device", default=None, metavar="DEVICE", help="torch device (default simulation.device)")
    add_threads_arg(p)
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--calibration", action="store_true",
                   help="also write the calibration report of every estimator: calibration.json, calibration.txt "
                        "(share of estimates inside the predicted 1 sigma / 2 sigma per site type, abstentions "
                        "apart; printed too) and calibration.png (reliability diagram, risk-coverage curve); "
                        "rendered descents only (docs/estimators.md); also calibration_sample.npz, the scored "
                        "steps (D, D_hat, confidence, events per window) that scripts/fit_calibration.py fits from")
    p.add_argument("--fit-calibration", action="store_true",
                   help="with --calibration: also fit each estimator's post-hoc confidence calibration on this "
                        "evaluation and write it as calibration_table_<estimator>.json (fly it with --set "
                        "estimator.calibration=PATH; judge it on other seeds; needs estimator.calibration=none)")
    p.add_argument("--scenarios", default=None, metavar="NAME,NAME",
                   help="hard scenarios flown after the descents, each a named segment of the report: "
                        "hover_start, slow_to_hover, feature_poor, noise_burst, 'all' or 'none' (default: all for "
                        "whole descents, none with --max-steps or --segment-steps; docs/estimators.md)")
    p.add_argument("--recording", default=None, metavar="PATH",
                   help="evaluate on a recorded event stream instead of rendered descents (.aedat4, .h5, .npz, "
                        ".npy tonic array, .csv); intervals of 1/camera.frame_rate_hz")
    p.add_argument("--ground-truth", default=None, metavar="PATH",
                   help="with --recording: ground-truth side file (CSV/npz: t_us or t_s, and divergence or "
                        "altitude_m + velocity_mps); not needed for files written by dvsland events, which carry "
                        "their per-frame ground truth")
    p.add_argument("--element", type=ranged(int, 0, 65_535, "--element"), default=0, metavar="B",
                   help="with --recording: the batch element b of a dvsland events file with several (dvsland "
                        "events --sites A,B writes b = 0, 1; default 0)")
    p.add_argument("--bin", default=None, metavar="F|dvs128",
                   help="with --recording: bin the pixels F x F (events at (x // F, y // F) of a W // F x H // F "
                        "sensor; a principal point in camera.principal_point_px moves with them), or 'dvs128' for "
                        "about the DVS128's pixel angle (60 deg / 128 px) from camera.fov_deg")
    p.add_argument("--t-unit", default=None, choices=("ns", "us", "ms", "s"),
                   help="with --recording: unit of the time column (default: integers = us, fractions = s)")
    p.set_defaults(func=run_evaluate)


def _split_estimators(text: str):
    """Split on commas outside [...]."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
        if ch == "," and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    out.append(cur)
    return [s.strip() for s in out if s.strip()]


def estimator_specs(text: str) -> list:
    """The ``--estimators`` list: each item as given (``dpr``, ``cmax[window_ms=300]``), or, for an
    item with an alias (``mine=pkg.mod:Class``, ``fast=dpr[baseline_steps=5]``), a tuple (alias,
    name, parameter overrides) so that the alias is its label in every table, JSON key, figure
    and TensorBoard folder. Labels must differ."""
    from dvsland.estimators.registry import split_alias
    from dvsland.evaluate.run import parse_estimator_spec

    out, labels = [], []
    for item in _split_estimators(text):
        alias, spec = split_alias(item)
        if alias is None:
            out.append(item)
            labels.append(parse_estimator_spec(item)[0])
        else:
            _, name, over = parse_estimator_spec(spec)
            out.append((alias, name, over))
            labels.append(alias)
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise ValueError(f"--estimators: {', '.join(dup)} named twice; give each its own alias (ALIAS=NAME)")
    return out


def _read_recording(cfg, args, specs):
    """The ``--recording`` file (with ``--ground-truth``, ``--t-unit``, ``--element``), read, binned
    (``--bin``) and its implied sizes checked (:func:`dvsland.evaluate.recording.check_recording_size`) before the run
    folder is made: a missing file is a ValueError naming the flag."""
    from dvsland.evaluate.recording import check_recording_size
    from dvsland.events import bin_recording, read_recording

    from .common import check_input_file

    check_input_file(args.recording, "--recording")
    if args.ground_truth is not None:
        check_input_file(args.ground_truth, "--ground-truth")
    recording = read_recording(args.recording, ground_truth=args.ground_truth, t_unit=args.t_unit, b=args.element)
    if args.bin is not None:
        recording = bin_recording(recording, _bin_factor(cfg, args.bin, recording.sensor_size))
    if len(recording.events):
        check_recording_size(cfg, recording, specs, args.max_steps)
    return recording


def _bin_factor(cfg, text: str, sensor_size) -> int:
    """``--bin``'s factor: an integer >= 1, or 'dvs128' (:func:`dvsland.evaluate.recording.dvs128_bin_factor`)."""
    from dvsland.evaluate.recording import dvs128_bin_factor

    W, H = sensor_size
    if str(text).strip().lower() == "dvs128":
        return dvs128_bin_factor(cfg, sensor_size)
    try:
        f = int(str(text).strip())
    except ValueError:
        f = 0
    if f < 1 or f > min(W, H):
        raise ValueError(f"--bin must be an integer in [1, {min(W, H)}] (the recording is {W} x {H} px) or "
                         f"'dvs128', got {text!r}")
    return f


def run_evaluate(args) -> int:
    from dvsland.config import dump_config
    from dvsland.evaluate import evaluate, format_table, write_outputs
    from dvsland.runs import make_run_dir

    sites = parse_sites(args.sites)  # before anything is loaded or written
    specs = estimator_specs(args.estimators)
    if args.recording and (args.sites or args.segment_steps or args.stride != 1 or args.scenarios):
        raise ValueError("--sites, --segment-steps, --stride and --scenarios select rendered descents; they do "
                         "not apply to --recording")
    if not args.recording and (args.ground_truth or args.t_unit or args.element or args.bin is not None):
        raise ValueError("--ground-truth, --t-unit, --element and --bin need --recording PATH")
    if args.element < 0:
        raise ValueError(f"--element must be >= 0, got {args.element}")
    if args.scenarios is not None:
        from dvsland.evaluate.scenarios import resolve_scenarios

        resolve_scenarios(args.scenarios)  # unknown names: an error before anything runs
    if args.fit_calibration and not args.calibration:
        raise ValueError("--fit-calibration needs --calibration")
    cfg = config_from_args(args)  # checks the device before the run folder exists
    _check_calibration_key(cfg, specs, args.fit_calibration)
    check_configured_sites(cfg, sites)
    apply_threads(cfg)  # --threads, else simulation.torch_threads (0 = torch's default)
    device = cfg.simulation.device
    recording = _read_recording(cfg, args, specs) if args.recording else None  # before the run folder
    run_dir = make_run_dir(cfg, args.out, kind="evaluate")
    quiet = bool(cfg.logging.quiet)
    if recording is not None:
        from dvsland.evaluate import evaluate_recording

        res = evaluate_recording(cfg, recording, specs, warmup_steps=args.warmup_steps, max_steps=args.max_steps,
                                 device=device, progress=not quiet)
    else:
        scen = args.scenarios if args.scenarios is not None else (
            "none" if args.max_steps or args.segment_steps else "all")
        res = evaluate(cfg, specs, sites, segment_steps=args.segment_steps,
                       stride=args.stride, max_steps=args.max_steps, warmup_steps=args.warmup_steps,
                       device=device, progress=not quiet, scenarios=scen)
    paths = write_outputs(res, run_dir, figures=not args.no_figures and cfg.logging.figures)
    table = format_table(res.summary)
    cal_table = None
    if args.calibration:
        from dvsland.evaluate.calibration_report import write_calibration

        cal_paths, cal_table = write_calibration(res, run_dir, figures=not args.no_figures and cfg.logging.figures)
        paths.update(cal_paths)
        paths.update(_write_calibration_fit(res, run_dir, cfg, args, specs, quiet))
    if cfg.logging.tensorboard:
        from dvsland.report.results import writes_under
        from dvsland.report.tensorboard import write_evaluation_tensorboard

        with writes_under(run_dir / "tb"):  # a full disk: one error naming the folder
            paths["tensorboard"] = write_evaluation_tensorboard(run_dir / "tb", res, dump_config(cfg), table)
    if not quiet:
        print(table)
        if cal_table is not None:
            print()
            print(cal_table)
        print(f"wrote {', '.join(str(p) for p in paths.values())}")
    print(f"run folder: {run_dir}")
    return 0


def _spec_names(specs) -> dict:
    """{label: estimator name} of the ``--estimators`` list."""
    from dvsland.evaluate.run import parse_estimator_spec

    out = {}
    for item in specs:
        if isinstance(item, tuple):
            out[item[0]] = item[1]
        else:
            label, name, _ = parse_estimator_spec(item)
            out[label] = name
    return out


def _spec_params(cfg, specs) -> dict:
    """{label: the estimator's parameters as it ran (its config section with the spec's overrides)}."""
    from dvsland.estimators.factory import estimator_params
    from dvsland.evaluate.run import parse_estimator_spec, variant_config

    out = {}
    for item in specs:
        label, name, over = item if isinstance(item, tuple) else parse_estimator_spec(item)
        try:
            out[label] = estimator_params(variant_config(cfg, name, over, label), name)
        except (ValueError, TypeError):  # a spec the evaluation itself refuses is reported there
            out[label] = {}
    return out


def _check_calibration_key(cfg, specs, fit: bool) -> None:
    """``estimator.calibration`` resolved for every estimator named, before the run folder exists
    (its errors name the key); ``--fit-calibration`` needs raw confidences."""
    from dvsland.estimators.calibrate import calibration_off, resolve_calibration
    from dvsland.estimators.factory import calibration_names

    value = getattr(cfg.estimator, "calibration", "none")
    for name in _spec_names(specs).values():
        for n in calibration_names(cfg, name):
            resolve_calibration(value, n)
    if fit and not calibration_off(value):
        raise ValueError(f"--fit-calibration fits raw confidences: run it with estimator.calibration=none "
                         f"(got {value!r})")


def _write_calibration_fit(res, run_dir, cfg, args, specs, quiet: bool) -> dict:
    """calibration_sample.npz and, with --fit-calibration, one calibration_table_<label>.json per
    estimator in the run folder; {kind: path}."""
    import re

    from dvsland.evaluate.calibration_report import (calibration_sample, fit_from_samples, format_fit,
                                                     write_calibration_sample)
    from dvsland.report.checkpoint import checkpoint_text
    from dvsland.report.results import write_json

    if getattr(res, "recording", None) is not None or not getattr(res, "confidence", None):
        return {}
    meta = {"config": cfg.name, "seed": int(cfg.simulation.seed), "overrides": list(args.overrides or []),
            "estimators": _spec_names(specs), "estimator_params": _spec_params(cfg, specs),
            "calibration": str(getattr(cfg.estimator, "calibration", "none")),
            "checkpoints": {k: checkpoint_text(v) for k, v in (getattr(res, "checkpoints", None) or {}).items()}}
    paths = {"calibration_sample": write_calibration_sample(res, run_dir, meta)}
    if not args.fit_calibration:
        return paths
    sample = dict(calibration_sample(res), meta=meta)
    for label in res.d_hat:
        obj = fit_from_samples([sample], label)
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", label)
        paths[f"calibration_table_{safe}"] = write_json(run_dir / f"calibration_table_{safe}.json", obj)
        if not quiet:
            print(format_fit(obj))
    return paths
