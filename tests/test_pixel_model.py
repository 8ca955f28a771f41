"""The non-ideal pixel parts (dvsland.events.pixel_model) against closed forms and statistics.

Every statistical bound is 5 standard deviations (a false failure about once in 1.7 million runs;
the seeds are fixed, so a run is reproducible)."""

import math

import numpy as np
import pytest
import torch

from dvsland.config import EmulatorConfig, load_config
from dvsland.events import EventEmulator, LEVEL_TOL
from dvsland.events import pixel_model as pm

Z = 5.0  # sigmas


def _run_static(emu, frame, n_steps, dt_us):
    emu.reset(frame, 0)
    evs = [emu.step(frame, dt_us * (k + 1)) for k in range(n_steps)]
    from dvsland.events import Events

    return Events.cat(evs)


# ------------------------------------------------------------------ photoreceptor bandwidth
def test_alpha_closed_form():
    irr = torch.tensor([0.0, 0.05, 0.5, 1.0, 3.0], dtype=torch.float64)
    a = pm.photoreceptor_alpha(irr, 1e-3, 20.0, full_irradiance=1.0)
    f = 20.0 * np.minimum(1.0, irr.numpy())
    np.testing.assert_allclose(a.numpy(), 1 - np.exp(-2 * np.pi * f * 1e-3), rtol=1e-12)
    assert a[0] == 0 and a[-1] == a[-2]


@pytest.mark.parametrize("i_rel", [1.0, 0.1])  # bright (f_max) and dark (f_max / 10) pixels
def test_lowpass_step_response_time_constant(i_rel):
    """A step of the input: L_lp(t) = L1 + (L0 - L1) exp(-t / tau), tau = 1 / (2 pi f_c(I1)),
    and the ON events counted so far equal floor((L_lp - L0) / theta)."""
    f_max, dt_us, th = 10.0, 1000, 0.05
    i0, i1 = 0.5 * i_rel, i_rel  # one octave up; f_c from the new frame's irradiance
    emu = EventEmulator(threshold=th, refractory_us=0.0, photoreceptor_cutoff_hz=f_max, log_eps=1e-4)
    emu.reset(torch.full((1, 2, 3), i0, dtype=torch.float64), 0)
    l0, l1 = math.log(i0 + 1e-4), math.log(i1 + 1e-4)
    tau_s = 1 / (2 * math.pi * f_max * min(1.0, i1))
    n_on = 0
    t_cross = None
    for k in range(1, 400):
        ev = emu.step(torch.full((1, 2, 3), i1, dtype=torch.float64), k * dt_us)
        assert bool((ev.p == 1).all())
        n_on += len(ev)
        expect = l1 + (l0 - l1) * math.exp(-k * dt_us * 1e-6 / tau_s)
        np.testing.assert_allclose(emu.photoreceptor_level.numpy(), expect, rtol=0, atol=1e-12)
        assert n_on == 6 * math.floor((expect - l0) / th + LEVEL_TOL)
        if t_cross is None and (expect - l0) / (l1 - l0) >= 1 - math.exp(-1):
            t_cross = k * dt_us * 1e-6
    # the 63 % rise time is the time constant (to one step)
    assert abs(t_cross - tau_s) <= dt_us * 1e-6
    assert abs(tau_s - (0.0159 if i_rel == 1 else 0.159)) < 1e-3  # darker pixel: 10x slower


def test_lowpass_static_scene_no_events_and_linear_needs_log():
    f = torch.rand(2, 5, 6, generator=torch.Generator().manual_seed(1)) + 0.01
    ev = _run_static(EventEmulator(photoreceptor_cutoff_hz=50.0), f, 5, 100_000)
    assert len(ev) == 0
    with pytest.raises(ValueError, match="photoreceptor_cutoff_hz"):
        EventEmulator(photoreceptor_cutoff_hz=5.0, interpolation="linear")
    with pytest.raises(ValueError, match="leak_rate_hz"):
        EventEmulator(leak_rate_hz=1.0, interpolation="linear")


# ---------------------------------------------------------------------------- shot noise
def test_shot_noise_rate_closed_form():
    r = pm.shot_noise_rate_hz(torch.tensor([0.0, 0.5, 1.0, 7.0]), 4.0, 0.25, 1.0)
    np.testing.assert_allclose(r.numpy(), [4.0, 2.5, 1.0, 1.0])


def test_shot_noise_rates_polarity_and_times():
    """A static scene with dark, half and full irradiance: counts per region within Poisson
    bounds of r(I) * T * pixels, ON/OFF balanced, times uniform, no relaxation events."""
    B, H, W = 3, 24, 30
    f = torch.zeros(B, H, W)
    f[:, 8:16] = 0.5
    f[:, 16:] = 2.0  # above full_irradiance: the bright rate
    rate, k, dt_us, n_steps = 20.0, 0.25, 50_000, 40
    emu = EventEmulator(shot_noise_rate_hz=rate, shot_noise_bright_factor=k, seed=4)
    ev = _run_static(emu, f, n_steps, dt_us)
    T = n_steps * dt_us * 1e-6
    for rows, factor in ((slice(0, 8), 1.0), (slice(8, 16), 1 + (k - 1) * 0.5), (slice(16, 24), k)):
        sel = (ev.y >= rows.start) & (ev.y < rows.stop)
        n = int(sel.sum())
        mu = rate * factor * T * B * 8 * W
        assert abs(n - mu) < Z * math.sqrt(mu), (rows, n, mu)
    n = len(ev)
    n_on = int((ev.p == 1).sum())
    assert abs(n_on - n / 2) < Z * math.sqrt(n / 4)
    u = ((ev.t - 1) % dt_us).double() / dt_us  # phase within the step, uniform on [0, 1)
    assert abs(float(u.mean()) - 0.5) < Z * math.sqrt(1 / 12 / n)
    # each shot event resets its pixel to the current level: no answer at the next step
    assert float(emu.reference.sub(torch.log(f.double() + 1e-4)).abs().max()) < 1e-12


def test_shot_noise_thinning_bright_factor_above_one():
    f = torch.cat([torch.zeros(1, 10, 40), torch.ones(1, 10, 40)], dim=1)
    emu = EventEmulator(shot_noise_rate_hz=10.0, shot_noise_bright_factor=3.0, seed=2)
    ev = _run_static(emu, f, 30, 100_000)
    dark, bright = int((ev.y < 10).sum()), int((ev.y >= 10).sum())
    for n, mu in ((dark, 10.0 * 3.0 * 400), (bright, 30.0 * 3.0 * 400)):
        assert abs(n - mu) < Z * math.sqrt(mu)


# ---------------------------------------------------------------------- leak, hot pixels
def test_leak_counts_and_times_closed_form():
    """Static scene: pixel i emits its k-th ON event at t = (k - u_i) / rho_i (u_i its initial
    phase, rho_i its rate), so floor(u_i + rho_i T) events by T."""
    B, H, W = 2, 12, 15
    f = torch.rand(B, H, W, generator=torch.Generator().manual_seed(3)) + 0.05
    rate, sigma, dt_us, n_steps = 3.0, 0.2, 100_000, 30
    emu = EventEmulator(leak_rate_hz=rate, leak_rate_sigma=sigma, refractory_us=0.0, seed=5)
    ev = _run_static(emu, f, n_steps, dt_us)
    assert bool((ev.p == 1).all())
    rho = emu.leak_rate_hz_map.double()
    u = emu.leak_phase.double()
    # the rate map: mean and std as drawn (sigma relative)
    n_pix = B * H * W
    assert abs(float(rho.mean()) - rate) < Z * rate * sigma / math.sqrt(n_pix)
    assert abs(float(rho.std()) / rate - sigma) < 0.05
    T = n_steps * dt_us * 1e-6
    expect = torch.floor(u + rho * T + LEVEL_TOL).to(torch.int64)
    counts = torch.zeros(B, H, W, dtype=torch.int64)
    counts.index_put_((ev.b, ev.y, ev.x), torch.ones(len(ev), dtype=torch.int64), accumulate=True)
    assert torch.equal(counts, expect)
    # times of every event of element 0, pixel by pixel in closed form (within 1 µs rounding)
    e0 = ev.select_batch(0)
    order = torch.argsort((e0.y * W + e0.x) * 10**9 + e0.t)
    y, x, t = e0.y[order], e0.x[order], e0.t[order]
    first = torch.ones_like(t, dtype=torch.bool)
    first[1:] = (y[1:] != y[:-1]) | (x[1:] != x[:-1])
    seg = torch.cumsum(first.long(), 0) - 1
    starts = torch.nonzero(first).squeeze(1)
    kth = torch.arange(len(t)) - starts[seg] + 1
    t_expect = (kth.double() - u[0, y, x]) / rho[0, y, x] * 1e6
    assert float((t.double() - t_expect).abs().max()) <= 1.0


def test_hot_pixels_fraction_and_rate():
    B, H, W = 2, 40, 50
    f = torch.full((B, H, W), 0.3)
    frac, hot_rate, dt_us, n_steps = 0.02, 200.0, 50_000, 10
    emu = EventEmulator(hot_pixel_fraction=frac, hot_pixel_rate_hz=hot_rate, refractory_us=0.0, seed=9)
    ev = _run_static(emu, f, n_steps, dt_us)
    hot = emu.hot_pixels
    n_pix = B * H * W
    n_hot = int(hot.sum())
    assert abs(n_hot - frac * n_pix) < Z * math.sqrt(n_pix * frac * (1 - frac))
    counts = torch.zeros(B, H, W, dtype=torch.int64)
    counts.index_put_((ev.b, ev.y, ev.x), torch.ones(len(ev), dtype=torch.int64), accumulate=True)
    T = n_steps * dt_us * 1e-6
    assert int(counts[~hot].sum()) == 0  # no leak: only the hot pixels fire
    hc = counts[hot]
    assert int(hc.min()) >= math.floor(hot_rate * T) and int(hc.max()) <= math.floor(hot_rate * T) + 1
    assert bool((ev.p == 1).all())


# ------------------------------------------------------------------------------ mismatch
def test_threshold_mismatch_mean_and_std():
    f = torch.full((4, 32, 32), 0.5)
    sigma = 0.05
    emu = EventEmulator(threshold=0.2, threshold_off=0.3, mismatch_sigma=sigma, seed=11)
    emu.reset(f, 0)
    n = 4 * 32 * 32
    for th, nominal in ((emu._th_on, 0.2), (emu._th_off, 0.3)):
        rel = th / nominal
        assert abs(float(rel.mean()) - 1) < Z * sigma / math.sqrt(n)
        assert abs(float(rel.std()) - sigma) < Z * sigma / math.sqrt(2 * n)


# ------------------------------------------------------------------- seeding and config
@pytest.mark.parametrize("kw", [dict(shot_noise_rate_hz=30.0), dict(leak_rate_hz=4.0),
                                dict(hot_pixel_fraction=0.05), dict(background_rate_hz=30.0)])
def test_noise_is_seeded_per_element(kw):
    """Element b's noise does not depend on the batch size; another seed gives other noise."""
    f = torch.rand(3, 10, 12, generator=torch.Generator().manual_seed(0)) + 0.1

    def run(B, seed):
        emu = EventEmulator(seed=seed, **kw)
        return _run_static(emu, f[:B], 4, 100_000)

    big, small, other = run(3, 1), run(1, 1), run(1, 2)
    assert len(small) > 0
    assert big.select_batch(0) == small
    assert not (other == small)


@pytest.mark.parametrize("name,value", [
    ("photoreceptor_cutoff_hz", -1.0), ("full_irradiance", 0.0), ("shot_noise_rate_hz", float("nan")),
    ("shot_noise_bright_factor", -0.5), ("leak_rate_hz", -1.0), ("leak_rate_sigma", float("inf")),
    ("hot_pixel_fraction", 1.5), ("hot_pixel_rate_hz", -3.0)])
def test_bad_noise_parameters_named(name, value):
    with pytest.raises(ValueError, match=name):
        EventEmulator(**{name: value})


def test_config_fields_reach_the_emulator_and_paper_is_ideal():
    cfg = EmulatorConfig(photoreceptor_cutoff_hz=30.0, shot_noise_rate_hz=1.0, leak_rate_hz=0.1,
                         hot_pixel_fraction=1e-3, full_irradiance=0.5)
    emu = EventEmulator.from_config(cfg)
    assert emu.pixel_model == pm.PixelModelParams(photoreceptor_cutoff_hz=30.0, shot_noise_rate_hz=1.0,
                                                  leak_rate_hz=0.1, hot_pixel_fraction=1e-3,
                                                  full_irradiance=0.5)
    paper = load_config("paper")
    assert not EventEmulator.from_config(paper.emulator).pixel_model.any
    from dvsland.config import ConfigError

    with pytest.raises(ConfigError, match="emulator.hot_pixel_fraction"):
        load_config("paper", ["emulator.hot_pixel_fraction=2"])


def test_all_parts_together_sorted_and_valid():
    rng = np.random.default_rng(0)
    f0 = torch.from_numpy(rng.uniform(0.01, 1.5, (2, 17, 23)).astype(np.float32))
    emu = EventEmulator(photoreceptor_cutoff_hz=40.0, shot_noise_rate_hz=5.0, leak_rate_hz=1.0,
                        hot_pixel_fraction=0.01, mismatch_sigma=0.03, background_rate_hz=1.0, seed=1)
    emu.reset(f0, 0)
    f = f0
    for k in range(6):
        f = f * torch.from_numpy(np.exp(rng.normal(0, 0.3, f.shape)).astype(np.float32))
        ev = emu.step(f, 33_333 * (k + 1))
        ev.validate(2, 17, 23)
        assert int(ev.t.min()) > 33_333 * k and int(ev.t.max()) <= 33_333 * (k + 1)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_noise_cuda_matches_cpu():
    """Draws are made on CPU and moved: the same noise on either device."""
    f = torch.rand(2, 12, 14, generator=torch.Generator().manual_seed(0)) + 0.1
    kw = dict(shot_noise_rate_hz=20.0, leak_rate_hz=3.0, hot_pixel_fraction=0.02, background_rate_hz=5.0,
              refractory_us=0.0, seed=3)
    cpu = _run_static(EventEmulator(**kw), f, 4, 100_000)
    gpu = _run_static(EventEmulator(device="cuda", **kw), f.cuda(), 4, 100_000)
    assert len(cpu) > 0 and gpu.to("cpu") == cpu


# ------------------------------------------------------------------------ properties
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), cutoff=st.sampled_from([0.0, 3.0, 300.0]),
       shot=st.sampled_from([0.0, 2.0, 50.0]), leak=st.sampled_from([0.0, 0.5, 20.0]),
       hot=st.sampled_from([0.0, 0.1]), refractory=st.sampled_from([0.0, 15.0, 5000.0]),
       bright=st.floats(0.0, 4.0), full=st.floats(0.05, 5.0))
def test_property_noisy_events_valid_and_in_interval(seed, cutoff, shot, leak, hot, refractory, bright, full):
    """Any mix of the parts: events sorted, on the sensor, p = ±1, times in (t_prev, t]; the
    reference ends every step within one threshold of the (filtered, drifting) level, since it
    moves by one threshold per crossing, emitted or not, and shot events set it to the level."""
    rng = np.random.default_rng(seed)
    B, H, W = 2, 4, 5
    f = rng.uniform(0.0, 2.0, (B, H, W))
    emu = EventEmulator(photoreceptor_cutoff_hz=cutoff, shot_noise_rate_hz=shot, shot_noise_bright_factor=bright,
                        leak_rate_hz=leak, hot_pixel_fraction=hot, refractory_us=refractory,
                        full_irradiance=full, seed=seed % 1000)
    t = int(rng.integers(0, 10 ** 9))
    emu.reset(torch.tensor(f, dtype=torch.float32), t)
    for _ in range(4):
        f = f * np.exp(rng.normal(0.0, 0.5, f.shape))
        dt = int(rng.integers(1, 150_000))
        ev = emu.step(torch.tensor(f, dtype=torch.float32), t + dt)
        ev.validate(B, H, W)
        if len(ev):
            assert int(ev.t.min()) > t and int(ev.t.max()) <= t + dt
        t += dt
        diff = emu._l_prev - emu.reference
        assert float(diff.max()) < 0.1 * (1 + 1e-6) and float(diff.min()) > -0.1 * (1 + 1e-6)


def test_background_from_drawn_counts_equals_the_plain_draw():
    """Counts drawn first (as the emulator does, the total read with its inputs) give the same
    events as the plain draw; without counts a rate is required."""
    seed, step = torch.arange(3, dtype=torch.int64) + 5, torch.full((3,), 4, dtype=torch.int64)
    rate, n_pix, dt = torch.tensor([50.0, 0.0, 200.0], dtype=torch.float64), 40 * 30, 100_000
    ref = pm.draw_background(seed, step, rate, n_pix, dt)
    base, n = pm.uniform_counts(seed, step, pm.background_lam(seed, rate, n_pix, torch.full((3,), dt)),
                                pm.TAG_BACKGROUND)
    got = pm.draw_background(seed, step, None, n_pix, dt, (base, n, int(n.sum())))
    assert len(ref[0]) > 0 and all(torch.equal(a, b) for a, b in zip(ref, got))
    with pytest.raises(ValueError, match="rate_hz must be given"):
        pm.draw_background(seed, step, None, n_pix, dt)
