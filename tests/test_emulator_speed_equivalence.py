"""Holding the emulator's tensors changes no event, and a step never touches a tensor the caller
holds (the step is pure: no buffer is recycled across steps; tests/test_emulator_pure.py)."""

import pytest
import torch

from dvsland.events import emulator as emu_mod
from dvsland.events.benchmark import smooth_frames
from dvsland.events.emulator import EventEmulator


# the torch path is the reference here, whether or not the compiled kernels are built
# (test_emulator_native compares them with it)
pytestmark = pytest.mark.usefixtures("torch_event_path")


CONFIGS = [dict(), dict(refractory_us=0.0), dict(refractory_us=3000.0), dict(threshold=0.05, threshold_off=0.2),
           dict(interpolation="linear"), dict(mismatch_sigma=0.1), dict(shot_noise_rate_hz=5.0),
           dict(photoreceptor_cutoff_hz=100.0), dict(leak_rate_hz=1.0, hot_pixel_fraction=0.01)]


def _frames():
    g = torch.Generator().manual_seed(7)
    yield torch.rand(6, 3, 17, 23, generator=g) * 2
    yield smooth_frames(2, 40, 48, 6, omega=0.8)  # dense: several events per pixel and frame


def _run(frames, kw, hold: bool):
    """Events of every step; ``hold`` keeps a reference to every level (no buffer is reused)."""
    emu = EventEmulator(seed=3, **kw)
    emu.reset(frames[0], 0)
    held, out = [], []
    for k in range(1, frames.shape[0]):
        out.append(emu.step(frames[k], k * 7919))
        if hold:
            held.append(emu._l_prev)
    return out, emu


@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("kw", CONFIGS, ids=lambda kw: ",".join(f"{k}={v}" for k, v in kw.items()) or "ideal")
def test_holding_levels_changes_no_event(kw, fast, monkeypatch):
    monkeypatch.setattr(emu_mod, "CPU_FAST_PATHS", fast)
    for frames in _frames():
        (ev_a, emu_a), (ev_b, emu_b) = _run(frames, kw, False), _run(frames, kw, True)
        assert sum(len(e) for e in ev_a) > 0
        for a, b in zip(ev_a, ev_b):
            for f in "bxytp":
                assert torch.equal(getattr(a, f), getattr(b, f)), f
        assert torch.equal(emu_a.reference, emu_b.reference)
        assert torch.equal(emu_a._t_last, emu_b._t_last)


def test_held_level_is_never_overwritten():
    frames = smooth_frames(2, 16, 16, 6, omega=0.5)
    emu = EventEmulator()
    emu.reset(frames[0], 0)
    emu.step(frames[1], 100)
    level = emu.photoreceptor_level  # the caller holds the tensor itself ...
    view = emu.photoreceptor_level[0]  # ... or a view of it (checked separately below)
    keep_level, keep_view = level.clone(), view.clone()
    for k in range(2, 6):
        emu.step(frames[k], 100 * k)
    assert torch.equal(level, keep_level)
    assert torch.equal(view, keep_view)
    expect = torch.log(frames[5].double() + emu.log_eps)
    assert torch.equal(emu.photoreceptor_level, expect)


def test_held_view_alone_blocks_reuse():
    frames = smooth_frames(1, 8, 8, 5, omega=0.5)
    emu = EventEmulator()
    emu.reset(frames[0], 0)
    emu.step(frames[1], 100)
    view = emu.photoreceptor_level.view(-1)  # only a view survives, not the tensor object
    keep = view.clone()
    for k in range(2, 5):
        emu.step(frames[k], 100 * k)
    assert torch.equal(view, keep)
