"""Front-end denoising (dvsland.events.denoise): the batched filters against tiny by-hand loops
written from tonic's definitions, across steps, and the emulator's denoise hook."""

import numpy as np
import pytest
import torch

from dvsland.events import EventEmulator, Events
from dvsland.events import denoise as dn


# ------------------------------------------------------------------ by-hand references (one event at a time)
def ref_baf(evs, B, H, W, time_us, neighbours, mem=None):
    mem = {} if mem is None else mem
    offs = dn._OFFSETS[neighbours]
    keep = []
    for b, x, y, t in evs:
        ok = False
        for dx, dy in offs:
            xn, yn = x + dx, y + dy
            if 0 <= xn < W and 0 <= yn < H and (b, xn, yn) in mem and t - mem[(b, xn, yn)] < time_us:
                ok = True
        mem[(b, x, y)] = t
        keep.append(ok)
    return keep, mem


def ref_refractory(evs, period_us, mem=None):
    mem = {} if mem is None else mem
    keep = []
    for b, x, y, t in evs:
        keep.append((b, x, y) not in mem or t - mem[(b, x, y)] > period_us)
        mem[(b, x, y)] = t
    return keep, mem


def ref_hot(evs, count, elapsed_us, rate_hz):
    for b, x, y, t in evs:
        count[(b, x, y)] = count.get((b, x, y), 0) + 1
    return [count[(b, x, y)] <= rate_hz * elapsed_us * 1e-6 for b, x, y, t in evs], count


def random_events(rng, n, B, H, W, t0, t1):
    b = rng.integers(0, B, n)
    t = rng.integers(t0 + 1, t1 + 1, n)
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    p = rng.choice([-1, 1], n)
    ev = Events(b=torch.from_numpy(b), x=torch.from_numpy(x), y=torch.from_numpy(y), t=torch.from_numpy(t),
                p=torch.from_numpy(p).to(torch.int8)).sort()
    return ev


def tuples(ev):
    return list(zip(ev.b.tolist(), ev.x.tolist(), ev.y.tolist(), ev.t.tolist()))


@pytest.fixture(params=[True, False], ids=["numpy", "generic"])
def paths(request, monkeypatch):
    """Both the CPU numpy path and the device-generic torch path (the one CUDA runs)."""
    monkeypatch.setattr(dn, "CPU_FAST_PATHS", request.param)


@pytest.mark.parametrize("neighbours", [4, 8])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_baf_matches_reference_over_steps(neighbours, seed, paths):
    rng = np.random.default_rng(seed)
    B, H, W = 2, 5, 6
    state = dn.init_state(B, H, W, 0)
    mem = {}
    for k in range(3):  # memory carried across steps
        ev = random_events(rng, 40, B, H, W, k * 1000, (k + 1) * 1000)
        window = 300 if seed else 300.5  # a window that is not whole microseconds too
        keep, m = dn.baf_keep(ev, state.baf_t_us, window, neighbours)
        state = state._replace(baf_t_us=m)
        want, mem = ref_baf(tuples(ev), B, H, W, window, neighbours, mem)
        assert keep.tolist() == want
    assert 0 < sum(want) < len(want)  # the case is not trivial


def test_baf_ties_and_self():
    # the pixel's own earlier event never supports it; a neighbour at the same time earlier in the stream does
    ev = Events(b=torch.tensor([0, 0, 0, 0]), x=torch.tensor([1, 1, 2, 3]), y=torch.tensor([1, 1, 1, 3]),
                t=torch.tensor([10, 20, 20, 5000]), p=torch.ones(4, dtype=torch.int8))
    st = dn.init_state(1, 4, 4, 0)
    keep, _ = dn.baf_keep(ev, st.baf_t_us, 100, 4)
    assert keep.tolist() == [False, False, True, False]


@pytest.mark.parametrize("seed", [0, 3])
def test_refractory_matches_reference(seed, paths):
    rng = np.random.default_rng(seed)
    B, H, W = 2, 3, 3
    state = dn.init_state(B, H, W, 0)
    mem = {}
    for k in range(3):
        ev = random_events(rng, 50, B, H, W, k * 1000, (k + 1) * 1000)
        keep, m = dn.refractory_keep(ev, state.refractory_t_us, 150 if seed else 150.5)
        state = state._replace(refractory_t_us=m)
        want, mem = ref_refractory(tuples(ev), 150 if seed else 150.5, mem)
        assert keep.tolist() == want
    assert 0 < sum(want) < len(want)


def test_hot_pixel_matches_reference():
    rng = np.random.default_rng(5)
    B, H, W = 2, 4, 4
    state = dn.init_state(B, H, W, 0)
    count = {}
    for k in range(3):
        ev = random_events(rng, 60, B, H, W, k * 100_000, (k + 1) * 100_000)
        # one hot pixel: 20 extra events per step
        hot = Events(b=torch.zeros(20, dtype=torch.int64), x=torch.full((20,), 2), y=torch.full((20,), 1),
                     t=torch.arange(20) * 1000 + k * 100_000 + 1, p=torch.ones(20, dtype=torch.int8))
        ev = Events.cat([ev, hot]).sort()
        keep, c = dn.hot_pixel_keep(ev, state.hot_count, (k + 1) * 100_000, 60.0)
        state = state._replace(hot_count=c)
        want, count = ref_hot(tuples(ev), count, (k + 1) * 100_000, 60.0)
        assert keep.tolist() == want
        assert not any(kp for kp, e in zip(want, tuples(ev)) if e[:3] == (0, 2, 1))


def test_chain_and_parse(paths):
    assert dn.parse_filters("none") == ()
    assert dn.parse_filters("hot_pixel+baf") == ("hot_pixel", "baf")
    with pytest.raises(ValueError, match="emulator.denoise"):
        dn.parse_filters("median")
    with pytest.raises(ValueError, match="denoise_baf_neighbours"):
        dn.EventDenoiser("baf", baf_neighbours=6)
    with pytest.raises(ValueError, match="denoise_baf_time_us"):
        dn.EventDenoiser("baf", baf_time_us=0)
    rng = np.random.default_rng(7)
    ev = random_events(rng, 80, 1, 4, 4, 0, 1000)
    d = dn.EventDenoiser("refractory+baf", baf_time_us=200, refractory_us=50)
    d.reset(1, 4, 4, 0)
    out = d(ev, 1000)
    k1, _ = ref_refractory(tuples(ev), 50)
    ev1 = ev[torch.tensor(k1)]
    k2, _ = ref_baf(tuples(ev1), 1, 4, 4, 200, 4)
    assert out == ev1[torch.tensor(k2)]


def test_unsorted_events_refused():
    ev = Events(b=torch.tensor([0, 0]), x=torch.tensor([0, 1]), y=torch.tensor([0, 0]), t=torch.tensor([5, 3]),
                p=torch.ones(2, dtype=torch.int8))
    d = dn.EventDenoiser("baf")
    d.reset(1, 2, 2, 0)
    with pytest.raises(ValueError, match="sorted"):
        d(ev, 10)


def test_emulator_hook_removes_isolated_noise():
    """With shot noise on a static scene every event is isolated noise: baf keeps only those with a
    neighbour within 500 us (about 1 - exp(-4 * 20 Hz * 0.5 ms) = 4 %),
    and the emulator with denoise='none' is unchanged."""
    f = torch.full((2, 32, 32), 0.05)
    kw = dict(shot_noise_rate_hz=20.0, seed=3)
    plain, filt = EventEmulator(**kw), EventEmulator(**kw, denoise="baf", denoise_baf_time_us=500)
    for e in (plain, filt):
        e.reset(f, 0)
    n_plain = n_filt = 0
    for k in range(1, 4):
        a, b = plain.step(f, k * 100_000), filt.step(f, k * 100_000)
        n_plain, n_filt = n_plain + len(a), n_filt + len(b)
        # the filtered events are a subset of the unfiltered ones (same noise stream)
        sa = set(tuples(a))
        assert all(e in sa for e in tuples(b))
    assert n_plain > 500 and n_filt < 0.1 * n_plain


@pytest.mark.parametrize("neighbours", [4, 8])
def test_native_filters_match_reference(neighbours, monkeypatch):
    """The compiled loops (DVSLAND_NATIVE_SORT; compiled on first use) against the by-hand
    references, across steps, with windows that are not whole microseconds."""
    from dvsland.events import native

    monkeypatch.setattr(native.LIBRARY, "chosen", True)
    if native.load() is None:
        pytest.skip("no C++ compiler here")
    rng = np.random.default_rng(9)
    B, H, W = 2, 5, 6
    state = dn.init_state(B, H, W, 0)
    mem_b, mem_r = {}, {}
    for k in range(3):
        ev = random_events(rng, 60, B, H, W, k * 1000, (k + 1) * 1000)
        keep, m = dn.baf_keep(ev, state.baf_t_us, 300.5, neighbours)
        want, mem_b = ref_baf(tuples(ev), B, H, W, 300.5, neighbours, mem_b)
        assert keep.tolist() == want
        keep_r, m_r = dn.refractory_keep(ev, state.refractory_t_us, 150.5)
        want_r, mem_r = ref_refractory(tuples(ev), 150.5, mem_r)
        assert keep_r.tolist() == want_r
        state = state._replace(baf_t_us=m, refractory_t_us=m_r)
    monkeypatch.setattr(native.LIBRARY, "chosen", False)
    assert 0 < sum(want) < len(want) and 0 < sum(want_r) < len(want_r)
