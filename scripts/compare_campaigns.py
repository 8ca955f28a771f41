"""Compare two campaigns of the same descents site by site: success rates with the 95 % interval of
their difference (Newcombe's hybrid score), and landing speeds (median |v| of the successes, with
the Mann-Whitney U test's p-value).

    python scripts/compare_campaigns.py logs/before logs/after [--markdown]

A difference interval that holds 0 and a large p-value mean the two campaigns agree at that level.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy.stats import mannwhitneyu

from dvsland.report.stats import difference_interval


def per_site(run_dir: Path) -> dict:
    """{site: (successes, n, landing speeds of the successes)} of a campaign's results.json."""
    runs = json.loads((Path(run_dir) / "results.json").read_text())["runs"]
    out = defaultdict(lambda: [0, 0, []])
    for r in runs:
        s = out[r["site"]]
        s[1] += 1
        if r["outcome"] == "success":
            s[0] += 1
            s[2].append(abs(float(r["v_end_mps"])))
    return dict(out)


def rows(before: dict, after: dict) -> list:
    """One row per site: rates, the difference's interval, median speeds and the U test's p."""
    res = []
    for site in sorted(set(before) | set(after)):
        k1, n1, v1 = before.get(site, (0, 0, []))
        k2, n2, v2 = after.get(site, (0, 0, []))
        lo, hi = difference_interval(k1, n1, k2, n2)
        p = float(mannwhitneyu(v1, v2).pvalue) if len(v1) >= 2 and len(v2) >= 2 else float("nan")
        res.append({"site": site, "before": f"{k1}/{n1}", "after": f"{k2}/{n2}", "diff_lo": round(lo, 3),
                    "diff_hi": round(hi, 3), "agree": bool(lo <= 0 <= hi),
                    "v_before": round(float(np.median(v1)), 2) if v1 else None,
                    "v_after": round(float(np.median(v2)), 2) if v2 else None, "v_p": round(p, 3)})
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--markdown", action="store_true")
    a = ap.parse_args(argv)
    rs = rows(per_site(Path(a.before)), per_site(Path(a.after)))
    if not a.markdown:
        for r in rs:
            print(json.dumps(r))
        return 0
    print("| site | success before | success after | after - before, 95 % | median landing speed before / after, m/s | "
          "Mann-Whitney p |\n|---|---|---|---|---|---|")
    for r in rs:
        print(f"| {r['site']} | {r['before']} | {r['after']} | [{r['diff_lo']:+.2f}, {r['diff_hi']:+.2f}] | "
              f"{r['v_before']} / {r['v_after']} | {r['v_p']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
