"""The emulator's step of some descents only (events/emulator_rows.py): the same events and state
for those rows as the whole batch's step, bit for bit, through every part of the pixel model."""

import pytest
import torch

from dvsland.events import EventEmulator, Events
from dvsland.events.emulator import emulator_step
from dvsland.events.emulator_rows import emulator_step_rows, state_rows
from dvsland.pytree import tree_equal

B, H, W = 5, 24, 32

PIXELS = {
    "ideal": {},
    "log_refractory": {"refractory_us": 800.0},
    "realistic": dict(mismatch_sigma=0.21, photoreceptor_cutoff_hz=300.0, full_irradiance=0.2,
                      shot_noise_rate_hz=50.0, leak_rate_hz=2.0, hot_pixel_fraction=0.01, background_rate_hz=20.0,
                      denoise="hot_pixel+baf"),
    "linear": {"interpolation": "linear", "background_rate_hz": 50.0},
}


def _frames(k: int) -> torch.Tensor:
    """(B, H, W) float32 textures drifting and zooming with the step ``k``, a different one per descent."""
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32),
                            indexing="ij")
    b = torch.arange(B, dtype=torch.float32).view(B, 1, 1)
    s = 1.0 + 0.03 * k * (1 + b)
    return 0.05 + 0.2 * (1 + torch.sin(0.7 * xx * s + 0.3 * b + 0.2 * k) * torch.cos(0.5 * yy * s - 0.1 * k)) ** 2


def _emulator(name: str) -> EventEmulator:
    emu = EventEmulator(seed=3, **PIXELS[name])
    if name == "realistic":  # per-descent values too
        emu.set_element_params(threshold_scale=torch.linspace(0.8, 1.2, B).tolist(),
                               background_rate_hz=torch.linspace(5.0, 40.0, B).tolist(),
                               refractory_us=torch.linspace(10.0, 500.0, B).tolist())
    return emu


def _rows_of(ev: Events, rows: torch.Tensor):
    keep = torch.isin(ev.b, rows)
    return tuple(getattr(ev, f)[keep] for f in ("b", "x", "y", "t", "p"))


@pytest.mark.parametrize("name", sorted(PIXELS))
def test_rows_step_is_the_batch_step_of_those_rows(name):
    emu = _emulator(name)
    state = emu.init_state(_frames(0), 0)
    full_state = part_state = state
    rows = torch.tensor([0, 2, 3])
    n_events = 0
    for k in range(1, 8):
        t_us = 100_000 * k
        full_state, full_ev = emulator_step(emu.params, full_state, _frames(k), t_us)
        part_state, part_ev = emulator_step_rows(emu.params, part_state, _frames(k), t_us, rows)
        assert part_ev.is_sorted() and part_ev.checked == (B, W, H)
        got = tuple(getattr(part_ev, f) for f in ("b", "x", "y", "t", "p"))
        want = _rows_of(full_ev, rows)
        assert all(torch.equal(a, b) for a, b in zip(got, want)), k
        n_events += len(part_ev)
        # the rows' state is the whole batch's; the others kept theirs, with the clock moved on
        assert tree_equal(state_rows(part_state, rows), state_rows(full_state, rows))
        assert bool((part_state.t_us == t_us).all())
        assert torch.equal(part_state.lref[1], state.lref[1])
        assert torch.equal(part_state.step[[1, 4]], state.step[[1, 4]])
    assert n_events > 100


def test_rows_step_with_every_row_and_none_flying_events():
    emu = _emulator("ideal")
    state = emu.init_state(_frames(0), 0)
    full_state, full_ev = emulator_step(emu.params, state, _frames(1), 100_000)
    all_state, all_ev = emulator_step_rows(emu.params, state, _frames(1), 100_000, torch.arange(B))
    assert torch.equal(all_ev.b, full_ev.b) and torch.equal(all_ev.t, full_ev.t)
    assert torch.equal(all_state.lref, full_state.lref)
    still = emu.init_state(torch.full((B, H, W), 0.1), 0)  # a static scene: no events at all
    _, ev = emulator_step_rows(emu.params, still, torch.full((B, H, W), 0.1), 100_000, torch.tensor([1]))
    assert len(ev) == 0 and ev.checked == (B, W, H)
    none_state, ev = emulator_step_rows(emu.params, state, _frames(1), 100_000, torch.zeros(0, dtype=torch.int64))
    assert len(ev) == 0 and bool((none_state.t_us == 100_000).all()) and torch.equal(none_state.lref, state.lref)


@pytest.mark.parametrize("name,native_on", [("ideal", True), ("ideal", False), ("linear", True)])
def test_compiled_pixel_step_says_which_kernel_steps(name, native_on, count_calls):
    """compiled_pixel_step: True exactly where the step runs the compiled pixel kernel (CPU, log
    interpolation, float64, the kernels built); the loop picks the rows' share from it."""
    from dvsland.events import native
    from dvsland.events.emulator import compiled_pixel_step

    if native_on and native.load() is None:
        pytest.skip("no C++ compiler here")
    emu = _emulator(name)
    emu.reset(_frames(0), 0)
    calls = count_calls(native.Kernels, "pixel_events")
    native.use_native_sort(native_on)
    try:
        want = native_on and name != "linear"
        assert compiled_pixel_step(emu.params, emu.state) is want
        emu.step(_frames(1), 100_000)
        assert bool(calls) is want
    finally:
        native.use_native_sort(None)
