"""Leaky integrate-and-fire neurons in plain torch, norse-style: parameters, state, one step.

A layer's state is a small named tuple of tensors with the batch first, so that ``reset(mask)``
zeroes chosen batch elements and the state can be carried across control steps. The spike uses
the SuperSpike surrogate gradient (Zenke & Ganguli 2018) so a network can be trained with
back-propagation through time. Discrete dynamics of one step of length ``dt_s``::

    v <- v + dt/tau_mem * (v_leak - v + i)     membrane
    i <- i - dt/tau_syn * i + input            synaptic current
    z  = H(v - v_th)                           spike (surrogate gradient)
    v <- v * (1 - z)                           reset to 0 where it spiked

:func:`li_step` is the non-spiking leaky integrator used as a read-out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch


@dataclass(frozen=True)
class LIFParameters:
    """LIF constants: time constants in s, threshold and leak in membrane units, surrogate
    sharpness ``alpha`` (SuperSpike: d z / d v = 1 / (alpha |v - v_th| + 1)^2)."""

    tau_mem_s: float = 0.1
    tau_syn_s: float = 0.05
    v_th: float = 1.0
    v_leak: float = 0.0
    alpha: float = 10.0

    def __post_init__(self):
        for name in ("tau_mem_s", "tau_syn_s", "v_th", "alpha"):
            if not getattr(self, name) > 0:
                raise ValueError(f"LIFParameters.{name} must be > 0, got {getattr(self, name)}")

    def check_dt(self, dt_s: float) -> None:
        """The explicit Euler step is stable for dt_s < tau_syn_s <= ...: ValueError otherwise."""
        if not 0 < dt_s < min(self.tau_mem_s, self.tau_syn_s):
            raise ValueError(f"the LIF step dt_s must be in (0, min(tau_mem_s, tau_syn_s)) = "
                             f"(0, {min(self.tau_mem_s, self.tau_syn_s)}), got {dt_s}")


class LIFState(NamedTuple):
    """Membrane ``v`` and synaptic current ``i``, both (B, ...) float32."""

    v: torch.Tensor
    i: torch.Tensor


class LIState(NamedTuple):
    """Leaky-integrator read-out state: ``v`` and ``i``, both (B, ...)."""

    v: torch.Tensor
    i: torch.Tensor


class _SuperSpike(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, alpha: float) -> torch.Tensor:
        ctx.save_for_backward(x)
        ctx.alpha = alpha
        return (x > 0).to(x.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (x,) = ctx.saved_tensors
        return grad / (ctx.alpha * x.abs() + 1.0) ** 2, None


def spike(x: torch.Tensor, alpha: float = 10.0) -> torch.Tensor:
    """Heaviside step H(x) with the SuperSpike surrogate gradient."""
    return _SuperSpike.apply(x, float(alpha))


def lif_state(shape, device=None, dtype=torch.float32) -> LIFState:
    """A resting LIF state of ``shape`` (batch first)."""
    z = torch.zeros(shape, device=device, dtype=dtype)
    return LIFState(z, z.clone())


def lif_step(x: torch.Tensor, state: LIFState, p: LIFParameters, dt_s: float, k_mem=None, k_syn=None):
    """One LIF step. x: input current (B, ...), same shape as the state. ``k_mem``, ``k_syn``:
    optional dt/tau factors in (0, 1) broadcastable to the state (per-neuron, learnable time
    constants); default dt_s / p.tau_*. Returns (spikes z (B, ...) float32 in {0, 1}, new state)."""
    k_mem = dt_s / p.tau_mem_s if k_mem is None else k_mem
    k_syn = dt_s / p.tau_syn_s if k_syn is None else k_syn
    v = state.v + k_mem * (p.v_leak - state.v + state.i)
    i = state.i * (1.0 - k_syn) + x
    z = spike(v - p.v_th, p.alpha)
    v = v * (1.0 - z)
    return z, LIFState(v, i)


@torch.no_grad()
def lif_step_inference(x: torch.Tensor, state: LIFState, p: LIFParameters, dt_s: float, k_mem=None, k_syn=None):
    """:func:`lif_step` without autograd, in fewer tensor operations (same arithmetic, same
    results bit for bit when ``p.v_leak`` is 0; otherwise it calls :func:`lif_step`). For
    inference, where the per-step overhead of small element-wise ops dominates."""
    if p.v_leak != 0.0:
        return lif_step(x, state, p, dt_s, k_mem, k_syn)
    k_mem = dt_s / p.tau_mem_s if k_mem is None else k_mem
    k_syn = dt_s / p.tau_syn_s if k_syn is None else k_syn
    v = state.i - state.v  # == v_leak - v + i for v_leak = 0
    v.mul_(k_mem).add_(state.v)
    i = state.i * (1.0 - k_syn)
    i.add_(x)
    fired = v > p.v_th
    v.masked_fill_(fired, 0.0)
    return fired.to(x.dtype), LIFState(v, i)


def li_step(x: torch.Tensor, state: LIState, p: LIFParameters, dt_s: float):
    """One leaky-integrator step (no spike, no reset). Returns (v (B, ...), new state)."""
    v = state.v + (dt_s / p.tau_mem_s) * (p.v_leak - state.v + state.i)
    i = state.i * (1.0 - dt_s / p.tau_syn_s) + x
    return v, LIState(v, i)


def reset_state(state, mask: torch.Tensor):
    """Zero the batch elements where ``mask`` (B,) bool is True; returns a new state."""
    keep = (~mask).to(state[0].dtype).view(-1, *([1] * (state[0].dim() - 1)))
    return type(state)(*(s * keep for s in state))
