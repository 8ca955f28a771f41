"""Benchmarks: speed against error, closed-loop success, scaling with B, and what each economy buys.

Public names: :func:`run_bench` (the ``dvsland bench`` command), :func:`time_stages` (ms per
control step of each stage for B descents), :func:`wilson_interval`, :func:`pareto_front`,
:func:`machine_info`. The stage benchmarks of single subsystems are the ``stage_*`` modules
(``scripts/bench_*.py`` wrap them).
"""

from .machine import machine_info
from .run import CHOICES, REPORT_PARTS, parse_what, run_bench
from .stages import time_stages
from .stats import wilson_interval
from .tradeoff import pareto_front

__all__ = ["run_bench", "parse_what", "CHOICES", "REPORT_PARTS", "time_stages", "wilson_interval", "pareto_front",
           "machine_info"]
