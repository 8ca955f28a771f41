"""Eq. 8 of the paper: divergence from the change of the distances between tracked centroids."""

from __future__ import annotations

import functools
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
        dt_s: time between the two, s (> 0): a float, or a (B,) float64 tensor per element.
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
    if isinstance(dt_s, torch.Tensor):
        dt_s = dt_s.to(torch.float64).view(-1, 1, 1)  # (B, 1, 1): no check here (a device sync)
    elif not dt_s > 0:
        raise ValueError(f"dt_s must be > 0, got {dt_s}")
    l0, l1 = _lengths(prev_xy, cur_xy)
    return _eq8(_pairs(valid, l0, min_length_px), l0, l1, dt_s, min_length_px, weighting)


def _lengths(prev_xy: torch.Tensor, cur_xy: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """The pairs' lengths (l0, l1), each (B, N, N) float64 px, at both steps at once (exact: no
    cdist); an untracked (NaN) centroid counts as (0, 0)."""
    pc = torch.stack([prev_xy, cur_xy]).to(torch.float64).nan_to_num_(0.0)
    ll = torch.linalg.vector_norm(pc.unsqueeze(3) - pc.unsqueeze(2), dim=-1)  # (2, B, N, N)
    return ll[0], ll[1]


def _pairs(valid: torch.Tensor, l0: torch.Tensor, min_length_px: float) -> torch.Tensor:
    """Eq. 8's pairs (B, N, N) bool: i < j, both tracked, not shorter than ``min_length_px`` before."""
    use = valid.unsqueeze(-1) & valid.unsqueeze(-2)
    use &= _upper(valid.shape[1], str(valid.device))
    use &= l0 > min_length_px
    return use


def _eq8(use, l0, l1, dt_s, min_length_px: float, weighting: str) -> Tuple[torch.Tensor, torch.Tensor]:
    """Eq. 8's mean over the pairs ``use`` of the lengths ``l0`` -> ``l1`` (B, N, N) float64 over
    ``dt_s`` (a float or (B, 1, 1) float64): (d (B,) float32, NaN without a pair; n_pairs (B,) int64).
    ValueError for a ``weighting`` other than "none" or "length" (both public entries pass it here)."""
    if weighting not in ("none", "length"):
        raise ValueError(f"weighting must be 'none' or 'length', got {weighting!r}")
    term = torch.where(use, (1.0 - l1 / l0.clamp_min(min_length_px)) / dt_s, _zero64(str(use.device)))
    n = use.sum((-1, -2))
    if weighting == "length":
        w = torch.where(use, l0, torch.zeros_like(l0))
        d = (term * w).sum((-1, -2)) / w.sum((-1, -2)).clamp_min(1e-12)
    else:
        d = term.sum((-1, -2)) / n.clamp_min(1)
    d = torch.where(n > 0, d, torch.full_like(d, float("nan")))
    return d.to(torch.float32), n


@functools.lru_cache(maxsize=16)
def _upper(n: int, device: str) -> torch.Tensor:
    """(n, n) bool, True above the diagonal (pairs i < j); cached."""
    return torch.ones(n, n, dtype=torch.bool, device=device).triu(1)


@functools.lru_cache(maxsize=16)
def _zero64(device: str) -> torch.Tensor:
    return torch.zeros((), dtype=torch.float64, device=device)


def baseline_divergence(cur_xy: torch.Tensor, past_xy: torch.Tensor, lag: torch.Tensor, elapsed_s: torch.Tensor,
                        min_length_px: float = 1e-6) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """D from pairs of tracked centroids over a per-pair baseline (a multi-step Eq. 8; not in paper).

    For a pair (i, j) tracked for the last ``lag[b, i, j]`` steps, with l its length now and l' its
    length ``lag`` steps ago, ``elapsed`` seconds earlier: D_ij = -log(l / l') / elapsed (exact for
    a constant D; Eq. 8's (1 - l / l') / dt is its first-order form). The pairs are averaged with
    inverse-variance weights (l' elapsed)^2: a centroid jitter of s px perturbs D_ij by about
    s / (l' elapsed).

    Args:
        cur_xy: (B, N, 2) centroids now, px.
        past_xy: (B, N, N, 2, 2) for each pair (i, j) the positions of i and j ``lag`` steps ago.
        lag: (B, N, N) int64 steps; a pair counts where lag >= 1 and i < j.
        elapsed_s: (B, N, N) float64 time between the two windows, s (> 0 where lag >= 1).

    Returns:
        d (B,) float32 (NaN without a pair), n_pairs (B,) int64, rel_std (B,) float64 standard
        error of d relative to |d| from the weighted spread of the pairs (inf with one pair).
    """
    B, N = cur_xy.shape[:2]
    c = cur_xy.to(torch.float64).nan_to_num(0.0)
    l1 = torch.linalg.vector_norm(c.unsqueeze(2) - c.unsqueeze(1), dim=-1)  # (B, N, N)
    p = past_xy.to(torch.float64).nan_to_num(0.0)
    l0 = torch.linalg.vector_norm(p[..., 0, :] - p[..., 1, :], dim=-1)
    use = (lag >= 1) & _upper(N, str(cur_xy.device)) & (l0 > min_length_px) & (l1 > min_length_px)
    el = torch.where(use, elapsed_s.to(torch.float64), torch.ones_like(l0))
    d, n, rel = _weighted_pairs(use, l0, l1, el, min_length_px)
    d = torch.where(n > 0, d, torch.full_like(d, float("nan")))
    return d.to(torch.float32), n, rel


def eq8_with_spread(prev_xy: torch.Tensor, cur_xy: torch.Tensor, valid: torch.Tensor, dt_s: torch.Tensor,
                    elapsed_s: torch.Tensor, min_length_px: float = 1e-6,
                    weighting: str = "none") -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eq. 8 between two consecutive steps and the spread of its pairs, from one pair of length matrices.

    The same values, bit for bit, as ``pairwise_divergence(prev_xy, cur_xy, valid, dt_s, min_length_px,
    weighting)`` beside the ``rel_std`` of ``baseline_divergence`` over a one-step baseline (every pair
    tracked at both steps has lag 1 and was ``elapsed_s`` apart), which computed the same lengths twice.

    Args:
        prev_xy, cur_xy: (B, N, 2) float32 centroids at the last step and now, px (NaN = untracked).
        valid: (B, N) bool, centroids tracked at both steps.
        dt_s: (B,) float64 time between the steps, s (Eq. 8's dt).
        elapsed_s: (B,) float64 time between the two windows' mean event times, s (the spread's).

    Returns:
        d (B,) float32 1/s (NaN without a pair), n_pairs (B,) int64, rel_std (B,) float64 (inf with
        fewer than two pairs of the baseline rule).
    """
    l0, l1 = _lengths(prev_xy, cur_xy)
    pair = _pairs(valid, l0, min_length_px)
    d, n = _eq8(pair, l0, l1, dt_s.to(torch.float64).view(-1, 1, 1), min_length_px, weighting)
    # the spread (baseline_divergence's formulas; its pairs also need l1 > min_length_px)
    use = pair & (l1 > min_length_px)
    el = torch.where(use, elapsed_s.to(torch.float64).view(-1, 1, 1), torch.ones_like(l0))
    return d, n, _weighted_pairs(use, l0, l1, el, min_length_px)[2]


def _weighted_pairs(use: torch.Tensor, l0: torch.Tensor, l1: torch.Tensor, el: torch.Tensor,
                    min_length_px: float) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`baseline_divergence`'s inverse-variance average of its pairs ``use`` (B, N, N) bool from
    the lengths then and now ``l0``, ``l1`` and the elapsed times ``el`` (B, N, N) float64 (1 where
    unused): (d (B,) float64, 0 without a pair; n_pairs (B,) int64; rel_std (B,) float64)."""
    B = use.shape[0]
    term = torch.where(use, -torch.log(l1.clamp_min(min_length_px) / l0.clamp_min(min_length_px)) / el,
                       torch.zeros_like(l0))
    w = torch.where(use, (l0 * el) ** 2, torch.zeros_like(l0))
    n = use.sum((-1, -2))
    ws = w.sum((-1, -2))
    d = (term * w).sum((-1, -2)) / ws.clamp_min(1e-12)
    var = (w * (term - d.view(B, 1, 1)) ** 2).sum((-1, -2)) / ws.clamp_min(1e-12)
    n_eff = ws ** 2 / (w * w).sum((-1, -2)).clamp_min(1e-24)
    se = torch.sqrt(var / (n_eff - 1).clamp_min(1e-12))
    return d, n, torch.where(n > 1, se / d.abs().clamp_min(1e-6), torch.full_like(se, float("inf")))
