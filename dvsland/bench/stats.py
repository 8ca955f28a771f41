"""Small statistics of the benchmark report."""

from __future__ import annotations

import math
from typing import Tuple


def wilson_interval(successes: int, n: int, z: float = 1.959963984540054) -> Tuple[float, float]:
    """Wilson score interval of a binomial proportion (default 95 %).

    Args:
        successes: k, 0 <= k <= n.
        n: number of trials, >= 0 (n = 0 gives (0, 1): nothing is known).
        z: standard-normal quantile (1.96 for 95 %).

    Returns:
        (low, high), both in [0, 1].
    """
    k, n = int(successes), int(n)
    if n < 0 or k < 0 or k > n:
        raise ValueError(f"need 0 <= successes <= n, got successes={successes}, n={n}")
    if z <= 0:
        raise ValueError(f"z must be > 0, got {z}")
    if n == 0:
        return 0.0, 1.0
    p = k / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    lo = 0.0 if k == 0 else max(0.0, centre - half)  # exact at the ends (no rounding residue)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return lo, hi
