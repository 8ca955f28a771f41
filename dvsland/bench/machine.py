"""What a benchmark ran on: machine, CPU model, torch, device, threads, git commit, load."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Optional

import torch


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux, else ``platform.processor()``)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_commit() -> Optional[str]:
    """The commit of the dvsland source checkout (plus ``-dirty``), or None in an installed copy."""
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None
    try:
        sha = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (sha + ("-dirty" if dirty else "")) or None


def load_average() -> Optional[list]:
    """1, 5 and 15 minute load averages (None where the OS has none)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def machine_info(device) -> dict:
    """A JSON-ready description of where the numbers come from."""
    from dvsland import __version__

    dev = torch.device(device)
    info = {
        "machine": platform.machine(), "system": platform.platform(), "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(), "python": sys.version.split()[0], "torch_version": torch.__version__,
        "dvsland_version": __version__, "git_commit": git_commit(), "device": str(dev),
        "torch_threads": torch.get_num_threads(), "load_average": load_average(),
    }
    if dev.type == "cuda" and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(dev)
    return info
