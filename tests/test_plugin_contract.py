"""The plug-in contract at the loop's boundary: a user's estimator or controller that raises or
returns the wrong thing ends in one PluginError naming the plug-in, the call, what was expected and
what came back; the run folder keeps its config, results (status failed) and traces."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

import dvsland
from dvsland.plugins import PluginError, call_plugin, check_batch_tensor

PLUGINS = textwrap.dedent('''
    import sys
    import numpy as np
    import torch

    class Base:
        needs_events = False
        def __init__(self, batch_size, sensor_size=None, device="cpu", **kw):
            self.batch_size, self.device = batch_size, torch.device(device)
        def reset(self, mask=None):
            pass
        def good(self, truth):
            return truth.divergence.to(torch.float32)

    class Fine(Base):
        def update(self, events, t_us, truth=None):
            return self.good(truth)

    class WrongLength(Base):
        def update(self, events, t_us, truth=None):
            return torch.zeros(self.batch_size + 1)

    class TwoD(Base):
        def update(self, events, t_us, truth=None):
            return torch.zeros(self.batch_size, 1)

    class Scalar(Base):
        def update(self, events, t_us, truth=None):
            return -0.1

    class AList(Base):
        def update(self, events, t_us, truth=None):
            return [-0.1] * self.batch_size

    class Numpy(Base):
        def update(self, events, t_us, truth=None):
            return np.full(self.batch_size, -0.1)

    class ReturnsNone(Base):
        def update(self, events, t_us, truth=None):
            return None

    class AString(Base):
        def update(self, events, t_us, truth=None):
            return "fast"

    class Bool(Base):
        def update(self, events, t_us, truth=None):
            return torch.ones(self.batch_size, dtype=torch.bool)

    class Complex(Base):
        def update(self, events, t_us, truth=None):
            return torch.zeros(self.batch_size, dtype=torch.complex64)

    class Meta(Base):
        def update(self, events, t_us, truth=None):
            return torch.zeros(self.batch_size, device="meta")

    class Grad(Base):
        def update(self, events, t_us, truth=None):
            return self.good(truth).requires_grad_(True) * 1.0

    class RaisesInInit(Base):
        def __init__(self, *a, **kw):
            raise RuntimeError("cannot build")

    class RaisesInReset(Fine):
        def reset(self, mask=None):
            raise KeyError("state")

    class RaisesInUpdate(Base):
        def update(self, events, t_us, truth=None):
            raise ZeroDivisionError("oops")

    class Exits(Base):
        def update(self, events, t_us, truth=None):
            sys.exit(3)

    class Recurses(Base):
        def update(self, events, t_us, truth=None):
            return self.update(events, t_us, truth)

    class BadConfidence(Fine):
        def confidence(self):
            return "high"

    class NotAnEstimator:
        def __init__(self, *a, **kw):
            pass

    def factory_none(*a, **kw):
        return None
''')

BAD = {  # class -> (call, words the message must hold)
    "WrongLength": ("update", "shape (5,)"),
    "TwoD": ("update", "shape (4, 1)"),
    "Scalar": ("update", "got float"),
    "AList": ("update", "got list"),
    "Numpy": ("update", "got ndarray"),
    "ReturnsNone": ("update", "got NoneType"),
    "AString": ("update", "got str"),
    "Bool": ("update", "dtype torch.bool"),
    "Complex": ("update", "dtype torch.complex64"),
    "Meta": ("update", "device meta"),
    "RaisesInInit": ("__init__", "raised RuntimeError: cannot build"),
    "RaisesInReset": ("reset", "raised KeyError"),
    "RaisesInUpdate": ("update", "raised ZeroDivisionError: oops"),
    "Exits": ("update", "raised SystemExit: 3"),
    "Recurses": ("update", "raised RecursionError"),
    "BadConfidence": ("confidence", "got str"),
    "NotAnEstimator": ("__init__", "expected a divergence estimator"),
    "factory_none": ("__init__", "got NoneType"),
}
QUIET = ["simulation.t_max_s=2", "logging.tensorboard=false", "logging.figures=false"]


@pytest.fixture(scope="module")
def plugin_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("plug") / "plugs.py"
    p.write_text(PLUGINS)
    return p


def test_a_well_behaved_plugin_flies(plugin_file, tmp_path):
    r = dvsland.simulate(None, estimator=f"{plugin_file}:Fine", sites="D,H", out=tmp_path / "ok", quiet=True,
                         overrides=QUIET)
    assert r.status == "complete" and len(r.runs) == 4


@pytest.mark.parametrize("cls", sorted(BAD))
def test_a_misbehaving_plugin_is_one_error_and_keeps_the_run(plugin_file, tmp_path, cls):
    call, words = BAD[cls]
    name = f"{plugin_file}:{cls}"
    out = tmp_path / cls
    with pytest.raises(PluginError) as info:
        dvsland.simulate(None, estimator=name, sites="D,H", out=out, quiet=True, overrides=QUIET)
    err = info.value
    assert err.plugin == name and err.call == call and words in str(err), str(err)
    res = json.loads((out / "results.json").read_text())
    assert res["status"] == "failed" and res["error"].startswith("PluginError")
    assert (out / "config.yaml").is_file()
    if call in ("update", "confidence"):  # it flew: the traces so far are kept
        assert (out / "traces.npz").is_file()
    if "raised" in words:
        assert (out / "plugin_error.log").is_file() and cls in (out / "plugin_error.log").read_text()


def test_estimates_with_grad_are_detached_and_the_flight_is_written(plugin_file, tmp_path):
    r = dvsland.simulate(None, estimator=f"{plugin_file}:Grad", sites="D", out=tmp_path / "g", quiet=True,
                         overrides=QUIET)
    assert r.status == "complete" and np.isfinite(r.traces["d_est"][1:-1]).all()


def test_cli_reports_a_plugin_fault_in_one_line(plugin_file, tmp_path):
    cmd = [sys.executable, "-m", "dvsland.cli.main", "simulate", "--estimator", f"{plugin_file}:RaisesInUpdate",
           "--sites", "D", "--out", str(tmp_path / "cli"), *sum([["--set", s] for s in QUIET], [])]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and "ZeroDivisionError: oops" in p.stderr and "call update" in p.stderr


# ------------------------------------------------------------------ the checks themselves
def test_check_batch_tensor_accepts_and_detaches():
    x = torch.zeros(3, requires_grad=True)
    y = check_batch_tensor(x * 2, 3, "cpu", "p", "update")
    assert not y.requires_grad and y.shape == (3,)
    assert check_batch_tensor(None, 3, "cpu", "p", "confidence", allow_none=True) is None
    with pytest.raises(PluginError, match=r"plug-in 'p', call update: expected a torch.Tensor of shape \(3,\)"):
        check_batch_tensor(torch.zeros(2), 3, "cpu", "p", "update")


def test_call_plugin_keeps_ctrl_c():
    def interrupted():
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        call_plugin("p", "update", interrupted)

