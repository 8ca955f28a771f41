"""The CPU fast paths of the emulator (numpy candidate scan and sort, blocking, dense-frame
kernels) give exactly the events and state of the device-generic reference path (the one CUDA
runs), on sparse and dense frames and with every pixel-model part on."""

import pytest
import torch

from dvsland.events import emulator as emu_mod
from dvsland.events.benchmark import smooth_frames
from dvsland.events.emulator import EventEmulator


# the torch path is the reference here, whether or not the compiled kernels are built
# (test_emulator_native compares them with it)
pytestmark = pytest.mark.usefixtures("torch_event_path")


CONFIGS = [dict(), dict(refractory_us=0.0), dict(refractory_us=3000.0), dict(threshold=0.05, threshold_off=0.2),
           dict(mismatch_sigma=0.1), dict(shot_noise_rate_hz=50.0), dict(shot_noise_rate_hz=5.0, background_rate_hz=20.0),
           dict(shot_noise_rate_hz=20.0, photoreceptor_cutoff_hz=100.0, leak_rate_hz=1.0, hot_pixel_fraction=0.01,
                mismatch_sigma=0.05, full_irradiance=0.5)]


def _frames():
    g = torch.Generator().manual_seed(11)
    yield torch.rand(5, 3, 17, 23, generator=g) * 2
    yield smooth_frames(3, 40, 48, 5, omega=0.8)  # dense: several events per pixel and frame
    yield smooth_frames(2, 33, 70, 4, omega=0.3)  # sizes that are not powers of two


def _run(frames, kw):
    emu = EventEmulator(seed=5, **kw)
    emu.reset(frames[0], 0)
    return [emu.step(frames[k], k * 50_000) for k in range(1, frames.shape[0])], emu


@pytest.mark.parametrize("kw", CONFIGS, ids=lambda kw: ",".join(f"{k}={v}" for k, v in kw.items()) or "ideal")
def test_fast_paths_equal_reference(kw, monkeypatch):
    for frames in _frames():
        monkeypatch.setattr(emu_mod, "CPU_FAST_PATHS", True)
        fast, emu_f = _run(frames, kw)
        monkeypatch.setattr(emu_mod, "CPU_FAST_PATHS", False)
        ref, emu_r = _run(frames, kw)
        assert sum(len(e) for e in ref) > 0
        for a, b in zip(fast, ref):
            assert a == b
            assert a.is_sorted()
        assert torch.equal(emu_f.reference, emu_r.reference)
        assert torch.equal(emu_f._t_last, emu_r._t_last)


def test_noise_candidates_uniform_and_poisson():
    """The counter-based noise candidates (pixel_model.uniform_events): Poisson counts per descent,
    uniform over pixels and integer times, descents independent of each other."""
    from dvsland.events import pixel_model as pm

    B, H, W, dt = 4, 21, 37, 100_000
    seed = torch.arange(B, dtype=torch.int64) + 3
    step = torch.ones(B, dtype=torch.int64)
    lam = torch.full((B,), 200.0 * dt * 1e-6 * H * W, dtype=torch.float64)
    flat, t_rel, u = pm.uniform_events(seed, step, lam, H * W, dt, pm.TAG_SHOT)
    b, pix = flat // (H * W), flat % (H * W)
    x, y = pix % W, pix // W
    assert flat.numel() > 1000 and int(t_rel.min()) >= 1 and int(t_rel.max()) <= dt
    counts = torch.bincount(b, minlength=B).double()
    assert abs(float(counts.mean()) / float(lam[0]) - 1) < 0.05
    assert torch.bincount(x, minlength=W).min() > 0.7 * flat.numel() / W
    assert torch.bincount(y, minlength=H).min() > 0.7 * flat.numel() / H
    assert abs(float(u.mean()) - 0.5) < 0.01


@pytest.mark.parametrize("rate_hz", [1e-15, 1e-3, 1e7])
def test_noise_candidates_at_extreme_rates(rate_hz):
    """A vanishing rate gives (almost surely) no event; a huge one a count near its mean (the normal
    approximation of the inverse CDF), every event on the sensor and in the interval."""
    from dvsland.events import pixel_model as pm

    seed, step = torch.tensor([0, 1]), torch.tensor([5, 5])
    lam = torch.full((2,), rate_hz * 1000 * 1e-6 * 16, dtype=torch.float64)
    flat, t_rel, u = pm.uniform_events(seed, step, lam, 16, 1000, pm.TAG_SHOT)
    n = flat.numel()
    if rate_hz < 1:
        assert n == 0
    else:
        mu = 2 * float(lam[0])
        assert abs(n - mu) < 5 * mu ** 0.5
        assert int(flat.min()) >= 0 and int(flat.max()) < 32 and int(t_rel.min()) >= 1 and int(t_rel.max()) <= 1000


@pytest.mark.parametrize("numpy_faster", [True, False])
@pytest.mark.parametrize("threads", [1, 2])
def test_cpu_sort_is_the_same_with_one_or_more_threads(threads, numpy_faster, monkeypatch):
    """The torch path sorts with numpy's sort where it is faster (or with several threads), else
    torch.sort: the same events either way."""
    from dvsland.events.emulator import _sort_values

    monkeypatch.setattr(emu_mod, "_numpy_sorts_faster", lambda: numpy_faster)
    g = torch.Generator().manual_seed(1)
    keys = torch.randint(0, 2 ** 40, (50_001,), generator=g)
    keys[::7] = keys[0]  # repeated keys too
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        assert torch.equal(_sort_values(keys.clone()), torch.sort(keys).values)
        frames = smooth_frames(2, 20, 24, 3, omega=0.5)
        got, _ = _run(frames, dict(shot_noise_rate_hz=50.0))
    finally:
        torch.set_num_threads(before)
    ref, _ = _run(frames, dict(shot_noise_rate_hz=50.0))
    assert got == ref and sum(len(e) for e in got) > 0


def test_merge_of_sorted_keys_equals_a_sort():
    from dvsland.events.emulator import _merge_sorted

    g = torch.Generator().manual_seed(2)
    a = torch.sort(torch.randint(0, 1000, (3_001,), generator=g)).values  # with ties inside and across
    b = torch.sort(torch.randint(0, 1000, (10_007,), generator=g)).values
    assert torch.equal(_merge_sorted(a, b), torch.sort(torch.cat((a, b))).values)
    assert torch.equal(_merge_sorted(a[:0], b), b) and torch.equal(_merge_sorted(a, b[:0]), a)


def test_sort_choice_is_measured_once_and_is_a_bool():
    emu_mod._numpy_sorts_faster.cache_clear()
    first = emu_mod._numpy_sorts_faster()
    assert isinstance(first, bool) and emu_mod._numpy_sorts_faster() is first
    assert emu_mod._numpy_sorts_faster.cache_info().misses == 1


@pytest.mark.parametrize("n, p", [(0, 0.5), (1, 1.0), (7, 0.0), (7, 1.0), (1000, 0.3), (4097, 0.9)])
def test_compact_equals_nonzero(n, p):
    """The sync-free compaction of the GPU path: the indices nonzero gives, given their number."""
    from dvsland.events.emulator import _compact

    m = torch.rand(n, generator=torch.Generator().manual_seed(n)) < p
    assert torch.equal(_compact(m, int(m.sum())), m.nonzero().squeeze(1))
