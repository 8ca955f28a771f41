"""A thrust policy trained by gradients through the closed loop (truncated backpropagation in time).

The loop's step is pure and differentiable where its maths is smooth (:func:`dvsland.sim.loop_step`
with ``grad=True``): the dynamics, the estimate of the ``oracle`` (a function of the true state) and
the thrust a policy commands. So a small network can learn to fly from the loss of the flight
itself, without a reinforcement-learning estimator of the gradient:

- observation (B, 4) float64: the estimate D_hat and the target D*(t) (both scaled by 1/0.05 1/s),
  their difference (scaled by 1/0.01 1/s) and the hover thrust as a fraction of the engine's top;
- action: thrust = sigmoid(net(obs)) x ``thrust_high_n`` (0 .. the engine's top, N);
- loss per step: ((D - D*(t)) / 0.01)^2 dt on the true divergence after the step, plus, on a
  descent's last step, (v / 2 m/s)^2 for a success and a constant for a crash or an ascent;
- windows of ``window`` steps: the graph is cut at each window's start (the state is detached) and
  finished descents restart with a new dispersed start (:func:`dvsland.sim.reset_where`), so a
  batch trains on a stream of descents.

D*(t) = -1 / max(tau0 - c2 t, tau_min) is the paper's time-to-contact profile (tau_min = 2 / the
crash divergence). Frames and events carry no gradient: a policy on an event estimator would see its
estimate as an input (not done here).
"""

from __future__ import annotations

import math
import time
from typing import Dict, Optional

import torch
from torch import nn

from dvsland.pytree import tree_map
from dvsland.sim import act_step, dispersed_start, init_state, reset_where, sense_step
from dvsland.sim.termination import SUCCESS

#: observation scales: divergence 1/s, tracking error 1/s
D_SCALE, ERR_SCALE = 0.05, 0.01


class PolicyNet(nn.Module):
    """obs (B, 4) float64 -> thrust fraction logit (B,); initialised near hover."""

    def __init__(self, hidden: int = 32, hover_fraction: float = 1.0 / 3.0):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(4, hidden), nn.Tanh(), nn.Linear(hidden, 1)).double()
        with torch.no_grad():
            self.net[2].weight.mul_(0.1)
            self.net[2].bias.fill_(math.log(hover_fraction / (1.0 - hover_fraction)))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs).squeeze(-1)


def divergence_target(stages, t_s: torch.Tensor) -> torch.Tensor:
    """D*(t) (B,) float64 1/s of each descent at flight time ``t_s`` (B,) s."""
    p = stages.params
    tau_min = 2.0 / stages.settings.crash_divergence
    return -1.0 / (p.tau0_s - p.c2 * t_s).clamp_min(tau_min)


def thrust_high_n(stages) -> float:
    """The engine's top, N: ``controller.thrust_max_n`` or 3 m0 g."""
    hi = getattr(stages.cfg.controller, "thrust_max_n", None)
    return float(hi) if hi else 3.0 * stages.settings.mass_kg * stages.settings.g_mps2


def observe(stages, out) -> torch.Tensor:
    """The policy's observation (B, 4) float64 from a :class:`~dvsland.sim.StepOutput` (keeps its graph)."""
    d = torch.nan_to_num(out.d_est, nan=0.0)
    d_star = divergence_target(stages, out.t_flight_s)
    hover = out.m_kg * stages.settings.g_mps2 / thrust_high_n(stages)
    return torch.stack((d / D_SCALE, d_star / D_SCALE, (d - d_star) / ERR_SCALE, hover), dim=1)


def policy_step(stages, net: PolicyNet, state, grad: bool = True):
    """One loop step flown with the policy's thrust: (next state, StepOutput, thrust (B,) N)."""
    sensed = sense_step(stages, state, grad=grad)
    u = torch.sigmoid(net(observe(stages, sensed.out))) * thrust_high_n(stages)
    nxt, out = act_step(stages, sensed, thrust=u)
    return nxt, out, u


def _restart(stages, state, episode: torch.Tensor, seed: int, dispersion: float):
    """Restart finished descents with starts dispersed by counter-based draws of (seed, descent, episode)."""
    done = ~state.active
    if not bool(done.any()):
        return state, episode
    episode = episode + done.to(torch.int64)
    b = torch.arange(state.batch_size, device=state.z_m.device)
    z0, v0 = dispersed_start(stages, (seed, b, episode), dispersion, 0.5 * dispersion, (0.7, 1.3), (0.8, 1.2))
    return reset_where(stages, state, done, z_m=z0, v_mps=v0), episode


def window_loss(stages, net: PolicyNet, state, window: int):
    """Fly ``window`` steps from ``state`` (detached) with the policy: (loss, next state, successes, ends)."""
    state = tree_map(lambda t: t.detach(), state)
    dt = stages.settings.dt_s
    loss = torch.zeros((), dtype=torch.float64)
    n_success = n_end = 0
    for _ in range(window):
        flying = state.active
        state, out, _ = policy_step(stages, net, state)
        d = state.v_mps / state.z_m
        t = out.t_flight_s + dt
        err = torch.where(flying, (d - divergence_target(stages, t)) / ERR_SCALE, torch.zeros_like(d))
        ended = flying & ~state.active
        success = ended & (state.outcome == SUCCESS)
        term = torch.where(success, (state.v_mps / 2.0) ** 2, torch.where(ended, torch.full_like(d, 25.0),
                                                                            torch.zeros_like(d)))
        loss = loss + (err.clamp(-30, 30) ** 2 * dt + term).sum() / state.batch_size
        n_success += int(success.sum())
        n_end += int(ended.sum())
    return loss, state, n_success, n_end


def train_policy(stages, seconds: float = 120.0, window: int = 40, lr: float = 3e-3, seed: int = 0,
                 dispersion: float = 0.05, net: Optional[PolicyNet] = None, log=None) -> Dict:
    """Train a :class:`PolicyNet` on ``stages`` (an ``oracle`` batch) for ``seconds`` of CPU time.

    Returns:
        {"net", "windows", "steps" (descent-steps simulated), "cpu_s", "successes", "ends"}.
    """
    torch.manual_seed(seed)
    net = net or PolicyNet()
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    state = init_state(stages)
    episode = torch.zeros(state.batch_size, dtype=torch.int64)
    c0, windows, succ, ends = time.process_time(), 0, 0, 0
    while time.process_time() - c0 < seconds:
        state, episode = _restart(stages, state, episode, seed, dispersion)
        loss, state, s, e = window_loss(stages, net, state, window)
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        windows, succ, ends = windows + 1, succ + s, ends + e
        if log is not None and windows % 25 == 0:
            log(f"window {windows}: loss {float(loss.detach()):.3f}, ends {ends}, successes {succ}")
    return {"net": net, "windows": windows, "steps": windows * window * state.batch_size,
            "cpu_s": time.process_time() - c0, "successes": succ, "ends": ends}


@torch.no_grad()
def evaluate_policy(stages, net: PolicyNet) -> Dict:
    """Fly every descent of ``stages`` once with the policy: outcomes and landing speeds."""
    state = init_state(stages)
    while bool(state.active.any()) and state.step < stages.settings.n_steps_max:
        state, _, _ = policy_step(stages, net, state, grad=False)
    success = state.outcome == SUCCESS
    v = state.v_mps[success].abs()
    return {"n": state.batch_size, "successes": int(success.sum()), "outcomes": state.outcome.tolist(),
            "landing_speed_mps": [round(float(x), 2) for x in v],
            "median_landing_speed_mps": round(float(v.median()), 2) if len(v) else None}


__all__ = ["PolicyNet", "observe", "policy_step", "window_loss", "train_policy", "evaluate_policy",
           "divergence_target", "thrust_high_n"]
