"""NaN-aware moving average of divergence estimates, with a per-element window length.

The paper averages the last n_bin estimates of D before inverting to TTC. Here every batch
element may have its own n_bin (controller settings side by side in one batch): the filter
keeps a ring of the last max(n_bin) estimates and a per-element mask of which ring slots count.
Missing estimates (NaN) are skipped; the filter reports how many it used.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

Tensor = torch.Tensor


def nan_moving_average(history: Tensor, n_bin: Tensor) -> Tuple[Tensor, Tensor]:
    """Mean of the newest ``n_bin`` finite entries window per element (NaN where none).

    Args:
        history: (N, B) float, newest first (row 0 = latest); NaN = missing.
        n_bin: (B,) int64 window lengths, 1 <= n_bin <= N.

    Returns:
        (mean, n_used): (B,) float (NaN where no finite value in the window) and (B,) int64.
    """
    n = history.shape[0]
    rows = torch.arange(n, device=history.device).unsqueeze(1)
    return _masked_mean(history, rows < n_bin.to(history.device).unsqueeze(0))


def _masked_mean(history: Tensor, in_window: Tensor) -> Tuple[Tensor, Tensor]:
    valid = in_window & torch.isfinite(history)
    n_used = valid.sum(0)
    mean = torch.where(valid, history, 0.0).sum(0) / n_used  # 0 / 0 = NaN where none
    return mean, n_used


class MovingAverageFilter:
    """Stateful batched NaN-aware moving average.

    Args:
        n_bin: (B,) int window lengths (or a sequence of ints), each >= 1.
        device: torch device.
        dtype: dtype of the stored history (float64 default).

    Example::

        f = MovingAverageFilter(torch.tensor([5, 10]))
        d_f, n_used = f.update(d_hat)   # d_hat (2,), NaN = missing
    """

    def __init__(self, n_bin, device="cpu", dtype: torch.dtype = torch.float64):
        n_bin = torch.as_tensor(n_bin, dtype=torch.int64, device=device).reshape(-1)
        if n_bin.numel() < 1 or bool((n_bin < 1).any()):
            raise ValueError(f"n_bin must be >= 1 for every element, got {n_bin.tolist()}")
        self.n_bin = n_bin
        self.batch_size = int(n_bin.numel())
        self.n_max = int(n_bin.max())
        self._hist = torch.full((self.n_max, self.batch_size), float("nan"), dtype=dtype, device=device)
        rows = torch.arange(self.n_max, device=device).unsqueeze(1)
        self._in_window = rows < n_bin.unsqueeze(0)  # (N, B) which ring rows count, newest first

    def reset(self, mask: Optional[Tensor] = None) -> None:
        """Forget the history of the elements where ``mask`` (B,) bool is True (all when None)."""
        if mask is None:
            self._hist.fill_(float("nan"))
        else:
            self._hist[:, mask] = float("nan")

    provides_altitude = False

    @classmethod
    def from_params(cls, p, **options) -> "MovingAverageFilter":
        """From the loop's :class:`~dvsland.control.DescentParams` (window = each setting's n_bin)."""
        if options:
            raise ValueError(f"filter 'moving_average' takes no options, got {sorted(options)}")
        return cls(p.n_bin, device=p.device)

    def update(self, d_hat: Tensor, mask: Optional[Tensor] = None, accel_mps2: Optional[Tensor] = None,
               thrust_accel_mps2: Optional[Tensor] = None, confidence: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """Push one estimate per element and return the filtered value.

        Args:
            d_hat: (B,) float estimates, 1/s; NaN = missing.
            mask: optional (B,) bool: only these elements take the new estimate (others keep
                their history unchanged; frozen descents).
            accel_mps2, thrust_accel_mps2, confidence: ignored (the efference-copy filter's
                inputs; the same call serves both filters).

        Returns:
            (d_filtered (B,), n_used (B,) int64).
        """
        if d_hat.shape != (self.batch_size,):
            raise ValueError(f"d_hat must have shape ({self.batch_size},), got {tuple(d_hat.shape)}")
        d_hat = d_hat.to(self._hist.dtype)
        rolled = torch.roll(self._hist, 1, dims=0)
        rolled[0] = d_hat
        if mask is not None:
            rolled = torch.where(mask.unsqueeze(0), rolled, self._hist)
        self._hist = rolled
        return _masked_mean(self._hist, self._in_window)
