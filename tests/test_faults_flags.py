"""Numeric flags and --out names out of range: one line naming the flag and its range, exit 2."""

from __future__ import annotations

import subprocess
import sys

import pytest

@pytest.mark.parametrize("args,words", [(["events", "--window-ms", "-5"], "--window-ms must be from"),
                                        (["events", "--window-ms", "nan"], "--window-ms must be from"),
                                        (["events", "--max-points", "-1"], "--max-points must be from"),
                                        (["render", "--gif-frames", "100000000"], "--gif-frames must be from"),
                                        (["bench", "tradeoff", "--estimators", "bogus", "--out", "{tmp}/bench"],
                                         "--estimators: unknown estimator(s) ['bogus']"),
                                        (["simulate", "--out", "/tmp/" + "x" * 300], "--out: a folder name may have")])
def test_bad_flags_are_one_line_errors(args, words, tmp_path):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    p = subprocess.run([sys.executable, "-m", "dvsland.cli.main", *args], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and words in p.stderr and "Traceback" not in p.stderr, p.stderr
