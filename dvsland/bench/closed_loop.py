"""Closed-loop success rate of an estimator from a short fixed-seed batch, with its 95 % Wilson interval.

Each estimator flies the configured experiment (sites x controller settings x ``n_seeds``) once
with :func:`dvsland.simulate` (no TensorBoard, no figures; the run folder goes under ``out``).
The seeds are fixed (``simulation.seed``), so the figure is reproducible; it is a small sample,
hence the interval.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from dvsland.config import Config

from .stats import wilson_interval


def closed_loop_success(cfg: Config, estimator: str, out: Path, sites: Optional[Sequence[str]] = None,
                        n_seeds: int = 1, device="cpu", t_max_s: Optional[float] = None) -> Dict:
    """Fly one batch with ``estimator`` (a registered name or ``name[key=value;...]``).

    Args:
        cfg: base config (e.g. ``realistic``: 100 kN engine).
        estimator: spec; overrides in brackets go to ``estimator.<name>.<key>``.
        out: run folder of this simulation (created).
        sites: subset of sites (default all configured).
        n_seeds: seeds per site and setting.
        device: torch device.
        t_max_s: optional shorter timeout.

    Returns:
        dict: estimator, n, successes, success_rate, wilson95 [low, high], outcomes {outcome: count},
        wall_s, n_steps, sanitised_estimates (sum over descents).
    """
    from dvsland.evaluate.run import parse_estimator_spec
    from dvsland.sim import simulate

    from .tradeoff import config_with

    _, name, over = parse_estimator_spec(estimator)
    overrides = [f"estimator.{name}.{k}={v}" for k, v in over.items()]
    overrides += ["logging.tensorboard=false", "logging.figures=false", "logging.quiet=true",
                  f"simulation.n_seeds={int(n_seeds)}", f"estimator.name={name}"]
    if t_max_s is not None:
        overrides.append(f"simulation.t_max_s={float(t_max_s)}")
    vcfg = config_with(cfg, overrides)
    t0 = time.perf_counter()
    res = simulate(vcfg, sites=list(sites) if sites else None, device=device, out=Path(out), quiet=True)
    wall = time.perf_counter() - t0
    n = len(res.runs)
    k = sum(r["outcome"] == "success" for r in res.runs)
    lo, hi = wilson_interval(k, n)
    return dict(estimator=estimator, n=n, successes=k, success_rate=k / n if n else float("nan"),
                wilson95=[lo, hi], outcomes=res.outcome_counts(), wall_s=wall, n_steps=res.n_steps,
                sanitised_estimates=int(sum(r.get("sanitised_estimates", 0) for r in res.runs)),
                n_seeds=int(n_seeds), sites=list(sites) if sites else None)


def run_closed_loop(cfg: Config, estimators: Sequence[str], out: Path, device="cpu", quick: bool = True,
                    log=print) -> List[Dict]:
    """:func:`closed_loop_success` for each estimator spec; a failure is recorded, not raised."""
    rows = []
    for i, est in enumerate(estimators):
        folder = Path(out) / f"closed_loop_{i:02d}_{est.split('[')[0]}"
        try:
            r = closed_loop_success(cfg, est, folder, device=device, n_seeds=1 if quick else 2)
        except Exception as exc:  # noqa: BLE001 - one failing estimator must not end the report
            r = dict(estimator=est, failed=f"{type(exc).__name__}: {exc}")
        r["run_dir"] = folder.name
        rows.append(r)
        if "failed" in r:
            log(f"  {est:<40} failed: {r['failed']}")
        else:
            log(f"  {est:<40} {r['successes']:>3d}/{r['n']:<3d} land  95 % CI [{100 * r['wilson95'][0]:.0f}, "
                f"{100 * r['wilson95'][1]:.0f}] %  ({r['wall_s']:.1f} s)")
    return rows
