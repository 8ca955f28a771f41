"""A reaper for the processes a driver starts but cannot take down when it is killed (Linux).

``ray.init()`` starts a local Ray instance: GCS server, raylet, workers, and agents that the raylet
starts in turn. When the driver ends normally, ``ray.shutdown()`` stops them. When the driver is
killed (SIGKILL, the OOM killer), Ray stops its own core processes, but its dashboard and
runtime-env agents stay behind, reparented to init (measured: both were still running minutes
later).

:func:`start_reaper` starts a small watcher process in its own session. While the driver lives it
notes the driver's descendants (pid and start time, from ``/proc``) every ``poll_s``; once the
driver is gone it SIGKILLs those still running (the start time guards against a reused pid) and
ends. A driver that ends normally stops the reaper with :func:`stop_reaper`.

Run as ``python path/to/reaper.py DRIVER_PID [POLL_S]`` (stdlib only: it imports no dvsland).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, Optional

#: seconds between two looks at the driver and its descendants
POLL_S = 0.5


def _stat(pid: int):
    """(ppid, start time in clock ticks) of ``pid`` from /proc, or None when it is gone."""
    try:
        raw = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = raw[raw.rindex(")") + 2:].split()  # after "pid (comm) ": state ppid ...
    return int(fields[1]), int(fields[19])


def descendants(root_pid: int) -> Dict[int, int]:
    """{pid: start time} of every live descendant of ``root_pid`` (not the root itself)."""
    children: Dict[int, list] = {}
    starts: Dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        st = _stat(int(entry))
        if st is not None:
            children.setdefault(st[0], []).append(int(entry))
            starts[int(entry)] = st[1]
    out, todo = {}, list(children.get(root_pid, []))
    while todo:
        pid = todo.pop()
        if pid not in out:
            out[pid] = starts[pid]
            todo.extend(children.get(pid, []))
    return out


def _alive(pid: int, start: Optional[int] = None) -> bool:
    st = _stat(pid)
    return st is not None and (start is None or st[1] == start)


def watch(driver_pid: int, poll_s: float = POLL_S) -> int:
    """The reaper's loop; returns the number of processes it killed."""
    me = os.getpid()
    seen: Dict[int, int] = {}
    driver_start = _stat(driver_pid)
    while driver_start is not None and _alive(driver_pid, driver_start[1]):
        seen.update(descendants(driver_pid))
        seen.pop(me, None)
        seen = {p: s for p, s in seen.items() if _alive(p, s)}
        time.sleep(poll_s)
    killed = 0
    for pid, start in seen.items():
        if _alive(pid, start):
            try:
                os.kill(pid, signal.SIGKILL)
                killed += 1
            except OSError:
                pass
    return killed


def start_reaper(driver_pid: Optional[int] = None, poll_s: float = POLL_S) -> Optional[subprocess.Popen]:
    """Start the reaper of ``driver_pid`` (default: this process); None where there is no /proc."""
    if not Path("/proc/self/stat").exists():
        return None
    driver_pid = os.getpid() if driver_pid is None else int(driver_pid)
    # the file alone (stdlib only), not the package: no torch import, a few MB of memory
    return subprocess.Popen([sys.executable, str(Path(__file__).resolve()), str(driver_pid), str(poll_s)],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


def stop_reaper(proc: Optional[subprocess.Popen]) -> None:
    """Stop a reaper whose driver ended normally (its processes are already shut down)."""
    if proc is None:
        return
    proc.kill()
    proc.wait()


if __name__ == "__main__":
    watch(int(sys.argv[1]), float(sys.argv[2]) if len(sys.argv) > 2 else POLL_S)
