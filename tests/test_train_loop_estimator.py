"""dvsland train-loop --what estimator: the learned estimator's weights trained through the closed loop."""

from __future__ import annotations

import json

import pytest
import torch

from dvsland.cli.main import main
from dvsland.config import load_config
from dvsland.estimators.learned import learned_step
from dvsland.estimators.learned.checkpoint import load_checkpoint
from dvsland.estimators.learned.estimator import SHIPPED
from dvsland.learn.loop_estimator import ESTIMATOR_KIND, GRAPH_BYTES_PER_GRID_CELL, EstimatorWeights
from dvsland.learn.loop_loss import LossWeights, gradient_mode, window_loss
from dvsland.learn.loop_run import CHECKPOINT, restore, trained_config
from dvsland.learn.loop_train import TrainLoopRun, TrainLoopSettings, check_horizon_fits, save_checkpoint
from dvsland.learn.loop_trainables import make_trainable
from dvsland.sim import init_state, loop_step
from dvsland.stages import build_stages

pytestmark = pytest.mark.usefixtures("one_thread")
COMMON = ["estimator.name=learned", "dispersion.terrain_variants=1", "simulation.n_seeds=1", "render.threads=1"]


def _stages(extra=(), sites="D"):
    return build_stages(load_config("montecarlo_efference", COMMON + list(extra)), sites)


def _fly(st, s, n):
    with torch.no_grad():
        for _ in range(n):
            prev = s
            s, out = loop_step(st, s)
    return prev, s, out


def test_gradient_reaches_the_weights():
    """A short closed-loop window with grad=True: d loss / d D_hat reaches every weight, finite."""
    st = _stages()
    tr = make_trainable(st, "estimator")
    assert isinstance(tr, EstimatorWeights) and gradient_mode(st) is True
    assert st.estimator.consts.ring_net is None and st.estimator.consts.model is tr.net  # shared, not copied
    _, s, out = _fly(st, init_state(st), 15)
    assert bool(torch.isfinite(out.d_est).any())  # the CNN estimates by now
    tr.apply_to(st)
    loss, terms, _ = window_loss(st, s, 8, LossWeights(track=0, landing=1, fail=25, fuel=0, filter=1))
    assert loss.requires_grad and terms["filter"] > 0
    loss.backward()
    grads = [p.grad for p in tr.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert sum(float(g.norm()) for g in grads) > 0 and float(tr.net.features[0].weight.grad.norm()) > 0


def test_plain_learned_step_unchanged_and_without_graph():
    """The flag keeps the outputs bit for bit; a graph only when training asks for it (and grad is on)."""
    st = _stages()
    est = st.estimator
    prev, s, out = _fly(st, init_state(st), 12)
    assert out.events is not None and not out.d_est.requires_grad
    args = (est.params, est.consts._replace(ring_net=None), prev.stage_state.estimator, out.events, out.t_us)
    plain = learned_step(*args)
    with torch.enable_grad():
        plain_on = learned_step(*args)  # grad on, flag off: no graph (the loop's plain path)
        trained = learned_step(est.params, args[1]._replace(grad=True), *args[2:])
    with torch.no_grad():
        flag_off = learned_step(est.params, args[1]._replace(grad=True), *args[2:])  # flag on, grad off
    for o in (plain, plain_on, trained, flag_off):
        assert torch.equal(torch.nan_to_num(o[1].d_hat, 9.0), torch.nan_to_num(plain[1].d_hat, 9.0))
        assert torch.equal(o[1].confidence, plain[1].confidence) and torch.equal(o[0].ring, plain[0].ring)
    assert not any(t.requires_grad for o in (plain, plain_on, flag_off) for t in (o[1].d_hat, o[1].confidence))
    assert trained[1].d_hat.requires_grad and not trained[0].ring.requires_grad  # the inputs: no graph
    ring = learned_step(est.params, est.consts, prev.stage_state.estimator, out.events, out.t_us)
    torch.testing.assert_close(ring[1].d_hat, plain[1].d_hat, rtol=1e-4, atol=0, equal_nan=True)


def test_the_memory_check_counts_the_network_graph():
    st = _stages()
    plain = check_horizon_fits(st, 40, 1e12)
    make_trainable(st, "estimator")
    assert check_horizon_fits(st, 40, 1e12) - plain == 40 * st.batch_size * GRAPH_BYTES_PER_GRID_CELL * 64 * 64
    with pytest.raises(ValueError, match="--window 40"):
        check_horizon_fits(st, 40, 2.0 * plain)


@pytest.mark.parametrize("extra, names, needle", [
    (["estimator.name=oracle"], (), "estimator.name is 'oracle'"),
    ([], ("kp_scale",), "--params"),
])
def test_bad_input(extra, names, needle):
    with pytest.raises(ValueError, match=needle) as info:
        make_trainable(_stages(extra), "estimator", names)
    if not names:
        assert "--what estimator" in str(info.value)


def test_checkpoint_round_trip_loads_and_flies(tmp_path):
    """checkpoint.pt is a `dvsland train` checkpoint: --resume restores it, trained.yaml flies it."""
    st = _stages()
    tr = make_trainable(st, "estimator")
    opt = torch.optim.Adam(tr.parameters(), lr=1e-3)
    with torch.no_grad():
        tr.net.features[0].bias.add_(0.01)
    path = tmp_path / CHECKPOINT
    save_checkpoint(path, tr, opt, TrainLoopSettings(what="estimator"), TrainLoopRun(windows=1), torch.zeros(1),
                    st.cfg.controller.name)
    tr2 = make_trainable(_stages(), "estimator")
    run, _, _ = restore(path, tr2, torch.optim.Adam(tr2.parameters(), lr=1e-3), st.cfg.controller.name)
    assert run.windows == 1 and torch.equal(tr2.net.features[0].bias, tr.net.features[0].bias)
    with pytest.raises(ValueError, match="a 'dvsland-loop-estimator' checkpoint"):
        restore(path, make_trainable(_stages(["controller.name=tau_p"]), "law"), opt, "tau_p")
    flown = trained_config(st.cfg, tr, path)
    assert flown.estimator.learned.checkpoint == str(path.resolve()) and flown.controller == st.cfg.controller
    net, _, _ = load_checkpoint(flown.estimator.learned.checkpoint)
    assert torch.equal(net.features[0].bias, tr.net.features[0].bias)
    st2 = build_stages(flown, "D")
    assert torch.equal(st2.estimator.model.features[0].bias, tr.net.features[0].bias)
    _, _, last = _fly(st2, init_state(st2), 12)
    assert bool(torch.isfinite(last.d_est).any()) and not last.d_est.requires_grad


def test_validation_batch_flies_the_trained_weights_on_a_fresh_ring_net():
    st, val = _stages(), _stages()
    tr = make_trainable(st, "estimator")
    with torch.no_grad():
        tr.net.features[0].weight.mul_(1.1)
    tr.apply_to(val)
    c = val.estimator.consts
    assert c.model is tr.net and not c.grad and c.ring_net is not None
    assert torch.equal(c.ring_net.w_vox.flatten(1, 2), tr.net.features[0].weight[:, :tr.net.n_bins])
    tr.apply_to(st)
    assert st.estimator.consts.grad and st.estimator.consts.ring_net is None


def test_cli_trains_resumes_and_flies_the_checkpoint(tmp_path, capsys):
    out = tmp_path / "run"
    base = ["--sites", "D", *sum((["--set", c] for c in COMMON + ["simulation.t_max_s=3"]), [])]
    rc = main(["train-loop", "montecarlo_efference", "--what", "estimator", "--window", "6", "--max-windows", "2",
               "--val-every", "0", "--lr", "1e-3", "--quiet", "--out", str(out), *base])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((out / "train_loop.json").read_text())
    assert summary["what"] == "estimator" and summary["windows"] == 2 and summary["values"]["weight_change"] > 0
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    assert ck["kind"] == ESTIMATOR_KIND and ck["format"] == "dvsland-learned"
    rc = main(["train-loop", "--what", "estimator", "--window", "6", "--max-windows", "3", "--val-every", "0",
               "--lr", "1e-3", "--quiet", "--resume", str(out), "--sites", "D"])
    assert rc == 0, capsys.readouterr().err
    assert json.loads((out / "train_loop.json").read_text())["windows"] == 3
    # trained.yaml names the checkpoint by absolute path; the learned estimator loads it and flies
    flown = load_config(str(out / "trained.yaml"))
    assert flown.estimator.learned.checkpoint == str((out / "checkpoint.pt").resolve())
    net, _, _ = load_checkpoint(flown.estimator.learned.checkpoint)
    shipped, _, _ = load_checkpoint(SHIPPED["cnn"])
    w = net.features[0].weight
    assert not torch.equal(w, shipped.features[0].weight)
    st = build_stages(flown, "D")
    assert torch.equal(st.estimator.model.features[0].weight, w) and st.estimator.consts.ring_net is not None
    _, _, last = _fly(st, init_state(st), 12)
    assert bool(torch.isfinite(last.d_est).any()) and not last.d_est.requires_grad
