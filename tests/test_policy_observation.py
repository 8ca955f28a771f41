"""The 'policy' law's opt-in observation (controller.policy.observation=efference: D_hat, confidence
and the filter's altitude beside the basic four) and its residual on div_gs (controller.policy.base)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from dvsland.config import load_config
from dvsland.control import PolicyNet, load_policy
from dvsland.control.policy import (D_SCALE, ERR_SCALE, POLICY_KIND, Z_REF_M, PolicyController,
                                    policy_observation)
from dvsland.learn.loop_train import TrainLoopRun, TrainLoopSettings, save_checkpoint
from dvsland.learn.loop_trainables import make_trainable
from dvsland.sim import fly_steps, init_state, loop_step
from dvsland.stages import build_stages

pytestmark = pytest.mark.usefixtures("one_thread")
COMMON = ["estimator.name=oracle", "dispersion.terrain_variants=1", "simulation.n_seeds=1", "render.threads=1"]
EFF = ["controller.name=policy", "controller.policy.observation=efference"]


def _stages(extra=(), preset="montecarlo_efference", site="D"):
    return build_stages(load_config(preset, COMMON + list(extra)), site)


def _controller(observation="efference", base="none", **kw):
    tau0 = torch.tensor([20.0, 30.0], dtype=torch.float64)
    return PolicyController(tau0, 0.25, 1.62, torch.tensor([9000.0, 9000.0], dtype=torch.float64),
                            thrust_max_n=1e5, observation=observation, base=base, hidden=8, **kw)


# ------------------------------------------------------------------ the observation
def test_efference_observation_columns_and_units():
    ctl = _controller()
    t = torch.tensor([4.0, 8.0], dtype=torch.float64)
    d = torch.tensor([-0.04, float("nan")], dtype=torch.float64)
    m = torch.tensor([9000.0, 8000.0], dtype=torch.float64)
    z = torch.tensor([1000.0, 0.2], dtype=torch.float64)
    d_hat = torch.tensor([-0.05, float("nan")], dtype=torch.float32)
    conf = torch.tensor([0.7, 0.9], dtype=torch.float64)  # no estimate: its confidence does not count
    obs, d_star = policy_observation(ctl.params, t, d, m, z, (d_hat, conf))
    assert obs.shape == (2, 7) and obs.dtype == torch.float64
    exp_star = -1.0 / (torch.tensor([20.0, 30.0], dtype=torch.float64) - 0.25 * t)
    assert torch.equal(d_star, exp_star)
    d0 = torch.tensor([-0.04, 0.0], dtype=torch.float64)
    assert torch.equal(obs[:, 0], d0 / D_SCALE) and torch.equal(obs[:, 1], exp_star / D_SCALE)
    assert torch.equal(obs[:, 2], (d0 - exp_star) / ERR_SCALE)
    assert torch.equal(obs[:, 3], m * 1.62 / 1e5)
    assert obs[0, 4] == pytest.approx(float(torch.tensor(-0.05, dtype=torch.float32)) / D_SCALE, rel=1e-12)
    assert obs[1, 4] == 0.0 and obs[0, 5] == 0.7 and obs[1, 5] == 0.0
    assert obs[0, 6] == pytest.approx(math.log(1000.0 / Z_REF_M)) and obs[1, 6] == pytest.approx(math.log(1 / Z_REF_M))


def test_efference_observation_needs_the_estimate():
    ctl = _controller()
    with pytest.raises(ValueError, match="controller.policy.observation=efference"):
        ctl(torch.zeros(2, dtype=torch.float64), torch.full((2,), -0.05, dtype=torch.float64),
            torch.full((2,), 9000.0, dtype=torch.float64))


def test_the_loop_hands_the_estimate_to_the_efference_policy_only():
    st = _stages(EFF)
    assert st.controller.needs_estimate and st.controller.needs_altitude
    s, outs = fly_steps(st, init_state(st), 5)
    assert all(torch.isfinite(o.thrust_n).all() for o in outs)
    basic = _stages(["controller.name=policy", "controller.filter=moving_average"])
    assert not basic.controller.needs_estimate and not basic.controller.needs_altitude


# ------------------------------------------------------------------ checkpoints
def _old_checkpoint(path, net):
    """A checkpoint as written before observation / base existed."""
    torch.save({"kind": POLICY_KIND, "hidden": net.hidden, "state_dict": net.state_dict()}, path)


def test_an_old_checkpoint_loads_and_flies_the_basic_law_bit_for_bit(tmp_path):
    torch.manual_seed(3)
    net = PolicyNet(8)
    with torch.no_grad():
        net.net[0].weight.add_(0.3 * torch.randn_like(net.net[0].weight))
    _old_checkpoint(tmp_path / "old.pt", net)
    loaded = load_policy(tmp_path / "old.pt")
    assert (loaded.observation, loaded.base) == ("basic", "none")
    cfg = ["controller.name=policy", f"controller.policy.checkpoint={tmp_path / 'old.pt'}"]
    st = build_stages(load_config("paper_montecarlo", COMMON + cfg), "D")
    assert not st.controller.needs_estimate and not st.controller.needs_altitude
    p, s, checked = st.controller.params, init_state(st), 0
    for _ in range(30):  # every command is the basic law's formula, written out here, of the step's inputs
        m = s.m_kg
        s, out = loop_step(st, s)
        d, t = out.d_filtered, out.t_flight_s
        d_star = -1.0 / (p.tau0_s - p.c2 * t).clamp_min(p.options.tau_min_s)
        obs = torch.stack((d / 0.05, d_star / 0.05, (d - d_star) / 0.01, m * p.g_mps2 / p.options.thrust_high_n), 1)
        with torch.no_grad():
            u = (torch.sigmoid(net.net(obs).squeeze(-1)) * p.options.thrust_high_n).clamp_min(p.thrust_min_n)
        if p.thrust_max_n is not None:
            u = u.clamp_max(p.thrust_max_n)
        ok = torch.isfinite(d)
        assert torch.equal(out.thrust_n[ok], u[ok])
        checked += int(ok.sum())
    assert checked > 20


def test_basic_thrust_is_the_formula(tmp_path):
    torch.manual_seed(4)
    net = PolicyNet(8)
    with torch.no_grad():
        for q in net.parameters():
            q.add_(0.2 * torch.randn_like(q))
    _old_checkpoint(tmp_path / "old.pt", net)
    tau0 = torch.tensor([20.0, 30.0], dtype=torch.float64)
    ctl = PolicyController(tau0, 0.25, 1.62, torch.tensor([9000.0, 9000.0], dtype=torch.float64), thrust_max_n=1e5,
                           checkpoint=str(tmp_path / "old.pt"))
    t = torch.tensor([3.0, 9.0], dtype=torch.float64)
    d = torch.tensor([-0.06, -0.02], dtype=torch.float64)
    m = torch.tensor([8800.0, 8500.0], dtype=torch.float64)
    out = ctl(t, d, m)
    d_star = -1.0 / (tau0 - 0.25 * t).clamp_min(4.0)
    obs = torch.stack((d / 0.05, d_star / 0.05, (d - d_star) / 0.01, m * 1.62 / 1e5), 1)
    with torch.no_grad():
        expected = torch.sigmoid(net.net(obs).squeeze(-1)) * 1e5
    assert torch.equal(out.thrust_n, expected)


def test_a_checkpoint_records_its_observation_and_a_mismatch_names_the_key(tmp_path):
    st = _stages(EFF)
    tr = make_trainable(st, "policy")
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, tr, torch.optim.Adam(tr.parameters()), TrainLoopSettings().check(), TrainLoopRun(),
                    torch.zeros(2, dtype=torch.int64), "policy")
    ck = torch.load(path, weights_only=True)
    assert (ck["observation"], ck["base"]) == ("efference", "none")
    assert load_policy(path).observation == "efference"
    with pytest.raises(ValueError, match=r"controller.policy.observation is 'basic'.*efference"):
        _stages(["controller.name=policy", f"controller.policy.checkpoint={path}"])
    with pytest.raises(ValueError, match=r"controller.policy.base is 'div_gs'"):
        _stages(EFF + ["controller.policy.base=div_gs", f"controller.policy.checkpoint={path}"])
    flown = _stages(EFF + [f"controller.policy.checkpoint={path}"])
    assert torch.equal(flown.controller.net.net[0].weight, tr.net.net[0].weight)
    with pytest.raises(ValueError, match="controller.policy.observation"):
        load_config("montecarlo_efference", ["controller.policy.observation=everything"])


# ------------------------------------------------------------------ the residual on div_gs
def test_an_untrained_residual_flies_div_gs_bit_for_bit():
    b = _stages(EFF + ["controller.policy.base=div_gs", "controller.div_gs.lambda_per_s=0.8"], site="I")
    a = _stages(["controller.name=div_gs", "controller.div_gs.lambda_per_s=0.8"], site="I")
    sa, oa = fly_steps(a, init_state(a), 60)
    sb, ob = fly_steps(b, init_state(b), 60)
    assert all(torch.equal(x.thrust_n, y.thrust_n) for x, y in zip(oa, ob))
    assert torch.equal(sa.z_m, sb.z_m) and torch.equal(sa.v_mps, sb.v_mps)
    with torch.no_grad():  # a non-zero output moves the command by m g tanh(net)
        b.controller.net.net[2].bias.fill_(0.1)
    sc, oc = fly_steps(b, init_state(b), 2)
    assert not torch.equal(oc[-1].thrust_n, oa[1].thrust_n)


def test_authority_scales_the_residual_and_is_recorded_in_the_checkpoint(tmp_path):
    """thrust = u_div_gs + authority x m g tanh(net): the same network at authority 0.25 moves the
    command by a quarter of what it moves it at 1; a checkpoint keeps its authority."""
    res = EFF + ["controller.policy.base=div_gs"]
    a = _stages(["controller.name=div_gs"], site="I")
    _, oa = fly_steps(a, init_state(a), 2)
    moved = {}
    for auth in (1.0, 0.25):
        st = _stages(res + [f"controller.policy.authority={auth}"], site="I")
        assert st.controller.net.authority == auth
        with torch.no_grad():
            st.controller.net.net[2].bias.fill_(0.01)  # a small output: no thrust clamp reached
        _, o = fly_steps(st, init_state(st), 2)
        moved[auth] = o[-1].thrust_n - oa[-1].thrust_n
    assert torch.allclose(moved[0.25], 0.25 * moved[1.0], rtol=1e-3)  # the first step moved the state a little
    assert float(moved[1.0].abs().min()) > 0.0
    st = _stages(res + ["controller.policy.authority=0.25"])
    tr = make_trainable(st, "policy")
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, tr, torch.optim.Adam(tr.parameters()), TrainLoopSettings().check(), TrainLoopRun(),
                    torch.zeros(2, dtype=torch.int64), "policy")
    assert torch.load(path, weights_only=True)["authority"] == 0.25
    assert load_policy(path).authority == 0.25
    with pytest.raises(ValueError, match=r"controller.policy.authority is 1.0 but .* authority 0.25"):
        _stages(res + [f"controller.policy.checkpoint={path}"])
    assert _stages(res + ["controller.policy.authority=0.25", f"controller.policy.checkpoint={path}"]
                   ).controller.net.authority == 0.25


def test_the_residual_reaches_the_step_output_and_the_loss():
    """StepOutput.control_residual is tanh(net) of a residual policy (None for div_gs), and the
    loss's ``residual`` term is weight x r^2 dt of the flying descents; asked of another law, it is
    refused naming --loss."""
    from dvsland.learn.loop_loss import LossWeights, step_terms

    st = _stages(EFF + ["controller.policy.base=div_gs", "controller.policy.authority=0.5"], site="I")
    with torch.no_grad():
        st.controller.net.net[2].bias.fill_(0.3)
    s0 = init_state(st)
    s1, out = loop_step(st, s0)
    assert out.control_residual is not None
    assert torch.allclose(out.control_residual, torch.full_like(out.control_residual, math.tanh(0.3)))
    terms = step_terms(st, s0, s1, out, LossWeights(residual=2.0))
    dt = st.settings.dt_s
    assert torch.allclose(terms["residual"], torch.full_like(s1.z_m, 2.0 * math.tanh(0.3) ** 2 * dt))
    gs = _stages(["controller.name=div_gs"], site="I")
    g0 = init_state(gs)
    g1, gout = loop_step(gs, g0)
    assert gout.control_residual is None and "residual" not in step_terms(gs, g0, g1, gout, LossWeights())
    with pytest.raises(ValueError, match="--loss residual=1.0: the law has no residual"):
        step_terms(gs, g0, g1, gout, LossWeights(residual=1.0))


@pytest.mark.parametrize("bad, match", [("controller.policy.authority=0", r"controller.policy.authority.*\(0"),
                                        ("controller.policy.authority=4", r"controller.policy.authority.*3"),
                                        ("controller.policy.authority=0.5", r"needs controller.policy.base=div_gs")])
def test_bad_authority_names_the_key(bad, match):
    with pytest.raises(ValueError, match=match):
        _stages(EFF + [bad])


# ------------------------------------------------------------------ gradients
def _first_layer_grad(extra, open_output: bool):
    """The gradient of the first layer's weights after 10 closed-loop steps of a toy loss."""
    st = _stages(extra)
    tr = make_trainable(st, "policy")
    if open_output:  # the residual's output layer starts at 0: open it so the first layer sees a gradient
        with torch.no_grad():
            tr.net.net[2].weight.fill_(0.05)
    tr.apply(st.controller)
    with torch.no_grad():
        s, _ = fly_steps(st, init_state(st), 20)
    loss = 0.0
    for _ in range(10):
        s, out = loop_step(st, s, grad=True)
        loss = loss + out.thrust_n.sum() * 1e-4 + (s.v_mps ** 2).sum() * 1e-3
    loss.backward()
    assert float(tr.net.net[2].weight.grad.abs().max()) > 0.0
    return tr.net.net[0].weight.grad


@pytest.mark.parametrize("base", ["none", "div_gs"])
def test_a_gradient_reaches_the_new_inputs_weights(base):
    g = _first_layer_grad(EFF + [f"controller.policy.base={base}"], base == "div_gs")
    assert g is not None and torch.isfinite(g).all()
    for col in (4, 5, 6):  # D_hat, confidence, ln z_hat
        assert float(g[:, col].abs().max()) > 0.0, col


# ------------------------------------------------------------------ the track_gs loss term
def test_track_gs_target_is_div_gs_s_target_at_the_true_altitude():
    from dvsland.learn.loop_loss import LossWeights, div_gs_target

    st = _stages(EFF)  # montecarlo_efference: d_final 0.03 1/s, v_min 2 m/s, c2 0.25
    tau0 = st.params.tau0_s
    assert LossWeights.parse("track_gs=2").track_gs == 2.0 and LossWeights().track_gs == 0.0
    t = torch.zeros_like(tau0)  # the TTC part: -1 / tau0
    assert torch.allclose(div_gs_target(st, t, torch.full_like(tau0, 3000.0)), -1.0 / tau0, rtol=1e-12)
    late = tau0 / 0.25  # tau* <= 0: the final part, -max(d_final, v_min / z)
    assert torch.equal(div_gs_target(st, late, torch.full_like(tau0, 1000.0)), torch.full_like(tau0, -0.03))
    assert torch.allclose(div_gs_target(st, late, torch.full_like(tau0, 40.0)), torch.full_like(tau0, -2.0 / 40))


# ------------------------------------------------------------------ the filter's doubt (efference_doubt)
DOUBT = ["controller.name=policy", "controller.policy.observation=efference_doubt"]


def test_doubt_observation_appends_the_clamped_offsets_and_rejected_share():
    from dvsland.control.policy import DOUBT_CLAMP

    ctl = _controller("efference_doubt")
    t = torch.tensor([4.0, 8.0], dtype=torch.float64)
    d = torch.tensor([-0.04, -0.03], dtype=torch.float64)
    m = torch.tensor([9000.0, 8000.0], dtype=torch.float64)
    z = torch.tensor([1000.0, 500.0], dtype=torch.float64)
    est = (torch.tensor([-0.05, -0.02]), torch.tensor([0.7, 0.9]))
    doubt = torch.tensor([[1.5, -0.5, 0.25], [-30.0, 12.0, 0.0]], dtype=torch.float64)
    obs, _ = policy_observation(ctl.params, t, d, m, z, est, doubt)
    base, _ = policy_observation(_controller("efference").params, t, d, m, z, est)
    assert obs.shape == (2, 10) and obs.dtype == torch.float64
    assert torch.equal(obs[:, :7], base)  # the efference observation first, unchanged
    assert obs[0, 7:].tolist() == [1.5, -0.5, 0.25]
    assert obs[1, 7:].tolist() == [-DOUBT_CLAMP, DOUBT_CLAMP, 0.0]
    with pytest.raises(ValueError, match="controller.policy.observation=efference_doubt needs the filter's doubt"):
        policy_observation(ctl.params, t, d, m, z, est)


def test_the_fit_filter_s_doubt_is_its_offset_in_prior_sigmas():
    from dvsland.control.efference_fit import EfferenceFitFilter

    f = EfferenceFitFilter(torch.tensor([1000.0, 2000.0], dtype=torch.float64),
                           torch.tensor([-40.0, -50.0], dtype=torch.float64), 0.1, prior_rel_sigma=0.1)
    s = f.init_state()
    accel = torch.zeros(2, dtype=torch.float64)
    for k in range(30):  # both read a divergence 30 % faster than planned: the fit moves off the plan
        d_plan = s.vdr / s.zdr
        s, out = f.step_state(s, (1.3 * d_plan).to(torch.float32), None, accel)
    assert out.doubt.shape == (2, 3) and out.doubt.dtype == torch.float64
    p = f.params
    assert torch.equal(out.doubt[:, 0], s.theta[:, 0] / p.sz0) and torch.equal(out.doubt[:, 1], s.theta[:, 1] / p.sv0)
    assert (out.doubt[:, 0].abs() > 0.5).all()  # moved by more than half a prior sigma
    assert torch.equal(out.doubt[:, 2], s.n_rejected.double() / s.n.double())


def test_the_loop_hands_the_doubt_to_the_policy_and_other_filters_are_refused():
    st = _stages(DOUBT)
    assert st.controller.needs_doubt and st.controller.needs_estimate and st.controller.needs_altitude
    seen = []
    step = st.controller.step_state

    def spy(*a, **kw):
        seen.append(kw.get("doubt"))
        return step(*a, **kw)

    st.controller.step_state = spy
    s, outs = fly_steps(st, init_state(st), 5)
    assert all(torch.isfinite(o.thrust_n).all() for o in outs)
    assert len(seen) == 5 and all(d is not None and d.shape == (1, 3) for d in seen)
    with pytest.raises(ValueError, match="efference_doubt.*controller.filter=efference_fit"):
        _stages(DOUBT + ["controller.filter=efference"])
    assert not _stages(EFF).controller.needs_doubt


def test_a_gradient_reaches_the_doubt_inputs_weights():
    g = _first_layer_grad(DOUBT + ["controller.policy.base=div_gs"], True)
    assert g is not None and torch.isfinite(g).all() and g.shape[1] == 10
    for col in (7, 8):  # the offsets (the rejected share may be 0 throughout on an oracle)
        assert float(g[:, col].abs().max()) > 0.0, col


SHIPPED = Path(__file__).resolve().parents[1] / "examples" / "policies" / "residual_div_gs_cnn_landing.pt"


def test_the_shipped_residual_policy_loads_and_flies():
    """examples/policies/residual_div_gs_cnn_landing.pt (docs/train_loop.md): the trained residual on
    div_gs with the cnn_landing estimator flies; its corrections stay well inside its reach."""
    st = _stages(EFF + ["controller.policy.base=div_gs", "controller.policy.authority=0.2",
                        f"controller.policy.checkpoint={SHIPPED}", "estimator.name=learned",
                        "estimator.learned.checkpoint=cnn_landing"], site="I")
    assert st.controller.net.authority == 0.2 and st.controller.net.observation == "efference"
    s, outs = fly_steps(st, init_state(st), 30)
    r = torch.stack([o.control_residual for o in outs])
    assert torch.isfinite(r).all() and float(r.abs().max()) < 0.5
