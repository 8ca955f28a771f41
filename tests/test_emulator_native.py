"""The optional compiled radix sort of the emulator's event keys (dvsland.events.native): off by
default, a clean fallback when it cannot be built, and (slow: it compiles) the same events."""

import numpy as np
import pytest
import torch

from dvsland.events import native
from dvsland.events.benchmark import smooth_frames
from dvsland.events.emulator import EventEmulator


def test_off_by_default_and_no_build(monkeypatch):
    monkeypatch.delenv("DVSLAND_NATIVE_SORT", raising=False)
    monkeypatch.setattr(native, "_enabled", None)
    monkeypatch.setattr(native, "load", lambda: pytest.fail("must not build when off"))
    assert not native.native_sort_enabled()
    assert native.radix_sort_(torch.tensor([3, 1, 2]), 2) is False


def test_build_failure_falls_back_to_numpy(monkeypatch):
    monkeypatch.setattr(native, "_enabled", True)
    monkeypatch.setattr(native, "_module", None)
    monkeypatch.setattr(native, "_failed", False)
    import torch.utils.cpp_extension as ce

    def broken(*a, **k):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(ce, "load_inline", broken)
    frames = smooth_frames(2, 20, 24, 3, omega=0.5)
    with pytest.warns(RuntimeWarning, match="could not be built"):
        emu = EventEmulator()
        emu.reset(frames[0], 0)
        ev = emu.step(frames[1], 100_000)
    monkeypatch.setattr(native, "_enabled", False)
    ref = EventEmulator()
    ref.reset(frames[0], 0)
    assert ev == ref.step(frames[1], 100_000) and len(ev) > 0


@pytest.mark.slow
def test_native_sort_gives_the_same_events(monkeypatch):
    monkeypatch.setattr(native, "_enabled", True)
    if native.load() is None:
        pytest.skip("no C++ toolchain for torch.utils.cpp_extension")
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 2 ** 40, 100_003)
    t = torch.from_numpy(keys.copy())
    assert native.radix_sort_(t, 40) and np.array_equal(t.numpy(), np.sort(keys))
    from test_emulator_fast_paths import CONFIGS

    g = torch.Generator().manual_seed(4)
    frame_sets = [smooth_frames(3, 40, 48, 5, omega=0.8), smooth_frames(2, 33, 70, 4, omega=0.3),
                  torch.rand(5, 3, 17, 23, generator=g) * 2]
    for kw in CONFIGS + [dict(leak_rate_hz=2.0, photoreceptor_cutoff_hz=50.0), dict(refractory_us=20_000.0)]:
        for frames in frame_sets:
            out, state = {}, {}
            for on in (True, False):
                monkeypatch.setattr(native, "_enabled", on)
                emu = EventEmulator(seed=2, **kw)
                emu.reset(frames[0], 0)
                out[on] = [emu.step(frames[k], k * 100_000) for k in range(1, frames.shape[0])]
                state[on] = (emu.reference.clone(), emu._t_last.clone())
            for a, b in zip(out[True], out[False]):
                assert a == b, kw
            assert sum(len(a) for a in out[True]) > 0
            assert torch.equal(state[True][0], state[False][0]) and torch.equal(state[True][1], state[False][1]), kw


@pytest.mark.slow
def test_native_kernel_respects_the_event_cap(monkeypatch):
    monkeypatch.setattr(native, "_enabled", True)
    if native.load() is None:
        pytest.skip("no C++ toolchain for torch.utils.cpp_extension")
    frames = smooth_frames(2, 40, 48, 3, omega=0.8)
    emu = EventEmulator(max_events_per_step=100)
    emu.reset(frames[0], 0)
    with pytest.raises(ValueError, match="max_events_per_step"):
        emu.step(frames[1], 100_000)
