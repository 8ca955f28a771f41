"""Test-time mirroring of a learned estimator's input: the mean over mirrored copies of its window.

A descent's divergence does not change when the scene is mirrored about the focus of expansion
(which the input mapping puts at the reference canvas's centre): its events mirrored across the
canvas's vertical or horizontal centre line, or transposed on a square canvas, are the events of a
mirrored scene at the same D. The recipe trains on such mirrorings at random (``dvsland train``
mirrors every sample in x and y and transposes it, each with probability 1/2), so a network's
estimates of the mirrored copies of one window are equally good guesses whose errors differ; their
mean is a better one (test-time augmentation).

``flips`` copies of each row, each copy one batched forward of the B rows: 1 (the window alone, the
default), 2 (and its 180 degree turn), 4 (and its mirrorings in x and in y), 8 (and the transposes
of these four: the whole symmetry group of a square canvas). The estimate is the mean of the copies' mu (log|D|);
its predicted variance is the copies' mean variance plus the variance of their mu (the spread of a
mixture of the copies' Gaussians). Spikes and synaptic operations add up over the copies: they are
the update's cost.
"""

from __future__ import annotations

from typing import Callable, List, Tuple

import torch

#: the allowed numbers of copies
FLIPS = (1, 2, 4, 8)


def check_flips(flips: int, sensor_size: Tuple[int, int], pool_px: int) -> int:
    """``flips`` as an int after checking it is one of :data:`FLIPS` and that the reference canvas
    (``sensor_size`` (W, H) px, cells of ``pool_px``) is tiled symmetrically about its centre (W and
    H multiples of ``pool_px``) and, for 8, square. ValueError naming ``estimator.learned.flips``."""
    if flips not in FLIPS:
        raise ValueError(f"estimator.learned.flips must be one of {', '.join(map(str, FLIPS))}, got {flips!r}")
    W, H = (int(v) for v in sensor_size)
    if flips > 1 and (W % pool_px or H % pool_px):
        raise ValueError(f"estimator.learned.flips = {flips} needs cells that tile the reference canvas symmetrically "
                         f"(W and H multiples of pool_px = {pool_px}, got {W} x {H}); use flips = 1")
    if flips == 8 and W != H:
        raise ValueError(f"estimator.learned.flips = 8 transposes the window, which needs a square reference "
                         f"canvas (got {W} x {H}); use flips = 1, 2 or 4")
    return int(flips)


def mirrored_copies(vox: torch.Tensor, flips: int) -> List[torch.Tensor]:
    """The ``flips`` mirrored copies of the windows ``vox`` (B, ..., h, w), each like ``vox``:
    identity, 180 degree turn, mirror in x, mirror in y, then the transposes of these four."""
    copies = [vox]
    if flips >= 2:
        copies.append(vox.flip((-2, -1)))
    if flips >= 4:
        copies += [vox.flip(-1), vox.flip(-2)]
    if flips == 8:
        copies += [c.transpose(-2, -1) for c in copies[:4]]
    return copies


def run_copies(net: Callable, vox: torch.Tensor, flips: int, *args):
    """``net(copy, *args)`` -> (mu, log_var, *activity) of each mirrored copy of ``vox`` in turn (one
    batch of B rows at a time: one batch of ``flips`` B rows cost 1.4 to 2.8 times more per row on a CPU),
    pooled by :func:`pool_copies`; with ``flips`` 1 the call as it is."""
    if flips == 1:
        return net(vox, *args)
    outs = [net(c, *args) for c in mirrored_copies(vox, flips)]  # a loop over the <= 8 copies, not the batch
    return pool_copies(*(torch.stack(o) for o in zip(*outs)))


def pool_copies(mu: torch.Tensor, log_var: torch.Tensor, *activity: torch.Tensor):
    """(mu (B,), log_var (B,), *activity) of B rows from the outputs of their copies, each stacked
    (flips, B, ...): the mean mu, the log of the mean variance plus the variance of mu, and each
    activity count summed over the copies."""
    mean = mu.mean(0)
    var = torch.exp(log_var).mean(0) + (mu - mean).square().mean(0)
    return (mean, torch.log(var), *(a.sum(0) for a in activity))


__all__ = ["FLIPS", "check_flips", "mirrored_copies", "pool_copies", "run_copies"]
