"""The printed summary table of a simulation: one line per descent, physical units in the
header, a legend that defines every column and outcome."""

from __future__ import annotations

from typing import List, Optional

from .checkpoint import checkpoint_text

#: (header, results.json key, definition) of every column, in order
COLUMNS = (
    ("run", "run", "site/controller setting (Kp in N/s, n = moving-average length)"),
    ("outcome", "outcome", "how the descent ended (see below)"),
    ("t_end [s]", "t_end_s", "flight time when it ended"),
    ("lowest [m]", "lowest_altitude_m", "lowest altitude reached"),
    ("v_end [m/s]", "v_end_mps", "vertical velocity when it ended (negative = descending)"),
    ("fuel [kg]", "fuel_used_kg", "propellant burnt"),
    ("max thrust", "max_thrust_n", "largest commanded thrust, in kN or MN"),
    ("λ [1/s]", "loop_gain", "the control law's loop gain: (tau) Eq. 2's Kp z0 / (m0 v0²), (div) the "
                             "divergence loop's Kp / (m z) at the end; λ dt > 1 (λ > 10 1/s at 10 Hz) means one "
                             "step over-corrects: the loop acts like a relay"),
    ("gain limit [m]", "gain_limit_altitude_m", "(div laws) the altitude below which that gain passes the "
                                                "sampled loop's limit"),
    ("held [steps]", "held_steps", "control steps without a usable filtered estimate (missing_policy applied)"),
)


def _f(x, fmt):
    return "-" if x is None else format(x, fmt)


def _gain(r) -> str:
    """Each law's own loop gain: tau-space lambda (tau_p) or Kp/(m z) at the end (div_p), 1/s."""
    g = _f(r.get("loop_gain"), ".3g")
    kind = r.get("loop_gain_kind")
    return g if g == "-" or not kind else f"{g} ({kind})"


def format_force(newton: Optional[float]) -> str:
    """A force with a readable unit: ``950 N``, ``100.0 kN``, ``212.3 MN``, ``1.2 GN``; ``-`` for None."""
    if newton is None:
        return "-"
    a = abs(newton)
    for scale, unit in ((1e9, "GN"), (1e6, "MN"), (1e3, "kN")):
        if a >= scale:
            return f"{newton / scale:.1f} {unit}"
    return f"{newton:.0f} N"


def outcome_legend(success_altitude_m: float = 50.0, crash_divergence: float = 0.5) -> str:
    """What each outcome means (the termination rules of the simulator)."""
    return (f"outcomes: success = reached z <= {success_altitude_m:g} m (v_end is the speed there); "
            f"crash = |D| = -v/z reached {crash_divergence:g} 1/s (too steep to stop; can happen high up) or z <= 0; "
            "ascent = v > 0 (climbing away); timeout = simulation.t_max_s reached")


def legend(success_altitude_m: float = 50.0, crash_divergence: float = 0.5) -> str:
    """The legend printed under the table: every column, then every outcome."""
    import textwrap

    cols = "columns: " + "; ".join(f"{h}: {d}" for h, _, d in COLUMNS)
    wrap = dict(width=110, subsequent_indent="  ", break_long_words=False)
    return "\n".join(textwrap.wrap(cols, **wrap) + textwrap.wrap(outcome_legend(success_altitude_m, crash_divergence),
                                                                  **wrap))


def format_table(runs: List[dict], markdown: bool = False, success_altitude_m: float = 50.0,
                 crash_divergence: float = 0.5, with_legend: bool = True) -> str:
    """One line per run: run, outcome, end time [s], lowest altitude [m], end velocity [m/s],
    fuel [kg], max thrust (kN or MN), the law's loop gain λ [1/s] (``tau``: Eq. 2's
    λ = Kp z0/(m0 v0²); ``div``: the divergence loop's Kp/(m z) at the end), for div laws the
    altitude below which that gain passes the sampled loop's limit, held steps; then the outcome
    counts and a legend that defines each column and outcome.

    Args:
        runs: the ``runs`` list of results.json.
        markdown: a Markdown table (for TensorBoard text and docs) instead of aligned text.
        success_altitude_m, crash_divergence: the termination thresholds, for the legend.
        with_legend: append the legend lines.
    """
    head = [h for h, _, _ in COLUMNS]
    rows = []
    for r in runs:
        rows.append([r.get("run", f"{r['site']}/{r['label']}"), r["outcome"], _f(r["t_end_s"], ".1f"),
                     _f(r["lowest_altitude_m"], ".1f"), _f(r["v_end_mps"], ".2f"), _f(r["fuel_used_kg"], ".0f"),
                     format_force(r["max_thrust_n"]), _gain(r), _f(r.get("gain_limit_altitude_m"), ".0f"),
                     str(r.get("held_steps", 0))])
    counts = {}
    for r in runs:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    count_line = "outcomes: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    cks = list(dict.fromkeys(checkpoint_text(r["checkpoint"]) for r in runs if r.get("checkpoint")))
    if cks:  # a trained estimator: which weights flew
        count_line += "; checkpoint " + ", ".join(cks)
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(row) + " |" for row in rows]
        if with_legend:
            lines += ["", count_line, "", *legend(success_altitude_m, crash_divergence).splitlines()]
        return "\n".join(lines)
    widths = [max(len(h), *(len(row[i]) for row in rows)) if rows else len(h) for i, h in enumerate(head)]
    fmt = "  ".join(f"{{:<{w}}}" if i < 2 else f"{{:>{w}}}" for i, w in enumerate(widths))
    lines = [fmt.format(*head), fmt.format(*["-" * w for w in widths])]
    lines += [fmt.format(*row) for row in rows]
    lines.append(count_line)
    if with_legend:
        lines += legend(success_altitude_m, crash_divergence).splitlines()
    return "\n".join(lines)
