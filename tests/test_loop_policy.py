"""dvsland.learn.loop_policy: a policy trained by gradients through the closed loop."""

from __future__ import annotations

import math

import pytest
import torch

from dvsland.config import load_config
from dvsland.learn.loop_policy import PolicyNet, evaluate_policy, observe, train_policy, window_loss
from dvsland.sim import init_state, sense_step
from dvsland.stages import build_stages

pytestmark = pytest.mark.usefixtures("one_thread")


def _stages(n_seeds=1):
    return build_stages(load_config("paper_montecarlo", ["estimator.name=oracle", "dispersion.terrain_variants=1",
                                                         f"simulation.n_seeds={n_seeds}"]), "D")


def test_observation_and_window_gradient():
    st = _stages()
    net = PolicyNet()
    obs = observe(st, sense_step(st, init_state(st)).out)
    assert obs.shape == (2, 4) and obs.dtype == torch.float64 and torch.isfinite(obs).all()
    loss, state, _, _ = window_loss(st, net, init_state(st), 10)
    loss.backward()
    grads = [p.grad for p in net.parameters()]
    assert math.isfinite(float(loss.detach())) and all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(float(g.abs().sum()) > 0 for g in grads) and state.step == 10


def test_short_training_runs_and_evaluates():
    st = _stages()
    run = train_policy(st, seconds=1.0, window=10)
    assert run["windows"] >= 1 and run["steps"] == run["windows"] * 10 * st.batch_size
    ev = evaluate_policy(_stages(), run["net"])
    assert ev["n"] == 2 and 0 <= ev["successes"] <= 2 and len(ev["outcomes"]) == 2
