"""Wilson interval and per-group statistics (dvsland.report.stats) against hand computations and scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dvsland.report.stats import default_group_keys, format_group_table, group_stats, wilson_interval


class TestWilson:
    def test_hand_computation(self):
        # k = 8, n = 10, z = 1.959964: p = 0.8; centre = (0.8 + z^2/20) / (1 + z^2/10);
        # half = z sqrt(0.016 + z^2/400) / (1 + z^2/10)  ->  (0.4902, 0.9433)
        z = 1.959963984540054
        d = 1 + z * z / 10
        c = (0.8 + z * z / 20) / d
        h = z * math.sqrt(0.8 * 0.2 / 10 + z * z / 400) / d
        lo, hi = wilson_interval(8, 10)
        assert lo == pytest.approx(c - h, abs=1e-12) and hi == pytest.approx(c + h, abs=1e-12)
        assert lo == pytest.approx(0.4902, abs=1e-4) and hi == pytest.approx(0.9433, abs=1e-4)

    @pytest.mark.parametrize("k,n", [(0, 5), (5, 5), (13, 18), (1, 50), (49, 50), (437, 900)])
    def test_against_scipy(self, k, n):
        stats = pytest.importorskip("scipy.stats")
        ci = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        lo, hi = wilson_interval(k, n)
        assert lo == pytest.approx(ci.low, abs=1e-12) and hi == pytest.approx(ci.high, abs=1e-12)

    @pytest.mark.parametrize("n", [1, 2, 7, 18, 1000])
    def test_ends_exact(self, n):
        """k = 0 starts at exactly 0, k = n ends at exactly 1, the other end is scipy's."""
        stats = pytest.importorskip("scipy.stats")
        lo, hi = wilson_interval(0, n)
        assert lo == 0.0 and hi == pytest.approx(stats.binomtest(0, n).proportion_ci(method="wilson").high, abs=1e-15)
        lo, hi = wilson_interval(n, n)
        assert hi == 1.0 and lo == pytest.approx(stats.binomtest(n, n).proportion_ci(method="wilson").low, abs=1e-15)
        assert isinstance(lo, float) and isinstance(hi, float)

    def test_one_implementation(self):
        from dvsland.bench import wilson_interval as bench_wilson

        assert bench_wilson is wilson_interval
        assert all(math.isnan(x) for x in bench_wilson(0, 0))

    def test_other_confidence(self):
        stats = pytest.importorskip("scipy.stats")
        ci = stats.binomtest(3, 9).proportion_ci(confidence_level=0.9, method="wilson")
        assert wilson_interval(3, 9, confidence=0.9) == pytest.approx((ci.low, ci.high), abs=1e-15)
        assert wilson_interval(3, 9, 0.9)[1] - wilson_interval(3, 9, 0.9)[0] < (
            wilson_interval(3, 9)[1] - wilson_interval(3, 9)[0])

    def test_edges_and_errors(self):
        assert all(math.isnan(x) for x in wilson_interval(0, 0))
        lo, hi = wilson_interval(0, 10)
        assert lo == 0.0 and 0 < hi < 0.35
        with pytest.raises(ValueError, match="successes"):
            wilson_interval(5, 3)
        with pytest.raises(ValueError, match="confidence"):
            wilson_interval(1, 3, confidence=1.5)
        with pytest.raises(ValueError, match="integers"):
            wilson_interval(1.5, 3)


def _runs():
    rng = np.random.default_rng(0)
    runs = []
    for site in "AB":
        for i in range(10):
            ok = i < (7 if site == "A" else 2)
            runs.append({"site": site, "label": "L", "estimator": "dpr", "outcome": "success" if ok else
                         ("crash" if i % 2 else "ascent"), "lowest_altitude_m": float(50 - i),
                         "v_at_50m_mps": float(-10 - i) if ok else None, "fuel_used_kg": float(rng.uniform(300, 400)),
                         "sweep": {"controller.thrust_max_n": "1e5"}})
    return runs


class TestGroups:
    def test_counts_rates_and_spread(self):
        runs = _runs()
        by = default_group_keys(runs)
        assert by == ["site", "label", "estimator", "sweep.controller.thrust_max_n"]
        rows = group_stats(runs, by)
        assert [r["site"] for r in rows] == ["A", "B"]
        a = rows[0]
        assert a["n"] == 10 and a["n_success"] == 7 and a["n_crash"] + a["n_ascent"] == 3
        assert a["success_rate"] == 0.7
        assert (a["success_lo"], a["success_hi"]) == wilson_interval(7, 10)
        lows = [50.0 - i for i in range(10)]
        assert a["lowest_m_median"] == pytest.approx(np.median(lows))
        assert a["lowest_m_p10"] == pytest.approx(np.percentile(lows, 10))
        v = [-10.0 - i for i in range(7)]  # only successes have a velocity at 50 m
        assert a["v50_mps_median"] == pytest.approx(np.median(v))
        assert a["v50_mps_q25"] == pytest.approx(np.percentile(v, 25))

    def test_group_without_values(self):
        runs = [{"site": "H", "label": "L", "estimator": "dpr", "outcome": "crash", "lowest_altitude_m": 90.0,
                 "v_at_50m_mps": None, "fuel_used_kg": 100.0}]
        row = group_stats(runs)[0]
        assert row["v50_mps_median"] is None and row["success_rate"] == 0.0
        text = format_group_table([row], ["site", "label", "estimator"])
        assert "H" in text and "0 %" in text
        md = format_group_table([row], ["site", "label", "estimator"], markdown=True)
        assert md.startswith("| site |")


def test_wilson_ends_are_exact_and_contain_the_rate():
    from dvsland.report.stats import wilson_interval

    for n in (1, 3, 6, 16, 50, 900):
        for k in (0, 1, n - 1, n):
            if not 0 <= k <= n:
                continue
            lo, hi = wilson_interval(k, n)
            assert lo <= k / n <= hi
        assert wilson_interval(0, n)[0] == 0.0 and wilson_interval(n, n)[1] == 1.0


def test_difference_interval_newcombe():
    from dvsland.report.stats import difference_interval

    lo, hi = difference_interval(48, 80, 56, 70)  # Newcombe (1998), 56/70 against 48/80, method 10: 0.0524 .. 0.3339
    assert (round(lo, 4), round(hi, 4)) == (0.0524, 0.3339)
    assert difference_interval(5, 10, 5, 10)[0] < 0 < difference_interval(5, 10, 5, 10)[1]
    lo, hi = difference_interval(0, 20, 20, 20)
    assert 0.6 < lo < hi <= 1.0
    assert all(v != v for v in difference_interval(0, 0, 3, 4))  # nan without trials


def test_median_is_the_one_median_of_the_table():
    """report.stats.median: the middle value, the mean of the middle two for an even count, None,
    NaN and inf left out, None when nothing is finite; group_stats' medians are this function's."""
    import math

    from dvsland.report.stats import group_stats, median

    assert median([3.0, 1.0, 2.0]) == 2.0
    assert median([4.0, 1.0, 3.0, 2.0]) == 2.5
    assert median([None, math.nan, 5.0, math.inf, 1.0]) == 3.0
    assert median([None, math.nan]) is None and median([]) is None
    vals = [2.12, 2.0, 2.06, 1.5]
    runs = [{"site": "A", "label": "s", "estimator": "dpr", "outcome": "success", "v_at_50m_mps": v,
             "lowest_altitude_m": 50.0 + v, "fuel_used_kg": 10 * v} for v in vals]
    (g,) = group_stats(runs)
    assert g["v50_mps_median"] == median(vals) and abs(g["v50_mps_median"] - 2.03) < 1e-12
    assert g["fuel_kg_median"] == median([10 * v for v in vals])
