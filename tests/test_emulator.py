"""EventEmulator against a plain, slow, independent per-pixel float64 reference (issue 4).

The reference below is written for clarity, not speed: Python loops over pixels and over
crossings, one crossing at a time, following the pixel model of docs/events.md literally. It shares no code
with :mod:`dvsland.events.emulator`.
"""

import math
from collections import Counter

import numpy as np
import pytest
import torch

from dvsland.config.schema import EmulatorConfig
from dvsland.events import LEVEL_TOL, EventEmulator, Events


# the torch path is the reference here, whether or not the compiled kernels are built
# (test_emulator_native compares them with it)
pytestmark = pytest.mark.usefixtures("torch_event_path")


# ----------------------------------------------------------------------------- reference
class ReferencePixelModel:
    """Per-pixel DVS model: loops over pixels and crossings; float64 throughout."""

    def __init__(self, theta_on, theta_off, refractory_us, eps, interpolation):
        self.th_on, self.th_off = theta_on, theta_off
        self.r, self.eps, self.interp = refractory_us, eps, interpolation

    def reset(self, frames, t_us):
        f = np.asarray(frames, dtype=np.float64)
        self.B, self.H, self.W = f.shape
        self.i_prev = f.copy()
        self.lref = np.log(f + self.eps)
        self.t_last = np.full(f.shape, -math.inf)
        self.t = int(t_us)

    def step(self, frames, t_us):
        f = np.asarray(frames, dtype=np.float64)
        t0, t1 = self.t, int(t_us)
        dt = float(t1 - t0)
        events = []  # (b, x, y, t, p)
        for b in range(self.B):
            for y in range(self.H):
                for x in range(self.W):
                    i0, i1 = self.i_prev[b, y, x], f[b, y, x]
                    l0, l1 = math.log(i0 + self.eps), math.log(i1 + self.eps)
                    lref = self.lref[b, y, x]
                    while True:
                        if (l1 - lref) / self.th_on + LEVEL_TOL >= 1.0:  # next ON level reached
                            level, pol = lref + self.th_on, 1
                        elif (lref - l1) / self.th_off + LEVEL_TOL >= 1.0:  # next OFF level
                            level, pol = lref - self.th_off, -1
                        else:
                            break
                        if self.interp == "log":  # L is linear in time
                            frac = (level - l0) / (l1 - l0)
                        else:  # I is linear in time
                            frac = (math.exp(level) - self.eps - i0) / (i1 - i0)
                        tau = dt * frac
                        if t0 + tau - self.t_last[b, y, x] >= self.r:  # not refractory
                            t_int = t0 + min(max(math.floor(tau + 0.5), 1), int(dt))
                            events.append((b, x, y, t_int, pol))
                            self.t_last[b, y, x] = t0 + tau
                        lref = level  # the reference moves even when the event is dropped
                    self.lref[b, y, x] = lref
        self.i_prev = f
        self.t = t1
        return events


def as_tuples(ev: Events):
    return list(zip(ev.b.tolist(), ev.x.tolist(), ev.y.tolist(), ev.t.tolist(), ev.p.tolist()))


def assert_same_multiset(got, want, tol_us=1):
    """Identical event multisets, timestamps within tol_us."""
    assert len(got) == len(want), (len(got), len(want))
    key = lambda e: (e[0], e[1], e[2], e[4])  # noqa: E731
    g, w = {}, {}
    for e in got:
        g.setdefault(key(e), []).append(e[3])
    for e in want:
        w.setdefault(key(e), []).append(e[3])
    assert g.keys() == w.keys()
    for k in g:
        a, b = sorted(g[k]), sorted(w[k])
        assert len(a) == len(b), k
        assert max(abs(x - y) for x, y in zip(a, b)) <= tol_us, (k, a, b)


def random_run(interpolation, refractory_us, th_on, th_off, seed, B=2, H=5, W=7, steps=6,
               sigma=0.8, dt_range=(40, 3000), t_start=1000):
    rng = np.random.default_rng(seed)
    emu = EventEmulator(threshold=th_on, threshold_off=th_off, refractory_us=refractory_us,
                        interpolation=interpolation)
    ref = ReferencePixelModel(th_on, th_off, refractory_us, 1e-4, interpolation)
    f = rng.uniform(0.0, 1.0, (B, H, W)).astype(np.float32)
    f[0, 0, 0] = 0.0  # an exactly dark pixel
    t = t_start
    emu.reset(torch.from_numpy(f), t)
    ref.reset(f, t)
    n_total = 0
    for _ in range(steps):
        f = (f * np.exp(rng.normal(0.0, sigma, f.shape))).astype(np.float32)
        f[rng.uniform(size=f.shape) < 0.1] *= 0  # some pixels go dark: large OFF jumps
        t_prev, t = t, t + int(rng.integers(*dt_range))  # varying intervals
        ev = emu.step(torch.from_numpy(f), t)
        want = ref.step(f, t)
        got = as_tuples(ev)
        assert ev.is_sorted()
        assert all(t_prev < e[3] <= t for e in got)
        assert_same_multiset(got, want)
        n_total += len(want)
    return n_total


# ----------------------------------------------------------------------------- feature
@pytest.mark.parametrize("interpolation", ["log", "linear"])
@pytest.mark.parametrize("refractory_us", [0.0, 15.0, 400.0])
@pytest.mark.parametrize("th_on,th_off", [(0.1, 0.1), (0.07, 0.23)])
def test_step_matches_reference(interpolation, refractory_us, th_on, th_off):
    n = 0
    for seed in range(2):
        n += random_run(interpolation, refractory_us, th_on, th_off, seed=seed)
    assert n > 200  # multiple crossings per step actually happened


def test_reference_run_has_drops_and_both_polarities():
    """The random runs exercise refractory drops, both polarities, several crossings per step."""
    rng = np.random.default_rng(0)
    f0 = rng.uniform(0.0, 1.0, (2, 5, 7)).astype(np.float32)
    f1 = (f0 * np.exp(rng.normal(0.0, 0.8, f0.shape))).astype(np.float32)
    counts = {}
    for r in (0.0, 400.0):
        emu = EventEmulator(threshold=0.07, threshold_off=0.23, refractory_us=r)
        emu.reset(torch.from_numpy(f0), 0)
        ev = emu.step(torch.from_numpy(f1), 1000)
        counts[r] = ev
    ev = counts[0.0]
    assert (ev.p == 1).any() and (ev.p == -1).any()
    per_pixel = Counter(zip(ev.b.tolist(), ev.y.tolist(), ev.x.tolist()))
    assert max(per_pixel.values()) >= 5
    assert len(counts[400.0]) < len(ev)  # refractory drops


def test_exact_theta_change_emits():
    """A change of exactly θ emits one event (tolerance LEVEL_TOL), at the interval end."""
    th = 0.1
    i0 = torch.full((1, 1, 1), 0.5, dtype=torch.float64)
    i1 = (torch.exp(torch.log(i0 + 1e-4) + th) - 1e-4)
    emu = EventEmulator(threshold=th, refractory_us=0.0)
    emu.reset(i0, 0)
    ev = emu.step(i1, 100)
    assert len(ev) == 1 and ev.t.item() == 100 and ev.p.item() == 1
    ev = emu.step(i0, 200)
    assert len(ev) == 1 and ev.t.item() == 200 and ev.p.item() == -1


RAMP_TH = 0.1
RAMP_L0 = math.log(0.2 + 1e-4)


def _log_ramp(refractory_us: float, t0_us: int = 0):
    """One pixel whose L rises linearly from RAMP_L0 by 10.5 θ (θ = RAMP_TH) over 1000 µs from
    ``t0_us``; returns (emulator, events)."""
    i1 = math.exp(RAMP_L0 + 10.5 * RAMP_TH) - 1e-4
    emu = EventEmulator(threshold=RAMP_TH, refractory_us=refractory_us)
    emu.reset(torch.tensor([[[0.2]]]), t0_us)
    return emu, emu.step(torch.tensor([[[i1]]], dtype=torch.float64), t0_us + 1000)


def test_log_ramp_times_closed_form():
    """L rising linearly by 10.5 θ over 1000 µs: events at 1000 k / 10.5 µs, k = 1..10."""
    _, ev = _log_ramp(0.0)
    want = [math.floor(1000 * k / 10.5 + 0.5) for k in range(1, 11)]
    assert ev.t.tolist() == want
    assert ev.p.tolist() == [1] * 10


def test_refractory_closed_form():
    """Crossings every 95.2 µs with r = 200 µs: every third crossing is emitted."""
    emu, ev = _log_ramp(200.0)
    want = [math.floor(1000 * k / 10.5 + 0.5) for k in (1, 4, 7, 10)]
    assert ev.t.tolist() == want
    # the reference moved by all 10 crossings: a small drop now gives OFF events
    assert torch.allclose(emu.reference, torch.tensor([[[RAMP_L0 + 10 * RAMP_TH]]], dtype=torch.float64))


def test_precision_at_1e4_seconds():
    """t = 1e4 s = 1e10 µs: timestamps stay µs-exact (float32 would be off by ~500 µs)."""
    t0 = 10_000 * 1_000_000
    _, ev = _log_ramp(0.0, t0)
    want = [t0 + math.floor(1000 * k / 10.5 + 0.5) for k in range(1, 11)]
    assert ev.t.dtype == torch.int64
    assert ev.t.tolist() == want


def test_precision_long_run_matches_reference():
    """Many steps up to t > 1e4 s with random frames: same events as the reference."""
    rng = np.random.default_rng(3)
    f = rng.uniform(0.1, 1.0, (1, 3, 4)).astype(np.float32)
    t = 10_000 * 1_000_000 - 5 * 100_000
    emu = EventEmulator(threshold=0.1, refractory_us=15.0)
    ref = ReferencePixelModel(0.1, 0.1, 15.0, 1e-4, "log")
    emu.reset(torch.from_numpy(f), t)
    ref.reset(f, t)
    for _ in range(10):
        f = (f * np.exp(rng.normal(0.0, 0.5, f.shape))).astype(np.float32)
        t += 100_000
        assert_same_multiset(as_tuples(emu.step(torch.from_numpy(f), t)), ref.step(f, t))
    assert t > 10_000 * 1_000_000


def test_events_output_contract():
    rng = np.random.default_rng(1)
    f0 = torch.from_numpy(rng.uniform(0, 1, (3, 8, 9)).astype(np.float32))
    f1 = f0 * torch.exp(torch.randn(3, 8, 9, generator=torch.Generator().manual_seed(0)))
    emu = EventEmulator()
    emu.reset(f0, 0)
    ev = emu.step(f1, 100_000)
    assert len(ev) > 0
    assert ev.b.dtype == torch.int64 and ev.x.dtype == torch.int64 and ev.y.dtype == torch.int64
    assert ev.t.dtype == torch.int64 and ev.p.dtype == torch.int8
    ev.validate(3, 8, 9)
    assert set(ev.p.tolist()) <= {-1, 1}


def test_no_change_no_events_and_empty():
    f = torch.rand(2, 4, 4)
    emu = EventEmulator()
    emu.reset(f, 0)
    ev = emu.step(f.clone(), 10)
    assert len(ev) == 0 and isinstance(ev, Events)


@pytest.mark.parametrize("refractory_us", [15.0, 3e9])
def test_int64_key_path_long_interval(refractory_us):
    """Steps too long for the int32 (b, t) key use the int64 key: same events as the reference
    (with r = 3e9 µs most crossings are dropped)."""
    rng = np.random.default_rng(5)
    f0 = rng.uniform(0.0, 1.0, (2, 3, 3)).astype(np.float32)
    f1 = (f0 * np.exp(rng.normal(0, 1.0, f0.shape))).astype(np.float32)
    emu = EventEmulator(refractory_us=refractory_us)
    ref = ReferencePixelModel(0.1, 0.1, refractory_us, 1e-4, "log")
    emu.reset(torch.from_numpy(f0), 0)
    ref.reset(f0, 0)
    dt = 2 ** 33  # > 31 bits with b
    got = emu.step(torch.from_numpy(f1), dt)
    assert got.is_sorted()
    assert_same_multiset(as_tuples(got), ref.step(f1, dt))


def test_dark_frames_and_float64_input():
    """I = 0 is allowed (L = log eps); float64 frames are accepted; input is not modified."""
    f0 = torch.zeros(1, 2, 2, dtype=torch.float64)
    f1 = torch.ones(1, 2, 2, dtype=torch.float64)
    keep = f1.clone()
    emu = EventEmulator(threshold=0.1, refractory_us=0.0)
    emu.reset(f0, 0)
    ev = emu.step(f1, 100_000)
    assert torch.equal(f1, keep)
    n = math.floor((math.log(1 + 1e-4) - math.log(1e-4)) / 0.1 + LEVEL_TOL)
    assert len(ev) == 4 * n


# ----------------------------------------------------------------------------- options
def test_from_config_and_mismatch_background_seeded():
    cfg = EmulatorConfig(threshold=0.2, threshold_off=0.3, refractory_us=5.0, interpolation="linear",
                         mismatch_sigma=0.1, background_rate_hz=50.0)
    emu = EventEmulator.from_config(cfg, device="cpu", seed=7)
    assert (emu.threshold, emu.threshold_off, emu.refractory_us, emu.interpolation) == (
        0.2, 0.3, 5.0, "linear")
    f = torch.rand(2, 16, 16, generator=torch.Generator().manual_seed(0)) + 0.1

    def run(seed):
        e = EventEmulator.from_config(cfg, seed=seed)
        e.reset(f, 0)
        return e.step(f * 1.5, 100_000)

    a, b, c = run(7), run(7), run(8)
    assert a == b and not (a == c)
    assert a.is_sorted()
    # background only: no change of the frames still gives events (about 50 Hz * 0.1 s * 512 px)
    e = EventEmulator(background_rate_hz=50.0, seed=1)
    e.reset(f, 0)
    ev = e.step(f, 100_000)
    assert 1500 < len(ev) < 3700 and ev.is_sorted()
    ev.validate(2, 16, 16)


def test_mismatch_is_per_element_and_changes_counts():
    f = torch.rand(4, 8, 8, generator=torch.Generator().manual_seed(0)) + 0.1
    ideal = EventEmulator(refractory_us=0.0)
    ideal.reset(f, 0)
    n_ideal = len(ideal.step(f * 3.0, 1000))
    emu = EventEmulator(refractory_us=0.0, mismatch_sigma=0.3, seed=3)
    emu.reset(f, 0)
    th4 = emu._th_on.clone()
    assert len(emu.step(f * 3.0, 1000)) != n_ideal
    emu2 = EventEmulator(refractory_us=0.0, mismatch_sigma=0.3, seed=3)
    emu2.reset(f[:2], 0)
    assert torch.equal(emu2._th_on, th4[:2])  # element b's draw does not depend on B


# ----------------------------------------------------------------------------- errors
@pytest.mark.parametrize("kwargs,match", [
    (dict(threshold=0.0), "threshold"),
    (dict(threshold=-1.0), "threshold"),
    (dict(threshold_off=0.0), "threshold_off"),
    (dict(threshold=float("nan")), "threshold"),
    (dict(refractory_us=-1.0), "refractory_us"),
    (dict(log_eps=0.0), "log_eps"),
    (dict(interpolation="cubic"), "interpolation"),
    (dict(mismatch_sigma=-0.1), "mismatch_sigma"),
    (dict(background_rate_hz=-1.0), "background_rate_hz"),
])
def test_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        EventEmulator(**kwargs)


def test_bad_frames_and_times():
    f = torch.rand(2, 4, 4)
    emu = EventEmulator()
    with pytest.raises(RuntimeError, match="reset"):
        emu.step(f, 1)
    with pytest.raises(ValueError, match="NaN"):
        emu.reset(torch.full((2, 4, 4), float("nan")), 0)
    with pytest.raises(ValueError, match="inf"):
        emu.reset(torch.full((2, 4, 4), float("inf")), 0)
    with pytest.raises(ValueError, match="negative"):
        emu.reset(-f, 0)
    with pytest.raises(ValueError, match=r"\(B, H, W\)"):
        emu.reset(f[0], 0)
    with pytest.raises(ValueError, match="floating"):
        emu.reset(torch.ones(2, 4, 4, dtype=torch.int64), 0)
    emu.reset(f, 100)
    with pytest.raises(ValueError, match="batch size"):
        emu.step(torch.rand(3, 4, 4), 200)
    with pytest.raises(ValueError, match="sensor size"):
        emu.step(torch.rand(2, 4, 5), 200)
    with pytest.raises(ValueError, match="increase"):
        emu.step(f, 100)
    with pytest.raises(ValueError, match="increase"):
        emu.step(f, 50)
    with pytest.raises(ValueError, match="t_us"):
        emu.step(f, 150.5)
    bad = f.clone()
    bad[1, 2, 3] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        emu.step(bad, 200)
    bad[1, 2, 3] = -0.5
    with pytest.raises(ValueError, match="negative"):
        emu.step(bad, 200)
    assert emu.t_us == 100  # a rejected step changes nothing
    assert len(emu.step(f, 200)) == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    rng = np.random.default_rng(0)
    f0 = torch.from_numpy(rng.uniform(0, 1, (4, 32, 32)).astype(np.float32))
    frames = [f0 * torch.exp(torch.randn(4, 32, 32, generator=torch.Generator().manual_seed(k)))
              for k in range(3)]
    out = {}
    for dev in ("cpu", "cuda"):
        emu = EventEmulator(refractory_us=50.0, device=dev)
        emu.reset(f0, 0)
        out[dev] = Events.cat([emu.step(f, 1000 * (k + 1)) for k, f in enumerate(frames)])
    assert out["cpu"] == out["cuda"].to("cpu")


@pytest.mark.parametrize("interpolation", ["log", "linear"])
def test_cpu_blocking_does_not_change_events(monkeypatch, interpolation):
    """Candidates processed in small blocks (cache blocking) give the same events and state."""
    import dvsland.events.emulator as emulator_mod

    rng = np.random.default_rng(11)
    frames = [torch.from_numpy(rng.uniform(0, 1, (3, 6, 7)).astype(np.float32))]
    for _ in range(4):
        frames.append(frames[-1] * torch.from_numpy(np.exp(rng.normal(0, 0.8, (3, 6, 7))).astype(np.float32)))
    out = {}
    for block in (1 << 17, 5):
        monkeypatch.setattr(emulator_mod, "_CPU_BLOCK", block)
        emu = EventEmulator(refractory_us=300.0, interpolation=interpolation)
        emu.reset(frames[0], 0)
        out[block] = [emu.step(f, 1000 * (k + 1)) for k, f in enumerate(frames[1:])]
        out[block].append(emu.reference.clone())
    for a, b in zip(out[1 << 17][:-1], out[5][:-1]):
        assert a == b and len(a) > 0
    assert torch.equal(out[1 << 17][-1], out[5][-1])


@pytest.mark.parametrize("interpolation", ["log", "linear"])
@pytest.mark.parametrize("th_off", [None, 0.15])
def test_generic_torch_paths_match_cpu_fast_paths(monkeypatch, interpolation, th_off):
    """The device-generic paths (torch.nonzero, torch.sort; used on CUDA) give the same events
    as the CPU fast paths (numpy scan and sort, blocking)."""
    import dvsland.events.emulator as emulator_mod

    rng = np.random.default_rng(12)
    frames = [torch.from_numpy(rng.uniform(0, 1, (3, 9, 8)).astype(np.float32))]
    for _ in range(3):
        frames.append(frames[-1] * torch.from_numpy(np.exp(rng.normal(0, 0.8, (3, 9, 8))).astype(np.float32)))
    out = {}
    for fast in (True, False):
        monkeypatch.setattr(emulator_mod, "CPU_FAST_PATHS", fast)
        emu = EventEmulator(threshold_off=th_off, refractory_us=200.0, interpolation=interpolation,
                            background_rate_hz=100.0, seed=3)
        emu.reset(frames[0], 0)
        out[fast] = [emu.step(f, 5000 * (k + 1)) for k, f in enumerate(frames[1:])]
    for a, b in zip(out[True], out[False]):
        assert a == b and len(a) > 0
