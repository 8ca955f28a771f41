"""dvsland train-loop --what filter: the efference_fit filter's constants trained by gradients through the loop."""

from __future__ import annotations

import json
import math

import pytest
import torch

from dvsland.cli.main import main
from dvsland.config import load_config
from dvsland.control.efference_fit import GATE_SURROGATE_WIDTH, gate_surrogate
from dvsland.learn.loop_loss import LossWeights, window_loss
from dvsland.learn.loop_run import trained_config
from dvsland.learn.loop_train import check_horizon_fits, fit_history_rows
from dvsland.learn.loop_trainables import FILTER_CONSTANTS, FILTER_DEFAULT, FilterConstants, make_trainable
from dvsland.sim import fly_steps, init_state, loop_step
from dvsland.stages import build_stages

pytestmark = pytest.mark.usefixtures("one_thread")
#: montecarlo_efference (div_gs + efference_fit) with a noisy oracle whose every estimate the filter uses
NOISY = ["estimator.name=oracle", "estimator.oracle.noise_rel=0.2", "estimator.oracle.noise_abs=0.002",
         "controller.efference.min_confidence=0", "dispersion.terrain_variants=1", "simulation.n_seeds=1",
         "render.threads=1"]


def _stages(extra=()):
    return build_stages(load_config("montecarlo_efference", NOISY + list(extra)), "D")


def _mid_flight(st, steps=120):
    with torch.no_grad():
        return fly_steps(st, init_state(st), steps)[0]


# ------------------------------------------------------------------ gradients
def test_gradient_reaches_every_default_constant():
    st = _stages()
    tr = make_trainable(st, "filter")
    assert tr.names == FILTER_DEFAULT and isinstance(tr, FilterConstants)
    start = _mid_flight(st)
    tr.apply_to(st)
    loss, terms, _ = window_loss(st, start, 20, LossWeights(track=1.0, filter=1.0))
    loss.backward()
    assert terms["filter"] > 0
    for name in FILTER_DEFAULT:
        g = tr.raw[name].grad
        assert g is not None and math.isfinite(float(g)) and float(g) != 0.0, name


@pytest.mark.parametrize("name", [n for n in FILTER_CONSTANTS if n != "gate_sigma"])
def test_filter_constant_gradient_matches_finite_differences(name):
    """float64 central differences on the log-constant over a 20-step closed-loop window (the
    tracking term: the gradient has to go through the law, the thrust and the dynamics too)."""
    st = _stages()
    tr = make_trainable(st, "filter", [name])
    w = LossWeights(track=1.0, landing=1.0, fail=25.0, filter=1.0)
    start = _mid_flight(st)

    def loss_at(raw: float) -> torch.Tensor:
        with torch.no_grad():
            tr.raw[name].fill_(raw)
        tr.apply_to(st)
        return window_loss(st, start, 20, w)[0]

    x0 = float(tr.raw[name].detach())
    tr.zero_grad()
    loss_at(x0).backward()
    g = float(tr.raw[name].grad)
    h = 1e-3  # measured: autograd and central differences agree to 1e-4 .. 4e-4 at h = 1e-2 and 1e-3
    with torch.no_grad():
        fd = (float(loss_at(x0 + h)) - float(loss_at(x0 - h))) / (2 * h)
    assert math.isfinite(g) and g != 0.0
    assert g == pytest.approx(fd, rel=5e-3)


def test_gate_surrogate_is_zero_with_a_sigmoid_gates_gradient():
    u2 = torch.tensor([0.0, 16.0, 24.0, 25.0, 26.0, 100.0, float("inf")], dtype=torch.float64)
    g = torch.tensor(5.0, dtype=torch.float64, requires_grad=True)
    out = gate_surrogate(u2, g)
    assert torch.equal(out.detach(), torch.zeros_like(u2))  # values: exactly the hard gate's
    out.sum().backward()
    w = GATE_SURROGATE_WIDTH
    want = sum(torch.sigmoid(t) * (1 - torch.sigmoid(t)) / w
               for t in (5.0 - u2.clamp_min(0).sqrt()) / w if torch.isfinite(t))
    assert float(g.grad) == pytest.approx(float(want), rel=1e-6)
    assert float(g.grad) > 0  # estimates near the gate pull it
    u = torch.tensor([0.0, 9.0], dtype=torch.float64, requires_grad=True)  # |u| = 0: sqrt's slope is infinite
    gate_surrogate(u, g).sum().backward()
    assert torch.isfinite(u.grad).all()


def test_gate_sigma_trains_without_moving_the_flight():
    """Trained, gate_sigma gets a finite, non-zero gradient from a closed-loop window (estimates
    near the gate), and the window flies exactly as with the gate as a plain number."""
    st = _stages(["controller.efference.gate_sigma=1.5"])  # tight: some estimates lie near the gate
    start = _mid_flight(st)
    w = LossWeights(track=1.0, landing=1.0, fail=25.0, filter=1.0)
    with torch.no_grad():
        ref, ref_terms, _ = window_loss(st, start, 20, w)
    tr = make_trainable(st, "filter", ["gate_sigma"])
    with torch.no_grad():
        tr.raw["gate_sigma"].fill_(math.log(1.5))
    tr.apply_to(st)
    loss, terms, _ = window_loss(st, start, 20, w)
    assert float(loss.detach()) == pytest.approx(float(ref), rel=1e-12)
    loss.backward()
    g = tr.raw["gate_sigma"].grad
    assert g is not None and math.isfinite(float(g)) and float(g) != 0.0


def test_no_grad_flight_unchanged_by_the_start_values():
    """The config's own values put back as tensors fly the same descent (to the last bits of exp(log(v)))."""
    st = _stages()
    s0 = init_state(st)
    ref = fly_steps(st, s0, 5)[0]
    FilterConstants(st.filter, FILTER_CONSTANTS).apply_to(st)
    with torch.no_grad():
        got = fly_steps(st, s0, 5)[0]
    assert torch.allclose(got.z_m, ref.z_m, rtol=1e-14) and torch.allclose(got.v_mps, ref.v_mps, rtol=1e-14)
    f_ref, f_got = ref.stage_state.filter, got.stage_state.filter
    assert torch.allclose(f_got.theta, f_ref.theta, rtol=1e-12, atol=1e-12)


def test_prior_constants_follow_each_filters_own_start():
    """prior_rel_sigma acts through sz0 = prior_rel_sigma |z0| of the filter it is put into."""
    st = _stages()
    tr = make_trainable(st, "filter", ["prior_rel_sigma", "prior_rel_sigma_v"])
    with torch.no_grad():
        tr.raw["prior_rel_sigma"].fill_(math.log(0.2))
        tr.raw["prior_rel_sigma_v"].fill_(math.log(0.1))
    other = build_stages(load_config("montecarlo_efference", NOISY + ["simulation.n_seeds=3"]), "D,E")
    tr.apply_to(other)
    p = other.filter.params
    assert torch.allclose(p.sz0, 0.2 * p.z0_m.abs()) and torch.allclose(p.sv0, 0.1 * p.v0_mps.abs())


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("extra, names, needle", [
    (["controller.filter=efference"], [], r"\-\-what filter.*controller\.filter"),
    (["controller.filter=moving_average", "controller.name=tau_p"], [], r"\-\-what filter.*controller\.filter"),
    ([], ["min_confidence"], r"\-\-params min_confidence.*zero almost everywhere"),
    ([], ["lambda_per_s"], r"\-\-params lambda_per_s: not a trainable constant.*efference_fit"),
    (["controller.efference.meas_sigma_rel=0"], ["meas_sigma_rel"], r"\-\-params meas_sigma_rel.*must start > 0"),
])
def test_bad_filter_input(extra, names, needle):
    with pytest.raises(ValueError, match=needle):
        make_trainable(_stages(extra), "filter", names)


def test_history_rows_count_in_the_memory_check():
    st = _stages()
    n = st.settings.n_steps_max
    assert fit_history_rows(st, 40) == n and fit_history_rows(st, 0) == n // 2
    assert check_horizon_fits(st, 40, 2**36) > 40 * st.batch_size * 2048 * n
    with pytest.raises(ValueError, match=r"--window 0: .* GiB of autograd graph"):
        check_horizon_fits(st, 0, 2**30)
    forget = _stages(["controller.efference.forget_s=5"])
    assert fit_history_rows(forget, 40) == math.ceil(12 * 5 / forget.settings.dt_s)


def test_trained_config_carries_the_constants(tmp_path):
    cfg = load_config("montecarlo_efference", NOISY + ["controller.efference.prior_rel_sigma_v=null"])
    st = build_stages(cfg, "D")
    tr = make_trainable(st, "filter")
    with torch.no_grad():
        tr.raw["meas_sigma_rel"].fill_(math.log(0.17))
    out = trained_config(cfg, tr, tmp_path / "checkpoint.pt").controller.efference
    assert out.meas_sigma_rel == pytest.approx(0.17) and out.cauchy_c == pytest.approx(2.0)
    assert out.prior_rel_sigma_v == pytest.approx(cfg.controller.efference.prior_rel_sigma)  # flown as trained


# ------------------------------------------------------------------ the command, end to end
def test_cli_trains_the_filter_and_simulate_flies_it(tmp_path, capsys):
    out = tmp_path / "run"
    base = ["--sites", "D", *sum((["--set", c] for c in NOISY + ["simulation.t_max_s=15"]), [])]
    rc = main(["train-loop", "montecarlo_efference", "--what", "filter", "--params", "meas_sigma_rel,prior_rel_sigma",
               "--window", "10", "--max-windows", "2", "--val-every", "0", "--quiet", "--out", str(out), *base])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((out / "train_loop.json").read_text())
    assert summary["what"] == "filter" and summary["windows"] == 2 and summary["history"][0]["filter"] > 0
    val = summary["validation"]  # the training's loss of the whole validation flights beside the landings
    assert val["loss"] == pytest.approx(sum(val["loss_terms"].values()), abs=1e-3) and val["loss_terms"]["filter"] > 0
    vals = summary["values"]
    assert set(vals) == {"meas_sigma_rel", "prior_rel_sigma"} and vals["meas_sigma_rel"] != pytest.approx(0.05)
    flown = load_config(str(out / "trained.yaml"))
    assert flown.controller.efference.meas_sigma_rel == pytest.approx(vals["meas_sigma_rel"])
    assert flown.controller.efference.prior_rel_sigma == pytest.approx(vals["prior_rel_sigma"])
    p = build_stages(flown, "D").filter.params  # what simulate flies
    assert p.cfg.meas_sigma_rel == pytest.approx(vals["meas_sigma_rel"])
    assert torch.allclose(p.sz0, vals["prior_rel_sigma"] * p.z0_m.abs())
    rc = main(["train-loop", "--what", "law", "--max-windows", "1", "--quiet", "--resume", str(out), "--sites", "D"])
    assert rc == 2 and "--resume" in capsys.readouterr().err  # a filter checkpoint is not a law's
    rc = main(["train-loop", "--what", "filter", "--params", "meas_sigma_rel,prior_rel_sigma", "--window", "10",
               "--max-windows", "3", "--val-every", "0", "--quiet", "--resume", str(out), "--sites", "D"])
    assert rc == 0, capsys.readouterr().err
    assert json.loads((out / "train_loop.json").read_text())["windows"] == 3


def test_loop_step_with_trained_values_keeps_no_graph_without_grad():
    st = _stages()
    make_trainable(st, "filter").apply_to(st)
    with torch.no_grad():
        s, out = loop_step(st, init_state(st))
    assert not out.thrust_n.requires_grad and not s.stage_state.filter.theta.requires_grad
