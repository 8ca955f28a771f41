"""Hard scenarios of the open-loop evaluation: profiles, the dust layer, the noise burst, phase
scores, and the estimators on the rendered hover start."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dvsland.config import load_config
from dvsland.evaluate import ZoomTextureFrames, evaluate
from dvsland.evaluate.scenario_run import format_scenario_table, run_scenarios, score_phases
from dvsland.evaluate.scenarios import (SCENARIOS, DustyFrames, NoisyEmulator, Scenario, altitude_at, divergence_at,
                                        resolve_scenarios, scenario_profiles)
from dvsland.events import Events


pytestmark = pytest.mark.usefixtures("one_thread")  # the shared fixture of conftest.py


def test_profile_is_exp_of_integrated_divergence():
    sc = SCENARIOS["hover_start"]
    t = np.linspace(0, 9, 9001)
    z = altitude_at(sc, t)
    d_num = np.gradient(np.log(z), t)  # D = d ln z / dt
    assert np.allclose(d_num[5:-5], divergence_at(sc, t)[5:-5], atol=1e-5)
    assert divergence_at(sc, [0.5, 1.0, 2.5, 4.0, 8.0]) == pytest.approx([-0.005, -0.005, -0.0275, -0.05, -0.05])
    assert z[0] == 100.0


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_shipped_profiles_need_thrust_within_a_lander(name):
    """a = z (dD/dt + D^2) must stay above -g (thrust >= 0) and below 6 m/s^2 (100 kN at 10 t: 8.4)."""
    sc = SCENARIOS[name]
    t = np.linspace(0, sc.duration_s, 4001)
    z = altitude_at(sc, t)
    v = divergence_at(sc, t) * z
    a = np.gradient(v, t)
    assert a.min() > -1.62 and a.max() < 6.0, (a.min(), a.max())
    assert z.min() > 50.0


def test_resolve_and_profiles_batch():
    assert resolve_scenarios("none") == () and len(resolve_scenarios("all")) == len(SCENARIOS)
    with pytest.raises(ValueError, match="unknown scenario 'nope'.*known"):
        resolve_scenarios("hover_start,nope")
    scs = resolve_scenarios("hover_start,noise_burst")
    z, v0, n = scenario_profiles(scs, 0.1)
    assert n == 200 and z.shape == (2, 202)
    assert v0 == pytest.approx([-0.005 * 100.0, -0.03 * 3000.0])


def test_dusty_frames_flatten_only_in_the_band():
    frames = torch.rand(2, 8, 8) + 0.5
    band = torch.tensor([[100.0, 200.0], [float("nan"), float("nan")]], dtype=torch.float64)
    dusty = DustyFrames(lambda z, i: frames[i], band, torch.tensor([0.1, 0.1]))
    out = dusty.render(torch.tensor([150.0, 150.0]), torch.tensor([0, 1]))
    m = frames[0].mean()
    assert torch.allclose(out[0], m + 0.1 * (frames[0] - m)) and torch.equal(out[1], frames[1])
    assert torch.equal(dusty.render(torch.tensor([250.0]), torch.tensor([0]))[0], frames[0])


class _Quiet:
    def reset(self, frames, t_us):
        pass

    def step(self, frames, t_us):
        z = torch.zeros(0, dtype=torch.long)
        return Events(z, z, z, z, torch.zeros(0, dtype=torch.int8))


def test_noisy_emulator_adds_the_burst_rate_only_inside_its_window():
    win = torch.tensor([[150_000, 350_000], [0, 0]])
    emu = NoisyEmulator(_Quiet(), win, torch.tensor([20.0, 20.0], dtype=torch.float64), (32, 16), seed=3)
    emu.reset(None, 0)
    counts = []
    for k in range(1, 6):
        ev = emu.step(None, k * 100_000)
        counts.append(ev.b.numel())
        assert (ev.b == 0).all()
        if ev.b.numel():
            assert int(ev.t.min()) > max((k - 1) * 100_000, 150_000) and int(ev.t.max()) <= min(k * 100_000, 350_000)
    # 20 Hz x 512 px x 0.2 s = 2048 events, in steps 2 (0.05 s), 3 (0.1 s) and 4 (0.05 s)
    assert counts == [0, 512, 1024, 512, 0]
    again = NoisyEmulator(_Quiet(), win, torch.tensor([20.0, 20.0], dtype=torch.float64), (32, 16), seed=3)
    again.reset(None, 100_000)
    first = NoisyEmulator(_Quiet(), win, torch.tensor([20.0, 20.0], dtype=torch.float64), (32, 16), seed=3)
    first.reset(None, 100_000)
    assert torch.equal(again.step(None, 200_000).x, first.step(None, 200_000).x)  # the same on every run


def test_score_phases_uses_each_phase_range():
    sc = Scenario("s", "", "A", 100.0, (0.0,), (-0.1,), 1.0, (("early", 0.0, 0.5), ("late", 0.5, 1.0)))
    t = np.arange(10) * 0.1
    d_true = np.full((1, 10), -0.1)
    d_hat = np.where(t < 0.5, -0.2, -0.1)[None]
    m = score_phases([sc], t, d_hat, d_true)["s"]
    assert m["early"]["n_steps"] == 5 and m["early"]["median_abs_rel_err"] == pytest.approx(1.0)
    assert m["late"]["median_abs_rel_err"] == pytest.approx(0.0)


def test_evaluate_reports_scenarios_as_named_segments():
    cfg = load_config("paper_eq2")
    res = evaluate(cfg, ["oracle"], ["A"], max_steps=12, frame_source=ZoomTextureFrames(9), progress=False,
                   scenarios="slow_to_hover,noise_burst")
    sc = res.summary["scenarios"]
    assert list(sc["scenarios"]) == ["slow_to_hover", "noise_burst"]
    m = sc["metrics"]["oracle"]["noise_burst"]["burst"]
    assert m["n_steps"] == 20 and m["median_abs_rel_err"] == pytest.approx(0.0, abs=1e-6)
    text = format_scenario_table(res.summary)
    assert "noise_burst" in text and "near hover 6-12 s" in text
    assert format_scenario_table({"estimators": {}}) == ""
