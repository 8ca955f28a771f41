"""Property tests (hypothesis) of the EventEmulator: invariants of the pixel model."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dvsland.events import LEVEL_TOL, EventEmulator


# the torch path is the reference here, whether or not the compiled kernels are built
# (test_emulator_native compares them with it)
pytestmark = pytest.mark.usefixtures("torch_event_path")


SETTINGS = settings(max_examples=30, deadline=None)


@st.composite
def runs(draw):
    """A random emulator setting and a random sequence of frames with varying intervals."""
    B = draw(st.integers(1, 3))
    H = draw(st.integers(1, 5))
    W = draw(st.integers(1, 5))
    n_steps = draw(st.integers(1, 5))
    seed = draw(st.integers(0, 2 ** 31 - 1))
    sigma = draw(st.floats(0.0, 2.0))
    rng = np.random.default_rng(seed)
    frames = [rng.uniform(0.0, 2.0, (B, H, W))]
    for _ in range(n_steps):
        nxt = frames[-1] * np.exp(rng.normal(0.0, sigma, (B, H, W)))
        nxt[rng.uniform(size=nxt.shape) < 0.05] = 0.0
        frames.append(nxt)
    dts = [int(d) for d in rng.integers(1, 200_000, n_steps)]
    t0 = draw(st.integers(0, 10 ** 10))
    params = dict(
        threshold=draw(st.floats(0.02, 1.0)),
        threshold_off=draw(st.one_of(st.none(), st.floats(0.02, 1.0))),
        refractory_us=draw(st.sampled_from([0.0, 1.0, 15.0, 1000.0])),
        interpolation=draw(st.sampled_from(["log", "linear"])),
    )
    return params, [torch.tensor(f, dtype=torch.float32) for f in frames], dts, t0


def _emulate(params, frames, dts, t0):
    emu = EventEmulator(**params)
    emu.reset(frames[0], t0)
    t, out = t0, []
    for f, dt in zip(frames[1:], dts):
        ev = emu.step(f, t + dt)
        out.append((t, t + dt, ev))
        t += dt
    return out


@SETTINGS
@given(runs())
def test_times_in_interval_and_sorted(run):
    params, frames, dts, t0 = run
    for t_prev, t, ev in _emulate(params, frames, dts, t0):
        if len(ev):
            assert int(ev.t.min()) > t_prev and int(ev.t.max()) <= t
        assert ev.is_sorted()
        ev.validate(*frames[0].shape)


@SETTINGS
@given(runs())
def test_per_pixel_times_non_decreasing_and_refractory(run):
    params, frames, dts, t0 = run
    B, H, W = frames[0].shape
    last = {}
    r = params["refractory_us"]
    for _, _, ev in _emulate(params, frames, dts, t0):
        for b, x, y, t in zip(ev.b.tolist(), ev.x.tolist(), ev.y.tolist(), ev.t.tolist()):
            k = (b, x, y)
            if k in last:
                assert t >= last[k]
                # emitted events are >= r apart in float time; after rounding, >= r - 1 µs
                assert t - last[k] >= r - 1
            last[k] = t


@SETTINGS
@given(runs())
def test_no_change_no_events(run):
    params, frames, dts, t0 = run
    emu = EventEmulator(**params)
    emu.reset(frames[0], t0)
    t = t0
    for dt in dts:
        t += dt
        assert len(emu.step(frames[0].clone(), t)) == 0


@SETTINGS
@given(runs())
def test_net_events_equal_quantised_log_change(run):
    """Without refractory, per pixel and step: net events = the log change from the pixel's
    reference quantised by the threshold (floor towards the reference), and the reference
    tracks L_init + θ_on * #ON - θ_off * #OFF."""
    params, frames, dts, t0 = run
    params = dict(params, refractory_us=0.0)
    th_on = params["threshold"]
    th_off = params["threshold_off"] if params["threshold_off"] is not None else th_on
    eps = 1e-4
    B, H, W = frames[0].shape
    lref = np.log(frames[0].numpy().astype(np.float64) + eps)
    for (t_prev, t, ev), f in zip(_emulate(params, frames, dts, t0), frames[1:]):
        l1 = np.log(f.numpy().astype(np.float64) + eps)
        on = np.zeros((B, H, W), np.int64)
        off = np.zeros((B, H, W), np.int64)
        for b, x, y, p in zip(ev.b.tolist(), ev.x.tolist(), ev.y.tolist(), ev.p.tolist()):
            (on if p > 0 else off)[b, y, x] += 1
        want_on = np.maximum(np.floor((l1 - lref) / th_on + LEVEL_TOL), 0)
        want_off = np.maximum(np.floor((lref - l1) / th_off + LEVEL_TOL), 0)
        assert np.array_equal(on, want_on) and np.array_equal(off, want_off)
        assert not np.any((on > 0) & (off > 0))  # one polarity per pixel and step
        lref = lref + on * th_on - off * th_off
        assert np.all(l1 - lref < th_on) and np.all(lref - l1 < th_off)
