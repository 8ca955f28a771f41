"""Fit an estimator's post-hoc confidence calibration from one or several evaluation runs.

Each run folder comes from ``dvsland evaluate [CONFIG] --estimators NAME --calibration`` (which writes
its ``calibration_sample.npz``: D, D_hat, raw confidence and the events of every scored step); the
samples are pooled (e.g. several seeds), the table is fitted
(:func:`dvsland.estimators.calibrate.fit_calibration`) and written as JSON, ready for
``--set estimator.calibration=PATH``. With ``--judge RUN`` the table is also applied to held-out
runs (other seeds) and their coverage per site type is printed before and after. docs/estimators.md,
"Calibration report".

    python scripts/fit_calibration.py logs/evaluate-seed1 logs/evaluate-seed2 --estimator cmax \\
        --out cmax_realistic.json --judge logs/evaluate-seed0
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    from dvsland.estimators.calibrate import FEATURES, apply_calibration_np, params_from_json
    from dvsland.evaluate.calibration_report import _coverage_rows, _pct, fit_from_samples, format_fit, read_calibration_sample
    from dvsland.report.results import write_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="evaluation run folders (or calibration_sample.npz files) to fit on")
    ap.add_argument("--estimator", required=True, help="the estimator's label in those runs (e.g. cmax, learned)")
    ap.add_argument("--out", required=True, help="the table to write (.json)")
    ap.add_argument("--feature", default="events", choices=FEATURES,
                    help="per-step feature besides the confidence (default events: the window's event count; "
                         "structure: cmax's score above the noise floor)")
    ap.add_argument("--sigma-bins", type=int, default=8, help="bins of the raw predicted sigma (default 8)")
    ap.add_argument("--feature-bins", type=int, default=6, help="bins of the feature (default 6)")
    ap.add_argument("--min-count", type=int, default=40, help="fewest estimates of a cell fitted on its own (default 40)")
    ap.add_argument("--judge", nargs="*", default=[], help="held-out run folders to print the coverage of, before / after")
    args = ap.parse_args(argv)
    if not args.out.endswith(".json"):
        ap.error("--out must name a .json file")
    samples = [read_calibration_sample(r) for r in args.runs]
    obj = fit_from_samples(samples, args.estimator, feature=args.feature, sigma_bins=args.sigma_bins,
                           feature_bins=args.feature_bins, min_count=args.min_count)
    obj["fit"]["fitted_by"] = "scripts/fit_calibration.py " + " ".join(Path(r).name for r in args.runs)
    write_json(args.out, obj)
    print(format_fit(obj))
    params, _ = params_from_json(obj, "--out")
    import numpy as np

    for run in args.judge:
        s = read_calibration_sample(run)
        labels = [str(x) for x in np.asarray(s["labels"]).tolist()]
        i = labels.index(args.estimator)
        dh, c = s[f"d_hat_{i}"], s[f"confidence_{i}"]
        before = _coverage_rows(s["d_true"], dh, c, s["site"])
        after = _coverage_rows(s["d_true"], dh, apply_calibration_np(params, dh, c, s["n_events"],
                                                                     s.get(f"structure_{i}")), s["site"])
        print(f"held out: {run} (config {s['meta'].get('config')}, seed {s['meta'].get('seed')}): 1 sigma / 2 sigma "
              f"before -> after")
        for grp, b in before.items():
            a = after[grp]
            ok = "ok" if a["within_5_points"] else ""
            print(f"  {grp:<14} {_pct(b['cover_1sigma']):>7} / {_pct(b['cover_2sigma']):>7} -> "
                  f"{_pct(a['cover_1sigma']):>7} / {_pct(a['cover_2sigma']):>7} {ok}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
