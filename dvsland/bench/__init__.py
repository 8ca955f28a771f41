"""Benchmarks: speed against error, closed-loop success, scaling with B, and what each economy buys.

Public names: :func:`run_bench` (the ``dvsland bench`` command), :func:`time_stages` (ms per
control step of each stage for B descents), :func:`wilson_interval`, :func:`pareto_front`,
:func:`machine_info`. The stage benchmarks of single subsystems are the ``stage_*`` modules
(``scripts/bench_*.py`` wrap them).
"""

from .parts import CHOICES, REPORT_PARTS, parse_what

_LAZY = {"run_bench": ".run", "time_stages": ".stages", "wilson_interval": ".stats", "pareto_front": ".tradeoff",
         "machine_info": ".machine"}


def __getattr__(name):  # the measuring modules load torch: imported on first use
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["run_bench", "parse_what", "CHOICES", "REPORT_PARTS", "time_stages", "wilson_interval", "pareto_front",
           "machine_info"]
