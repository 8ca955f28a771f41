"""dvsland.allocator: the command line keeps freed memory in the process (no fresh pages, so no page
faults, for the next step's large arrays). Each case runs in a fresh interpreter: the allocator is
process state, and the test process's own must stay as it is."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

_CHILD = r"""
import json, os, resource, sys
from dvsland.allocator import tune_allocator, tuned
done = tune_allocator() if sys.argv[1] == "tune" else {}
import torch

def faults_of_a_64mb_tensor():
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    x = torch.empty(8 * 2 ** 20, dtype=torch.float64)
    x.fill_(1.0)  # touch every page
    del x
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0

faults_of_a_64mb_tensor()  # the first one always pays its pages
print(json.dumps({"done": done, "tuned": tuned(), "faults": faults_of_a_64mb_tensor(),
                  "thp": os.environ.get("THP_MEM_ALLOC_ENABLE")}))
"""


def _run(mode: str, **env) -> dict:
    full = {k: v for k, v in os.environ.items() if k not in ("THP_MEM_ALLOC_ENABLE", "DVSLAND_KEEP_FREED_MEMORY")}
    full.update(env)
    out = subprocess.run([sys.executable, "-c", _CHILD, mode], capture_output=True, text=True, env=full, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_tuned_process_reuses_freed_memory():
    """A second 64 MB tensor: about 16,000 fresh pages without the tuning (4 KB pages, huge pages
    off), next to none with it (a few hundred faults of the interpreter's own can fall in the
    measured span on a loaded machine: CI once read 544, so the bound is a tenth of the plain run)."""
    plain = _run("plain", THP_MEM_ALLOC_ENABLE="0")
    assert plain["faults"] > 8000 and plain["tuned"] is False
    tuned = _run("tune")
    assert tuned["done"] == {"keep_freed": True, "huge_pages": True} and tuned["tuned"] is True
    assert tuned["faults"] < plain["faults"] / 10 and tuned["thp"] == "1"


def test_switches_off_and_an_explicit_choice_is_kept():
    off = _run("tune", DVSLAND_KEEP_FREED_MEMORY="0")
    assert off["done"] == {"keep_freed": False, "huge_pages": False} and off["thp"] is None
    no_thp = _run("tune", THP_MEM_ALLOC_ENABLE="0")
    assert no_thp["done"]["huge_pages"] is False and no_thp["thp"] == "0"
