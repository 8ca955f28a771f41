"""Ctrl-C and SIGTERM stop a command within 2 s even when its main thread is inside one long
native call (the interrupt watchdog), and the run folder says so."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from dvsland.watchdog import InterruptWatchdog

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals, Linux timings")

#: a guarded command whose main thread sits in one native call that never looks at signals: an
#: eigen-decomposition of a 3000 x 3000 matrix (tens of seconds on one thread; LAPACK releases the GIL)
STUCK = textwrap.dedent("""
    import os, sys
    os.environ["OPENBLAS_NUM_THREADS"] = os.environ["OMP_NUM_THREADS"] = "1"
    import numpy as np
    from dvsland.config import load_config
    from dvsland.runs import guarded_run, make_run_dir

    @guarded_run
    def command(out):
        make_run_dir(load_config("paper"), out)
        a = np.random.default_rng(0).random((3000, 3000))
        print("ready", flush=True)
        np.linalg.eigvals(a)
        return 0

    sys.exit(command(sys.argv[1]))
""")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_command_stuck_in_native_code_stops_within_2_s(tmp_path, sig):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-c", STUCK, str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "ready"
    time.sleep(0.2)
    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        proc.wait(timeout=10)
    finally:
        proc.kill()
    waited = time.monotonic() - t0
    err = proc.stderr.read()
    assert waited < 2.0, f"stopped after {waited:.1f} s"
    assert proc.returncode == 128 + sig, err
    assert "interrupted" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    res = json.loads((out / "results.json").read_text())
    assert res["status"] == "interrupted" and signal.Signals(sig).name in res["error"]
    assert (out / "config.yaml").is_file()


def test_a_responsive_command_is_not_ended_by_the_watchdog():
    """The handler ran (acknowledged): the watchdog leaves the process alone."""
    ended = []
    with InterruptWatchdog(ended.append, grace_s=0.3) as dog:
        old = signal.signal(signal.SIGINT, lambda s, f: dog.acknowledge())
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.8)
        finally:
            signal.signal(signal.SIGINT, old)
    assert ended == []


def test_grace_must_be_positive():
    with pytest.raises(ValueError, match="grace_s"):
        InterruptWatchdog(lambda s: None, grace_s=0)
