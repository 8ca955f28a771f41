"""Where shards run: here one after another, in a local process pool, or on Ray.

An executor maps ``run_shard`` over shards and yields each result as it completes (any order);
the campaign driver writes every result to its own file as soon as it arrives.

Ray (``pip install dvsland[ray]``): ``ray.init()`` starts a local instance with ``workers`` CPUs,
or joins the cluster named by the ``RAY_ADDRESS`` environment variable (``ray start --head`` on
one node, ``ray start --address=HEAD:6379`` on the others; on SLURM, Ray's own
``ray start`` recipe in an sbatch script). Shard results travel back to the driver, so the
workers need no shared file system.
"""

from __future__ import annotations

import os
from typing import Iterator, List, Optional

from .shard import run_shard

EXECUTORS = ("local", "ray")


def ray_available() -> bool:
    """True when the optional ``ray`` package imports."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def run_local(config: dict, shards: List[dict], workers: int = 1, keep_dirs: Optional[List[Optional[str]]] = None
              ) -> Iterator[dict]:
    """Shards one after another (``workers <= 1``) or in a process pool of ``workers`` processes
    (spawned: no fork of a torch process), yielding results as they complete."""
    keep_dirs = keep_dirs or [None] * len(shards)
    if workers <= 1:
        for sh, kd in zip(shards, keep_dirs):
            yield run_shard(config, sh, kd)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    pool = ProcessPoolExecutor(max_workers=int(workers), mp_context=mp.get_context("spawn"))
    futs = [pool.submit(run_shard, config, sh, kd) for sh, kd in zip(shards, keep_dirs)]
    try:
        for f in as_completed(futs):
            yield f.result()
    except BaseException:
        # Ctrl-C / SIGTERM / a failing shard: stop now. Waiting for the running shards (minutes
        # each) would leave the campaign deaf to the interrupt; finished shards are already on
        # disk, and --resume runs the rest.
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.terminate()
        raise
    pool.shutdown(wait=True)


def run_ray(config: dict, shards: List[dict], workers: Optional[int] = None,
            keep_dirs: Optional[List[Optional[str]]] = None, address: Optional[str] = None) -> Iterator[dict]:
    """Shards as Ray tasks (one CPU each), yielding results as they complete.

    Args:
        workers: CPUs of a local Ray instance (ignored when joining a cluster).
        address: a cluster address; default ``$RAY_ADDRESS``; neither = a local instance.
    """
    try:
        import ray
    except ImportError as exc:
        raise ValueError("--executor ray needs Ray: pip install 'dvsland[ray]'") from exc
    keep_dirs = keep_dirs or [None] * len(shards)
    address = address or os.environ.get("RAY_ADDRESS") or None
    started = False
    if not ray.is_initialized():
        kw = {"address": address} if address else {"num_cpus": int(workers) if workers else None}
        ray.init(ignore_reinit_error=True, log_to_driver=False, include_dashboard=False, **kw)
        started = True
    try:
        task = ray.remote(num_cpus=1)(run_shard)
        cfg_ref = ray.put(config)
        pending = [task.remote(cfg_ref, sh, kd) for sh, kd in zip(shards, keep_dirs)]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    except BaseException:
        for ref in locals().get("pending", []) or []:
            try:
                ray.cancel(ref, force=True)
            except Exception:  # noqa: BLE001 - best effort
                pass
        raise
    finally:
        if started:
            ray.shutdown()
