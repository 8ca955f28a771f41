"""``learned``: any network trained by the recipe (``dvsland train --model ...``) as a loop estimator.

Each control step the events since the previous update become a voxel grid (:mod:`.inputs`);
the model sees the grids of the last ``n_windows`` steps of its checkpoint (a ring per row,
zeros after a reset) and predicts mu and log_var of log|D| (:mod:`.models`); the estimate is
D_hat = -exp(mu) (1/s, descending). Rows with fewer than ``min_events`` events in the latest
window return NaN.

The stage contract (:mod:`dvsland.pytree`): params are :class:`~dvsland.config.schema.LearnedConfig`
(``LearnedEstimator.params``) with the constants :class:`LearnedConsts` (the network and its input
mapping: weights are constants in flight); the state is :class:`LearnedState` (the ring, its event
counts, the last estimate and its predicted spread, the clock); the step is the pure
:func:`learned_step`. Each step builds a new ring (the input state is never written); ``donate=True``
(opt-in) writes the new window into the input state's ring instead, which then must not be used again.

``confidence()``: 1 / (1 + (sigma_rel / 0.1)^2) with sigma_rel = exp(log_var / 2), the predicted
standard deviation of log|D| (about the relative error of D_hat); 0 where the estimate is NaN.
"""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path
from typing import Any, Dict, NamedTuple, Optional, Tuple

import torch

from dvsland.checks import check_range
from dvsland.config.schema import LearnedConfig
from dvsland.pytree import check_state_like, tree_where

from ..base import DivergenceEstimator, EstimateOut, Truth, confidence_from_rel_std
from ..registry import register_estimator
from .checkpoint import load_checkpoint
from .models import SpikingVoxelNet, VoxelCNN
from .fast import RingCNN
from .flips import check_flips, run_copies
from .rows import rows_path, run_rows
from .inputs import InputSpec, camera_map, coord_channels, events_voxel_grid, pixel_cells, row_counts

#: the shipped checkpoints by name (trained by `dvsland train`, commands in docs/learning.md): the CNN,
#: the CNN fine-tuned on events of the realistic pixel as well ("Through a realistic pixel"), the CNN
#: fine-tuned on the landing loss through the closed loop (`dvsland train-loop --what estimator`,
#: docs/train_loop.md), the CNN fine-tuned on the recipe's datasets flown through both pixels, the
#: spiking model, the spiking model on eight windows, that one refined onto 2-pixel cells, that one
#: fine-tuned on four more seeds of both laws, the eight-window model fine-tuned through both pixels,
#: and that one trained on its own closed-loop flights through the realistic pixel (DAgger;
#: docs/learning.md)
SHIPPED = {"cnn": Path(__file__).with_name("learned_cnn.pt"),
           "cnn_realistic": Path(__file__).with_name("learned_cnn_realistic.pt"),
           "cnn_landing": Path(__file__).with_name("learned_cnn_landing.pt"),
           "cnn_wide": Path(__file__).with_name("learned_cnn_wide.pt"),
           "cnn_dagger": Path(__file__).with_name("learned_cnn_dagger.pt"),
           "cnn_both": Path(__file__).with_name("learned_cnn_both.pt"),
           "spiking": Path(__file__).with_name("learned_spiking.pt"),
           "spiking8": Path(__file__).with_name("learned_spiking8.pt"),
           "spiking8_px2": Path(__file__).with_name("learned_spiking8_px2.pt"),
           "spiking8_px2_more": Path(__file__).with_name("learned_spiking8_px2_more.pt"),
           "spiking8_both": Path(__file__).with_name("learned_spiking8_both.pt"),
           "spiking8_dagger": Path(__file__).with_name("learned_spiking8_dagger.pt")}


class LearnedState(NamedTuple):
    """State of the ``learned`` estimator for B rows (K = n_windows, nb = n_bins, (h, w) the grid).

    Attributes:
        d: (B,) float32 last D_hat, 1/s (NaN = none).
        sigma_rel: (B,) float32 predicted relative std. dev. of the last estimate (NaN = none).
        n_events: (B,) int64 events of the last window.
        ring: (B, nb, h, w) float32 the voxel grids of the last K steps in a circular buffer
            (slot q = bins q bpw .. (q + 1) bpw - 1; slot ``newest`` the latest, newest + 1 mod K
            the oldest: :func:`ordered_ring` gives them oldest first).
        ring_counts: (B, K) int64 the slots' events on the reference canvas.
        ring_abs: (B, K) float32 the slots' sums of |value|.
        newest: (B,) int64 the slot of the latest window; the same in every row (every row steps
            at once; a restart empties a row's ring but keeps the position).
        t_prev_us: (B,) int64 time of the last step, µs (-1 = none yet): the next window starts
            there (else ``dt_s`` before the step).
    """

    d: torch.Tensor
    sigma_rel: torch.Tensor
    n_events: torch.Tensor
    ring: torch.Tensor
    ring_counts: torch.Tensor
    ring_abs: torch.Tensor
    newest: torch.Tensor
    t_prev_us: torch.Tensor


class LearnedConsts(NamedTuple):
    """What a ``learned`` step needs besides :class:`LearnedConfig` (made once, never written).

    Attributes:
        batch_size: B. dt_s: the nominal step, s (the first window's length).
        spec: the checkpoint's :class:`InputSpec`. cmap, cells: the camera's mapping onto the
            reference canvas (:func:`~.inputs.camera_map`, :func:`~.inputs.pixel_cells`; None for
            the identity). coords: (1, 2, h, w) float32 coordinate channels.
        model: the network (eval mode). ring_net: the CNN on its circular ring
            (:class:`~.fast.RingCNN`), or None (the model then gets the ordered ring).
        grad: keep the network's autograd graph (``dvsland train-loop --what estimator``: D_hat
            then carries the gradient to the weights) when the caller has grad enabled; the
            voxel grid and the ring are still built without one. The ring net copies the first
            layer's weights, so training sets ``ring_net`` None. False (default): no graph.
        rows_exact: for a built-in model without a ring net (the spiking one): the verdicts of
            :func:`~.rows.run_rows` (the network runs on a CPU batch's rows with an estimate only);
            None: every row runs (plug-in models, which may not be row by row).
    """

    batch_size: int
    dt_s: float
    spec: InputSpec
    cmap: Any
    cells: Any
    coords: torch.Tensor
    model: torch.nn.Module
    ring_net: Optional[torch.nn.Module]
    grad: bool = False
    rows_exact: Optional[Dict[Tuple[int, int], bool]] = None


def initial_state(batch_size: int, spec: InputSpec, device) -> LearnedState:
    """Every row without an estimate, an empty ring and no step yet."""
    nan = torch.full((batch_size,), float("nan"), dtype=torch.float32, device=device)
    i64 = dict(dtype=torch.int64, device=device)
    return LearnedState(nan, nan.clone(), torch.zeros(batch_size, **i64),
                        torch.zeros(batch_size, spec.n_bins, *spec.grid_hw, device=device),
                        torch.zeros(batch_size, spec.n_windows, **i64),
                        torch.zeros(batch_size, spec.n_windows, dtype=torch.float32, device=device),
                        torch.full((batch_size,), spec.n_windows - 1, **i64), torch.full((batch_size,), -1, **i64))


def reset_rows(state: LearnedState, mask: torch.Tensor) -> LearnedState:
    """``state`` with the rows where ``mask`` (B,) bool is True back to no estimate, ring empty;
    the ring position ``newest`` and the clock ``t_prev_us`` are kept (shared by every row)."""
    B, dev = state.d.shape[0], state.d.device
    fresh = LearnedState(*(torch.zeros((), dtype=t.dtype, device=dev).expand_as(t) for t in state))
    nan = torch.full((B,), float("nan"), dtype=torch.float32, device=dev)
    fresh = fresh._replace(d=nan, sigma_rel=nan, newest=state.newest, t_prev_us=state.t_prev_us)
    return tree_where(mask, fresh, state)


def ordered_ring(state: LearnedState, spec: InputSpec) -> torch.Tensor:
    """(B, n_bins, h, w) float32: the ring's windows oldest first (the model's input order)."""
    B, nb, h, w = state.ring.shape
    K = spec.n_windows
    if K == 1:
        return state.ring
    newest = torch.as_tensor(state.newest, device=state.ring.device).reshape(-1).expand(B)
    idx = (newest.unsqueeze(1) + 1 + torch.arange(K, device=newest.device)) % K  # (B, K) oldest first
    rows = torch.arange(B, device=newest.device).unsqueeze(1)
    return state.ring.view(B, K, nb // K, h, w)[rows, idx].reshape(B, nb, h, w)


def _write_window(state: LearnedState, grid: torch.Tensor, on_canvas: torch.Tensor, K: int, donate: bool):
    """(ring, ring_counts, ring_abs, newest) with the window ``grid`` (B, bpw, h, w) in the oldest
    slot: a new ring (``donate``: written into ``state.ring`` in place, no copy)."""
    B, nb, h, w = state.ring.shape
    q = (state.newest + 1) % K  # (B,) the oldest slot takes the new window
    slot = torch.arange(K, device=q.device) == q.unsqueeze(1)  # (B, K)
    ring = state.ring if donate else state.ring.clone()  # a clone and a slot write: the fastest new ring
    ring.view(B, K, nb // K, h, w)[torch.arange(B, device=q.device), q] = grid
    counts = torch.where(slot, on_canvas.unsqueeze(1), state.ring_counts)
    sums = torch.where(slot, grid.abs().sum(dim=(1, 2, 3)).unsqueeze(1), state.ring_abs)
    return ring, counts, sums, q


def learned_step(p: LearnedConfig, c: LearnedConsts, state: LearnedState, events, t_us: int,
                 donate: bool = False):
    """Pure step of ``learned``: (next :class:`LearnedState`, :class:`EstimateOut`).

    Runs without autograd (not inference_mode: D_hat and the state are ordinary tensors the loop
    may edit), unless ``c.grad`` and the caller's grad mode are both on: then the network's forward
    keeps its graph (D_hat and the confidence carry the gradient to the weights) and only the
    inputs (voxel grid, ring) are built without one.

    Args:
        p, c: the params and constants. state: :class:`LearnedState` of B rows.
        events: :class:`dvsland.events.Events` of the interval (sorted by (b, t), b in [0, B)).
        t_us: end of the window, int µs; it starts at the last step (``dt_s`` before at first).
        donate: write the new window into ``state.ring`` (no copy of the ring; ``state`` must not
            be used again). Off by default: ``state`` is left unchanged.
    """
    if c.grad and torch.is_grad_enabled():
        return _learned_step(p, c, state, events, t_us, donate, True)
    with torch.no_grad():
        return _learned_step(p, c, state, events, t_us, donate, False)


def _learned_step(p: LearnedConfig, c: LearnedConsts, state: LearnedState, events, t_us: int, donate: bool,
                  train: bool):
    """:func:`learned_step`; ``train``: grad is on, the inputs are built under no_grad."""
    t_us = int(t_us)
    B, spec = c.batch_size, c.spec
    with torch.no_grad() if train else nullcontext():  # the events are inputs: no graph to the ring
        last = state.t_prev_us
        t0 = torch.where((last >= 0) & (last < t_us), last, torch.full_like(last, t_us - int(round(c.dt_s * 1e6))))
        grid, on_canvas = events_voxel_grid(events, t0, t_us, B, spec, c.cmap, c.cells)
        n = row_counts(events.b, B) if not c.cmap.identity else on_canvas
        ring, counts, sums, q = _write_window(state, grid, on_canvas, spec.n_windows, donate)
        total = counts.sum(1).to(torch.float32)
        if not c.cmap.identity:
            total = total * c.cmap.count_scale
    st = state._replace(ring=ring, ring_counts=counts, ring_abs=sums, newest=q)
    activity: Dict[str, torch.Tensor] = {}
    ok = n >= p.min_events
    rows_only = rows_path(ring) and not train  # the network on the rows with an estimate only
    ring_net = c.ring_net if p.flips == 1 else None  # mirrored copies: the model as trained
    if ring_net is not None and rows_only:
        mu, log_var = ring_net.forward_rows(ring, sums, q, torch.log1p(total), ok)
    elif ring_net is not None:
        mu, log_var = ring_net(ring, sums, q, torch.log1p(total))
    else:
        mu, log_var, activity = _model_forward(c, ordered_ring(st, spec), torch.log1p(total),
                                               ok if rows_only else None, p.flips)
    nan = torch.full((), float("nan"), device=ring.device)
    d = torch.where(ok, -torch.exp(mu), nan).to(torch.float32)
    sig = torch.where(ok, torch.exp(0.5 * log_var), nan).to(torch.float32)
    st = st._replace(d=d, sigma_rel=sig, n_events=n.to(torch.int64), t_prev_us=torch.full_like(last, t_us))
    conf = confidence_from_rel_std(sig, d)
    return st, EstimateOut(d, conf, {"sigma_rel": sig, "n_events": st.n_events, "confidence": conf, **activity})


def _model_forward(c: LearnedConsts, vox: torch.Tensor, log_count: torch.Tensor, need: Optional[torch.Tensor],
                   flips: int = 1):
    """(mu, log_var, activity) of the model without a ring net: on the rows of ``need`` (B,) bool
    only where given and ``c.rows_exact`` is set (:func:`~.rows.run_rows`; a row not run has 0
    spikes and synaptic operations), else on every row; each row as the pool of its ``flips``
    mirrored copies (:mod:`.flips`)."""
    keys: list = []

    def net(v, lc):
        mu, log_var = c.model(v, c.coords, lc)
        act = getattr(c.model, "last_activity", {})
        keys[:] = list(act)
        return (mu, log_var, *(act[k] for k in keys))

    def call(v, lc):
        return run_copies(net, v, flips, lc)

    if need is None or c.rows_exact is None:
        out = call(vox, log_count)
    else:  # (with no row needed, the padding rows run: the activity keeps its keys)
        out = run_rows(call, (vox, log_count), need, c.rows_exact)  # copies run in turn: the same batch shapes
    return out[0], out[1], {k: v.clone() for k, v in zip(keys, out[2:])}


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
    """``""`` or ``"cnn"`` -> the shipped CNN, another name of :data:`SHIPPED` (``"cnn_realistic"``,
    ``"cnn_landing"``, ``"cnn_wide"``, ``"cnn_dagger"``, ``"cnn_both"``, ``"spiking"``, ``"spiking8"``,
    ``"spiking8_px2"``, ``"spiking8_px2_more"``, ``"spiking8_both"``, ``"spiking8_dagger"``) -> that
    checkpoint, else a path."""
    key = str(checkpoint or "cnn")
    return SHIPPED.get(key, Path(key))


@register_estimator("learned")
class LearnedEstimator(DivergenceEstimator):
    """A recipe checkpoint as an estimator (see module doc).

    Args:
        checkpoint: path of a ``dvsland train --model`` checkpoint; ``""``/``"cnn"`` = the shipped
            CNN, ``"cnn_realistic"`` = the CNN fine-tuned through the realistic pixel,
            ``"cnn_landing"`` = the CNN fine-tuned on the landing loss through the closed loop,
            ``"cnn_wide"``, ``"cnn_dagger"``, ``"cnn_both"`` = the CNN fine-tuned on zoomed textures,
            on its own closed-loop flights, on its datasets through both pixels (docs/learning.md),
            ``"spiking"`` = the shipped spiking model, ``"spiking8"`` = the spiking model on eight
            control steps (0.8 s) of events, ``"spiking8_px2"`` = ``spiking8`` refined onto 2-pixel
            cells, ``"spiking8_px2_more"`` = that one fine-tuned on four more seeds of both laws
            (the ideal pixel's best spiking model), ``"spiking8_both"`` = ``spiking8``
            fine-tuned on its datasets flown through both pixels, ``"spiking8_dagger"`` = that one
            trained on its own closed-loop flights through the realistic pixel (DAgger).
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
        donate: the object API's steps write each new window into the held ring in place (no
            copy of the ring per step: the object owns the state it holds, so this is the default;
            a state read from ``state`` before an update shares the ring and changes with it:
            ``tree_clone`` it to keep it). ``False``: a new ring per update. :meth:`step_state`
            never donates unless its caller asks.
        flips: 1 (default), 2, 4 or 8 mirrored copies of each window, their estimates averaged
            (test-time mirroring, :mod:`.flips`): each copy costs one more forward; with more
            than 1 the CNN runs as trained (``fast`` does not apply).

    Params: ``params`` (:class:`LearnedConfig`) and ``consts`` (:class:`LearnedConsts`); state:
    :class:`LearnedState`.
    """

    accepts_donate = True  # step_state(..., donate=True): the new window written into the ring

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, checkpoint: str = "",
                 min_events: int = 20, principal_point_px=None, focal_px: Optional[float] = None,
                 fast: str = "ring", donate: bool = True, flips: int = 1):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        check_range("estimator.learned.min_events", min_events, 1, 1e9)
        self.checkpoint = resolve_checkpoint(checkpoint)
        net, self.spec, ck = load_checkpoint(self.checkpoint)
        flips = check_flips(flips, self.spec.sensor_size, self.spec.pool_px)
        self.params = LearnedConfig(checkpoint=str(checkpoint), min_events=int(min_events), flips=flips)
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
        if fast and type(self.model) is VoxelCNN and flips == 1:
            self.ring_net = RingCNN(self.model, self.coords, self.spec.n_windows,
                                    dtype=torch.bfloat16 if fast == "bf16" else torch.float32,
                                    channels_last=torch.device(self.device).type == "cuda")
        self.donate = bool(donate)
        self.consts = LearnedConsts(self.batch_size, self.dt_s, self.spec, self.cmap, self.cells, self.coords,
                                    self.model, self.ring_net,
                                    rows_exact={} if type(self.model) is SpikingVoxelNet else None)
        self._template = self.init_state()
        self.state = self.init_state()

    @property
    def min_events(self) -> int:
        return self.params.min_events

    # ------------------------------------------------------------------ the stage contract
    def init_state(self) -> LearnedState:
        """B rows without an estimate, ring empty (:class:`LearnedState`)."""
        return initial_state(self.batch_size, self.spec, self.device)

    def reset_where(self, state: LearnedState, mask: torch.Tensor) -> LearnedState:
        """``state`` with the rows where ``mask`` (B,) bool is True restarted (:func:`reset_rows`)."""
        return reset_rows(state, self._mask(mask))

    def step_state(self, state: LearnedState, events, t_us: int, truth: Optional[Truth] = None,
                   donate: bool = False):
        """Pure step (:func:`learned_step`): (next :class:`LearnedState`, :class:`EstimateOut`)."""
        check_state_like("learned", state, self._template)
        return learned_step(self.params, self.consts, state, events, t_us, donate=donate)

    # ------------------------------------------------------------------ object API
    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        """The base class's update (one step of the held state; events checked once, by the
        gate of ``update``), the ring written in place with ``donate``."""
        check_state_like("learned", self.state, self._template)
        self.state, self._last = learned_step(self.params, self.consts, self.state, events, t_us, donate=self.donate)
        return self._last.d_hat.clone()

    @property
    def _d(self) -> torch.Tensor:
        return self.state.d

    def diagnostics(self):
        """sigma_rel (B,) predicted relative std. dev.; n_events (B,); confidence (B,); for a
        spiking model also spikes and synops (B,) of the last update."""
        out = {"sigma_rel": self.state.sigma_rel.clone(), "n_events": self.state.n_events.clone(),
               "confidence": self.confidence()}
        last = getattr(self, "_last", None)
        for k, v in (last.diagnostics.items() if last is not None else ()):
            if k not in out:
                out[k] = v.clone()
        return out
