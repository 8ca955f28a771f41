"""Regression tests of issue 28 at the config's and the checkpoint's edges: values inside the
schema's old ranges that crashed, flew to null states or leaked NaN; memory the estimate did not
count; names the file system refuses; and snn checkpoints with NaN/inf or wrongly shaped tensors.
Each test names the case it guards."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import dvsland
from dvsland.cli.main import main
from dvsland.config import ConfigError, load_config
from dvsland.config.validate import check_memory
from dvsland.estimators.snn.estimator import DEFAULT_CHECKPOINT, load_checkpoint

QUIET = ["logging.figures=false", "logging.quiet=true", "logging.tensorboard=false", "render.threads=1"]
LONG = "x" * 5000


# ------------------------------------------------------------------ 3. values that crashed
@pytest.mark.parametrize("override, name, allowed", [
    ("dynamics.isp_s=1e-320", "dynamics.isp_s", "allowed [1.0, 100000.0]"),  # flew 'complete', every state null
    ("dynamics.g0_mps2=5e-324", "dynamics.g0_mps2", "allowed [0.1, 100.0]"),
    ("simulation.sites.0.z0_m=5e-324", "simulation.sites[0].z0_m", "allowed [1.0, 100000.0]"),  # NaN/inf in D
    ("estimator.cmax.radial_bin_px=5e-324", "estimator.cmax.radial_bin_px", "allowed 0 (off) or [0.01, 1000]"),
    ("estimator.cmax.n_grid=10000", "estimator.cmax.n_grid", "allowed [3, 2001]"),  # 10 GB per descent
    ("render.threads=1024", "render.threads", "allowed [0, 256]"),  # the process died
    ("simulation.torch_threads=1024", "simulation.torch_threads", "allowed [0, 256]"),
    (f"controller.settings.0.label={LONG}", "controller.settings[0].label", "up to 120 characters"),
    (f"name={LONG}", "name", "allowed 1 to 120 characters"),  # File name too long
    (f"estimator.snn.checkpoint=/tmp/{LONG}", "estimator.snn.checkpoint", "each folder or file name up to 255"),
])
def test_values_that_crashed_are_refused(override, name, allowed):
    with pytest.raises(ConfigError) as info:
        load_config(None, QUIET + [override])
    msg = str(info.value)
    assert msg.startswith(name) and allowed in msg and len(msg) < 500, msg


@pytest.mark.parametrize("args", [["--set", f"controller.settings.0.label={LONG}"],
                                  ["--set", f"estimator.snn.checkpoint=/tmp/{LONG}", "--estimator", "snn"]])
def test_cli_long_names_are_one_short_line(tmp_path, capsys, args):
    """A 5,000-character run label or checkpoint path died with OSError: File name too long."""
    assert main(["simulate", "--sites", "D", "--quiet", "--out", str(tmp_path / "r")] + args) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and len(err) < 500 and "Traceback" not in err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("overrides", [["dynamics.isp_s=1", "dynamics.g0_mps2=0.1"],
                                       ["simulation.sites.3.z0_m=1"]])
def test_lowest_allowed_values_fly_to_finite_states(tmp_path, overrides):
    """The new lower bounds run: every final state and the divergence trace finite."""
    cfg = load_config(None, QUIET + ["simulation.t_max_s=20"] + overrides)
    res = dvsland.simulate(cfg, estimator="oracle", sites="D", out=tmp_path / "r", quiet=True)
    assert res.status == "complete"
    for r in res.runs:
        assert all(np.isfinite(r[k]) for k in ("t_end_s", "lowest_altitude_m", "v_end_mps", "fuel_used_kg")), r
    active = np.asarray(res.traces["active"], dtype=bool)
    assert np.isfinite(np.asarray(res.traces["d_true"])[active]).all()


def test_memory_estimate_counts_terrain_preparation():
    """camera.width_px=4096 died allocating 3.9 GB in the terrain level preparation, which the
    estimate did not count (it counted pixels, and a 4096 x 128 camera has few)."""
    cfg = load_config(None, QUIET + ["camera.width_px=4096", "simulation.max_memory_gb=16"])
    with pytest.raises(ConfigError, match=r"simulation.max_memory_gb.* GiB to prepare a terrain level"):
        check_memory(cfg, n_sites=1, batch_size=2)
    check_memory(load_config(None, QUIET + ["simulation.max_memory_gb=4"]))  # the paper experiment fits


def test_memory_estimate_counts_the_cmax_search():
    """estimator.cmax.n_grid near its bound asks for about 32 MB per descent (the warp factors of
    every candidate), once uncounted."""
    cfg = load_config(None, QUIET + ["estimator.name=cmax", "estimator.cmax.n_grid=1001", "simulation.max_memory_gb=1.6"])
    with pytest.raises(ConfigError, match=r"for the cmax search \(estimator.cmax.n_grid = 1001\)"):
        check_memory(cfg)
    check_memory(load_config(None, QUIET + ["estimator.name=cmax", "simulation.max_memory_gb=1.6"]))


# ------------------------------------------------------------------ 6. checkpoints validated on load
def _nan(sd):
    sd["conv2.weight"][0, 0, 0, 0] = float("nan")


def _inf(sd):
    sd["readout.bias"][0] = float("inf")


def _shape(sd):
    sd["conv1.weight"] = sd["conv1.weight"][:4]


def _dtype(sd):
    sd["conv1.bias"] = sd["conv1.bias"].long()


def _missing(sd):
    del sd["readout.weight"]


def _extra(sd):
    sd["conv3.weight"] = torch.zeros(3)


@pytest.mark.parametrize("damage, tensor, what", [
    (_nan, "conv2.weight", "NaN or infinite"), (_inf, "readout.bias", "NaN or infinite"),
    (_shape, "conv1.weight", "has shape (4, 2, 5, 3), expected (8, 2, 5, 3)"),
    (_dtype, "conv1.bias", "expected a floating-point tensor"), (_missing, "readout.weight", "tensors missing"),
    (_extra, "conv3.weight", "unexpected"),
])
def test_damaged_checkpoint_tensors_are_named(tmp_path, damage, tensor, what):
    """A checkpoint with NaN weights loaded silently (the estimator then gave NaN every step);
    a wrongly shaped tensor gave 'Error(s) in loading state_dict' without its name."""
    ck = torch.load(DEFAULT_CHECKPOINT, map_location="cpu", weights_only=True)
    damage(ck["state_dict"])
    path = tmp_path / "damaged.pt"
    torch.save(ck, path)
    with pytest.raises(ValueError) as info:
        load_checkpoint(path)
    msg = str(info.value)
    assert msg.startswith(f"estimator.snn.checkpoint: {path}") and tensor in msg and what in msg, msg
    load_checkpoint(DEFAULT_CHECKPOINT)  # the shipped one passes
