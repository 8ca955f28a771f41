"""Run one shard (one batch through :func:`dvsland.simulate`) and return its runs.

The function is plain (no campaign state): the local process pool and Ray call it the same way,
and the driver writes the returned result into the campaign folder (so a shard computed on a
remote Ray node needs no shared file system).
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from typing import Optional

import numpy as np


def velocity_at_altitude(z_m: np.ndarray, v_mps: np.ndarray, altitude_m: float) -> np.ndarray:
    """Velocity (m/s) where each trace first reaches ``altitude_m``, linearly interpolated
    between the two bracketing rows; NaN where it never does.

    Args:
        z_m, v_mps: (rows, B) float traces (NaN rows after the end are ignored).
    """
    z = np.asarray(z_m, dtype=np.float64)
    v = np.asarray(v_mps, dtype=np.float64)
    rows, B = z.shape
    out = np.full(B, np.nan)
    below = np.where(np.isfinite(z), z <= altitude_m, False)
    hit = below.any(axis=0)
    first = np.argmax(below, axis=0)
    for b in np.nonzero(hit)[0]:  # host-side summary, once per run
        i = int(first[b])
        if i == 0:
            out[b] = v[0, b]
            continue
        z0, z1 = z[i - 1, b], z[i, b]
        w = 0.0 if z0 == z1 else (z0 - altitude_m) / (z0 - z1)
        out[b] = v[i - 1, b] + w * (v[i, b] - v[i - 1, b])
    return out


def run_shard(plan_config: dict, shard: dict, keep_dir: Optional[str] = None, threads: int = 1,
              progress_slot: Optional[int] = None) -> dict:
    """Fly one shard; return ``{"id", "sweep", "seed_offset", "n_seeds", "runs", "wall_time_s",
    "status", "host", "config_hash"}``. Each run gets ``sweep`` (the grid point) and
    ``v_at_50m_mps``; ``config_hash`` (:func:`~.plan.shard_hash`) names what the shard flew.

    Args:
        plan_config: the campaign's base config (plain dict).
        shard: a :class:`~dvsland.campaign.plan.Shard` as a dict.
        keep_dir: write the shard's run folder (config.yaml, results.json, traces.npz) here;
            None = a temporary folder, removed afterwards.
        threads: torch threads of this worker.
        progress_slot: report the steps flown into this slot after every step (:mod:`.progress`).
    """
    import torch

    from dvsland.sim import simulate

    from . import progress
    from .plan import Shard, config_from_dict, shard_hash

    sh = Shard(**shard)
    cfg = config_from_dict(plan_config, sh.overrides())
    torch.set_num_threads(max(1, int(threads)))
    t0 = time.perf_counter()
    if keep_dir is not None and os.path.isdir(keep_dir):  # a killed earlier try of this shard: start afresh
        import shutil

        shutil.rmtree(keep_dir)
    with tempfile.TemporaryDirectory(prefix="dvsland-shard-") as tmp:
        out = keep_dir if keep_dir is not None else os.path.join(tmp, sh.id)
        on_step = (None if progress_slot is None
                   else (lambda loop, _out: progress.report(progress_slot, loop.state.step)))
        res = simulate(cfg, out=out, quiet=True, on_step=on_step)
        alt = float(cfg.simulation.success_altitude_m)
        v50 = velocity_at_altitude(res.traces["z_m"], res.traces["v_mps"], alt)
    runs = []
    for b, r in enumerate(res.runs):
        r = dict(r)
        r["sweep"] = dict(sh.sweep)
        r["v_at_50m_mps"] = float(v50[b]) if math.isfinite(v50[b]) else None
        runs.append(r)
    return {"id": sh.id, "index": sh.index, "sweep": sh.sweep, "seed_offset": sh.seed_offset,
            "n_seeds": sh.n_seeds, "runs": runs, "status": res.status, "n_steps": res.n_steps,
            "wall_time_s": time.perf_counter() - t0, "host": os.uname().nodename,
            "config_hash": shard_hash(plan_config, shard)}
