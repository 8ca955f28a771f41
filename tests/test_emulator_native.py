"""The compiled kernels of the emulator (dvsland.events.native): mode auto builds them on first use
where a C++ compiler is found and is silent without one, off never loads, a failed build falls back
to the torch path, and the same events and state as the torch path, which stays the reference."""

import warnings

import numpy as np
import pytest
import torch

from dvsland.events import native
from dvsland.events.benchmark import smooth_frames
from dvsland.events.emulator import EventEmulator


@pytest.fixture
def fresh(monkeypatch):
    """No module loaded, no failure recorded, the environment's mode."""
    lib = native.LIBRARY
    for k, v in (("_bound", None), ("_failed", False), ("_absent", False), ("chosen", None)):
        monkeypatch.setattr(lib, k, v)
    return monkeypatch


def _no_build(*a, **k):
    pytest.fail("must not compile")


def _events(frames, elem=None, **kw):
    """Events of every step; ``elem``: per-element values (set_element_params) for B elements."""
    emu = EventEmulator(seed=2, **kw)
    if elem is not None:
        B = frames.shape[1]
        emu.set_element_params(**{k: (v(B) if callable(v) else v) for k, v in elem.items()})
    emu.reset(frames[0], 0)
    return [emu.step(frames[k], k * 100_000) for k in range(1, frames.shape[0])], emu


def test_auto_without_a_build_or_a_compiler_is_silent(fresh):
    fresh.delenv("DVSLAND_NATIVE_SORT", raising=False)
    fresh.setattr(native.LIBRARY, "cached", lambda: False)
    fresh.setattr("dvsland.native_build.compiler", lambda: None)
    fresh.setattr(native.LIBRARY, "build", _no_build)
    assert native.mode() == "auto" and not native.native_sort_enabled() and native.load() is None
    fresh.setattr(native.LIBRARY, "cached", lambda: pytest.fail("looked at the cache again"))
    assert not native.native_sort_enabled()  # once per process
    frames = smooth_frames(2, 20, 24, 3, omega=0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # silent fallback
        ev, _ = _events(frames)
    assert sum(len(e) for e in ev) > 0 and native.radix_sort_(torch.tensor([3, 1, 2]), 2) is False


def test_auto_builds_on_first_use_into_the_cache(fresh, tmp_path):
    """A fresh cache and a compiler: auto builds the kernels at first use (a second or two), once."""
    from dvsland import native_build

    if native_build.compiler() is None:
        pytest.skip("no C++ compiler here")
    fresh.delenv("DVSLAND_NATIVE_SORT", raising=False)
    fresh.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    assert not native.cached() and native.native_sort_enabled()
    assert native.kernels() is not None and native.cached()
    assert native.build_dir().parent == tmp_path and sorted(p.suffix for p in native.build_dir().iterdir()
                                                            if p.suffix in (".so", ".cpp")) == [".cpp", ".so"]
    frames = smooth_frames(2, 20, 24, 3, omega=0.5)
    ev, _ = _events(frames)
    fresh.setattr(native.LIBRARY, "chosen", False)
    assert ev == _events(frames)[0]


@pytest.mark.parametrize("value, mode", [("", "auto"), ("auto", "auto"), ("1", "on"), ("YES", "on"),
                                         ("0", "off"), ("false", "off")])
def test_mode_from_the_environment(fresh, value, mode):
    fresh.setenv("DVSLAND_NATIVE_SORT", value)
    assert native.mode() == mode


def test_off_never_loads_and_bad_values_are_named(fresh):
    fresh.setenv("DVSLAND_NATIVE_SORT", "0")
    fresh.setattr(native.LIBRARY, "cached", lambda: True)
    fresh.setattr("dvsland.native_build.load_library", _no_build)
    fresh.setattr(native.LIBRARY, "build", _no_build)
    assert not native.native_sort_enabled() and native.load() is None
    fresh.setenv("DVSLAND_NATIVE_SORT", "maybe")
    with pytest.raises(ValueError, match="DVSLAND_NATIVE_SORT"):
        native.mode()


def test_the_build_name_follows_the_source(fresh):
    name = native.module_name()
    assert name.startswith("dvsland_events_native_") and native.build_dir().name == name
    fresh.setattr(native.LIBRARY, "src", native._SRC + "\n// changed\n")
    assert native.module_name() != name  # an edited kernel is never loaded from an old build


def test_build_failure_falls_back_to_the_torch_path(fresh):
    fresh.setattr(native.LIBRARY, "chosen", True)
    fresh.setattr(native.LIBRARY, "cached", lambda: False)

    def broken(*a, **k):
        raise RuntimeError("no compiler here")

    fresh.setattr(native.LIBRARY, "build", broken)
    frames = smooth_frames(2, 20, 24, 3, omega=0.5)
    with pytest.warns(RuntimeWarning, match="could not be built"):
        ev, _ = _events(frames)
    fresh.setattr(native.LIBRARY, "chosen", False)
    ref, _ = _events(frames)
    assert ev == ref and sum(len(e) for e in ev) > 0


def _compare_with_torch_path(monkeypatch, configs, frame_sets):
    for kw in configs:
        for frames in frame_sets:
            out, state = {}, {}
            for on in (True, False):
                monkeypatch.setattr(native.LIBRARY, "chosen", on)
                out[on], emu = _events(frames, **kw)
                state[on] = (emu.reference.clone(), emu._t_last.clone())
            for a, b in zip(out[True], out[False]):
                assert a == b, kw
            assert sum(len(a) for a in out[True]) > 0
            assert torch.equal(state[True][0], state[False][0]) and torch.equal(state[True][1], state[False][1]), kw


#: per-element sensors as a Monte Carlo batch draws them (threshold maps, per-element refractory
#: periods, some 0 and some long enough to drop crossings)
ELEMENTS = [dict(elem=dict(threshold_scale=lambda B: np.linspace(0.8, 1.2, B), mismatch_sigma=lambda B: np.full(B, 0.03),
                           refractory_us=lambda B: np.linspace(0.0, 30_000.0, B))),
            dict(threshold_off=0.15, elem=dict(refractory_us=lambda B: np.linspace(5.0, 50.0, B))),
            dict(shot_noise_rate_hz=20.0, elem=dict(mismatch_sigma=lambda B: np.linspace(0.0, 0.1, B)))]


def _frame_sets():
    g = torch.Generator().manual_seed(4)
    return [smooth_frames(3, 40, 48, 5, omega=0.8), smooth_frames(2, 33, 70, 4, omega=0.3),
            torch.rand(5, 3, 17, 23, generator=g) * 2]


def test_kernels_give_the_torch_paths_events(fresh):
    """The kernels (built here when not cached) against the torch path, on a few configurations."""
    if native.load() is None:
        pytest.skip("no C++ compiler here")
    from test_emulator_fast_paths import CONFIGS

    _compare_with_torch_path(fresh, CONFIGS[:2] + CONFIGS[-2:] + ELEMENTS[:1], _frame_sets()[:2])


def test_native_kernels_give_the_same_events(fresh):
    fresh.setattr(native.LIBRARY, "chosen", True)
    if native.load() is None:
        pytest.skip("no C++ compiler here")
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 2 ** 40, 100_003)
    t = torch.from_numpy(keys.copy())
    assert native.radix_sort_(t, 40) and np.array_equal(t.numpy(), np.sort(keys))
    from test_emulator_fast_paths import CONFIGS

    _compare_with_torch_path(fresh, CONFIGS + ELEMENTS + [dict(leak_rate_hz=2.0, photoreceptor_cutoff_hz=50.0),
                                                          dict(refractory_us=20_000.0),
                                                          dict(refractory_us=0.0, threshold=0.01)],
                             _frame_sets())


def test_native_kernel_in_place_gives_the_same_events_and_state(fresh):
    """A donated state (the kernel moves the reference and last-event times in place, and neither
    writes nor reads a quiet pixel's) against fresh buffers: the same events and state, bit for bit,
    with scalar and per-pixel thresholds, per-element refractory periods, and rows longer than the
    kernel's chunk of 256 pixels."""
    fresh.setattr(native.LIBRARY, "chosen", True)
    if native.load() is None:
        pytest.skip("no C++ compiler here")
    from test_emulator_fast_paths import CONFIGS

    wide = smooth_frames(2, 7, 300, 4, omega=0.9)
    for kw in CONFIGS[:2] + ELEMENTS + [dict(refractory_us=20_000.0)]:
        for frames in _frame_sets()[:2] + [wide]:
            kw = dict(kw)
            elem = kw.pop("elem", None)
            emu = EventEmulator(seed=3, **kw)
            if elem is not None:
                emu.set_element_params(**{k: v(frames.shape[1]) for k, v in elem.items()})
            a = b = emu.init_state(frames[0], 0)
            n = 0
            for k in range(1, frames.shape[0]):
                a, ev_a = emu.step_state(a, frames[k], k * 100_000)
                b, ev_b = emu.step_state(b, frames[k], k * 100_000, donate=True)
                assert ev_a == ev_b, kw
                assert torch.equal(a.lref, b.lref) and torch.equal(a.t_last, b.t_last), kw
                n += len(ev_a)
            assert n > 0


def test_native_kernel_respects_the_event_cap(fresh):
    fresh.setattr(native.LIBRARY, "chosen", True)
    if native.load() is None:
        pytest.skip("no C++ compiler here")
    frames = smooth_frames(2, 40, 48, 3, omega=0.8)
    emu = EventEmulator(max_events_per_step=100)
    emu.reset(frames[0], 0)
    with pytest.raises(ValueError, match="max_events_per_step"):
        emu.step(frames[1], 100_000)


@pytest.mark.parametrize("P", [1, 15, 16, 37, 16 * 40 + 3])
def test_widen_range_is_the_float64_copy_and_its_amin_amax(fresh, P):
    """The emulator's float64 copy of the frames and each descent's range in one pass: the values of
    ``to(float64)``, ``amin`` and ``amax`` (NaN in the row's vector part, in its tail, inf, -0.0)."""
    fresh.setattr(native.LIBRARY, "chosen", True)
    kern = native.load()
    if kern is None:
        pytest.skip("no C++ compiler here")
    g = torch.Generator().manual_seed(P)
    f = torch.rand(6, P, generator=g) * 100
    f[1, P // 2] = float("nan")
    f[2, P - 1] = float("nan")
    f[3, 0] = float("inf")
    f[4, :] = -0.0
    f[5, P - 1] = -3.0
    out, lo, hi = kern.widen_range(f)
    assert out.dtype == torch.float64 and torch.equal(out.nan_to_num(7.0), f.double().nan_to_num(7.0))
    for got, want in ((lo, f.amin(1).double()), (hi, f.amax(1).double())):
        assert torch.equal(torch.isnan(got), torch.isnan(want))
        assert torch.equal(got.nan_to_num(7.0), want.nan_to_num(7.0))


def test_native_kernel_cap_boundary_keeps_every_key(fresh):
    """A step of exactly the cap's events gives them all (the kernel keeps keys while its running
    count is within the cap); one event fewer allowed refuses the step."""
    fresh.setattr(native.LIBRARY, "chosen", True)
    if native.load() is None:
        pytest.skip("no C++ compiler here")
    frames = smooth_frames(2, 40, 48, 3, omega=0.8)
    free = EventEmulator(max_events_per_step=None)
    free.reset(frames[0], 0)
    ev = free.step(frames[1], 100_000)
    n = len(ev)
    assert n > 100
    exact = EventEmulator(max_events_per_step=n)
    exact.reset(frames[0], 0)
    got = exact.step(frames[1], 100_000)
    for name in ("b", "x", "y", "t", "p"):
        assert torch.equal(getattr(got, name), getattr(ev, name)), name
    short = EventEmulator(max_events_per_step=n - 1)
    short.reset(frames[0], 0)
    with pytest.raises(ValueError, match="max_events_per_step"):
        short.step(frames[1], 100_000)


def test_cli_build_native_builds_both_kernels_and_reports(monkeypatch, capsys):
    """`dvsland build-native` builds the terrain's, the renderer's, the emulator's, cmax's and dpr's kernels
    and the efference_fit filter's (compile mocked here) and returns 1 when one cannot be built, naming it."""
    from dvsland.cli.main import main
    from dvsland.control import native_fit
    from dvsland.estimators import native_cmax, native_dpr
    from dvsland.render import native_render
    from dvsland.terrain import native_noise

    built = []
    monkeypatch.setattr(native_noise.LIBRARY, "build", lambda verbose=False: built.append("terrain"))
    monkeypatch.setattr(native_render.LIBRARY, "build", lambda verbose=False: built.append("render"))
    monkeypatch.setattr(native.LIBRARY, "build", lambda verbose=False: built.append("events"))
    monkeypatch.setattr(native_cmax.LIBRARY, "build", lambda verbose=False: built.append("cmax"))
    monkeypatch.setattr(native_dpr.LIBRARY, "build", lambda verbose=False: built.append("dpr"))
    monkeypatch.setattr(native_fit.LIBRARY, "build", lambda verbose=False: built.append("fit"))
    assert main(["build-native"]) == 0 and built == ["terrain", "render", "events", "cmax", "dpr", "fit"]
    out = capsys.readouterr().out
    assert all(f"dvsland.{m}" in out for m in ("terrain.native_noise", "render.native_render", "events.native",
                                               "estimators.native_cmax", "estimators.native_dpr",
                                               "control.native_fit"))

    def broken(verbose=False):
        raise RuntimeError("no compiler")

    monkeypatch.setattr(native_cmax.LIBRARY, "build", broken)
    assert main(["build-native"]) == 1
    assert "could not build the cmax kernel" in capsys.readouterr().err


def test_unwritable_kernel_folder_warns_once_and_runs_the_torch_path(fresh, tmp_path):
    """A kernel cache that cannot be written (here: a folder path below a file) gives one warning
    that names the mode variable and the folder variable, then the torch path's events."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    fresh.delenv("DVSLAND_NATIVE_SORT", raising=False)
    fresh.setenv("TORCH_EXTENSIONS_DIR", str(blocker / "kernels"))
    fresh.setattr("dvsland.native_build.compiler", lambda: "/usr/bin/c++")
    frames = smooth_frames(2, 20, 24, 3, omega=0.5)
    with pytest.warns(RuntimeWarning, match="DVSLAND_NATIVE_SORT=0 .*TORCH_EXTENSIONS_DIR"):
        ev, _ = _events(frames)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per process
        assert native.load() is None
    fresh.setattr(native.LIBRARY, "chosen", False)
    assert ev == _events(frames)[0]


def test_a_mode_switched_off_after_a_load_gives_the_torch_path(fresh):
    """``load()`` and ``kernels()`` follow the mode as it is now, also after the kernels were loaded."""
    fresh.setattr(native.LIBRARY, "chosen", True)
    if native.load() is None:
        pytest.skip("no C++ compiler here")
    fresh.setattr(native.LIBRARY, "chosen", False)
    assert native.load() is None and native.kernels() is None and native.radix_sort_(torch.tensor([2, 1]), 2) is False
    fresh.setattr(native.LIBRARY, "chosen", None)
    fresh.delenv("DVSLAND_NATIVE_SORT", raising=False)
    assert native.load() is not None


@pytest.mark.parametrize("B, n, sorted_by_b", [(18, 60_000, True), (300, 2_000, True), (3, 5, True), (7, 4_000, False)])
def test_sort_decode_in_pixel_order_sorts_each_descent_alone(fresh, B, n, sorted_by_b):
    """Keys in pixel order (lo_bit = t_shift): each descent's run is sorted alone, short runs by
    insertion; the order is a stable sort by (b, t) either way, also when the keys are not ordered by
    descent (the kernel then falls back to the whole sort)."""
    fresh.setattr(native.LIBRARY, "chosen", True)
    kern = native.load()
    if kern is None:
        pytest.skip("no C++ compiler here")
    g = torch.Generator().manual_seed(B)
    b = torch.randint(0, B, (n,), generator=g)
    if sorted_by_b:
        b = torch.sort(b).values
    t = torch.randint(1, 100_000, (n,), generator=g)
    t[: n // 3] = t[0]  # many equal times: the order among them must be the input's
    pix = torch.randint(0, 1 << 15, (n,), generator=g)
    bb = max(1, (B - 1).bit_length())
    keys = (b << 32) | (t << 15) | pix
    ref = keys[torch.sort(keys >> 15, stable=True).indices]
    out_b, out_x, out_y, out_t, out_p = kern.sort_decode(keys.clone(), 32 + bb, 15, keys.new_empty(0), 32, 15, 8,
                                                         127, 127, 10)
    assert torch.equal(out_b, ref >> 32) and torch.equal(out_t, ((ref >> 15) & ((1 << 17) - 1)) + 10)
    assert torch.equal(out_x, (ref >> 1) & 127) and torch.equal(out_y, (ref >> 8) & 127)
    assert torch.equal(out_p, 1 - 2 * (ref & 1).to(torch.int8))
