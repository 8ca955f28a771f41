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


def test_a_forked_child_does_not_wait_for_its_parents_build_thread(library):
    """A process forked while its parent's background build runs has no builder thread: its first
    use builds (or waits on the build lock) instead of waiting forever for the parent's thread."""
    import os
    import sys

    if sys.platform != "linux":
        pytest.skip("fork")
    lib = library()
    assert native_build.build_in_background([lib]) == 1
    pid = os.fork()
    if pid == 0:  # the child: load within the alarm, or die by it
        import signal

        signal.alarm(60)
        ok = lib.load() is not None and lib.load().dvs_answer() == 42
        os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0
    assert lib.load().dvs_answer() == 42
