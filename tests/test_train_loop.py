"""dvsland train-loop: a law's constants and the 'policy' law trained by gradients through the loop."""

from __future__ import annotations

import json
import math

import pytest
import torch

from dvsland.cli.main import main
from dvsland.config import load_config
from dvsland.control import PolicyNet, load_policy
from dvsland.learn.loop_loss import LossWeights, window_loss
from dvsland.learn.loop_train import TrainLoopRun, TrainLoopSettings, check_finite_loss, save_checkpoint
from dvsland.learn.loop_trainables import LawConstants, make_trainable
from dvsland.sim import fly_steps, init_state, loop_step
from dvsland.stages import build_stages

pytestmark = pytest.mark.usefixtures("one_thread")
COMMON = ["estimator.name=oracle", "dispersion.terrain_variants=1", "simulation.n_seeds=1", "render.threads=1"]


def _stages(controller="div_gs", extra=()):
    return build_stages(load_config("paper_montecarlo", COMMON + [f"controller.name={controller}", *extra]), "D")


# ------------------------------------------------------------------ the policy law
def test_policy_law_flies_without_a_graph():
    st = _stages("policy")
    s = init_state(st)
    for _ in range(3):
        s, out = loop_step(st, s)
    assert out.thrust_n.shape == (2,) and torch.isfinite(out.thrust_n).all() and not out.thrust_n.requires_grad
    assert not any(p.requires_grad for p in st.controller.net.parameters())


def test_policy_checkpoint_round_trip_and_errors(tmp_path):
    st = _stages("policy")
    tr = make_trainable(st, "policy")
    with torch.no_grad():
        tr.net.net[0].weight.add_(0.5)
    opt = torch.optim.Adam(tr.parameters())
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, tr, opt, TrainLoopSettings().check(), TrainLoopRun(), torch.zeros(2, dtype=torch.int64),
                    "policy")
    net = load_policy(path)
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), tr.net.state_dict().values()))
    flown = build_stages(load_config("paper_montecarlo", COMMON + ["controller.name=policy",
                                                                   f"controller.policy.checkpoint={path}"]), "D")
    assert torch.equal(flown.controller.net.net[0].weight, tr.net.net[0].weight)
    with pytest.raises(ValueError, match="controller.policy.checkpoint.*no such file|controller.policy.checkpoint"):
        load_policy(tmp_path / "missing.pt")
    torch.save({"kind": "something-else"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a policy checkpoint"):
        load_policy(tmp_path / "other.pt")
    ck = torch.load(path, weights_only=True)
    ck["state_dict"]["net.0.weight"][0, 0] = float("nan")
    torch.save(ck, tmp_path / "nan.pt")
    with pytest.raises(ValueError, match="NaN"):
        load_policy(tmp_path / "nan.pt")


# ------------------------------------------------------------------ law constants: gradients
@pytest.mark.parametrize("controller, name", [("div_gs", "lambda_per_s"), ("tau_p", "kp_scale")])
def test_law_constant_gradient_matches_finite_differences(controller, name):
    st = _stages(controller)
    tr = make_trainable(st, "law", [name])
    w = LossWeights(track=1.0, landing=1.0, fail=25.0, fuel=0.1)
    with torch.no_grad():  # past the start, where the paper laws sit on their clamp at 0 N
        start, _ = fly_steps(st, init_state(st), 300)

    def loss_at(raw: float) -> torch.Tensor:
        with torch.no_grad():
            tr.raw[name].fill_(raw)
        tr.apply(st.controller)
        return window_loss(st, start, 30, w)[0]

    x0 = float(tr.raw[name].detach())
    tr.zero_grad()
    loss_at(x0).backward()
    g = float(tr.raw[name].grad)
    h = 1e-3  # smaller steps drown in round-off: the loss is O(1), its derivative O(1e-4)
    with torch.no_grad():
        fd = (float(loss_at(x0 + h)) - float(loss_at(x0 - h))) / (2 * h)
    assert math.isfinite(g) and g != 0.0
    assert g == pytest.approx(fd, rel=1e-2)


def test_d_final_reaches_the_landing_speed():
    """d_final acts on the final approach only: its gradient over a whole descent is not zero."""
    st = _stages("div_gs")
    tr = make_trainable(st, "law", ["d_final_per_s"])
    tr.apply(st.controller)
    loss, terms, state = window_loss(st, init_state(st), 0, LossWeights(track=0.0))
    loss.backward()
    assert terms["ended"] == 2 and not bool(state.active.any())
    assert float(tr.raw["d_final_per_s"].grad) > 0  # a slower final approach lands softer


def test_no_grad_flight_unchanged_by_trainable_values():
    """Putting the config's own values back as tensors flies the same descent bit for bit."""
    st = _stages("div_gs")
    s0 = init_state(st)
    ref, _ = loop_step(st, loop_step(st, s0)[0])
    LawConstants(st.controller, "div_gs").apply(st.controller)
    with torch.no_grad():
        got, _ = loop_step(st, loop_step(st, s0)[0])
    assert torch.allclose(got.z_m, ref.z_m, rtol=1e-14) and torch.allclose(got.v_mps, ref.v_mps, rtol=1e-14)


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("controller, what, names, needle", [
    ("tau_p", "law", ["lambda_per_s"], "--params lambda_per_s"),
    ("tau_p", "policy", [], "controller.name=policy"),
    ("policy", "law", [], "--what law"),
    ("policy", "policy", ["kp_scale"], "--params"),
    ("tau_p", "nonsense", [], "--what"),
])
def test_bad_what_and_params(controller, what, names, needle):
    with pytest.raises(ValueError, match=needle.replace("--", r"\-\-")):
        make_trainable(_stages(controller), what, names)


def test_bad_loss_and_nonfinite_loss():
    with pytest.raises(ValueError, match="--loss"):
        LossWeights.parse("speed=1")
    with pytest.raises(ValueError, match="--loss"):
        LossWeights.parse("fuel=-1")
    tr = make_trainable(_stages("div_gs"), "law")
    with pytest.raises(ValueError, match="not finite"):
        check_finite_loss(torch.tensor(float("nan")), tr, 0)


@pytest.mark.parametrize("argv, needle", [
    (["--what", "law", "--window", "-1"], "--window"),
    (["--what", "law", "--lr", "0"], "--lr"),
    (["--what", "law", "--cpu-minutes", "nan"], "--cpu-minutes"),
    (["--what", "law", "--resume", "/nonexistent/dir"], "--resume"),
])
def test_cli_bad_options_make_no_folder(tmp_path, capsys, argv, needle):
    out = tmp_path / "run"
    rc = main(["train-loop", "paper_montecarlo", "--set", "controller.name=div_gs", "--out", str(out), *argv]
              if "--resume" not in argv else ["train-loop", *argv])
    assert rc == 2 and needle in capsys.readouterr().err and not out.exists()


# ------------------------------------------------------------------ the command, end to end
def test_cli_trains_resumes_and_flies_the_result(tmp_path, capsys):
    out = tmp_path / "run"
    base = ["--sites", "D", *sum((["--set", c] for c in COMMON + ["controller.name=div_gs",
                                                                   "simulation.t_max_s=40"]), [])]
    rc = main(["train-loop", "paper_montecarlo", "--what", "law", "--window", "20", "--max-windows", "2",
               "--val-every", "1", "--quiet", "--out", str(out), *base])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((out / "train_loop.json").read_text())
    assert summary["windows"] == 2 and len(summary["history"]) == 2 and "val" in summary["history"][0]
    assert (out / "checkpoint.pt").is_file() and any((out / "tb").iterdir())
    rc = main(["train-loop", "--what", "law", "--window", "20", "--max-windows", "3", "--val-every", "0",
               "--quiet", "--resume", str(out), "--sites", "D"])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((out / "train_loop.json").read_text())
    assert summary["windows"] == 3 and len(summary["history"]) == 3
    flown = load_config(str(out / "trained.yaml"))
    assert flown.controller.div_gs.lambda_per_s == pytest.approx(summary["values"]["lambda_per_s"])
    assert flown.controller.div_gs.d_final_per_s == pytest.approx(summary["values"]["d_final_per_s"])
    assert summary["values"]["lambda_per_s"] != 1.0


def test_policy_net_starts_near_hover():
    net = PolicyNet(8)
    with torch.no_grad():
        frac = float(torch.sigmoid(net(torch.zeros(1, 4, dtype=torch.float64))))
    assert frac == pytest.approx(1 / 3, rel=0.05)


def test_straight_through_gradient_with_an_event_estimator():
    """With events in the loop the estimate keeps its value and takes the true divergence's gradient."""
    st = build_stages(load_config("paper_montecarlo", ["estimator.name=dpr", "dispersion.terrain_variants=1",
                                                       "simulation.n_seeds=1", "render.threads=1",
                                                       "controller.name=div_gs"]), "D")
    s0 = init_state(st)
    ref = fly_steps(st, s0, 12)[1][-1]
    z0 = s0.z_m.clone().requires_grad_(True)
    s = s0._replace(z_m=z0)
    for _ in range(12):
        s, out = loop_step(st, s, grad="straight_through")
    assert torch.equal(torch.isnan(out.d_est), torch.isnan(ref.d_est))
    ok = ~torch.isnan(ref.d_est)
    assert bool(ok.any()) and torch.allclose(out.d_est[ok], ref.d_est[ok], rtol=1e-12)
    assert out.d_est.grad_fn is not None
    s.z_m.sum().backward()
    assert z0.grad is not None and torch.isfinite(z0.grad).all()


def test_dynamics_gradient_finite_at_zero_thrust():
    """A step at 0 N (engine off) has a finite gradient: no 0/0 in the burnout branch not taken."""
    from dvsland.dynamics.lander import LanderParams, step_exact

    u = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    z, v, m, _ = step_exact(torch.full((3,), 1000.0, dtype=torch.float64), torch.full((3,), -20.0, dtype=torch.float64),
                            torch.tensor([1e4, 1e3, 5e3], dtype=torch.float64), u, 0.1, LanderParams())
    (z + v + m).sum().backward()
    assert torch.isfinite(u.grad).all()


def test_a_horizon_that_does_not_fit_memory_is_refused():
    from dvsland.learn.loop_train import check_horizon_fits

    st = _stages("div_gs")
    assert check_horizon_fits(st, 40, 2**34) > 0
    with pytest.raises(ValueError, match=r"--window 0: .* GiB of autograd graph"):
        check_horizon_fits(st, 0, 2**20)
