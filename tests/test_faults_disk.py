"""A disk that fills, or a folder that cannot be written, during a command: one line naming the path
(exit 2), never a traceback, and what was written before stays readable.

Two kinds of test: a real small file system (a tmpfs of a few kB, mounted where the test may mount
one: Linux as root; skipped elsewhere), and patched writers for the faults a test cannot make for
real (a read-only remount while files are open, a TensorBoard writer thread failing).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from dvsland.cli.main import main
from dvsland.report.results import RunWriteError, writes_under

FAST = ["--set", "simulation.t_max_s=3", "--set", "logging.quiet=true"]


@pytest.fixture
def small_disk():
    """A function ``make(size)`` -> a fresh folder on a tmpfs of ``size`` (e.g. ``"16k"``); unmounted after."""
    if not sys.platform.startswith("linux") or os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small tmpfs needs Linux and root")
    mounted = []

    def make(size: str) -> Path:
        point = Path(f"/tmp/dvsland-small-{uuid.uuid4().hex[:8]}")
        point.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(point)], capture_output=True)
        if r.returncode != 0:
            point.rmdir()
            pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
        mounted.append(point)
        return point

    yield make
    for point in mounted:
        subprocess.run(["umount", str(point)], capture_output=True)
        point.rmdir()


def _one_line_error(capsys, rc: int) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if "%|" not in ln]  # progress bars aside
    assert rc == 2, err
    assert "Traceback" not in err and len(lines) == 1, err
    assert "No space left on device" in lines[0] and "cannot write" in lines[0], err
    return lines[0]


# ------------------------------------------------------------------ a real full disk
@pytest.mark.parametrize("size", ["16k", "48k", "200k"])
def test_simulate_on_a_small_disk(small_disk, capsys, size):
    """At 16 kB TensorBoard's first file, at 48 kB its writer thread, at 200 kB a figure failed with
    tracebacks; each is now one line, and config.yaml is kept whenever it fit."""
    out = small_disk(size) / "run"
    rc = main(["simulate", "paper", "--sites", "A", "--out", str(out)] + FAST)
    _one_line_error(capsys, rc)
    assert (out / "config.yaml").is_file()
    if (out / "results.json").is_file():
        json.loads((out / "results.json").read_text())  # whole, never half a file


@pytest.mark.parametrize("size", ["16k", "60k"])
def test_evaluate_on_a_small_disk(small_disk, capsys, size):
    out = small_disk(size) / "e"
    rc = main(["evaluate", "paper", "--sites", "A", "--estimators", "dpr", "--max-steps", "20", "--out", str(out)]
              + FAST)
    _one_line_error(capsys, rc)


@pytest.mark.parametrize("size", ["24k", "400k"])
def test_dataset_build_on_a_small_disk(small_disk, capsys, size):
    """HDF5 on a full disk used to fail inside its own bookkeeping and the process died with a
    segmentation fault; the shard writer now checks the room before each block. (24 kB: room for
    the lock, config.yaml and dataset.json, two 4 kB pages each, and not for the shard.)"""
    out = small_disk(size) / "d"
    rc = main(["dataset", "build", "paper", "--sites", "A", "--n-seeds", "1", "--out", str(out)] + FAST)
    line = _one_line_error(capsys, rc)
    assert ".h5" in line
    assert not list(out.rglob("*.tmp*"))  # the half shard is removed


def test_render_on_a_small_disk(small_disk, capsys):
    out = small_disk("16k") / "r"
    rc = main(["render", "paper", "--sites", "A,B", "--out", str(out), "--quiet"])
    _one_line_error(capsys, rc)


# ------------------------------------------------------------------ patched faults
class _FailingLogger:
    """Stands in for TensorBoardLogger: its writer 'thread' failed (OSError on the next call)."""

    def __init__(self, *args, **kwargs):
        self.log_dir = Path(args[0])

    def add_config(self, text):
        pass

    def on_step(self, out):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    def close(self, *args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))


def test_tensorboard_on_a_read_only_folder_is_one_error(tmp_path, monkeypatch, capsys):
    """A TensorBoard write failing mid-flight (read-only remount): one line naming the tb folder,
    and the run folder keeps its config and a results.json saying what happened."""
    import dvsland.report.tensorboard as tb

    monkeypatch.setattr(tb, "TensorBoardLogger", _FailingLogger)
    out = tmp_path / "run"
    rc = main(["simulate", "paper", "--sites", "A", "--out", str(out), "--set", "logging.tensorboard=true"] + FAST)
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"{out / 'tb'}" in err and "EROFS" in err
    res = json.loads((out / "results.json").read_text())
    assert res["status"] == "interrupted" and "EROFS" in res["error"]


def test_a_disk_fault_nobody_converted_is_still_one_error(tmp_path, monkeypatch, capsys):
    """Any ENOSPC/EROFS/EDQUOT that reaches a command (a writer dvsland does not wrap) is one line
    naming the file the OS named."""
    import dvsland.report.figures as figures

    def full(*args, **kwargs):
        raise OSError(errno.EDQUOT, os.strerror(errno.EDQUOT), str(tmp_path / "run" / "figures" / "x.png"))

    monkeypatch.setattr(figures, "write_figures", full)
    rc = main(["simulate", "paper", "--sites", "A", "--out", str(tmp_path / "run"),
               "--set", "logging.figures=true"] + FAST)
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and "x.png" in err and "EDQUOT" in err, err


def test_program_errors_are_not_disguised_as_disk_faults(tmp_path, monkeypatch):
    """Only the disk's errnos are converted: a FileNotFoundError from a bug stays what it is."""
    import dvsland.report.figures as figures

    def missing(*args, **kwargs):
        raise FileNotFoundError(errno.ENOENT, "no such file", "/nonexistent/x")

    monkeypatch.setattr(figures, "write_figures", missing)
    with pytest.raises(FileNotFoundError):
        main(["simulate", "paper", "--sites", "A", "--out", str(tmp_path / "run"), "--set", "logging.figures=true"]
             + FAST)


def test_writes_under_names_the_folder(tmp_path):
    with pytest.raises(RunWriteError) as info:
        with writes_under(tmp_path / "tb"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert info.value.path == tmp_path / "tb" and info.value.errno == errno.ENOSPC


def test_figures_are_written_atomically(tmp_path, monkeypatch):
    """A figure that cannot be written leaves the previous PNG whole (it was written in place)."""
    from dvsland.report.style import pyplot, save_atomic

    plt = pyplot()
    fig = plt.figure()
    path = save_atomic(fig, tmp_path / "f.png")
    before = path.read_bytes()
    real_write = os.write

    def fail(fd, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "write", fail)
    with pytest.raises(RunWriteError):
        save_atomic(fig, path)
    monkeypatch.setattr(os, "write", real_write)
    plt.close(fig)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["f.png"]
