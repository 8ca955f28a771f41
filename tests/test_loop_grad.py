"""Gradients through the pure loop: the dynamics and the laws pass gradcheck (float64), and with the
oracle (the estimate a function of the true state) a 50-step closed loop carries the gradient of the
final state with respect to the initial one, as finite differences give it."""

from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck

from dvsland.config import load_config
from dvsland.dynamics.lander import LanderParams, step_euler, step_exact
from dvsland.sim import init_state, loop_step
from dvsland.stages import build_stages

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = dict(dtype=torch.float64)


@pytest.mark.parametrize("step", [step_exact, step_euler])
def test_dynamics_gradcheck(step):
    p = LanderParams()
    args = [torch.tensor(v, **F64, requires_grad=True) for v in
            ([3000.0, 1500.0], [-80.0, -40.0], [9000.0, 8000.0], [12000.0, 20000.0])]
    assert gradcheck(lambda z, v, m, u: step(z, v, m, u, 0.1, p)[:3], args)


@pytest.mark.parametrize("law", ["tau_p", "div_p", "div_gs"])
def test_law_gradcheck(law):
    ctl = build_stages(load_config("paper", [f"controller.name={law}", "estimator.name=oracle"]), "D").controller
    s0, t, alive = ctl.init_state(), torch.tensor([10.0, 10.0], **F64), torch.ones(2, dtype=torch.bool)
    z = torch.tensor([3000.0, 3000.0], **F64)
    d = torch.tensor([-0.03, -0.025], **F64, requires_grad=True)
    m = torch.tensor([9000.0, 9000.0], **F64, requires_grad=True)
    assert gradcheck(lambda d, m: ctl.step_state(s0, t, d, m, alive, z)[1].thrust_n, (d, m))


def _final_altitude(stages, v0: torch.Tensor, n: int) -> torch.Tensor:
    state = init_state(stages)._replace(v_mps=v0)
    for _ in range(n):
        state, _ = loop_step(stages, state, grad=True)
    return state.z_m


def test_closed_loop_gradient_matches_finite_differences():
    stages = build_stages(load_config("paper", ["estimator.name=oracle", "controller.name=div_p"]), "D")
    # faster than planned (-100 m/s): the law's thrust starts above its clamp at 0 (at the planned start
    # its error is exactly 0, on the clamp's kink, where one-sided derivatives differ)
    v0 = torch.tensor([-110.0, -105.0], **F64, requires_grad=True)
    z = _final_altitude(stages, v0, 50)
    (g,) = torch.autograd.grad(z.sum(), v0)
    eps = 0.5  # m/s: the estimate is float32 (the contract), so a smaller step differences its rounding
    for b in range(2):
        dv = torch.zeros(2, **F64)
        dv[b] = eps
        with torch.no_grad():
            fd = (_final_altitude(stages, v0 + dv, 50) - _final_altitude(stages, v0 - dv, 50)).sum() / (2 * eps)
        assert torch.isfinite(g[b]) and abs(float(g[b]) - float(fd)) <= 1e-5 * max(1.0, abs(float(fd)))
    with torch.no_grad():  # the default (grad=False) flies the same numbers
        state = init_state(stages)._replace(v_mps=v0.detach())
        for _ in range(50):
            state, _ = loop_step(stages, state)
    assert torch.equal(state.z_m, z.detach())
