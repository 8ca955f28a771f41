"""The time-to-contact target of the paper: tau*(t) = tau0 - c^2 t, tau0 = z0 / |v0|."""

from __future__ import annotations

import torch

Tensor = torch.Tensor


def initial_ttc(z0_m: Tensor, v0_mps: Tensor) -> Tensor:
    """tau0 = z0 / |v0|, s. ``z0_m``, ``v0_mps``: (B,) float64 (v0 != 0)."""
    z0 = torch.as_tensor(z0_m, dtype=torch.float64)
    v0 = torch.as_tensor(v0_mps, dtype=torch.float64, device=z0.device)
    if bool((v0 == 0).any()) or bool((z0 <= 0).any()):
        raise ValueError("initial_ttc needs z0_m > 0 and v0_mps != 0 for every element")
    return z0 / v0.abs()


def tau_target(t_s: Tensor, tau0_s: Tensor, c2: float) -> Tensor:
    """tau*(t) = tau0 - c^2 t, s.

    Args:
        t_s: (B,) or scalar float64 time of flight, s.
        tau0_s: (B,) float64 initial TTC, s.
        c2: c^2 in (0, 1).

    Returns:
        (B,) float64 target TTC, s (it goes negative after tau0 / c^2; the descent ends long before).
    """
    if not 0 < c2 < 1:
        raise ValueError(f"c2 must be in (0, 1), got {c2}")
    return tau0_s - c2 * t_s
