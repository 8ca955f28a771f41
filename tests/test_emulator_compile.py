"""``emulator.compile``: the ideal pixel's step over every pixel at once (dvsland.events.emulator_dense),
traced by ``torch.compile``, emits the candidate path's events and leaves its state. Traced with dynamo's
``eager`` backend it runs the same operations: the same bits. Inductor's fused code (slow: tens of
seconds of compiling on a CPU) keeps the events and holds the state to float rounding. The compiled
C++ pixel kernel is turned off here: with it, a CPU never takes either torch path."""

from __future__ import annotations

import pytest
import torch

import dvsland.compiled as compiled
from dvsland.events import emulator as E
from dvsland.events import native
from dvsland.events.benchmark import smooth_frames

FRAMES = smooth_frames(6, 32, 40, 8, omega=0.3)


@pytest.fixture
def traced(monkeypatch):
    """Dynamo's eager backend, a fresh traced function, and the torch paths (no C++ pixel kernel)."""
    monkeypatch.setattr(compiled, "BACKEND", "eager")
    monkeypatch.setattr(E, "_DENSE", None)
    torch._dynamo.reset()
    with native.native_sort_mode(False):
        yield


def _fly(compile_: str, frames=FRAMES, element=None, **kw):
    emu = E.EventEmulator(compile=compile_, seed=3, **kw)
    if element:
        emu.set_element_params(**element)
    emu.reset(frames[0], 0)
    events = [emu.step(frames[i], i * 100_000) for i in range(1, len(frames))]
    return events, emu.state


def _same_events(a, b) -> None:
    assert [len(e) for e in a] == [len(e) for e in b]
    for ea, eb in zip(a, b):
        for f in "bxytp":
            assert torch.equal(getattr(ea, f), getattr(eb, f)), f


CASES = {
    "default": {},
    "no_refractory": dict(refractory_us=0.0),
    "long_refractory": dict(refractory_us=30_000.0),
    "asymmetric": dict(threshold_off=0.15),
    "mismatch_maps": dict(mismatch_sigma=0.05),
    "per_descent": dict(element=dict(refractory_us=[5.0, 50.0, 500.0, 5_000.0, 15.0, 0.0],
                                     threshold_scale=[1.0, 0.8, 1.2, 1.0, 0.9, 1.1])),
    "noise_and_lowpass": dict(shot_noise_rate_hz=2.0, background_rate_hz=0.5, photoreceptor_cutoff_hz=200.0),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_traced_step_emits_the_candidate_paths_events(case, traced):
    kw = dict(CASES[case])
    (ev0, st0), (ev1, st1) = _fly("false", **kw), _fly("true", **kw)
    _same_events(ev0, ev1)
    assert sum(len(e) for e in ev1) > 0
    assert torch.equal(st0.lref, st1.lref) and torch.equal(st0.t_last, st1.t_last)
    assert E._DENSE is not None and not E._DENSE.eager  # traced, not fallen back


def test_the_device_generic_compaction_emits_the_same_events(traced, monkeypatch):
    """Without the CPU's numpy shortcuts (the path a GPU takes: compactions of known size, no nonzero)."""
    monkeypatch.setattr(E, "CPU_FAST_PATHS", False)
    for kw in (CASES["default"], CASES["per_descent"]):
        (ev0, st0), (ev1, st1) = _fly("false", **kw), _fly("true", **kw)
        _same_events(ev0, ev1)
        assert torch.equal(st0.lref, st1.lref) and torch.equal(st0.t_last, st1.t_last)


def test_one_trace_serves_other_batch_sizes_and_empty_steps(traced):
    for b in (6, 2, 4):
        frames = FRAMES[:, :b].clone()
        frames[3] = frames[2]  # a step without any change: no event
        (ev0, st0), (ev1, st1) = _fly("false", frames), _fly("true", frames)
        _same_events(ev0, ev1)
        assert len(ev1[2]) == 0
        assert torch.equal(st0.lref, st1.lref) and torch.equal(st0.t_last, st1.t_last)


def test_the_event_cap_holds_and_the_state_is_kept(traced):
    emu = E.EventEmulator(compile="true", max_events_per_step=1000)
    emu.reset(FRAMES[0], 0)
    before = emu.state
    with pytest.raises(ValueError, match="emulator.max_events_per_step"):
        emu.step(FRAMES[1], 100_000)
    assert emu.state is before and torch.equal(before.lref, E.EventEmulator().init_state(FRAMES[0], 0).lref)


def test_the_setting_is_resolved_and_checked(traced):
    from dvsland.config import ConfigError, load_config

    assert load_config("paper").emulator.compile == "false"
    assert load_config("paper", ["emulator.compile=on"]).emulator.compile == "true"  # YAML's boolean
    with pytest.raises(ConfigError, match=r"emulator\.compile.*'fast'.*'auto', 'true', 'false'"):
        load_config("paper", ["emulator.compile=fast"])
    with pytest.raises(ValueError, match="compile must be one of"):
        E.EventEmulator(compile="sometimes")
    _fly("auto")  # auto on a CPU: the candidate path
    assert E._DENSE is None
    assert E.EventEmulator.from_config(load_config("paper", ["emulator.compile=auto"]).emulator).params.compile == "auto"


def test_the_cpu_kernel_runs_regardless(monkeypatch):
    monkeypatch.setattr(E, "_DENSE", None)
    if native.kernels() is None:
        pytest.skip("no C++ compiler: the pixel kernel cannot be built here")
    _fly("true")
    assert E._DENSE is None


def test_a_failing_compile_steps_eagerly_and_warns_once(traced, failing_compile):
    with pytest.warns(RuntimeWarning, match=r"emulator\.compile: torch\.compile failed for the pixels' step"):
        ev1, st1 = _fly("true")
    ev0, st0 = _fly("false")
    _same_events(ev0, ev1)
    assert E._DENSE.eager


@pytest.mark.slow
def test_inductor_keeps_the_events_and_the_state_within_rounding(monkeypatch):
    monkeypatch.setattr(E, "_DENSE", None)
    torch._dynamo.reset()
    with native.native_sort_mode(False):
        for kw in (CASES["default"], CASES["mismatch_maps"]):
            (ev0, st0), (ev1, st1) = _fly("false", **kw), _fly("true", **kw)
            _same_events(ev0, ev1)
            torch.testing.assert_close(st1.lref, st0.lref, rtol=1e-12, atol=1e-12)
            torch.testing.assert_close(st1.t_last, st0.t_last, rtol=1e-12, atol=1e-9)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_auto_on_cuda_emits_the_eager_events_within_rounding(monkeypatch):
    monkeypatch.setattr(E, "_DENSE", None)
    frames = FRAMES.cuda()
    (ev0, st0), (ev1, st1) = _fly("false", frames), _fly("auto", frames)
    n0, n1 = sum(len(e) for e in ev0), sum(len(e) for e in ev1)
    assert E._DENSE is not None and abs(n1 - n0) <= 1e-4 * n0
    torch.testing.assert_close(st1.lref, st0.lref, rtol=1e-12, atol=1e-9)
