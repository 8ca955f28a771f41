"""Kernels compiled in the background while a run prepares its scenes (native_build.build_in_background)."""

from __future__ import annotations

import warnings

import pytest

from dvsland import native_build

_SRC = 'extern "C" int dvs_answer() { return 42; }\n'


@pytest.fixture
def library(tmp_path, monkeypatch):
    """A tiny library in an empty build cache, mode from DVSLAND_TEST_BG (auto when unset)."""
    if native_build.compiler() is None:
        pytest.skip("no C++ compiler here")
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    monkeypatch.delenv("DVSLAND_TEST_BG", raising=False)
    return lambda src=_SRC: native_build.NativeLibrary("dvsland_test_bg", src, ["-O1"], "DVSLAND_TEST_BG",
                                                       "the test kernel", lambda lib: lib)


def test_a_background_build_is_what_the_first_use_loads(library):
    lib = library()
    assert not lib.cached()
    assert native_build.build_in_background([lib]) == 1
    assert lib.load().dvs_answer() == 42  # waits for the build
    assert lib.cached()
    assert native_build.build_in_background([lib]) == 0  # loaded: nothing to start


def test_nothing_starts_when_cached_or_off(library, monkeypatch):
    lib = library()
    lib.build()
    assert native_build.build_in_background([library()]) == 0  # cached
    monkeypatch.setenv("DVSLAND_TEST_BG", "0")
    other = library('extern "C" int dvs_answer() { return 7; }\n')
    assert native_build.build_in_background([other]) == 0 and not other.cached()
    assert other.load() is None


def test_a_failed_background_build_warns_at_first_use_as_before(library):
    lib = library("this is not C++\n")
    assert native_build.build_in_background([lib]) == 1
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert lib.load() is None
    assert any("the test kernel" in str(w.message) and "using the torch path" in str(w.message) for w in caught)
    assert lib.load() is None  # once failed, not built again


@pytest.mark.parametrize("estimator,renderer,want", [
    ("dpr", None, ["terrain", "render", "events", "dpr"]),
    ("cmax", None, ["terrain", "render", "events", "cmax"]),
    ("learned", None, ["terrain", "render", "events"]),
    ("dpr", "pyrender", ["events", "dpr"]),
])
def test_a_run_starts_the_builds_of_the_kernels_it_uses(estimator, renderer, want, monkeypatch):
    """build_stages starts (on CPU) the builds of the kernels its stages load on first use."""
    from dvsland import stages
    from dvsland.config import load_config
    from dvsland.estimators import get_estimator

    asked = []
    monkeypatch.setattr(native_build, "build_in_background", lambda libs: asked.extend(libs) or 0)
    cfg = load_config("paper")
    est = get_estimator(estimator, 2, (128, 128))
    assert stages.start_kernel_builds(cfg, est, renderer) == 0
    assert [lib.prefix.split("_")[1] for lib in asked] == want


def test_the_efference_fit_filter_starts_its_kernels_build(monkeypatch):
    from dvsland import stages
    from dvsland.config import load_config
    from dvsland.estimators import get_estimator

    asked = []
    monkeypatch.setattr(native_build, "build_in_background", lambda libs: asked.extend(libs) or 0)
    cfg = load_config("montecarlo_efference")
    assert cfg.controller.filter == "efference_fit"
    assert stages.start_kernel_builds(cfg, get_estimator("learned", 2, (128, 128))) == 0
    assert [lib.prefix.split("_")[1] for lib in asked] == ["terrain", "render", "events", "fit"]


def _fork_and_load(lib) -> int:
    """Fork; the child loads ``lib`` within a 60 s alarm and exits 0 when its kernel answers; the
    child's wait status."""
    import os
    import signal

    pid = os.fork()
    if pid == 0:  # the child: load within the alarm, or die by it
        signal.alarm(60)
        ok = lib.load() is not None and lib.load().dvs_answer() == 42
        os._exit(0 if ok else 1)
    return os.waitpid(pid, 0)[1]


@pytest.mark.parametrize("when", ["any time", "lock held"])
def test_a_forked_child_does_not_wait_for_its_parents_build_thread(library, monkeypatch, when):
    """A process forked while its parent's background build runs has no builder thread: its first
    use builds (or waits on the build lock) instead of waiting forever for the parent's thread. With
    "lock held" the fork comes while the parent's thread holds the build lock (its compile slowed to
    2 s): the child's copy of the lock's descriptor must not keep the lock from it."""
    import os
    import subprocess
    import sys
    import time

    if sys.platform != "linux":
        pytest.skip("fork")
    lib = library()
    if when == "lock held":
        run = subprocess.run
        monkeypatch.setattr(native_build.subprocess, "run", lambda *a, **k: time.sleep(2) or run(*a, **k))
    assert native_build.build_in_background([lib]) == 1
    if when == "lock held":
        owner = lib.build_dir() / native_build.OWNER_LOCK
        deadline = time.monotonic() + 30
        while not (owner.is_file() and owner.read_text().strip() == str(os.getpid())):
            assert time.monotonic() < deadline, "the background build never took its lock"
            time.sleep(0.01)
    status = _fork_and_load(lib)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0, f"child status {status}"
    assert lib.load().dvs_answer() == 42
