"""Where shards run: here one after another, in a local process pool, or on Ray.

An executor maps ``run_shard`` over shards and yields each result as it completes (any order);
the campaign driver writes every result to its own file as soon as it arrives.

Ray (``pip install dvsland[ray]``): ``ray.init()`` starts a local instance with ``workers`` CPUs,
or joins the cluster named by the ``RAY_ADDRESS`` environment variable (``ray start --head`` on
one node, ``ray start --address=HEAD:6379`` on the others; on SLURM, Ray's own
``ray start`` recipe in an sbatch script). Shard results travel back to the driver, so the
workers need no shared file system.

Local workers die with their driver: each sets ``PR_SET_PDEATHSIG`` (Linux) and watches its
parent's pid, so a driver killed with SIGKILL (no clean-up of its own) leaves no worker running.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Iterator, List, Optional

from .reaper import start_reaper, stop_reaper
from .shard import run_shard

EXECUTORS = ("local", "ray")


def ray_available() -> bool:
    """True when the optional ``ray`` package imports."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


#: seconds between two checks of a worker that its driver is still alive
PARENT_POLL_S = 0.5


def _die_with_parent(parent_pid: int) -> None:
    """Process-pool initializer: end this worker as soon as its driver ``parent_pid`` is gone
    (SIGKILL included): the kernel's parent-death signal on Linux, and a thread that polls the
    parent pid everywhere (the signal follows the thread that started the worker)."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the driver died while this worker started
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True, name="dvsland-parent-watch").start()


def _watch_parent(parent_pid: int) -> None:
    while True:
        time.sleep(PARENT_POLL_S)
        if os.getppid() != parent_pid:
            os._exit(1)


class WorkerLostError(RuntimeError):
    """A pool worker ended without returning (killed: most often by the system's out-of-memory killer)."""


def make_pool(workers: int):
    """A spawned process pool of ``workers`` processes that die with this process."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(max_workers=int(workers), mp_context=mp.get_context("spawn"),
                               initializer=_die_with_parent, initargs=(os.getpid(),))


def _stop_pool(pool) -> None:
    """Cancel what has not started and terminate the workers now (no waiting for a shard)."""
    # the processes first: shutdown() forgets them (pool._processes = None), and a worker left
    # running kept the driver waiting at exit until its shard was flown (minutes)
    # SIGKILL: a worker writes its shard file atomically, so there is nothing to let it finish
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for proc in procs:
        proc.kill()
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        proc.join(timeout=1.0)


def run_local(config: dict, shards: List[dict], workers: int = 1, keep_dirs: Optional[List[Optional[str]]] = None
              ) -> Iterator[dict]:
    """Shards one after another (``workers <= 1``) or in a process pool of ``workers`` processes
    (spawned: no fork of a torch process), yielding results as they complete."""
    keep_dirs = keep_dirs or [None] * len(shards)
    if workers <= 1:
        for sh, kd in zip(shards, keep_dirs):
            yield run_shard(config, sh, kd)
        return
    from concurrent.futures import as_completed

    from dvsland.runs import deferred_interrupts

    pool = make_pool(min(int(workers), len(shards)) or 1)  # no idle processes
    try:
        futs = [pool.submit(run_shard, config, sh, kd) for sh, kd in zip(shards, keep_dirs)]
        for f in as_completed(futs):
            yield _result(f)
    except BaseException:
        # Ctrl-C / SIGTERM / a failing shard: stop now. Waiting for the running shards (minutes
        # each) would leave the campaign deaf to the interrupt; finished shards are already on
        # disk, and --resume runs the rest. A second Ctrl-C waits until the workers are told.
        with deferred_interrupts():
            _stop_pool(pool)
        raise
    pool.shutdown(wait=True)


def _result(fut) -> dict:
    """``fut.result()``, with a worker that died (BrokenProcessPool) as one :class:`WorkerLostError`."""
    from concurrent.futures.process import BrokenProcessPool

    try:
        return fut.result()
    except BrokenProcessPool as exc:
        raise WorkerLostError("a campaign worker process was killed before finishing its shard (most often by "
                              "the system's out-of-memory killer: `dmesg | grep -i killed`); finished shards are "
                              "kept: resume with `dvsland campaign --resume RUN_DIR` and fewer --workers, a smaller --shard-seeds or a lower "
                              "simulation.max_memory_gb") from exc


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
    started, reaper = False, None
    if not ray.is_initialized():
        kw = {"address": address} if address else {"num_cpus": int(workers) if workers else None}
        reaper = None if address else start_reaper()  # a killed driver leaves no local Ray process behind
        try:
            ray.init(ignore_reinit_error=True, log_to_driver=False, include_dashboard=False, **kw)
        except BaseException:
            stop_reaper(reaper)
            raise
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
        stop_reaper(reaper)
