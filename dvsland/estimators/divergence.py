"""Eq. 8 of the paper: divergence from the change of the distances between tracked centroids."""

from __future__ import annotations

from typing import Tuple

import torch


def pairwise_divergence(prev_xy: torch.Tensor, cur_xy: torch.Tensor, valid: torch.Tensor, dt_s: float,
                        min_length_px: float = 1e-6, weighting: str = "none") -> Tuple[torch.Tensor, torch.Tensor]:
    """D = mean over tracked pairs (i < j) of (1 - l_t / l_{t-dt}) / dt   (paper Eq. 8).

    ``l`` is the distance between two centroids. Features spread apart while descending
    (l_t > l_{t-dt}), so D < 0 then.

    Args:
        prev_xy: (B, N, 2) float, centroids (x, y) at t - dt, px.
        cur_xy: (B, N, 2) float, the same centroids at t, px.
        valid: (B, N) bool, centroids tracked at both times.
        dt_s: time between the two, s (> 0).
        min_length_px: pairs shorter than this at t - dt are skipped (no division by ~0).
        weighting: "none" (the paper: plain mean) or "length" (weights l_{t-dt}: long pairs, whose
            ratio is least disturbed by centroid jitter, count more; not in paper).

    Returns:
        d: (B,) float32 divergence, 1/s; NaN where fewer than one pair.
        n_pairs: (B,) int64 pairs used.
    """
    if prev_xy.shape != cur_xy.shape or prev_xy.dim() != 3 or prev_xy.shape[-1] != 2:
        raise ValueError(f"prev_xy and cur_xy must both be (B, N, 2), got {tuple(prev_xy.shape)} "
                         f"and {tuple(cur_xy.shape)}")
    if valid.shape != prev_xy.shape[:2]:
        raise ValueError(f"valid must be (B, N) = {tuple(prev_xy.shape[:2])}, got {tuple(valid.shape)}")
    if not dt_s > 0:
        raise ValueError(f"dt_s must be > 0, got {dt_s}")
    if weighting not in ("none", "length"):
        raise ValueError(f"weighting must be 'none' or 'length', got {weighting!r}")
    N = prev_xy.shape[1]
    p = prev_xy.to(torch.float64)
    c = cur_xy.to(torch.float64)
    p = p.nan_to_num(0.0)
    c = c.nan_to_num(0.0)
    l0 = (p.unsqueeze(2) - p.unsqueeze(1)).norm(dim=-1)  # (B, N, N), exact (no cdist mm shortcut)
    l1 = (c.unsqueeze(2) - c.unsqueeze(1)).norm(dim=-1)
    upper = torch.ones(N, N, dtype=torch.bool, device=valid.device).triu(1)
    use = upper & valid.unsqueeze(-1) & valid.unsqueeze(-2) & (l0 > min_length_px)
    term = torch.where(use, (1.0 - l1 / l0.clamp_min(min_length_px)) / dt_s, torch.zeros((), dtype=torch.float64,
                                                                                         device=valid.device))
    n = use.sum((-1, -2))
    if weighting == "length":
        w = torch.where(use, l0, torch.zeros_like(l0))
        d = (term * w).sum((-1, -2)) / w.sum((-1, -2)).clamp_min(1e-12)
    else:
        d = term.sum((-1, -2)) / n.clamp_min(1)
    d = torch.where(n > 0, d, torch.full_like(d, float("nan")))
    return d.to(torch.float32), n
