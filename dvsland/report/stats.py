"""Monte Carlo statistics of many descents: Wilson intervals and per-group summaries.

A group is every run sharing the same values of the ``by`` keys (by default site, controller
setting, estimator and any swept value). Per group: n, outcome counts, the success rate with its
95 % Wilson score interval, and median / IQR / p10-p90 of the lowest altitude, the velocity at
50 m (successful descents) and the fuel used.
"""

from __future__ import annotations

import math
from typing import Dict, Iterable, List, Optional, Sequence

import numpy as np

OUTCOME_ORDER = ("success", "crash", "ascent", "timeout", "interrupted")
#: run fields summarised per group -> column prefix
METRICS = {"lowest_altitude_m": "lowest_m", "v_at_50m_mps": "v50_mps", "fuel_used_kg": "fuel_kg"}
#: the default group keys (a run's "sweep" values are added after these)
GROUP_KEYS = ("site", "label", "estimator")


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple:
    """Wilson score interval of a binomial proportion: the one implementation in dvsland (campaign
    groups, the paper pattern and the benchmark's closed-loop table all use it).

    ``scipy.stats.binomtest(k, n).proportion_ci(method="wilson")``; at k = 0 the low end is exactly
    0 and at k = n the high end exactly 1.

    Args:
        successes: k, 0 <= k <= n.
        n: trials, >= 0. n = 0 gives (nan, nan): with no trials there is no rate (k / n is NaN
            too), and the strict JSON files write both as null.
        confidence: two-sided level in (0, 1).

    Returns:
        (low, high) as floats in [0, 1], or (nan, nan) for n = 0.

    Raises:
        ValueError: k or n negative, k > n, or confidence outside (0, 1).
    """
    if not (0 < confidence < 1):
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    k, n_ = int(successes), int(n)
    if k != successes or n_ != n or n_ < 0 or k < 0 or k > n_:
        raise ValueError(f"need integers 0 <= successes <= n, got successes={successes}, n={n}")
    if n_ == 0:
        return (math.nan, math.nan)
    from scipy.stats import binomtest

    ci = binomtest(k, n_).proportion_ci(confidence_level=confidence, method="wilson")
    lo = 0.0 if k == 0 else min(1.0, max(0.0, float(ci.low)))
    hi = 1.0 if k == n_ else min(1.0, max(0.0, float(ci.high)))
    return (lo, hi)


def difference_interval(k1: int, n1: int, k2: int, n2: int, confidence: float = 0.95) -> tuple:
    """Interval of the difference of two binomial proportions p2 - p1 (Newcombe's hybrid score
    interval, method 10 of Newcombe 1998, from the two :func:`wilson_interval` s): whether two
    campaigns' success rates differ. (nan, nan) when either n is 0.

    Returns:
        (low, high) floats in [-1, 1]; an interval that holds 0 means no difference at that level.
    """
    l1, u1 = wilson_interval(k1, n1, confidence)
    l2, u2 = wilson_interval(k2, n2, confidence)
    if math.isnan(l1) or math.isnan(l2):
        return (math.nan, math.nan)
    p1, p2 = k1 / n1, k2 / n2
    d = p2 - p1
    lo = d - math.sqrt((p2 - l2) ** 2 + (u1 - p1) ** 2)
    hi = d + math.sqrt((u2 - p2) ** 2 + (p1 - l1) ** 2)
    return (max(-1.0, lo), min(1.0, hi))


def _finite(values: Iterable[Optional[float]]) -> np.ndarray:
    """(n,) float64 of the finite entries of ``values`` (None, NaN and inf left out)."""
    return np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=np.float64)


def median(values: Iterable[Optional[float]]) -> Optional[float]:
    """The median of the finite entries of ``values`` (None, NaN, inf left out): the middle value,
    or the mean of the two middle values for an even count; None when none is finite. The one
    median of a campaign: the group table (:func:`group_stats`) and the campaign figure's median
    bars both use it, so they print and draw the same number."""
    a = _finite(values)
    return float(np.median(a)) if a.size else None


def _spread(values: Sequence[float]) -> Dict[str, Optional[float]]:
    a = _finite(values)
    if a.size == 0:
        return {"median": None, "q25": None, "q75": None, "p10": None, "p90": None}
    q = np.percentile(a, [25, 75, 10, 90])
    return {"median": median(a), "q25": float(q[0]), "q75": float(q[1]), "p10": float(q[2]), "p90": float(q[3])}


def group_key(run: dict, by: Sequence[str]) -> tuple:
    """The values of ``by`` for one run (missing keys give None); ``sweep.<key>`` reads the run's
    ``sweep`` dict. An estimator with an alias (``mine=pkg.mod:Class``) is its alias."""
    from dvsland.estimators.registry import estimator_label

    out = []
    for k in by:
        if k.startswith("sweep."):
            v = (run.get("sweep") or {}).get(k[len("sweep."):])
        else:
            v = run.get(k)
        if k in ("estimator", "sweep.estimator.name") and isinstance(v, str):
            v = estimator_label(v)  # 'mine=pkg.mod:Class' is shown (and grouped) as 'mine'
        out.append(v)
    return tuple(out)


def default_group_keys(runs: Iterable[dict]) -> List[str]:
    """GROUP_KEYS plus ``sweep.<key>`` for every swept key found in the runs (sorted)."""
    swept = sorted({k for r in runs for k in (r.get("sweep") or {})})
    return list(GROUP_KEYS) + [f"sweep.{k}" for k in swept if k != "estimator.name"]


def group_stats(runs: List[dict], by: Optional[Sequence[str]] = None, confidence: float = 0.95) -> List[dict]:
    """One summary dict per group of ``runs`` (in order of first appearance).

    Each dict: the ``by`` values, ``n``, ``n_<outcome>`` for every outcome, ``success_rate``,
    ``success_lo`` / ``success_hi`` (Wilson interval at ``confidence``), and for each metric of
    :data:`METRICS` its ``<prefix>_median``, ``_q25``, ``_q75``, ``_p10``, ``_p90`` (None when no
    run of the group has the value: e.g. the velocity at 50 m of a group that never got there).
    """
    by = list(by) if by is not None else default_group_keys(runs)
    groups: Dict[tuple, List[dict]] = {}
    for r in runs:
        groups.setdefault(group_key(r, by), []).append(r)
    out = []
    for key, rs in groups.items():
        row = dict(zip(by, key))
        n = len(rs)
        counts = {o: 0 for o in OUTCOME_ORDER}
        for r in rs:
            counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
        k = counts["success"]
        lo, hi = wilson_interval(k, n, confidence)
        row.update(n=n, **{f"n_{o}": c for o, c in counts.items()}, success_rate=k / n if n else math.nan,
                   success_lo=lo, success_hi=hi)
        for field, prefix in METRICS.items():
            for name, v in _spread([r.get(field) for r in rs]).items():
                row[f"{prefix}_{name}"] = v
        out.append(row)
    return out


def format_group_table(rows: List[dict], by: Sequence[str], markdown: bool = False) -> str:
    """The printed (or Markdown) table of :func:`group_stats` rows."""
    head = [k.replace("sweep.", "") for k in by] + ["n", "success", "95% CI", "crash", "ascent", "timeout",
                                                      "lowest_m med [p10,p90]", "v50_mps med [IQR]",
                                                      "fuel_kg med [IQR]"]

    def f(x, fmt):
        return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)

    body = []
    for r in rows:
        body.append([str(r.get(k)) for k in by] + [
            str(r["n"]), f(100 * r["success_rate"], ".0f") + " %",
            f"{f(100 * r['success_lo'], '.0f')}-{f(100 * r['success_hi'], '.0f')} %",
            str(r["n_crash"]), str(r["n_ascent"]), str(r["n_timeout"]),
            f"{f(r['lowest_m_median'], '.0f')} [{f(r['lowest_m_p10'], '.0f')},{f(r['lowest_m_p90'], '.0f')}]",
            f"{f(r['v50_mps_median'], '.2f')} [{f(r['v50_mps_q25'], '.2f')},{f(r['v50_mps_q75'], '.2f')}]",
            f"{f(r['fuel_kg_median'], '.0f')} [{f(r['fuel_kg_q25'], '.0f')},{f(r['fuel_kg_q75'], '.0f')}]"])
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        return "\n".join(lines + ["| " + " | ".join(b) + " |" for b in body])
    widths = [max(len(h), *(len(b[i]) for b in body)) if body else len(h) for i, h in enumerate(head)]
    fmt = "  ".join(f"{{:<{w}}}" if i < len(by) else f"{{:>{w}}}" for i, w in enumerate(widths))
    return "\n".join([fmt.format(*head), fmt.format(*["-" * w for w in widths])] + [fmt.format(*b) for b in body])


def write_csv(path, rows: List[dict]) -> None:
    """Write dict rows to CSV (union of keys, in first-seen order), atomically."""
    import csv
    import os
    from pathlib import Path

    path = Path(path)
    cols: List[str] = []
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in cols})
    os.replace(tmp, path)
