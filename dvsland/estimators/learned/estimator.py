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
from .models import VoxelCNN
from .fast import RingCNN
from .inputs import InputSpec, camera_map, coord_channels, events_voxel_grid, pixel_cells, row_counts

#: the shipped checkpoints (trained by `dvsland train`, commands in docs/learning.md)
SHIPPED = {"cnn": Path(__file__).with_name("learned_cnn.pt"), "spiking": Path(__file__).with_name("learned_spiking.pt")}


class LearnedState(NamedTuple):
    """Per-row state: ``d`` (B,) float32 last D_hat (1/s, NaN = none), ``sigma_rel`` (B,) float32
    predicted relative std. dev., ``n_events`` (B,) int64 events of the last window, ``ring``
    (B, n_bins, h, w) float32 the voxel grids of the last n_windows steps in a circular buffer
    (slot q = bins q bpw .. (q + 1) bpw - 1; slot ``newest`` the latest, newest + 1 mod K the
    oldest: :func:`ordered_ring` gives them oldest first), ``ring_counts`` (B, n_windows) int64
    their events on the reference canvas, ``ring_abs`` (B, n_windows) float32 their sums of
    |value|, ``newest`` the slot of the latest window (an int, the same for every row). ``update``
    writes the new window into ``ring`` in place (a state kept from before sees it too); the other
    tensors are new each update."""

    d: torch.Tensor
    sigma_rel: torch.Tensor
    n_events: torch.Tensor
    ring: torch.Tensor
    ring_counts: torch.Tensor
    ring_abs: torch.Tensor
    newest: int


def initial_state(batch_size: int, spec: InputSpec, device) -> LearnedState:
    """Every row without an estimate and an empty ring."""
    nan = torch.full((batch_size,), float("nan"), dtype=torch.float32, device=device)
    return LearnedState(nan, nan.clone(), torch.zeros(batch_size, dtype=torch.int64, device=device),
                        torch.zeros(batch_size, spec.n_bins, *spec.grid_hw, device=device),
                        torch.zeros(batch_size, spec.n_windows, dtype=torch.int64, device=device),
                        torch.zeros(batch_size, spec.n_windows, dtype=torch.float32, device=device),
                        spec.n_windows - 1)


def reset_rows(state: LearnedState, mask: torch.Tensor) -> LearnedState:
    """``state`` with the rows where ``mask`` (B,) bool is True back to no estimate, ring empty."""
    nan = torch.tensor(float("nan"), device=state.d.device)
    keep = (~mask).view(-1, 1, 1, 1)
    return LearnedState(torch.where(mask, nan, state.d), torch.where(mask, nan, state.sigma_rel),
                        torch.where(mask, torch.zeros_like(state.n_events), state.n_events),
                        state.ring * keep, state.ring_counts * (~mask)[:, None],
                        state.ring_abs * (~mask)[:, None], state.newest)


def ordered_ring(state: LearnedState, spec: InputSpec) -> torch.Tensor:
    """(B, n_bins, h, w) float32: the ring's windows oldest first (the model's input order)."""
    B, nb, h, w = state.ring.shape
    K = spec.n_windows
    shift = (K - 1 - state.newest) % K
    if shift == 0:
        return state.ring
    return state.ring.view(B, K, nb // K, h, w).roll(shift, dims=1).reshape(B, nb, h, w)


def default_focal_px(sensor_size) -> float:
    """Focal length in px of the sensor preset of ``sensor_size`` (W, H) with a lens
    (``davis346``: 5.5 mm on 18.5 um), else of a 60 degree field of view across W."""
    from dvsland.config.schema import DEFAULT_FOV_DEG, SENSOR_PRESETS, focal_length_px

    W, H = (int(v) for v in sensor_size)
    for w, h, pitch_um, focal_mm in SENSOR_PRESETS.values():
        if (w, h) == (W, H) and focal_mm is not None:
            return 1000.0 * focal_mm / pitch_um
    return focal_length_px(W, DEFAULT_FOV_DEG)


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
        principal_point_px: focus of expansion: the events are resampled about it onto the
            checkpoint's reference canvas (:mod:`.inputs`), whose centre it becomes.
        focal_px: the camera's focal length in px (events of another lens are rescaled to the
            reference's pixel angle); None = from the sensor preset of this size (``davis346``,
            ``gen4``, ...; :data:`dvsland.config.schema.SENSOR_PRESETS`), else a 60 degree field
            of view across the width. Set it for a custom lens: W / (2 tan(fov / 2)).
        fast: how a :class:`~.models.VoxelCNN` runs: ``"ring"`` (default) on its circular ring
            with the folded first layer (:mod:`.fast`), ``"bf16"`` the same with the convolutions
            in bfloat16 (faster on a CPU with AVX512-BF16; D_hat moves by up to about 1 %), ``""``
            the model as trained (the reference "ring" agrees with to float32 rounding).
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, checkpoint: str = "",
                 min_events: int = 20, principal_point_px=None, focal_px: Optional[float] = None,
                 fast: str = "ring"):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        check_range("estimator.learned.min_events", min_events, 1, 1e9)
        self.min_events = int(min_events)
        self.checkpoint = resolve_checkpoint(checkpoint)
        net, self.spec, ck = load_checkpoint(self.checkpoint)
        self.model = net.to(self.device)
        self.meta = {k: ck.get(k) for k in ("model", "input", "data", "train")}
        if fast not in ("ring", "bf16", ""):
            raise ValueError(f"estimator.learned.fast must be 'ring', 'bf16' or '', got {fast!r}")
        if focal_px is not None:
            check_range("estimator.learned.focal_px", focal_px, 1e-3, 1e7)
        self.focal_px = float(focal_px) if focal_px is not None else default_focal_px(self.sensor_size)
        self.cmap = camera_map(self.spec, self.sensor_size, self.principal_point_px, self.focal_px)
        self.cells = None if self.cmap.identity else pixel_cells(self.cmap, self.spec, self.sensor_size, self.device)
        W0, H0 = self.spec.sensor_size
        self.coords = coord_channels(self.spec, ((W0 - 1) / 2.0, (H0 - 1) / 2.0), self.device)
        #: the CNN on its circular ring (:mod:`.fast`); None for other models (they get the ordered ring)
        self.ring_net = None
        if fast and type(self.model) is VoxelCNN:
            self.ring_net = RingCNN(self.model, self.coords, self.spec.n_windows,
                                    dtype=torch.bfloat16 if fast == "bf16" else torch.float32)
        self.state = initial_state(self.batch_size, self.spec, self.device)
        self._t_prev: Optional[int] = None

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        self.state = reset_rows(self.state, self._mask(mask))

    @torch.no_grad()  # not inference_mode: D_hat and the state are ordinary tensors the loop may edit
    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        t_us = int(t_us)
        t0 = self._t_prev if self._t_prev is not None and self._t_prev < t_us else t_us - int(round(self.dt_s * 1e6))
        self._t_prev = t_us
        B = self.batch_size
        grid, on_canvas = events_voxel_grid(events, t0, t_us, B, self.spec, self.cmap, self.cells)
        n = row_counts(events.b, B) if not self.cmap.identity else on_canvas
        st = self.state
        K, bpw = self.spec.n_windows, self.spec.bins_per_window
        q = (st.newest + 1) % K  # the oldest slot takes the new window (in place: no copy of the ring)
        st.ring[:, q * bpw:(q + 1) * bpw] = grid
        counts, sums = st.ring_counts.clone(), st.ring_abs.clone()
        counts[:, q] = on_canvas
        sums[:, q] = grid.abs().sum(dim=(1, 2, 3))
        total = counts.sum(1).to(torch.float32)
        if not self.cmap.identity:
            total = total * self.cmap.count_scale
        st = st._replace(ring_counts=counts, ring_abs=sums, newest=q)
        if self.ring_net is not None:
            mu, log_var = self.ring_net(st.ring, sums, q, torch.log1p(total))
        else:
            mu, log_var = self.model(ordered_ring(st, self.spec), self.coords, torch.log1p(total))
        ok = n >= self.min_events
        nan = torch.tensor(float("nan"), device=self.device)
        d = torch.where(ok, -torch.exp(mu), nan).to(torch.float32)
        sig = torch.where(ok, torch.exp(0.5 * log_var), nan).to(torch.float32)
        self.state = st._replace(d=d, sigma_rel=sig, n_events=n.to(torch.int64))
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
