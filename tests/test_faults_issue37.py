"""Regression tests of issue 37 (the old edges that remained): ``--controller ""``, config files
that are not UTF-8 or name a base the file system refuses, emulator rates that imply more events
than a step may emit, ``evaluate --recording`` with a missing or oversized recording, Ctrl-C
during the CLI's imports and a stale lock of the native build. Each test names the case it guards."""

from __future__ import annotations

import pytest

from dvsland.cli.main import main
from dvsland.config import ConfigError, load_config


# ------------------------------------------------------------------ 15. --controller ""
def test_empty_controller_flag_is_refused_not_dropped(tmp_path, capsys, monkeypatch):
    """``--controller ""`` silently flew the default law."""
    import dvsland.sim
    from dvsland.stages import check_names

    def fake_simulate(cfg, **kw):
        check_names(cfg)
        raise AssertionError(f"would fly controller {cfg.controller.name!r}")

    monkeypatch.setattr(dvsland.sim, "simulate", fake_simulate)
    assert main(["simulate", "--controller", "", "--quiet", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "controller.name" in err and "unknown controller ''" in err and "Traceback" not in err, err


# ------------------------------------------------------------------ 13. config files not UTF-8
@pytest.mark.parametrize("where", ["file", "base"])
@pytest.mark.parametrize("content", ["latin1", "binary"])
def test_config_not_utf8_names_the_file(tmp_path, where, content):
    """A Latin-1 or binary file (itself or its ``extends:`` base): "'utf-8' codec can't decode ..."
    without the file's name."""
    bad = tmp_path / "bad.yaml"
    bad.write_bytes("name: caf\xe9\n".encode("latin-1") if content == "latin1" else bytes(range(256)) * 4)
    path = bad
    if where == "base":
        path = tmp_path / "top.yaml"
        path.write_text("extends: bad.yaml\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    msg = str(info.value)
    assert str(bad) in msg and "UTF-8" in msg and len(msg) < 400, msg


def test_extends_too_long_a_name_is_a_config_error(tmp_path):
    """``extends:`` naming a 300-character file: OSError 'File name too long' from the loader."""
    top = tmp_path / "top.yaml"
    top.write_text(f"extends: {'x' * 300}.yaml\n")
    with pytest.raises(ConfigError) as info:
        load_config(top)
    msg = str(info.value)
    assert str(top) in msg and "extends" in msg and "too long" in msg and len(msg) < 600, msg


def test_config_path_too_long_is_a_config_error(tmp_path):
    """The config path itself too long: a ConfigError, not an OSError."""
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / ("y" * 300 + ".yaml"))
    assert "too long" in str(info.value)


# ------------------------------------------------------------------ 14. rates that imply too many events
@pytest.mark.parametrize("override, name", [("emulator.background_rate_hz=10000", "emulator.background_rate_hz = 10000"),
                                            ("emulator.leak_rate_hz=10000", "emulator.leak_rate_hz = 10000"),
                                            ("emulator.threshold_off=1e-9", "emulator.threshold_off = 1e-09")])
def test_event_rates_over_the_cap_name_the_value(override, name):
    """Values inside the schema's ranges were refused mid-flight by a message naming only
    emulator.max_events_per_step."""
    from dvsland.config.validate import check_memory

    cfg = load_config(None, [override])
    with pytest.raises(ConfigError) as info:
        check_memory(cfg, n_sites=1, batch_size=2)
    msg = str(info.value)
    assert name in msg and "emulator.max_events_per_step = 20000000" in msg and len(msg) < 700, msg


@pytest.mark.parametrize("override", ["emulator.background_rate_hz=100", "emulator.threshold_off=0.01",
                                      "emulator.leak_rate_hz=1"])
def test_event_rates_under_the_cap_pass(override):
    from dvsland.config.validate import check_memory

    check_memory(load_config(None, [override]), n_sites=9, batch_size=18)


def test_event_rates_over_the_cap_leave_no_run_folder(tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["simulate", "--sites", "D", "--quiet", "--out", str(out), "--set",
                 "emulator.background_rate_hz=10000"]) == 2
    err = capsys.readouterr().err
    assert "emulator.background_rate_hz = 10000" in err and "Traceback" not in err and not out.exists(), err


# ------------------------------------------------------------------ 11. evaluate --recording <missing>
@pytest.mark.parametrize("flag", ["--recording", "--ground-truth"])
def test_evaluate_missing_recording_is_one_line_and_no_run_folder(tmp_path, capsys, flag):
    """A FileNotFoundError traceback, and the run folder was made before the file was read."""
    good = tmp_path / "ok.csv"
    good.write_text("t,x,y,p\n0,1,1,1\n100000,2,2,0\n")
    missing = tmp_path / "missing.csv"
    args = ["--recording", str(missing)] if flag == "--recording" else [
        "--recording", str(good), "--ground-truth", str(missing)]
    out = tmp_path / "r"
    assert main(["evaluate", *args, "--estimators", "dpr", "--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert flag in err and str(missing) in err and "Traceback" not in err and len(err.splitlines()) == 1, err
    assert not out.exists()


# ------------------------------------------------------------------ 12. sizes implied by a recording
SPANS = {"31 years": "t,x,y,p\n0,1,1,1\n978285600000000,2,2,0\n",  # np.arange over 9.8e9 intervals
         "t = 2^62 us": f"t,x,y,p\n0,1,1,1\n{2 ** 62},2,2,0\n",
         "40001 px": "t,x,y,p\n0,1,1,1\n100000,40000,40000,0\n"}  # 6.4 GB per estimator array


@pytest.mark.parametrize("case", sorted(SPANS))
def test_recording_implied_sizes_are_refused_up_front(tmp_path, case):
    from dvsland.evaluate import evaluate_recording

    f = tmp_path / "rec.csv"
    f.write_text(SPANS[case])
    cfg = load_config(None, ["simulation.max_memory_gb=4"])
    with pytest.raises(ValueError) as info:
        evaluate_recording(cfg, f, ["dpr", "cmax"], progress=False)
    msg = str(info.value)
    words = "40001x40001 px" if case == "40001 px" else "intervals of 100 ms"
    assert str(f) in msg and words in msg and "simulation.max_memory_gb" in msg and len(msg) < 700, msg


def test_recording_implied_sizes_leave_no_run_folder(tmp_path, capsys):
    f = tmp_path / "rec.csv"
    f.write_text(SPANS["31 years"])
    out = tmp_path / "r"
    assert main(["evaluate", "--recording", str(f), "--estimators", "dpr", "--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(f) in err and "Traceback" not in err and not out.exists(), err


def test_recording_of_ordinary_size_still_runs(tmp_path):
    from dvsland.evaluate import evaluate_recording

    f = tmp_path / "rec.csv"
    f.write_text("t,x,y,p\n" + "".join(f"{k * 20000},{k % 7},{k % 5},{k % 2}\n" for k in range(100)))
    res = evaluate_recording(load_config(None, ["simulation.max_memory_gb=4"]), f, ["dpr"], progress=False)
    assert res.summary["n_steps"] == 20 and res.summary["sensor_size"] == [7, 5]


# ------------------------------------------------------------------ 10. Ctrl-C during the CLI's imports
_PRELUDE = """
import importlib, sys
real = importlib.import_module
def interrupted(name, *a, **k):
    if name.startswith("dvsland.cli.cmd_"):
        raise KeyboardInterrupt  # Ctrl-C while build_parser imports the sub-commands
    return real(name, *a, **k)
importlib.import_module = interrupted
from dvsland.cli.main import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("args", [["config", "show"], ["--version"]])
def test_interrupt_during_the_parsers_imports_is_one_line(args):
    """A KeyboardInterrupt traceback from the imports in build_parser() (outside main's try)."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-c", _PRELUDE, *args], capture_output=True, text=True, timeout=120)
    assert p.returncode == 130 and "Traceback" not in p.stderr, p.stderr
    assert p.stderr.strip().startswith("dvsland: interrupted") and len(p.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("sig", ["SIGINT", pytest.param("SIGTERM", marks=pytest.mark.slow)])  # 10 s each
def test_signal_in_the_first_seconds_is_never_a_traceback(sig):
    """A real signal at several moments of the start-up (imports, parsing, the command)."""
    import signal
    import subprocess
    import sys
    import time

    for delay in (0.3, 0.6, 1.0, 1.5):  # past the interpreter's own start-up (~0.05 s), which no code owns
        p = subprocess.Popen([sys.executable, "-m", "dvsland.cli.main", "config", "show", "paper"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        time.sleep(delay)
        p.send_signal(getattr(signal, sig))
        err = p.communicate(timeout=120)[1]
        assert "Traceback" not in err, (delay, err)
        assert p.returncode in (0, 130, -getattr(signal, sig)), (delay, p.returncode, err)


_CHILD_CALLBACK = """
import os, signal, sys, time, weakref
import dvsland.cli.main as m
from dvsland.runs import guarded_run

class A:
    pass

def callback(_ref):  # the signal handler runs inside this weakref callback, whose exceptions are unraisable
    os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    for _ in range(1000):
        pass

def command(args):
    a = A()
    ref = weakref.ref(a, callback)
    del a
    time.sleep(20)
    return 0

def run(argv, started):
    started.append("cmd")
    return guarded_run(command)(None)

m._run = run
sys.exit(m.main([]))
"""


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_signal_inside_an_unraisable_callback_still_interrupts(sig):
    """An interrupt raised inside a weakref callback (CPython prints and drops it) still ends the
    command in one line and status 130, not a traceback and a command that runs on."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-c", _CHILD_CALLBACK, sig], capture_output=True, text=True, timeout=60)
    assert p.returncode == 130, (p.returncode, p.stderr)
    assert "Traceback" not in p.stderr and "Exception ignored" not in p.stderr, p.stderr
    assert p.stderr.strip().startswith("dvsland: interrupted") and len(p.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------ 8. build-native after a SIGKILL
_CHILD_BUILD = """
import os, sys, time
from dvsland import native_build

d = native_build.library_dir("dvsland_test_lib")
d.mkdir(parents=True, exist_ok=True)
with native_build.build_lock(d):
    (d / f"dvsland_test_lib.so.{os.getpid()}.tmp").write_bytes(b"half a library")
    print("compiling", flush=True)
    time.sleep(float(sys.argv[1]))
"""

_SRC = 'extern "C" int dvs_answer() { return 42; }\n'


def _start_child_build(tmp_path, seconds: float):
    import os
    import subprocess
    import sys

    env = dict(os.environ, TORCH_EXTENSIONS_DIR=str(tmp_path))
    child = subprocess.Popen([sys.executable, "-c", _CHILD_BUILD, str(seconds)], env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "compiling", child.stderr.read()
    return child


def _need_compiler():
    from dvsland import native_build

    if native_build.compiler() is None:
        pytest.skip("no C++ compiler here")


def test_build_after_a_killed_build_needs_no_cleanup(tmp_path, monkeypatch):
    """A build killed by SIGKILL mid-compile leaves only its temporary output, never a library under
    the final name; the next build neither waits nor loads it, and removes it."""
    import warnings

    from dvsland import native_build

    _need_compiler()
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    child = _start_child_build(tmp_path, 600)
    child.kill()
    child.wait(timeout=30)
    d = tmp_path / "dvsland_test_lib"
    assert list(d.glob("*.tmp")) and not native_build.library_cached("dvsland_test_lib")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        path = native_build.build_library("dvsland_test_lib", _SRC, ["-O1"])
    assert native_build.load_library("dvsland_test_lib").dvs_answer() == 42 and path.is_file()
    assert not list(d.glob("*.tmp"))


def test_build_waits_for_a_live_build(tmp_path, monkeypatch):
    """A build running in another process is waited for; its temporary output is left alone."""
    import time

    from dvsland import native_build

    _need_compiler()
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    child = _start_child_build(tmp_path, 2.0)
    t0 = time.monotonic()
    native_build.build_library("dvsland_test_lib", _SRC, ["-O1"])
    assert time.monotonic() - t0 > 1.0
    assert child.wait(timeout=30) == 0, child.stderr.read()
    assert native_build.load_library("dvsland_test_lib").dvs_answer() == 42


def test_a_failed_compile_names_the_compiler_and_leaves_nothing(tmp_path, monkeypatch):
    from dvsland import native_build

    _need_compiler()
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    with pytest.raises(RuntimeError, match="failed .* on .*dvsland_test_bad.cpp"):
        native_build.build_library("dvsland_test_bad", "this is not C++\n", [])
    d = tmp_path / "dvsland_test_bad"
    assert not native_build.library_cached("dvsland_test_bad") and not list(d.glob("*.tmp"))
    monkeypatch.setattr(native_build, "compiler", lambda: None)
    with pytest.raises(RuntimeError, match="no C\\+\\+ compiler"):
        native_build.build_library("dvsland_test_bad", _SRC, [])


def test_interrupt_inside_exec_during_imports_exits_130_not_by_sigint(monkeypatch, capsys):
    """A Ctrl-C that lands inside code exec()-ed from a string (dataclasses' generated methods, while
    the sub-commands are imported) left CPython's unhandled-KeyboardInterrupt flag set although main
    handled it: ``python -m dvsland.cli.main`` then ended by SIGINT (status -2), not 130."""
    import ctypes
    import importlib

    try:
        flag = ctypes.c_int.in_dll(ctypes.pythonapi, "_Py_UnhandledKeyboardInterrupt")
    except (ValueError, AttributeError):
        pytest.skip("this interpreter does not export _Py_UnhandledKeyboardInterrupt")
    real = importlib.import_module

    def interrupted(name, *a, **k):
        if name.startswith("dvsland.cli.cmd_"):
            exec("raise KeyboardInterrupt")  # noqa: S102
        return real(name, *a, **k)

    monkeypatch.setattr(importlib, "import_module", interrupted)
    assert main(["config", "show"]) == 130
    assert flag.value == 0
    assert "dvsland: interrupted" in capsys.readouterr().err


# ------------------------------------------------------------------ 10. Ctrl-C right after planning
import json as _json
import os as _os
import signal as _signal
import subprocess as _subprocess
import sys as _sys
import time as _time
from pathlib import Path as _Path

_REPO = _Path(__file__).resolve().parents[1]


def _proc_stat(pid: int):
    """(state, ppid) of ``pid`` from /proc, or None when it is gone."""
    try:
        raw = _Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = raw[raw.rindex(")") + 2:].split()
    return fields[0], int(fields[1])


def _group_alive(pgid: int) -> list:
    """Live (not zombie) processes of the process group ``pgid``."""
    out = []
    for d in _Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if _os.getpgid(int(d.name)) != pgid:
                continue
        except OSError:
            continue
        st = _proc_stat(int(d.name))
        if st is not None and st[0] != "Z":
            out.append(int(d.name))
    return out


def _spawned_children(pid: int) -> list:
    out = []
    for d in _Path("/proc").iterdir():
        try:
            if d.name.isdigit() and _proc_stat(int(d.name))[1] == pid and \
                    b"spawn_main" in (d / "cmdline").read_bytes():
                out.append(int(d.name))
        except (OSError, TypeError):
            continue
    return out


def _wait_for(cond, timeout_s: float) -> bool:
    t_end = _time.monotonic() + timeout_s
    while _time.monotonic() < t_end:
        if cond():
            return True
        _time.sleep(0.02)
    return False


def _ctrl_c_campaign(out: _Path, when: str, delay_s: float):
    """Start `campaign --workers 2` in its own process group, wait for phase ``when`` (``folder``:
    its campaign.json is written; ``spawn``: its workers are being started), wait ``delay_s``
    and press Ctrl-C (SIGINT to the whole group, as a terminal does). Returns (rc, stderr, pgid)."""
    env = {**_os.environ, "OMP_NUM_THREADS": "1"}
    drv = _subprocess.Popen([_sys.executable, "-m", "dvsland.cli.main", "campaign", "configs/montecarlo.yaml",
                             "--n-seeds", "4", "--sites", "A,D", "--shard-seeds", "2", "--workers", "2",
                             "--out", str(out)], cwd=_REPO, env=env, stdout=_subprocess.PIPE,
                            stderr=_subprocess.PIPE, start_new_session=True)
    try:
        seen = _wait_for((lambda: (out / "campaign.json").is_file()) if when == "folder"
                         else (lambda: len(_spawned_children(drv.pid)) > 0), 120)
        assert seen, f"the campaign never reached phase {when!r}"
        _time.sleep(delay_s)
        _os.killpg(drv.pid, _signal.SIGINT)
        _, err = drv.communicate(timeout=60)
    finally:
        if drv.poll() is None:
            _os.killpg(drv.pid, _signal.SIGKILL)
            drv.wait()
    return drv.returncode, err.decode(errors="replace"), drv.pid


@pytest.mark.skipif(not _sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("when, delay_s", [("folder", 0.0), ("spawn", 0.3), ("spawn", 1.5)])
def test_ctrl_c_right_after_planning_leaves_results_and_no_worker(tmp_path, when, delay_s):
    """A campaign interrupted right after planning printed a spawn worker's traceback (its
    imports got the terminal's SIGINT too) and once left no results.json (an interrupt before
    the shards flew was caught by the command and never reported); now one line, status 130, a
    results.json saying interrupted, and no process of the command left."""
    out = tmp_path / "c"
    rc, err, pgid = _ctrl_c_campaign(out, when, delay_s)
    left = [] if _wait_for(lambda: not _group_alive(pgid), 15) else _group_alive(pgid)
    for pid in left:  # only what this test started
        _os.kill(pid, _signal.SIGKILL)
    assert rc == 130, err
    assert "Traceback" not in err and "EOFError" not in err, err
    saved = _json.loads((out / "results.json").read_text())
    assert saved["status"] == "interrupted", saved
    assert f"dvsland campaign --resume {out}" in err, err  # the folder to resume, named
    assert left == [], f"processes left behind: {left}"
