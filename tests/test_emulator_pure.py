"""The emulator under the stage contract (dvsland.pytree): EmulatorParams + EmulatorState + the pure
step. The step never writes its input state and depends on nothing else; reset_where restarts some
descents and leaves the others bit-identical; the noise is counter-based data (seed, step, pixel,
stream), so a descent's noise does not depend on its batch-mates, the device or a Python loop over
the batch; a malformed state is refused naming the field."""

import math

import numpy as np
import pytest
import torch

from dvsland import pytree
from dvsland.events import Events, EventEmulator
from dvsland.events import emulator as emu_mod
from dvsland.events import pixel_model as pm
from dvsland.events.benchmark import smooth_frames
from dvsland.events.emulator import EmulatorState, emulator_step
from dvsland.pytree import tree_clone, tree_equal

Z = 5.0  # sigmas

NOISY = dict(mismatch_sigma=0.05, background_rate_hz=20.0, shot_noise_rate_hz=10.0, photoreceptor_cutoff_hz=50.0,
             leak_rate_hz=2.0, hot_pixel_fraction=0.02, refractory_us=50.0)
CONFIGS = [dict(), dict(interpolation="linear", threshold_off=0.15), NOISY,
           dict(NOISY, denoise="hot_pixel+baf+refractory"), dict(mismatch_sigma=0.1, background_rate_hz=50.0)]
IDS = ["ideal", "linear", "noisy", "noisy+denoise", "mismatch+background"]


def _frames(B=3, H=12, W=14, n=5):
    return smooth_frames(B, H, W, n, omega=0.6)


def _events_of(ev: Events, b: int) -> Events:
    e = ev.select_batch(b)
    return Events(torch.zeros_like(e.b), e.x, e.y, e.t, e.p)


# ------------------------------------------------------------------------------- purity
@pytest.mark.parametrize("kw", CONFIGS, ids=IDS)
def test_step_is_pure(kw):
    frames = _frames()
    emu = EventEmulator(seed=4, **kw)
    st = emu.init_state(frames[0], 1000)
    for k in range(1, frames.shape[0]):
        before = tree_clone(st)
        a_state, a_ev = emu.step_state(st, frames[k], 1000 + k * 20_000)
        assert tree_equal(before, st)  # the input state is not written
        b_state, b_ev = emu.step_state(st, frames[k], 1000 + k * 20_000)
        assert a_ev == b_ev and tree_equal(a_state, b_state)  # same state -> same outputs
        st = a_state
    assert int(st.step[0]) == frames.shape[0] - 1 and bool((st.t_us == 1000 + 4 * 20_000).all())


@pytest.mark.parametrize("kw", CONFIGS, ids=IDS)
def test_object_api_is_the_contract(kw):
    """reset / step hold one state: the same events and state as init_state / step_state."""
    frames = _frames()
    emu = EventEmulator(seed=2, **kw)
    emu.reset(frames[0], 0)
    st = emu.init_state(frames[0], 0)
    for k in range(1, frames.shape[0]):
        ev = emu.step(frames[k], k * 30_000)
        st, ev2 = emu.step_state(st, frames[k], k * 30_000)
        assert ev == ev2
    assert tree_equal(st, emu.state)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])
@pytest.mark.parametrize("kw", [dict(), NOISY, dict(refractory_us=20_000.0, threshold_off=0.15)],
                         ids=["ideal", "noisy", "refractory"])
def test_donate_gives_the_same_events(kw, compiled, monkeypatch):
    """donate=True works on the handed-over buffers in place: the same events and next state, with
    the compiled pixel kernel and with the torch path (the one a GPU runs, where the loop donates too)."""
    from dvsland.events import native

    monkeypatch.setattr(native.LIBRARY, "chosen", compiled)
    if compiled and native.load() is None:
        pytest.skip("no C++ compiler here")
    frames = _frames()
    emu = EventEmulator(seed=1, **kw)
    a = b = emu.init_state(frames[0], 0)
    for k in range(1, frames.shape[0]):
        a, ev_a = emu.step_state(a, frames[k], k * 10_000)
        b, ev_b = emu.step_state(tree_clone(b), frames[k], k * 10_000, donate=True)
        assert ev_a == ev_b and tree_equal(a, b)


# --------------------------------------------------------------------------- reset_where
@pytest.mark.parametrize("kw", CONFIGS, ids=IDS)
def test_reset_where_leaves_the_others_bit_identical(kw):
    frames = _frames(B=4)
    emu = EventEmulator(seed=6, **kw)
    st = emu.init_state(frames[0], 0)
    st, _ = emu.step_state(st, frames[1], 10_000)
    mask = torch.tensor([False, True, False, True])
    new_frames = frames[2].flip(-1)
    seeds = torch.tensor([100, 101, 102, 103])
    rs = emu.reset_where(st, mask, new_frames, 10_000, seed=seeds)
    for name, (x, y) in zip(pytree.tree_leaves(st), zip(pytree.tree_leaves(st).values(),
                                                        pytree.tree_leaves(rs).values())):
        assert torch.equal(x[~mask], y[~mask]), name
    assert torch.equal(rs.seed, torch.where(mask, seeds, st.seed)) and rs.step.tolist() == [1, 0, 1, 0]
    if not (kw.get("leak_rate_hz") or kw.get("photoreceptor_cutoff_hz")):
        assert torch.equal(rs.lref[mask], torch.log(new_frames[mask].double() + emu.log_eps))
    # stepping on: the unmasked descents' events and state as without the restart
    a, b = st, rs
    for k in (3, 4):
        a, ev_a = emu.step_state(a, frames[k], k * 5_000)
        b, ev_b = emu.step_state(b, frames[k], k * 5_000)
        for i in (0, 2):
            assert _events_of(ev_a, i) == _events_of(ev_b, i)
    for x, y in zip(pytree.tree_leaves(a).values(), pytree.tree_leaves(b).values()):
        assert torch.equal(x[~mask], y[~mask])


def _devices():
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", _devices())
@pytest.mark.parametrize("kw", CONFIGS, ids=IDS)
def test_reset_where_initialises_only_the_restarted_rows(kw, device):
    """The restarted rows get the bits of a whole batch's init at those rows (per-descent sensor
    values too): only they are initialised, and the others are not touched (also on CUDA)."""
    frames = _frames(B=4).to(device)
    emu = EventEmulator(seed=6, device=device, **kw)
    emu.set_element_params(threshold_scale=torch.tensor([0.9, 1.0, 1.1, 1.2], dtype=torch.float64),
                           element_seeds=torch.tensor([5, 6, 7, 8]))
    st = emu.init_state(frames[0], 0)
    st, _ = emu.step_state(st, frames[1], 10_000)
    seeds = torch.tensor([100, 101, 102, 103], device=device)
    whole = emu.init_state(frames[2], 10_000, seed=seeds)
    for mask in (torch.tensor([False, True, False, True]), torch.tensor([True, False, False, False])):
        mask = mask.to(device)
        rs = emu.reset_where(st, mask, frames[2], 10_000, seed=seeds)
        assert tree_equal(rs, pytree.tree_where(mask, whole, st))


def test_restarted_descent_equals_a_fresh_one():
    """A descent restarted with seed s steps as a fresh emulator started there with seed s."""
    kw = dict(NOISY, denoise="hot_pixel")
    frames = _frames(B=3)
    emu = EventEmulator(seed=3, **kw)
    st = emu.init_state(frames[0], 0)
    st, _ = emu.step_state(st, frames[1], 10_000)
    mask = torch.tensor([False, False, True])
    st = emu.reset_where(st, mask, frames[2], 10_000, seed=torch.tensor([0, 0, 77]))
    one = emu.init_state(frames[2][2:], 10_000, seed=torch.tensor([77]))
    for k in (3, 4):
        st, ev = emu.step_state(st, frames[k], 10_000 + k * 7_000)
        one, ev1 = emu.step_state(one, frames[k][2:], 10_000 + k * 7_000)
        assert len(ev1) > 0 and _events_of(ev, 2) == ev1


# ----------------------------------------------------------------------------- the noise
@pytest.mark.parametrize("kw", [dict(background_rate_hz=40.0), dict(shot_noise_rate_hz=30.0),
                                dict(leak_rate_hz=5.0, hot_pixel_fraction=0.05), dict(mismatch_sigma=0.2), NOISY],
                         ids=["background", "shot", "leak", "mismatch", "noisy"])
def test_noise_does_not_depend_on_batch_mates(kw):
    """The same seed alone (B = 1) and at index 2 of B = 3 beside other descents: the same events."""
    frames = _frames(B=3)
    emu = EventEmulator(**kw)
    one = emu.init_state(frames[0][2:], 0, seed=torch.tensor([12345]))
    three = emu.init_state(frames[0], 0, seed=torch.tensor([7, 8, 12345]))
    n = 0
    for k in range(1, frames.shape[0]):
        one, ev1 = emu.step_state(one, frames[k][2:], k * 40_000)
        three, ev3 = emu.step_state(three, frames[k], k * 40_000)
        assert _events_of(ev3, 2) == ev1
        n += len(ev1)
    assert n > 0


def test_default_seeds():
    """Descent b's seed: element_seeds where set, else (seed * 1000003 + b) mod 2^63."""
    f = torch.rand(3, 4, 5) + 0.1
    emu = EventEmulator(seed=9)
    assert emu.init_state(f, 0).seed.tolist() == [9 * 1_000_003 + b for b in range(3)]
    emu.set_element_params(element_seeds=[5, 6, 7])
    assert emu.init_state(f, 0).seed.tolist() == [5, 6, 7]
    assert EventEmulator(seed=-1).init_state(f, 0).seed.tolist() == [(-1_000_003 + b) % 2 ** 63 for b in range(3)]


def test_element_background_rates_per_descent():
    """Per-descent background rates (set_element_params): each descent's count within Poisson
    bounds of its own rate x time x pixels, ON/OFF balanced, uniform times."""
    B, H, W, dt, n = 3, 20, 25, 50_000, 20
    rates = [0.0, 10.0, 40.0]
    emu = EventEmulator(refractory_us=0.0)
    emu.set_element_params(background_rate_hz=rates)
    f = torch.full((B, H, W), 0.3)
    st = emu.init_state(f, 0)
    evs = []
    for k in range(1, n + 1):
        st, ev = emu.step_state(st, f, k * dt)
        evs.append(ev)
    ev = Events.cat(evs)
    T = n * dt * 1e-6
    for b, r in enumerate(rates):
        got, mu = int((ev.b == b).sum()), r * T * H * W
        assert (got == 0) if r == 0 else abs(got - mu) < Z * math.sqrt(mu), (b, got, mu)
    on = int((ev.p == 1).sum())
    assert abs(on - len(ev) / 2) < Z * math.sqrt(len(ev) / 4)
    phase = ((ev.t - 1) % dt).double() / dt
    assert abs(float(phase.mean()) - 0.5) < Z * math.sqrt(1 / 12 / len(ev))


@pytest.mark.parametrize("lam", [0.0, 0.3, 3.0, 40.0, 64.0, 200.0, 5e4])
def test_poisson_inverse_cdf_matches_the_model(lam):
    """On a fine grid of uniforms the inverse CDF reproduces the Poisson pmf (exact branch) or its
    mean and variance (normal approximation above POISSON_EXACT_MAX)."""
    M = 200_000
    u = (torch.arange(M, dtype=torch.float64) + 0.5) / M
    n = pm.poisson_inverse_cdf(torch.full((M,), lam, dtype=torch.float64), u)
    assert n.dtype == torch.int64 and int(n.min()) >= 0
    mean, var = float(n.double().mean()), float(n.double().var())
    assert abs(mean - lam) < 1e-3 * max(1.0, lam) and abs(var - lam) < 2e-2 * max(1.0, lam)
    if lam <= pm.POISSON_EXACT_MAX:
        k = torch.arange(int(lam + 10 * math.sqrt(lam) + 10), dtype=torch.float64)
        pmf = torch.exp(torch.xlogy(k, torch.tensor(lam)) - lam - torch.lgamma(k + 1))
        freq = torch.bincount(n, minlength=k.numel())[:k.numel()].double() / M
        assert float((freq - pmf).abs().max()) <= 1.0 / M + 1e-12


def test_pinned_noisy_events():
    """The counter-based draws as recorded once (a regression pin, re-recorded when the draws
    change on purpose): a noisy run's event count and checksum."""
    frames = _frames(B=2, H=10, W=12, n=4)
    emu = EventEmulator(seed=11, **NOISY)
    emu.reset(frames[0], 0)
    ev = Events.cat([emu.step(frames[k], k * 25_000) for k in range(1, 4)])
    key = (ev.b * 1_000_003 + ev.y * 1009 + ev.x * 31 + ev.p.long()) * 7 + ev.t
    assert (len(ev), int(key.sum()), int((ev.p == 1).sum())) == PINNED


PINNED = (3998, 15369565549, 3242)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("kw", [NOISY, dict(NOISY, denoise="hot_pixel+baf"), dict(mismatch_sigma=0.1)],
                         ids=["noisy", "noisy+denoise", "mismatch"])
def test_cpu_and_cuda_draw_the_same(kw):
    """Every draw is a torch op on the state's device: the same events and state on CPU and CUDA."""
    frames = _frames()
    out = {}
    for dev in ("cpu", "cuda"):
        emu = EventEmulator(seed=5, device=dev, **kw)
        st = emu.init_state(frames[0], 0)
        evs = []
        for k in range(1, frames.shape[0]):
            st, ev = emu.step_state(st, frames[k], k * 20_000)
            evs.append(ev.to("cpu"))
        out[dev] = (evs, pytree.tree_to(st, "cpu"))
    for a, b in zip(out["cpu"][0], out["cuda"][0]):
        assert a == b
    # thresholds and noise draws bit-identical; levels equal up to the devices' log / exp rounding
    for name, x in pytree.tree_leaves(out["cpu"][1]).items():
        y = pytree.tree_leaves(out["cuda"][1])[name]
        if x.is_floating_point():
            assert torch.allclose(x, y, rtol=1e-12, atol=1e-12, equal_nan=True), name
        else:
            assert torch.equal(x, y), name


# ------------------------------------------------------------------- no loop over the batch
def test_no_python_loop_over_the_batch(monkeypatch):
    """The number of draws (hash calls) per step does not grow with the batch size."""
    calls = {"n": 0}
    orig = pytree.hash_bits

    def counting(*keys):
        calls["n"] += 1
        return orig(*keys)

    monkeypatch.setattr(pytree, "hash_bits", counting)
    monkeypatch.setattr(pm, "hash_bits", counting)
    per_step = {}
    for B in (1, 7):
        frames = smooth_frames(B, 10, 12, 3, omega=0.5)
        emu = EventEmulator(seed=1, **NOISY)
        st = emu.init_state(frames[0], 0)
        st, _ = emu.step_state(st, frames[1], 10_000)
        calls["n"] = 0
        st, ev = emu.step_state(st, frames[2], 20_000)
        per_step[B] = calls["n"]
    assert per_step[1] == per_step[7] > 0


# ------------------------------------------------------------------------- bad states
def _state():
    emu = EventEmulator(seed=1, **dict(NOISY, denoise="baf"))
    frames = _frames()
    return emu, emu.init_state(frames[0], 0), frames


@pytest.mark.parametrize("field,bad", [
    ("lref", lambda s: s.lref[:, :, :-1]), ("t_last", lambda s: s.t_last.float()),
    ("step", lambda s: s.step.to(torch.int32)), ("seed", lambda s: s.seed[:2]),
    ("th_on", lambda s: None), ("drift", lambda s: s.drift[0]), ("l_lp", lambda s: None)])
def test_bad_state_names_the_field(field, bad):
    emu, st, frames = _state()
    st = st._replace(**{field: bad(st)})
    with pytest.raises(ValueError, match=rf"EventEmulator.*{field}"):
        emu.step_state(st, frames[1], 10_000)


def test_bad_nested_state_and_types():
    emu, st, frames = _state()
    den = st.denoise._replace(baf_t_us=st.denoise.baf_t_us.double())
    with pytest.raises(ValueError, match=r"EventEmulator.*denoise\.baf_t_us"):
        emu.step_state(st._replace(denoise=den), frames[1], 10_000)
    with pytest.raises(ValueError, match="EmulatorState"):
        emu.step_state(tuple(st), frames[1], 10_000)
    with pytest.raises(ValueError, match="t_us"):  # descents at different times
        emu.step_state(st._replace(t_us=st.t_us + torch.tensor([0, 1, 0])), frames[1], 10_000)
    with pytest.raises(ValueError, match="mask"):
        emu.reset_where(st, torch.tensor([1, 0, 1]), frames[1], 0)
    with pytest.raises(ValueError, match="seed"):
        emu.init_state(frames[0], 0, seed=torch.tensor([1, 2]))
    with pytest.raises(ValueError, match="batch size"):
        emu.step_state(st, frames[1][:2], 10_000)
    assert isinstance(st, EmulatorState) and emulator_step is emu_mod.emulator_step
