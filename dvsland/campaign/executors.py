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

import contextlib
import os
import signal
import sys
import threading
import time
from typing import Iterator, List, Optional, Tuple

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


#: what :class:`WorkerLostError` says to do next when the caller names nothing else
CAMPAIGN_HINT = ("resume with `dvsland campaign --resume RUN_DIR` and fewer --workers, a smaller --shard-seeds "
                 "or a lower simulation.max_memory_gb")


def _init_worker(parent_pid: int, slots=None, tune: bool = False) -> None:
    """Process-pool initializer: die with the driver, report shard progress into ``slots``, and keep
    freed memory as the driver does (``tune``: :func:`dvsland.allocator.tune_allocator`)."""
    _die_with_parent(parent_pid)
    if tune:
        from dvsland.allocator import tune_allocator

        tune_allocator()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the driver's Ctrl-C (it stops the pool), not ours
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    if slots is not None:
        from . import progress

        progress.install(slots)


def make_pool(workers: int, slots=None):
    """A spawned process pool of ``workers`` processes that die with this process; ``slots`` (a
    shared array, :class:`~.progress.StepBar`) receives their shards' progress."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from dvsland.allocator import tuned

    return ProcessPoolExecutor(max_workers=int(workers), mp_context=mp.get_context("spawn"),
                               initializer=_init_worker, initargs=(os.getpid(), slots, tuned()))


@contextlib.contextmanager
def _sigint_blocked():
    """SIGINT blocked in this thread inside the block, so processes spawned here start with it
    blocked (a terminal's Ctrl-C reaches the whole process group: a worker importing its modules
    printed a KeyboardInterrupt traceback). The driver still gets it: another thread takes it, or
    it waits until the block ends. The resource tracker of multiprocessing starts the same way."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    from multiprocessing import resource_tracker

    # first: starting the tracker unblocks SIGINT in this thread when it is done (its own trick)
    resource_tracker.ensure_running()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


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
        proc.join(timeout=2.0)


def map_pool(fn, calls: List[tuple], workers: int, tick=None, slots=None,
             hint: str = CAMPAIGN_HINT) -> Iterator[Tuple[int, object]]:
    """``fn(*call)`` for each of ``calls`` in a pool of ``workers`` spawned processes, yielding
    ``(index, result)`` as each completes: the one worker lifetime of every dvsland pool.

    - Workers die with the driver, SIGKILL included (:func:`_die_with_parent`).
    - Workers start with SIGINT blocked, and are started with the driver's interrupts held back
      (:func:`dvsland.runs.deferred_interrupts`), so a Ctrl-C while they start is the driver's
      alone: no worker is half-started (its traceback, EOFError or KeyboardInterrupt, on the
      terminal) or unknown to the driver (left running after it).
    - Ctrl-C, SIGTERM, a failing call or the consumer closing the generator: the workers are
      killed and reaped at once (a finished result is already with the driver; nothing of a
      killed one is kept). A worker that dies (the OOM killer) is a :class:`WorkerLostError`
      ending with ``hint``.
    - ``tick()`` is called about every 0.25 s while waiting (a progress bar's refresh); ``slots``
      are given to the workers (:mod:`.progress`).
    """
    from concurrent.futures import FIRST_COMPLETED, wait

    from dvsland.runs import deferred_interrupts

    pool = None
    try:
        with deferred_interrupts(), _sigint_blocked():
            pool = make_pool(min(int(workers), len(calls)) or 1, slots)  # no idle processes
            futs = {pool.submit(fn, *call): i for i, call in enumerate(calls)}
        pending = set(futs)
        while pending:
            done, pending = wait(pending, timeout=0.25 if tick is not None else None, return_when=FIRST_COMPLETED)
            for f in sorted(done, key=futs.get):
                yield futs[f], _result(f, hint)
            if tick is not None:
                tick()
    except BaseException:
        # Ctrl-C / SIGTERM / a failing shard: stop now. Waiting for the running shards (minutes
        # each) would leave the command deaf to the interrupt; finished shards are already on
        # disk, and a resume runs the rest. A second Ctrl-C waits until the workers are reaped.
        with deferred_interrupts():
            if pool is not None:
                _stop_pool(pool)
        raise
    pool.shutdown(wait=True)


def run_local(config: dict, shards: List[dict], workers: int = 1, keep_dirs: Optional[List[Optional[str]]] = None,
              bar=None) -> Iterator[dict]:
    """Shards one after another (``workers <= 1``) or in a process pool of ``workers`` processes
    (spawned: no fork of a torch process, :func:`map_pool`), yielding results as they complete.
    ``bar``: a :class:`~.progress.StepBar` over ``shards`` (slot i = shard i) that follows their steps."""
    from . import progress

    keep_dirs = keep_dirs or [None] * len(shards)
    slot = (lambda i: i) if bar is not None else (lambda i: None)
    if workers <= 1:
        progress.install(bar.slots if bar is not None else None, bar.refresh if bar is not None else None)
        try:
            for i, (sh, kd) in enumerate(zip(shards, keep_dirs)):
                yield run_shard(config, sh, kd, progress_slot=slot(i))
        finally:
            progress.install(None)
        return
    calls = [(config, sh, kd, 1, slot(i)) for i, (sh, kd) in enumerate(zip(shards, keep_dirs))]
    for _, res in map_pool(run_shard, calls, workers, tick=bar.refresh if bar is not None else None,
                           slots=bar.slots if bar is not None else None):
        yield res


def _result(fut, hint: str = CAMPAIGN_HINT):
    """``fut.result()``, with a worker that died (BrokenProcessPool) as one :class:`WorkerLostError`."""
    from concurrent.futures.process import BrokenProcessPool

    try:
        return fut.result()
    except BrokenProcessPool as exc:
        raise WorkerLostError("a worker process was killed before finishing its shard (most often by the "
                              "system's out-of-memory killer: `dmesg | grep -i killed`); finished shards are "
                              f"kept: {hint}") from exc


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
