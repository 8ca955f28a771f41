#!/usr/bin/env python
"""What one step of the ``efference_fit`` filter costs on the CPU, with its compiled round terms and
with the torch path, after a history of L steps (the cost grows with the flight).

    OMP_NUM_THREADS=1 python scripts/bench_fit.py --batches 18,45 --lengths 300,1500 --repeat 20

The filter has ``configs/montecarlo_efference.yaml``'s settings (the estimator's confidence as noise,
gate 3, 3 rounds); the history holds noisy estimates of a constant divergence. Prints one row per
(B, L): ms per step, median of ``--rounds`` interleaved rounds of ``--repeat`` steps each.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch


def _filled(B: int, L: int):
    """A filter of B descents and its state after L steps of estimates."""
    from dvsland.control import EfferenceFitFilter

    g = torch.Generator().manual_seed(0)
    f64 = torch.float64
    z0 = 3000.0 + 2000.0 * torch.rand(B, generator=g, dtype=f64)
    v0 = -80.0 - 20.0 * torch.rand(B, generator=g, dtype=f64)
    f = EfferenceFitFilter(z0, v0, 0.1, prior_rel_sigma=0.06, prior_rel_sigma_v=0.03, meas_noise="confidence",
                           min_confidence=0.5, gate_sigma=3.0)
    st = f.init_state()
    zero = torch.zeros(B, dtype=f64)
    for k in range(L):
        d = v0 / z0 * (1.0 + 0.1 * torch.randn(B, generator=g, dtype=f64))
        st, _ = f.step_state(st, d, None, None if k == 0 else zero, None, torch.rand(B, generator=g, dtype=f64))
    return f, st, v0 / z0, zero, torch.full((B,), 0.9, dtype=f64)


def _time(f, st, d, zero, conf, repeat: int) -> float:
    t0 = time.perf_counter()
    for _ in range(repeat):
        f.step_state(st, d, None, zero, None, conf)
    return (time.perf_counter() - t0) / repeat * 1e3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", default="18,45")
    ap.add_argument("--lengths", default="300,1500")
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    from dvsland.control import native_fit

    if native_fit.LIBRARY.load() is None:
        print("the compiled terms are not available here (no C++ compiler?): only the torch path runs")
    print("| B | history L | torch path, ms/step | compiled terms, ms/step | ratio |\n|---|---|---|---|---|")
    with torch.no_grad():
        for B in (int(x) for x in a.batches.split(",")):
            for L in (int(x) for x in a.lengths.split(",")):
                f, st, d, zero, conf = _filled(B, L)
                times = {False: [], True: []}
                for _ in range(a.rounds):
                    for on in (False, True):
                        native_fit.use_native_fit(on)
                        times[on].append(_time(f, st, d, zero, conf, a.repeat))
                native_fit.use_native_fit(None)
                t_torch, t_native = statistics.median(times[False]), statistics.median(times[True])
                print(f"| {B} | {L} | {t_torch:.2f} | {t_native:.2f} | {t_torch / t_native:.1f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
