"""The spiking divergence network: log-polar event rates -> two LIF conv layers -> leaky read-out.

Per time slice (``dt_s`` = control interval / n_sub):

- input (B, 2, n_rho, n_phi) events per pixel (ON, OFF), times a learned gain, compressed as log1p;
- conv 5x3 (rho x phi, circular in phi) -> 16 LIF neurons per bin;
- conv 5x3, stride 2 in rho -> 32 LIF neurons per bin;
- time constants: learned per channel (``learn_tau``, initialised log-spaced over 0.05-0.5 s in
  layer 1 and 0.1-2 s in layer 2: slow neurons keep the last seconds of a slow expansion), or
  fixed (0.1 s and 0.5 s);
- spikes averaged over phi -> (32, n_rho / 2) -> linear -> leaky-integrator read-out v; the
  estimate is D_hat = ``d_scale`` * v (1/s, negative while descending).

The state (membranes and currents of all layers) is carried across control steps and reset per
batch element. Shapes: batch first; all float32.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn as nn

from .lif import LIFParameters, LIFState, LIState, li_step, lif_state, lif_step, lif_step_inference, reset_state

#: upper bound of a learned dt/tau (explicit Euler stays stable below 1)
_K_MAX = 0.9


class SNNState(NamedTuple):
    l1: LIFState
    l2: LIFState
    out: LIState


class SpikingDivergenceNet(nn.Module):
    """See module doc. ``forward(x, state) -> (d_hat (B,), state, rates dict)`` for one slice."""

    def __init__(self, n_rho: int = 24, n_phi: int = 24, dt_s: float = 0.025, channels=(16, 32),
                 d_scale: float = 0.1, in_gain: float = 50.0, init_scale=(3.0, 4.0), learn_tau: bool = True):
        super().__init__()
        c1, c2 = int(channels[0]), int(channels[1])
        self.n_rho, self.n_phi, self.dt_s, self.d_scale = int(n_rho), int(n_phi), float(dt_s), float(d_scale)
        # zero padding of 2 in rho inside the convolutions, circular padding in phi by _pad
        self.conv1 = nn.Conv2d(2, c1, (5, 3), padding=(2, 0))
        self.conv2 = nn.Conv2d(c1, c2, (5, 3), stride=(2, 1), padding=(2, 0))
        # input gain (learned, log scale): a slice holds ~0.01 events per pixel on average, which
        # would leave every neuron silent (no spikes, hardly any surrogate gradient)
        self.log_in_gain = nn.Parameter(torch.tensor(float(in_gain)).log())
        with torch.no_grad():  # larger initial weights so that both layers spike from the start
            self.conv1.weight.mul_(init_scale[0])
            self.conv2.weight.mul_(init_scale[1])
        self.n_rho2 = (self.n_rho + 4 - 5) // 2 + 1
        self.readout = nn.Linear(c2 * self.n_rho2, 1)
        self.p1 = LIFParameters(tau_mem_s=0.1, tau_syn_s=0.05, v_th=1.0)
        self.p2 = LIFParameters(tau_mem_s=0.5, tau_syn_s=0.1, v_th=1.0)
        self.po = LIFParameters(tau_mem_s=0.5, tau_syn_s=0.1)
        self.channels = (c1, c2)
        self.learn_tau = bool(learn_tau)
        # the fixed time constants of p1 / p2 are used only without learn_tau (learned ones are
        # bounded by construction: dt / tau < 0.9)
        for p in (self.p1, self.p2, self.po) if not self.learn_tau else (self.po,):
            p.check_dt(self.dt_s)
        if self.learn_tau:
            # per-channel membrane / synaptic time constants, learned (heterogeneous time constants
            # give neurons different delays, which motion detection needs); initialised log-spaced,
            # membranes over [0.05, 0.5] s (layer 1) and [0.1, 2] s (layer 2); synapses over
            # [0.025 s + dt, 0.25 s] and [0.05 s + dt, 1 s] (about half, and always longer than dt)
            def raw(lo, hi, n):  # never shorter than 2 dt (dt / tau <= 0.5 < _K_MAX)
                lo, hi = max(lo, 2 * self.dt_s), max(hi, 4 * self.dt_s)
                k = self.dt_s / torch.logspace(math.log10(lo), math.log10(hi), n)
                return nn.Parameter(torch.logit(k / _K_MAX))
            self.raw_mem1, self.raw_syn1 = raw(0.05, 0.5, c1), raw(0.05 / 2 + self.dt_s, 0.25, c1)
            self.raw_mem2, self.raw_syn2 = raw(0.1, 2.0, c2), raw(0.05 + self.dt_s, 1.0, c2)

    @staticmethod
    def _pad(x: torch.Tensor) -> torch.Tensor:
        """Circular padding of 1 in phi (the zero padding of 2 in rho is the convolutions')."""
        return torch.cat([x[..., -1:], x, x[..., :1]], dim=-1)

    def initial_state(self, batch_size: int, device=None) -> SNNState:
        c1, c2 = self.channels
        return SNNState(lif_state((batch_size, c1, self.n_rho, self.n_phi), device),
                        lif_state((batch_size, c2, self.n_rho2, self.n_phi), device),
                        LIState(*lif_state((batch_size, 1), device)))

    @staticmethod
    def reset(state: SNNState, mask: torch.Tensor) -> SNNState:
        return SNNState(reset_state(state.l1, mask), reset_state(state.l2, mask), reset_state(state.out, mask))

    def _time_constants(self) -> dict:
        if not self.learn_tau:
            return {}
        return {n: (_K_MAX * torch.sigmoid(getattr(self, "raw_" + n)))[:, None, None]
                for n in ("mem1", "syn1", "mem2", "syn2")}

    def input_current(self, x: torch.Tensor) -> torch.Tensor:
        """Layer-1 input current of slices x (N, 2, n_rho, n_phi) -> (N, c1, n_rho, n_phi). It does
        not depend on the state, so a step's slices go through it as one batch."""
        return self.conv1(self._pad(torch.log1p(x * self.log_in_gain.exp())))

    def forward(self, x: torch.Tensor, state: SNNState, current: torch.Tensor = None, k: dict = None):
        """x: (B, 2, n_rho, n_phi) events per pixel of one slice (or ``current``, its
        :meth:`input_current`). Returns (d_hat (B,) 1/s, new state, {"rate1": (B,), "rate2": (B,)}
        mean spike rates of the slice)."""
        dt = self.dt_s
        k = self._time_constants() if k is None else k
        current = self.input_current(x) if current is None else current
        step = lif_step if torch.is_grad_enabled() else lif_step_inference
        z1, s1 = step(current, state.l1, self.p1, dt, k.get("mem1"), k.get("syn1"))
        z2, s2 = step(self.conv2(self._pad(z1)), state.l2, self.p2, dt, k.get("mem2"), k.get("syn2"))
        feat = z2.mean(dim=-1).flatten(1)  # (B, c2 * n_rho2)
        v, so = li_step(self.readout(feat), state.out, self.po, dt)
        rates = {"rate1": z1.mean(dim=(1, 2, 3)), "rate2": z2.mean(dim=(1, 2, 3))}
        return self.d_scale * v[:, 0], SNNState(s1, s2, so), rates

    def run_step(self, x: torch.Tensor, state: SNNState):
        """All slices of one control step: x (B, n_sub, 2, n_rho, n_phi). Returns (d_hat (B,) after
        the last slice, state, mean rates)."""
        b, n_sub = x.shape[:2]
        cur = self.input_current(x.flatten(0, 1)).unflatten(0, (b, n_sub))
        k = self._time_constants()
        rates = {}
        d = None
        for j in range(n_sub):
            d, state, r = self(None, state, cur[:, j], k)
            for n, v in r.items():
                rates[n] = rates.get(n, 0) + v / n_sub
        return d, state, rates
