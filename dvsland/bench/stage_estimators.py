#!/usr/bin/env python
"""Benchmark of the divergence estimators: time per ``update`` and the open-loop table.

1. Time per update for B = 18 and B = 256 (``--batch``) on CPU, and on CUDA when available, for
   ``dpr``, ``cmax`` and ``oracle`` (``--estimators``), fed synthetic zooming-blob events
   (``--events-per-element`` per 0.1 s step, default 2400: about the mean of the rendered
   sites A-G). Each estimator first runs ``--warmup`` steps (the DPR initialisation happens
   there; tracking steps are what is timed), then ``--steps`` timed steps; the median and the
   10th-90th percentiles are reported. DPR re-initialisation steps are included if they occur.
2. With ``--eval``: the open-loop evaluation of all nine sites (``dvsland.evaluate``), its table
   printed and written with JSON and figures into ``--out`` (default logs/bench-estimators-<stamp>).

On a shared machine wall-clock timings are inflated and noisy; torch intra-op threads compete
with other processes (``--threads 1`` is often faster then). The "cpu ms" column is the process
CPU time of the update (``time.process_time``): with one thread it is close to the wall time the
update would take on an idle core.

Usage::

    python scripts/bench_estimators.py                          # timings
    python scripts/bench_estimators.py --threads 1 --eval       # + evaluation of the nine sites
    python scripts/bench_estimators.py --batch 18 --steps 20 --json out.json
"""

from __future__ import annotations

import argparse
import json
import shlex
import time
from typing import Callable, List, Optional

import numpy as np
import torch

from dvsland.config import load_config
from dvsland.estimators import Truth, make_estimator
from dvsland.evaluate.synthetic import blob_layout, zoom_blob_events


def _sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def time_estimator(cfg, name, B, device, steps, warmup, events_per_element, seed=0):
    """Median / p10 / p90 ms per update of estimator ``name`` for B elements."""
    W, H = cfg.camera.width_px, cfg.camera.height_px
    est = make_estimator(cfg, B, device, name=name)
    n_blobs = 60
    offsets = blob_layout(B, n_blobs, (W, H), extent=0.8, seed=seed)
    D = torch.full((B,), -0.1, dtype=torch.float64)
    z = torch.full((B,), 1000.0, dtype=torch.float64, device=device)
    truth = Truth(z, D.to(device) * z)
    per_blob = max(1, events_per_element // n_blobs)
    # events are drawn before timing (not part of the estimator's cost)
    evs = [zoom_blob_events(offsets, D, k * 100_000, (k + 1) * 100_000, (W, H), events_per_blob=per_blob,
                            sigma_px=0.7, seed=k, device=device) for k in range(warmup + steps)]
    times, cpu_times, reinit = [], [], 0
    for k, ev in enumerate(evs):
        _sync(device)
        t0 = time.perf_counter()
        c0 = time.process_time()
        d = est.update(ev, (k + 1) * 100_000, truth)
        _sync(device)
        if k >= warmup:
            times.append((time.perf_counter() - t0) * 1e3)
            cpu_times.append((time.process_time() - c0) * 1e3)
            rf = est.diagnostics().get("reinit")
            if rf is not None:
                reinit += int(rf.sum())
    finite = float(torch.isfinite(d).float().mean())
    q = np.percentile(times, [10, 50, 90])
    return dict(estimator=name, batch_size=B, device=str(device), steps=steps,
                events_per_step=int(sum(len(e) for e in evs[warmup:]) / steps),
                ms_median=float(q[1]), ms_p10=float(q[0]), ms_p90=float(q[2]),
                cpu_ms_median=float(np.median(cpu_times)), reinit_elements=reinit,
                finite_fraction=finite, threads=torch.get_num_threads())


def _evaluation_argv(args) -> List[str]:
    """The ``dvsland evaluate`` command line of ``--eval`` (with ``--eval-args``, ``--out``, ``--threads``)."""
    argv = ["evaluate", "--estimators", "dpr,dpr[pair_weighting=length],cmax"] + shlex.split(args.eval_args)
    if args.out:
        argv += ["--out", args.out]
    if args.threads:
        argv += ["--threads", str(args.threads)]
    return argv


def main(argv=None, run_command: Optional[Callable[[List[str]], int]] = None) -> int:
    """The benchmark's command line (``argv``, default ``sys.argv[1:]``).

    ``run_command`` runs a ``dvsland`` command line (``dvsland.cli.main.main``, which
    ``scripts/bench_estimators.py`` passes in): ``--eval`` needs it, since the bench sits below the
    command line and does not import it.
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=None, help="YAML config (default configs/paper.yaml)")
    ap.add_argument("--estimators", default="dpr,cmax,oracle")
    ap.add_argument("--batch", default="18,256", help="batch sizes, comma separated")
    ap.add_argument("--devices", default=None, help="default: cpu, plus cuda when available")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--warmup", type=int, default=8)
    ap.add_argument("--events-per-element", type=int, default=2400)
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--eval", action="store_true", help="also run the open-loop evaluation of all sites")
    ap.add_argument("--eval-args", default="", help="e.g. '--segment-steps 20 --stride 10' for a quick sample")
    ap.add_argument("--out", default=None, help="run folder of --eval")
    args = ap.parse_args(argv)
    if args.eval and run_command is None:
        ap.error("--eval runs `dvsland evaluate`: use scripts/bench_estimators.py --eval (or run the command)")
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    devices = args.devices.split(",") if args.devices else (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    rows = []
    print(f"{'estimator':<9} {'B':>4} {'device':<6} {'events/step':>11} {'median ms':>10} {'p10-p90 ms':>16} "
          f"{'cpu ms':>8} {'reinit':>6} {'finite':>6}")
    for dev in devices:
        for B in (int(b) for b in args.batch.split(",")):
            for name in args.estimators.split(","):
                steps = args.steps if (B <= 32 or name != "cmax" or dev != "cpu") else max(5, args.steps // 4)
                r = time_estimator(cfg, name, B, dev, steps, args.warmup, args.events_per_element)
                rows.append(r)
                print(f"{name:<9} {B:>4} {dev:<6} {r['events_per_step']:>11d} {r['ms_median']:>10.2f} "
                      f"{r['ms_p10']:>7.2f}-{r['ms_p90']:<8.2f} {r['cpu_ms_median']:>8.2f} "
                      f"{r['reinit_elements']:>6d} {r['finite_fraction']:>6.2f}",
                      flush=True)
    out = {"timings": rows, "torch_threads": torch.get_num_threads(), "torch": torch.__version__}
    if args.eval:
        run_command(_evaluation_argv(args))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
