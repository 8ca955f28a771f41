"""``oracle``: the true divergence, optionally with noise and delay, for controller studies."""

from __future__ import annotations

from typing import Optional

import torch

from dvsland.checks import check_fields
from dvsland.config.schema import OracleConfig

from .base import DivergenceEstimator, Truth
from .registry import register_estimator


@register_estimator("oracle")
class OracleEstimator(DivergenceEstimator):
    """Returns D = v/z from ``truth``, plus Gaussian noise, delayed by ``delay_steps`` updates.

    Args:
        noise_abs: additive noise sigma, 1/s.
        noise_rel: proportional noise sigma (fraction of |D|).
        delay_steps: the estimate returned at step k is the one of step k - delay_steps
            (NaN before enough steps exist).
        seed: seed of the noise generator (drawn on CPU, then moved).
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, noise_abs: float = 0.0,
                 noise_rel: float = 0.0, delay_steps: int = 0, seed: int = 0, principal_point_px=None):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        # the ranges of the config schema (estimator.oracle), written once there
        check_fields(OracleConfig, noise_abs=noise_abs, noise_rel=noise_rel, delay_steps=delay_steps)
        self.noise_abs = float(noise_abs)
        self.noise_rel = float(noise_rel)
        self.delay_steps = int(delay_steps)
        self.needs_events = False
        self._gen = torch.Generator(device="cpu").manual_seed(int(seed))
        # ring of past estimates, (delay + 1, B); NaN = not yet available
        self._ring = torch.full((self.delay_steps + 1, self.batch_size), float("nan"),
                                dtype=torch.float32, device=self.device)
        self._k = 0  # updates so far (ring write position)

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        mask = self._mask(mask)
        self._ring[:, mask] = float("nan")
        if hasattr(self, "_d"):
            self._d[mask] = float("nan")

    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        if truth is None:
            raise ValueError("the 'oracle' estimator needs truth=Truth(altitude_m, velocity_mps)")
        d = truth.divergence.to(device=self.device, dtype=torch.float64)
        if self.noise_abs > 0 or self.noise_rel > 0:
            n = torch.randn(self.batch_size, generator=self._gen, dtype=torch.float64).to(self.device)
            d = d + n * (self.noise_abs + self.noise_rel * d.abs())
        # slot k mod (delay + 1) takes this step; the one written delay steps ago is next in line
        n_slots = self.delay_steps + 1
        self._ring[self._k % n_slots] = d
        self._k += 1
        self._d = self._ring[self._k % n_slots].clone()
        return self._d.clone()

    def confidence(self) -> torch.Tensor:
        """(B,) float32: 1 / (1 + (noise_rel / 0.1)^2) where the estimate is finite (additive noise
        ignored), 0 where NaN."""
        d = getattr(self, "_d", None)
        if d is None:
            return torch.zeros(self.batch_size, dtype=torch.float32, device=self.device)
        c = torch.full_like(d, 1.0 / (1.0 + (self.noise_rel / 0.1) ** 2))
        return torch.where(torch.isfinite(d), c, torch.zeros_like(c))

    def diagnostics(self):
        return {"d_oracle": self._ring[(self._k - 1) % (self.delay_steps + 1)].clone(),
                "confidence": self.confidence()}
