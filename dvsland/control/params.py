"""What the loop hands every controller: the per-descent parameters of the batch.

A controller is built from one :class:`DescentParams` (all tensors (B,), float64 unless said)
plus its own law options from the config. The loop fills it from the batch layout (sites x
settings x seeds) and the config, so a law never reads the config itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import torch

Tensor = torch.Tensor


@dataclass
class DescentParams:
    """Per-descent parameters of a batch of B descents.

    Attributes:
        kp: (B,) float64 gain Kp of each element's setting (units are the law's: N/s for ``tau_p``,
            N s for ``div_p``, whose error is a divergence in 1/s).
        n_bin: (B,) int64 moving-average length of each element's setting, estimates.
        tau0_s: (B,) float64 initial time to contact z0/|v0|, s.
        z0_m: (B,) float64 nominal initial altitude, m.
        v0_mps: (B,) float64 nominal initial velocity, m/s (< 0).
        m0_kg: (B,) float64 initial mass, kg.
        c2: the TTC target's slope: tau*(t) = tau0 - c2 t.
        g_mps2: gravity, m/s^2.
        dt_s: control interval, s.
        thrust_min_n: lower thrust bound, N (>= 0).
        thrust_max_n: upper thrust bound, N, or None (unbounded).
        missing_policy: ``"hold"`` (keep the last thrust) or ``"hover"`` (m g) when the filtered
            estimate is missing.
    """

    kp: Tensor
    n_bin: Tensor
    tau0_s: Tensor
    z0_m: Tensor
    v0_mps: Tensor
    m0_kg: Tensor
    c2: float = 0.5
    g_mps2: float = 1.62
    dt_s: float = 0.1
    thrust_min_n: float = 0.0
    thrust_max_n: Optional[float] = None
    missing_policy: str = "hold"
    extra: dict = field(default_factory=dict)

    @property
    def batch_size(self) -> int:
        return int(self.kp.numel())

    @property
    def device(self) -> torch.device:
        return self.kp.device

    def __post_init__(self):
        B = self.kp.numel()
        for name in ("n_bin", "tau0_s", "z0_m", "v0_mps", "m0_kg"):
            t = getattr(self, name)
            if t.shape != (B,):
                raise ValueError(f"DescentParams.{name} must have shape ({B},) like kp, got {tuple(t.shape)}")
        if self.missing_policy not in ("hold", "hover"):
            raise ValueError(f"missing_policy must be 'hold' or 'hover', got {self.missing_policy!r}")
        if not 0 < self.c2 < 1:
            raise ValueError(f"c2 must be in (0, 1), got {self.c2}")
        if not self.dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {self.dt_s}")

    @classmethod
    def simple(cls, kp, n_bin, z0_m, v0_mps, m0_kg=1e4, device="cpu", **kw) -> "DescentParams":
        """Build from plain numbers or lists (broadcast to a common B); for tests and scripts."""
        f64 = torch.float64
        kp = torch.as_tensor(kp, dtype=f64, device=device).reshape(-1)
        z0 = torch.as_tensor(z0_m, dtype=f64, device=device).reshape(-1)
        v0 = torch.as_tensor(v0_mps, dtype=f64, device=device).reshape(-1)
        B = max(kp.numel(), z0.numel(), v0.numel())
        kp, z0, v0 = kp.expand(B).clone(), z0.expand(B).clone(), v0.expand(B).clone()
        nb = torch.as_tensor(n_bin, dtype=torch.int64, device=device).reshape(-1).expand(B).clone()
        m0 = torch.as_tensor(m0_kg, dtype=f64, device=device).reshape(-1).expand(B).clone()
        return cls(kp=kp, n_bin=nb, tau0_s=z0 / v0.abs(), z0_m=z0, v0_mps=v0, m0_kg=m0, **kw)
