"""``render.compile``: the fast renderer's torch sampling (relief and both levels) through ``torch.compile``
renders the eager torch path's frames; the setting is resolved per device and checked. Tracing with
dynamo's ``eager`` backend runs the same operations, so those frames are the same bits; inductor's
fused code (slow: tens of seconds of compiling on a CPU) is held to float rounding."""

from __future__ import annotations

import pytest
import torch

import dvsland.compiled as compiled
from dvsland.config import CameraConfig, RenderConfig, load_config
from dvsland.render.fast import FastRenderer

CAM = CameraConfig(width_px=48, height_px=48, fov_deg=60.0)
SITES = ["A", "E", "G", "H"]


def _altitudes(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    alt = torch.exp(torch.empty(n).uniform_(2.31, 9.9, generator=g))  # 10.1 m ... 19.9 km, log-uniform
    return alt, torch.randint(0, len(SITES), (n,), generator=g)


def _renderer(compile_: str, device: str = "cpu", **kw) -> FastRenderer:
    sites = kw.pop("sites", SITES)
    cam = kw.pop("camera", CAM)
    return FastRenderer(sites, cam, RenderConfig(threads=1, compile=compile_), device=device, disk_cache=False,
                        native=False, **kw)


@pytest.mark.parametrize("value, device, on", [("false", "cpu", False), ("auto", "cpu", False),
                                               ("true", "cpu", True)])
def test_the_setting_is_resolved_per_device(value, device, on):
    assert (_renderer(value, device)._compiled is not None) is on


@pytest.mark.parametrize("value, device, on", [("auto", "cuda", True), ("auto", "cuda:1", True),
                                               ("auto", "cpu", False), ("false", "cuda", False)])
def test_auto_means_a_cuda_device(value, device, on):
    assert compiled.compile_on(value, torch.device(device) if ":" not in device else device) is on


def test_the_setting_is_checked():
    from dvsland.config import ConfigError

    assert load_config("paper").render.compile == "false"
    assert load_config("paper", ["render.compile=yes"]).render.compile == "true"  # YAML's boolean
    with pytest.raises(ConfigError, match=r"render\.compile.*'fused'.*'auto', 'true', 'false'"):
        load_config("paper", ["render.compile=fused"])


@pytest.mark.parametrize("case", ["default", "no_parallax", "two_parallax", "nearest_level", "per_site_gain",
                                  "odd_sensor"])
def test_traced_sampling_renders_the_eager_frames(case, monkeypatch):
    """Every branch (relief at half or full resolution, shared and per-site gains, nearest level), over
    batch sizes that change between calls (dynamic shapes: one trace serves them)."""
    monkeypatch.setattr(compiled, "BACKEND", "eager")
    torch._dynamo.reset()
    kw = {"default": {}, "no_parallax": dict(parallax_iters=0), "two_parallax": dict(parallax_iters=2),
          "nearest_level": dict(blend_levels=False),
          "per_site_gain": dict(sites=["A", "E"], suns=[(12.0, 0.0), (18.0, 5.0)]),
          "odd_sensor": dict(camera=CameraConfig(width_px=35, height_px=27, fov_deg=60.0))}[case]
    eager, traced = _renderer("false", **kw), _renderer("true", **kw)
    n_sites = len(kw.get("sites", SITES))
    for n in (9, 4, 13):
        alt, idx = _altitudes(n, seed=n)
        idx = idx % n_sites
        assert torch.equal(traced.render(alt, idx), eager.render(alt, idx))
    assert not any(f.eager for f in traced._compiled)  # traced, not fallen back


def test_a_failing_compile_renders_eagerly_and_warns_once(failing_compile):
    eager, traced = _renderer("false"), _renderer("true")
    alt, idx = _altitudes(6)
    with pytest.warns(RuntimeWarning, match=r"render\.compile: torch\.compile failed for the relief.*no working"):
        frames = traced.render(alt, idx)
    assert torch.equal(frames, eager.render(alt, idx))
    assert all(f.eager for f in traced._compiled)


@pytest.mark.slow
def test_inductor_frames_equal_the_eager_ones_within_rounding():
    """Inductor's fused kernels (C++ on a CPU) against the eager torch path: within float rounding of the
    samples (a few 1e-5 of the irradiance, which lies in [0, 1.3])."""
    torch._dynamo.reset()
    eager, fused = _renderer("false"), _renderer("true")
    for n in (9, 4):
        alt, idx = _altitudes(n, seed=n)
        torch.testing.assert_close(fused.render(alt, idx), eager.render(alt, idx), rtol=1e-4, atol=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_auto_compiles_on_cuda_and_renders_the_eager_frames():
    eager, fused = _renderer("false", "cuda"), _renderer("auto", "cuda")
    assert fused._compiled is not None
    alt, idx = _altitudes(64)
    torch.testing.assert_close(fused.render(alt.cuda(), idx.cuda()), eager.render(alt.cuda(), idx.cuda()),
                               rtol=1e-4, atol=1e-4)
