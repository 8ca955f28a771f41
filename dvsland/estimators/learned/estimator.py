"""``learned``: any network trained by the recipe (``dvsland train --model ...``) as a loop estimator.

Each control step the events since the previous update become a voxel grid (:mod:`.inputs`);
the model sees the grids of the last ``n_windows`` steps of its checkpoint (a ring per row,
zeros after a reset) and predicts mu and log_var of log|D| (:mod:`.models`); the estimate is
D_hat = -exp(mu) (1/s, descending). Rows with fewer than ``min_events`` events in the latest
window return NaN. The per-row state (:class:`LearnedState`) is the ring, its event counts, the
last estimate and its predicted spread.

``confidence()``: 1 / (1 + (sigma_rel / 0.1)^2) with sigma_rel = exp(log_var / 2), the predicted
standard deviation of log|D| (about the relative error of D_hat); 0 where the estimate is NaN.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, Optional

import torch

from dvsland.checks import check_range

from ..base import DivergenceEstimator, Truth, confidence_from_rel_std
from ..registry import register_estimator
from .checkpoint import load_checkpoint
from .inputs import InputSpec, coord_channels, events_voxel_grid

#: the shipped checkpoints (trained by `dvsland train`, commands in docs/learning.md)
SHIPPED = {"cnn": Path(__file__).with_name("learned_cnn.pt"), "spiking": Path(__file__).with_name("learned_spiking.pt")}


class LearnedState(NamedTuple):
    """Per-row state: ``d`` (B,) float32 last D_hat (1/s, NaN = none), ``sigma_rel`` (B,) float32
    predicted relative std. dev., ``n_events`` (B,) int64 events of the last window, ``ring``
    (B, n_bins, h, w) float32 the voxel grids of the last n_windows steps (oldest first),
    ``ring_counts`` (B, n_windows) int64 their events."""

    d: torch.Tensor
    sigma_rel: torch.Tensor
    n_events: torch.Tensor
    ring: torch.Tensor
    ring_counts: torch.Tensor


def initial_state(batch_size: int, spec: InputSpec, device) -> LearnedState:
    """Every row without an estimate and an empty ring."""
    nan = torch.full((batch_size,), float("nan"), dtype=torch.float32, device=device)
    return LearnedState(nan, nan.clone(), torch.zeros(batch_size, dtype=torch.int64, device=device),
                        torch.zeros(batch_size, spec.n_bins, *spec.grid_hw, device=device),
                        torch.zeros(batch_size, spec.n_windows, dtype=torch.int64, device=device))


def reset_rows(state: LearnedState, mask: torch.Tensor) -> LearnedState:
    """``state`` with the rows where ``mask`` (B,) bool is True back to no estimate, ring empty."""
    nan = torch.tensor(float("nan"), device=state.d.device)
    keep = (~mask).view(-1, 1, 1, 1)
    return LearnedState(torch.where(mask, nan, state.d), torch.where(mask, nan, state.sigma_rel),
                        torch.where(mask, torch.zeros_like(state.n_events), state.n_events),
                        state.ring * keep, state.ring_counts * (~mask)[:, None])


def resolve_checkpoint(checkpoint: str) -> Path:
    """``""`` or ``"cnn"`` -> the shipped CNN, ``"spiking"`` -> the shipped spiking model, else a path."""
    key = str(checkpoint or "cnn")
    return SHIPPED.get(key, Path(key))


@register_estimator("learned")
class LearnedEstimator(DivergenceEstimator):
    """A recipe checkpoint as an estimator (see module doc).

    Args:
        checkpoint: path of a ``dvsland train --model`` checkpoint; ``""``/``"cnn"`` = the shipped
            CNN, ``"spiking"`` = the shipped spiking model.
        min_events: windows with fewer events give NaN, in [1, 1e9].
        principal_point_px: focus of expansion (coordinate channels are relative to it).
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, checkpoint: str = "",
                 min_events: int = 20, principal_point_px=None):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        check_range("estimator.learned.min_events", min_events, 1, 1e9)
        self.min_events = int(min_events)
        self.checkpoint = resolve_checkpoint(checkpoint)
        net, self.spec, ck = load_checkpoint(self.checkpoint, self.sensor_size)
        self.model = net.to(self.device)
        self.meta = {k: ck.get(k) for k in ("model", "input", "data", "train")}
        self.coords = coord_channels(self.spec, self.principal_point_px, self.device)
        self.state = initial_state(self.batch_size, self.spec, self.device)
        self._t_prev: Optional[int] = None

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        self.state = reset_rows(self.state, self._mask(mask))

    @torch.no_grad()
    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        t_us = int(t_us)
        t0 = self._t_prev if self._t_prev is not None and self._t_prev < t_us else t_us - int(round(self.dt_s * 1e6))
        self._t_prev = t_us
        B = self.batch_size
        grid = events_voxel_grid(events, t0, t_us, B, self.spec)
        n = torch.bincount(events.b, minlength=B)[:B].to(self.device)
        st = self.state
        ring = torch.cat([st.ring[:, self.spec.bins_per_window:], grid], dim=1)
        counts = torch.cat([st.ring_counts[:, 1:], n[:, None].to(torch.int64)], dim=1)
        mu, log_var = self.model(ring, self.coords, torch.log1p(counts.sum(1).to(torch.float32)))
        ok = n >= self.min_events
        nan = torch.tensor(float("nan"), device=self.device)
        d = torch.where(ok, -torch.exp(mu), nan).to(torch.float32)
        sig = torch.where(ok, torch.exp(0.5 * log_var), nan).to(torch.float32)
        self.state = LearnedState(d, sig, n.to(torch.int64), ring, counts)
        return d.clone()

    @property
    def _d(self) -> torch.Tensor:
        return self.state.d

    def confidence(self) -> torch.Tensor:
        """(B,) float32 in [0, 1] from the predicted relative spread; 0 where NaN."""
        return confidence_from_rel_std(self.state.sigma_rel, self.state.d)

    def diagnostics(self):
        """sigma_rel (B,) predicted relative std. dev.; n_events (B,); confidence (B,); for a
        spiking model also spikes and synops (B,) of the last update."""
        out = {"sigma_rel": self.state.sigma_rel.clone(), "n_events": self.state.n_events.clone(),
               "confidence": self.confidence()}
        for k, v in getattr(self.model, "last_activity", {}).items():
            out[k] = v.clone()
        return out
