"""Device correctness without a GPU: a tensor subclass plays a second device, so a tensor drawn on
the CPU generator that meets a tensor of "the other device" raises, as CUDA does with CPU tensors.
(The CUDA runs of the same code are in the estimator tests; they skip without CUDA.)"""

from __future__ import annotations

import pytest
import torch

from dvsland.evaluate.synthetic import ZoomTextureFrames, blob_layout, zoom_blob_events


def _tensors(obj):
    if isinstance(obj, torch.Tensor):
        yield obj
    elif isinstance(obj, (list, tuple)):
        for o in obj:
            yield from _tensors(o)
    elif isinstance(obj, dict):
        for o in obj.values():
            yield from _tensors(o)


class OtherDevice(torch.Tensor):
    """A CPU tensor standing for a tensor on another device: an op mixing it with a plain tensor
    of one or more dimensions raises (0-dim tensors mix freely, as CPU scalars do with CUDA);
    ``.cpu()`` / ``.to('cpu')`` bring it back as a plain tensor."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        if name == "cpu" or (name == "to" and any(a == "cpu" or a == torch.device("cpu")
                                                  for a in list(args[1:]) + list(kwargs.values()))):
            with torch._C.DisableTorchFunctionSubclass():
                out = func(*args, **kwargs)
            return out.as_subclass(torch.Tensor)
        ts = list(_tensors(args)) + list(_tensors(kwargs))
        if any(isinstance(t, OtherDevice) for t in ts) and any(
                not isinstance(t, OtherDevice) and t.dim() > 0 for t in ts):
            raise RuntimeError(f"Expected all tensors to be on the same device ({name})")
        return super().__torch_function__(func, types, args, kwargs)


def test_harness_raises_on_mixing():
    a = torch.ones(3).as_subclass(OtherDevice)
    with pytest.raises(RuntimeError, match="same device"):
        a * torch.ones(3)
    assert type(a.cpu() * torch.ones(3)) is torch.Tensor
    assert type(a * torch.tensor(2.0)) is OtherDevice  # a 0-dim tensor mixes, like a CUDA op with a CPU scalar


def test_zoom_blob_events_accepts_inputs_on_another_device():
    """The divergence and active mask may live on the estimator's device (the bug: CPU-drawn
    times met a CUDA divergence)."""
    B, W, H = 3, 64, 48
    offsets = blob_layout(B, 10, (W, H), seed=1)
    d_cpu = torch.tensor([-0.1, -0.2, -0.3], dtype=torch.float64)
    active = torch.tensor([True, False, True])
    ref = zoom_blob_events(offsets, d_cpu, 0, 100_000, (W, H), seed=5, active=active)
    ev = zoom_blob_events(offsets.as_subclass(OtherDevice), d_cpu.as_subclass(OtherDevice), 0, 100_000, (W, H),
                          seed=5, active=active.as_subclass(OtherDevice))
    assert len(ev) == len(ref) > 0
    for f in ("b", "x", "y", "t", "p"):
        assert torch.equal(getattr(ev, f).as_subclass(torch.Tensor), getattr(ref, f))
    assert int((ev.b == 1).sum()) == 0  # the inactive element got none


def test_zoom_blob_events_output_device():
    offsets = blob_layout(2, 4, (32, 32), seed=0)
    ev = zoom_blob_events(offsets, torch.tensor([-0.1, -0.1]), 0, 100_000, (32, 32), device="meta")
    assert ev.b.device.type == "meta" and ev.t.device.type == "meta"


def test_zoom_texture_frames_render_on_their_device():
    fr = ZoomTextureFrames(2, (16, 16), texture_px=64, device="meta")
    out = fr(torch.tensor([100.0, 200.0]), torch.tensor([0, 1]))
    assert out.device.type == "meta" and out.shape == (2, 16, 16)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_zoom_blob_events_cuda_divergence():
    offsets = blob_layout(2, 4, (32, 32), seed=0)
    d = torch.tensor([-0.1, -0.2], device="cuda")
    ev = zoom_blob_events(offsets, d, 0, 100_000, (32, 32), device="cuda")
    ref = zoom_blob_events(offsets, d.cpu(), 0, 100_000, (32, 32))
    assert ev.t.device.type == "cuda" and torch.equal(ev.t.cpu(), ref.t)
