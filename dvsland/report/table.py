"""The printed summary table of a simulation."""

from __future__ import annotations

from typing import List


def _f(x, fmt):
    return "-" if x is None else format(x, fmt)


def _gain(r) -> str:
    """Each law's own loop gain: tau-space lambda (tau_p) or Kp/(m z) at the end (div_p), 1/s."""
    g = _f(r.get("loop_gain"), ".3g")
    kind = r.get("loop_gain_kind")
    return g if g == "-" or not kind else f"{g} ({kind})"


def format_table(runs: List[dict], markdown: bool = False) -> str:
    """One line per run: site, setting, outcome, end time, lowest altitude, fuel, max thrust, the law's
    loop gain (``tau``: Eq. 2's lambda = Kp z0/(m0 v0^2); ``div``: the divergence loop's Kp/(m z) at
    the end) and, for div_p, the altitude below which that gain passes the sampled loop's limit.

    Args:
        runs: the ``runs`` list of results.json.
        markdown: a Markdown table (for TensorBoard text and docs) instead of aligned text.
    """
    head = ["run", "outcome", "t_end_s", "lowest_m", "v_end_mps", "fuel_kg", "max_thrust_kN", "loop_gain",
            "gain_limit_m", "held"]
    rows = []
    for r in runs:
        rows.append([r.get("run", f"{r['site']}/{r['label']}"), r["outcome"], _f(r["t_end_s"], ".1f"),
                     _f(r["lowest_altitude_m"], ".1f"), _f(r["v_end_mps"], ".2f"), _f(r["fuel_used_kg"], ".0f"),
                     _f(None if r["max_thrust_n"] is None else r["max_thrust_n"] / 1e3, ".1f"),
                     _gain(r), _f(r.get("gain_limit_altitude_m"), ".0f"), str(r.get("held_steps", 0))])
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(row) + " |" for row in rows]
        return "\n".join(lines)
    widths = [max(len(h), *(len(row[i]) for row in rows)) if rows else len(h) for i, h in enumerate(head)]
    fmt = "  ".join(f"{{:<{w}}}" if i < 2 else f"{{:>{w}}}" for i, w in enumerate(widths))
    lines = [fmt.format(*head), fmt.format(*["-" * w for w in widths])]
    lines += [fmt.format(*row) for row in rows]
    counts = {}
    for r in runs:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    lines.append("outcomes: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    return "\n".join(lines)
