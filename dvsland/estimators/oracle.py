"""``oracle``: the true divergence, optionally with noise and delay, for controller studies."""

from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

import torch

from dvsland.checks import check_fields
from dvsland.config.schema import OracleConfig

from dvsland.pytree import hash_normal, tree_where

from .base import DivergenceEstimator, EstimateOut, Truth
from .registry import register_estimator


class OracleState(NamedTuple):
    """State of the ``oracle`` estimator for B descents.

    Attributes:
        ring: (B, delay_steps + 1) float64 past true divergences, 1/s (NaN = not yet available).
        k: (B,) int64 updates since each descent's (re)start (the ring's write position and the
            noise draw's counter).
        seed: (B,) int64 noise seed of each descent.
    """

    ring: torch.Tensor
    k: torch.Tensor
    seed: torch.Tensor


#: stream tag of the oracle's noise draws (:func:`dvsland.pytree.hash_normal`)
TAG_ORACLE_NOISE = 0x0AC1E


def oracle_step(p: OracleConfig, state: OracleState, truth: Truth) -> Tuple[OracleState, torch.Tensor]:
    """Pure step of the ``oracle``: (next state, D_hat (B,) float64, the estimate of ``delay_steps``
    updates ago, NaN before that many exist). Noise is a counter-based draw of (seed, k)."""
    ring, k = state.ring, state.k
    d = truth.divergence.to(device=ring.device, dtype=torch.float64)
    if p.noise_abs > 0 or p.noise_rel > 0:
        n = hash_normal(state.seed, k, TAG_ORACLE_NOISE)
        d = d + n * (p.noise_abs + p.noise_rel * d.abs())
    n_slots = ring.shape[1]
    rows = torch.arange(ring.shape[0], device=ring.device)
    ring = ring.index_put((rows, k % n_slots), d)
    k = k + 1
    return OracleState(ring, k, state.seed), ring[rows, k % n_slots]


@register_estimator("oracle")
class OracleEstimator(DivergenceEstimator):
    """Returns D = v/z from ``truth``, plus Gaussian noise, delayed by ``delay_steps`` updates.

    Args:
        noise_abs: additive noise sigma, 1/s.
        noise_rel: proportional noise sigma (fraction of |D|).
        delay_steps: the estimate returned at step k is the one of step k - delay_steps
            (NaN before enough steps exist).
        seed: seed of the noise (counter-based draws of (seed, descent, update)).

    Its params are :class:`dvsland.config.schema.OracleConfig`; its state :class:`OracleState`.
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, noise_abs: float = 0.0,
                 noise_rel: float = 0.0, delay_steps: int = 0, seed: int = 0, principal_point_px=None):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        # the ranges of the config schema (estimator.oracle), written once there
        check_fields(OracleConfig, noise_abs=noise_abs, noise_rel=noise_rel, delay_steps=delay_steps)
        self.params = OracleConfig(noise_abs=float(noise_abs), noise_rel=float(noise_rel), delay_steps=int(delay_steps))
        self.seed = int(seed)
        self.needs_events = False
        self.state = self.init_state()

    @property
    def noise_abs(self) -> float:
        return self.params.noise_abs

    @property
    def noise_rel(self) -> float:
        return self.params.noise_rel

    @property
    def delay_steps(self) -> int:
        return self.params.delay_steps

    def init_state(self) -> OracleState:
        B, dev = self.batch_size, self.device
        seeds = ((self.seed * 1_000_003) % (2 ** 62) + torch.arange(B, dtype=torch.int64)) % (2 ** 62)
        return OracleState(torch.full((B, self.delay_steps + 1), float("nan"), dtype=torch.float64, device=dev),
                           torch.zeros(B, dtype=torch.int64, device=dev), seeds.to(dev))

    def reset_where(self, state: OracleState, mask: torch.Tensor) -> OracleState:
        return tree_where(self._mask(mask), self.init_state(), state)

    def step_state(self, state: OracleState, events, t_us: int, truth: Optional[Truth] = None):
        if truth is None:
            raise ValueError("the 'oracle' estimator needs truth=Truth(altitude_m, velocity_mps)")
        state, d = oracle_step(self.params, state, truth)
        d32 = d.to(torch.float32)
        c = torch.full_like(d32, 1.0 / (1.0 + (self.noise_rel / 0.1) ** 2))
        conf = torch.where(torch.isfinite(d32), c, torch.zeros_like(c))
        return state, EstimateOut(d32, conf, {"d_oracle": d32, "confidence": conf})
