"""Compiler-specific flags of the compiled kernels (native_build.GATHER_FLAGS and NativeLibrary.gcc_flags)."""

from __future__ import annotations

import os
import stat

import pytest

from dvsland import native_build
from dvsland.render import native_render


def _fake_compiler(tmp_path, name: str, version_text: str, dumpversion: str = "12.2.0") -> str:
    """A script that answers ``--version`` and ``-dumpversion`` like a compiler (compiles nothing)."""
    path = tmp_path / name
    path.write_text("#!/bin/sh\n"
                    f"if [ \"$1\" = \"-dumpversion\" ]; then echo '{dumpversion}'; exit 0; fi\n"
                    f"cat <<'EOF'\n{version_text}\nEOF\n")
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return str(path)


_GCC = "c++ (Debian 12.2.0-14) 12.2.0\nCopyright (C) 2022 Free Software Foundation, Inc."
_CLANG = "Debian clang version 14.0.6\nTarget: x86_64-pc-linux-gnu"


def test_gcc_is_told_from_clang_and_by_version(tmp_path):
    assert native_build.is_gcc(_fake_compiler(tmp_path, "gcc12", _GCC))
    assert not native_build.is_gcc(_fake_compiler(tmp_path, "gcc11", _GCC, "11.4.0"))  # no use_gather_*parts
    assert not native_build.is_gcc(_fake_compiler(tmp_path, "clang", _CLANG, "14.0.6"))
    assert not native_build.is_gcc(str(tmp_path / "missing"))
    assert not native_build.is_gcc(None)


def test_gcc_flags_join_the_flags_and_the_name_only_under_gcc(tmp_path, monkeypatch):
    src = 'extern "C" int dvs_answer() { return 42; }\n'
    lib = native_build.NativeLibrary("dvsland_test_flags", src, ["-O1"], "DVSLAND_TEST_FLAGS", "the test kernel",
                                     lambda x: x, gcc_flags=["-mtune-ctrl=use_gather"])
    monkeypatch.setenv("CXX", _fake_compiler(tmp_path, "gcc", _GCC))
    assert lib.flags == ["-O1", "-mtune-ctrl=use_gather"]
    name_gcc = lib.name()
    monkeypatch.setenv("CXX", _fake_compiler(tmp_path, "clang", _CLANG, "14.0.6"))
    assert lib.flags == ["-O1"]
    assert lib.name() != name_gcc  # a build for one compiler is never loaded for the other


def test_the_renderer_builds_with_gathers_under_gcc():
    cxx = native_build.compiler()
    if not native_build.is_gcc(cxx):
        pytest.skip("the gather flags apply to GCC 12 or later only")
    assert set(native_build.GATHER_FLAGS) <= set(native_render.LIBRARY.flags)
    if os.environ.get("DVSLAND_NATIVE_RENDER", "").lower() in ("0", "off", "false", "no"):
        return
    # the flags compile: the renderer's kernels load (test_render_native pins their frames to torch's)
    assert native_render.LIBRARY.load() is not None
