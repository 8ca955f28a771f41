"""Small statistics of the benchmark report.

The Wilson interval is :func:`dvsland.report.stats.wilson_interval` (scipy's; n = 0 gives
(nan, nan)), re-exported here for the benchmark's closed-loop table.
"""

from __future__ import annotations

from dvsland.report.stats import wilson_interval

__all__ = ["wilson_interval"]
