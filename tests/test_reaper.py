"""The reaper: processes a killed driver started (a local Ray instance's agents) do not outlive it."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dvsland.campaign.reaper import descendants, start_reaper

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] not in "ZX"
    except (OSError, IndexError):
        return False


def _wait_dead(pids, timeout_s: float) -> list:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and any(_alive(p) for p in pids):
        time.sleep(0.1)
    return [p for p in pids if _alive(p)]


#: a driver that starts a reaper, then a grandchild in a session of its own (as Ray's agents are:
#: started by a child, reparented to init when that child dies), and prints the grandchild's pid
_DRIVER = r"""
import subprocess, sys, time
from dvsland.campaign.reaper import start_reaper
start_reaper(poll_s=0.1)
time.sleep(1.0)
mid = subprocess.Popen([sys.executable, "-c",
    "import subprocess, sys, time; p = subprocess.Popen(['sleep', '600'], start_new_session=True); "
    "print(p.pid, flush=True); time.sleep(600)"], stdout=subprocess.PIPE)
print(mid.stdout.readline().decode().strip(), mid.pid, flush=True)
time.sleep(600)
"""


def test_a_killed_drivers_descendants_are_killed():
    drv = subprocess.Popen([sys.executable, "-c", _DRIVER], stdout=subprocess.PIPE, cwd=REPO)
    pids = [int(p) for p in drv.stdout.readline().split()]
    try:
        assert len(pids) == 2 and all(_alive(p) for p in pids)
        time.sleep(0.5)  # the reaper has seen them
        drv.send_signal(signal.SIGKILL)
        drv.wait(10)
        assert _wait_dead(pids, 10.0) == []
    finally:
        drv.kill()
        for p in pids:
            try:
                os.kill(p, signal.SIGKILL)
            except OSError:
                pass


def test_a_reaper_of_a_living_driver_kills_nothing_and_stops():
    child = subprocess.Popen(["sleep", "30"])
    reaper = start_reaper(poll_s=0.1)
    try:
        time.sleep(0.5)
        assert child.pid in descendants(os.getpid()) and reaper.pid in descendants(os.getpid())
        assert reaper.poll() is None and _alive(child.pid)
    finally:
        reaper.kill()
        reaper.wait()
        child.kill()
        child.wait()


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="needs the ray extra")
def test_ray_campaign_leaves_no_process_after_sigkill(tmp_path):
    """SIGKILL of `campaign --executor ray` left Ray's dashboard and runtime-env agents running."""
    env = {**os.environ, "PYOPENGL_PLATFORM": "egl", "EGL_PLATFORM": "surfaceless"}
    drv = subprocess.Popen([sys.executable, "-m", "dvsland.cli.main", "campaign", "paper", "--executor", "ray",
                            "--workers", "2", "--n-seeds", "4", "--sites", "A,B", "--quiet", "--out",
                            str(tmp_path / "c")], env=env, cwd=REPO, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    try:
        end = time.monotonic() + 120
        while time.monotonic() < end:
            kids = descendants(drv.pid)
            names = [Path(f"/proc/{p}/cmdline").read_bytes() for p in kids if _alive(p)]
            if sum(b"run_shard" in n for n in names) >= 2:
                break
            time.sleep(0.5)
        kids = list(descendants(drv.pid))
        assert len(kids) >= 4, "Ray did not start"
        time.sleep(1.0)
        drv.send_signal(signal.SIGKILL)
        drv.wait(10)
        assert _wait_dead(kids, 30.0) == []
    finally:
        drv.kill()
