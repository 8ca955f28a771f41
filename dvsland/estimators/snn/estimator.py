"""``snn``: the trained spiking divergence estimator behind the common interface.

Each control step, the events since the previous update are encoded in ``n_sub`` log-polar slices
(:class:`~.encoding.LogPolarEncoder`) and fed through :class:`~.model.SpikingDivergenceNet`, whose
membranes carry over between steps. The first ``warmup_steps`` updates after a reset return NaN
(the read-out is still charging), and so does every update after ``max_silent_steps``
consecutive updates without an event in the log-polar annulus (a featureless or dark scene: the
membranes then only decay, and the read-out would drift to a D the events never said).

``confidence()``: 0 where the estimate is NaN, else n / (n + ``confidence_events``) with n the
mean number of annulus events per update over the last second (an exponential average): the
network gives no uncertainty of its own, so the evidence it saw stands in for it.

``diagnostics()`` reports the network's activity per control step and batch element: ``spikes``
(spikes of both LIF layers over the step's slices) and ``synops`` (synaptic operations: every
input bin with events and every spike times its fan-out, c_out * kernel / stride, the read-out
counting one per layer-2 spike).

The stage contract (:mod:`dvsland.pytree`): params are :class:`~dvsland.config.schema.SNNConfig`
(``SpikingEstimator.params``) with the constants :class:`SNNConsts` (the network, the encoder);
the state is :class:`SpikingState` (the LIF states of the network, :class:`~.model.SNNState`, and
the counters); the step is the pure :func:`snn_step`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, NamedTuple, Optional

import torch

from dvsland.checks import check_fields
from dvsland.config.schema import SNNConfig
from dvsland.pytree import check_state_like, tree_where

from ..base import DivergenceEstimator, EstimateOut, Truth
from ..registry import register_estimator
from ..state_dict_check import check_finite_numbers, read_checkpoint_file, short_path
from ..state_dict_check import check_state_dict as check_weights
from .encoding import LogPolarEncoder
from .model import SNNState, SpikingDivergenceNet

#: the checkpoint shipped with dvsland (trained by scripts/train_snn.py)
DEFAULT_CHECKPOINT = Path(__file__).with_name("snn_default.pt")


def save_checkpoint(path, model: SpikingDivergenceNet, encoder: LogPolarEncoder, meta: dict) -> None:
    """Weights plus what is needed to rebuild encoder and model, plus ``meta`` (training record)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"format": 1, "state_dict": model.state_dict(),
                "encoder": {"n_rho": encoder.n_rho, "n_phi": encoder.n_phi, "r_min_px": encoder.r_min_px,
                            "r_max_px": encoder.r_max_px, "n_sub": encoder.n_sub},
                "model": {"channels": list(model.channels), "d_scale": model.d_scale, "learn_tau": model.learn_tau,
                          "slice_dt_s": model.dt_s},
                "meta": meta}, path)


def _hint(param: str) -> str:
    """What the snn messages add: how to get a good checkpoint."""
    shipped = ", or leave estimator.snn.checkpoint empty for the shipped one" \
        if param == "estimator.snn.checkpoint" else ""
    return f"train one with `dvsland train`{shipped}"


def check_state_dict(path, state: dict, model: torch.nn.Module, param: str = "estimator.snn.checkpoint") -> None:
    """Every tensor of a checkpoint's ``state`` against ``model`` (names, shapes, floating dtypes,
    finite values): :func:`dvsland.estimators.state_dict_check.check_state_dict`, the messages
    naming ``param`` and the file."""
    check_weights(state, model, f"{param}: {short_path(path)}")


def read_snn_checkpoint(path, param: str = "estimator.snn.checkpoint") -> dict:
    """The dict of an snn checkpoint file, its description checked: the fields ``state_dict``,
    ``encoder`` (``n_rho``, ``n_phi``, ``r_min_px``, ``r_max_px``, ``n_sub``) and ``model``
    (``channels``, ``d_scale``: a finite number > 0, 1/s per read-out unit), every number finite.

    Raises:
        ValueError: ``"<param>: <path> ..."`` (:mod:`~dvsland.estimators.state_dict_check`).
    """
    ck = read_checkpoint_file(path, param, "dvsland snn checkpoint", _hint(param))
    where = f"{param}: {short_path(path)}"
    missing = [k for k in ("state_dict", "encoder", "model") if k not in ck]
    if missing:
        raise ValueError(f"{param}: {short_path(path)} is not a readable dvsland snn checkpoint (it has no "
                         f"{missing}); {_hint(param)}")
    e, m = ck["encoder"], ck["model"]
    try:
        _ = (e["n_rho"], e["n_phi"], e["r_min_px"], e["r_max_px"], e["n_sub"], m["channels"], m["d_scale"])
    except (KeyError, TypeError, AttributeError):
        raise ValueError(f"{where} is not a readable dvsland snn checkpoint (its encoder or model description is "
                         f"incomplete); {_hint(param)}") from None
    check_finite_numbers(e, where, "encoder")
    check_finite_numbers(m, where, "model")
    d_scale = m["d_scale"]
    if isinstance(d_scale, bool) or not isinstance(d_scale, (int, float)) or not d_scale > 0:
        raise ValueError(f"{where}: model.d_scale is {d_scale!r}; expected a finite number > 0 (the read-out's "
                         f"scale to D, 1/s; a damaged checkpoint)")
    return ck


def load_checkpoint(path=None, sensor_size=(128, 128), dt_s: float = 0.1, device="cpu", principal_point_px=None,
                    param: str = "estimator.snn.checkpoint"):
    """(model, encoder, meta) from ``path`` (default: the shipped checkpoint). Raises ValueError
    starting with ``param`` and the path for a missing, corrupt or foreign file, a path the OS
    refuses, a description with a non-finite number or d_scale <= 0 (:func:`read_snn_checkpoint`),
    and tensors of the wrong name, shape or dtype or with NaN / inf values (:func:`check_state_dict`,
    naming the tensor)."""
    path = Path(path) if path else DEFAULT_CHECKPOINT
    ck = read_snn_checkpoint(path, param)
    e, m = ck["encoder"], ck["model"]
    try:
        trained_dt = m.get("slice_dt_s", 0.1 / e["n_sub"]) * e["n_sub"]
        learn_tau = m.get("learn_tau", False)
    except Exception:
        trained_dt, learn_tau = None, None
    if learn_tau and trained_dt is not None and abs(trained_dt - dt_s) > 1e-9:
        raise ValueError(f"{param}: {short_path(path)} was trained at a control interval of {trained_dt:g} s (its "
                         f"learned time constants are per slice); got dt_s = {dt_s:g} s (camera.frame_rate_hz)")
    try:  # a damaged description (a flipped byte in a number) must fail here, clearly, whatever breaks
        enc = LogPolarEncoder(sensor_size, e["n_rho"], e["n_phi"], e["r_min_px"], e["r_max_px"], e["n_sub"], device,
                              principal_point_px=principal_point_px)
        model = SpikingDivergenceNet(e["n_rho"], e["n_phi"], dt_s=dt_s / e["n_sub"], channels=m["channels"],
                                     d_scale=m["d_scale"], learn_tau=learn_tau)
    except Exception as exc:
        first = (str(exc).splitlines() or [""])[0][:200]
        raise ValueError(f"{param}: {short_path(path)}: its encoder or model description does not make a "
                         f"network ({type(exc).__name__}: {first})") from None
    check_state_dict(path, ck["state_dict"], model, param)
    try:
        model.load_state_dict(ck["state_dict"])
    except Exception as exc:
        first = (str(exc).splitlines() or [""])[0][:200]
        raise ValueError(f"{param}: {short_path(path)}: its weights or description do not fit the network "
                         f"it describes ({type(exc).__name__}: {first})") from None
    return model.to(device).eval(), enc, ck.get("meta", {})


class SpikingState(NamedTuple):
    """State of the ``snn`` estimator for B descents.

    Attributes:
        net: the network's :class:`~.model.SNNState` (LIF membranes ``v`` and currents ``i`` of
            both layers, (B, c, n_rho, n_phi) and (B, c2, n_rho2, n_phi) float32, and of the
            read-out, (B, 1) float32).
        steps: (B,) int64 updates since the descent's (re)start.
        silent: (B,) int64 consecutive updates without an event in the annulus.
        ev_avg: (B,) float32 annulus events per update, exponential average over 1 s.
        t_prev_us: (B,) int64 time of the last update, µs (-1 = none yet): the next step's events
            are split in slices from there (else from ``dt_s`` before the step).
    """

    net: SNNState
    steps: torch.Tensor
    silent: torch.Tensor
    ev_avg: torch.Tensor
    t_prev_us: torch.Tensor


class SNNConsts(NamedTuple):
    """What an ``snn`` step needs besides :class:`SNNConfig` (made once, never written).

    Attributes:
        batch_size: B. dt_s: the control interval, s. model: the network (eval mode; weights are
        constants). encoder: the :class:`~.encoding.LogPolarEncoder`. avg: the 1 s average's
        weight per update, 1 - exp(-dt_s / 1 s). fan_in, fan1: synaptic fan-out of an input bin
        and of a layer-1 spike. n1, n2: neurons x slices of the two layers.
    """

    batch_size: int
    dt_s: float
    model: SpikingDivergenceNet
    encoder: LogPolarEncoder
    avg: float
    fan_in: float
    fan1: float
    n1: float
    n2: float


def snn_consts(model: SpikingDivergenceNet, encoder: LogPolarEncoder, batch_size: int, dt_s: float) -> SNNConsts:
    """The :class:`SNNConsts` of a network and its encoder."""
    c1, c2 = model.channels
    n_sub = encoder.n_sub
    kh, kw = model.conv1.kernel_size
    kh2, kw2 = model.conv2.kernel_size
    return SNNConsts(int(batch_size), float(dt_s), model, encoder, 1.0 - math.exp(-float(dt_s) / 1.0),
                     float(c1 * kh * kw), float(c2 * kh2 * kw2) / float(model.conv2.stride[0] * model.conv2.stride[1]),
                     float(c1 * model.n_rho * model.n_phi) * n_sub, float(c2 * model.n_rho2 * model.n_phi) * n_sub)


def snn_init_state(c: SNNConsts, device) -> SpikingState:
    """B descents at rest, no update yet."""
    B = c.batch_size
    i64 = dict(dtype=torch.int64, device=device)
    return SpikingState(c.model.initial_state(B, device), torch.zeros(B, **i64), torch.zeros(B, **i64),
                        torch.zeros(B, dtype=torch.float32, device=device), torch.full((B,), -1, **i64))


def snn_reset_where(c: SNNConsts, state: SpikingState, mask: torch.Tensor) -> SpikingState:
    """``state`` with the descents where ``mask`` (B,) bool is True restarted (membranes zeroed as
    :meth:`~.model.SpikingDivergenceNet.reset` does); the clock ``t_prev_us`` is kept."""
    fresh = snn_init_state(c, state.steps.device)._replace(net=c.model.reset(state.net, mask),
                                                            t_prev_us=state.t_prev_us)
    return tree_where(mask, fresh, state)


@torch.no_grad()
def snn_step(p: SNNConfig, c: SNNConsts, state: SpikingState, events, t_us: int):
    """Pure step of ``snn``: (next :class:`SpikingState`, :class:`EstimateOut`); ``state`` unchanged.

    Args:
        p, c: the params and constants. state: :class:`SpikingState` of B descents.
        events: :class:`dvsland.events.Events` of the interval (or None / empty).
        t_us: end of the interval, int µs; its slices start at the last update (``dt_s`` before
            at first).
    """
    t_us = int(t_us)
    last = state.t_prev_us
    t0 = torch.where((last >= 0) & (last < t_us), last, torch.full_like(last, t_us - int(round(c.dt_s * 1e6))))
    x, n_ev, dropped = c.encoder.encode_counts(events, t0, t_us, c.batch_size)
    d, net, rates = c.model.run_step(x, state.net)
    steps = state.steps + 1
    silent = torch.where(n_ev > 0, torch.zeros_like(state.silent), state.silent + 1)
    ev_avg = state.ev_avg + c.avg * (n_ev.to(torch.float32) - state.ev_avg)
    # activity: spikes of the step (rates are means over neurons and slices) and synaptic ops
    s1, s2 = rates["rate1"] * c.n1, rates["rate2"] * c.n2
    nnz = (x > 0).flatten(1).sum(1).to(torch.float32)
    ok = steps > p.warmup_steps
    if p.max_silent_steps > 0:
        ok &= silent < p.max_silent_steps
    d = torch.where(ok, d, torch.full_like(d, float("nan"))).to(torch.float32)
    conf = ev_avg / (ev_avg + p.confidence_events)
    conf = torch.where(torch.isfinite(d), conf, torch.zeros_like(conf))
    new = SpikingState(net, steps, silent, ev_avg, torch.full_like(last, t_us))
    diag = {"steps_since_reset": steps, "silent_steps": silent, **{f"spike_{k}": v for k, v in rates.items()},
            "spikes": s1 + s2, "synops": nnz * c.fan_in + s1 * c.fan1 + s2, "events_in_annulus": n_ev,
            "dropped_events": dropped, "confidence": conf}
    return new, EstimateOut(d, conf, diag)


@register_estimator("snn")
class SpikingEstimator(DivergenceEstimator):
    """Trained spiking estimator (see module doc).

    Args:
        checkpoint: path of a checkpoint from scripts/train_snn.py ("" = the shipped one).
        warmup_steps: updates after a reset that return NaN.
        max_silent_steps: after this many consecutive updates without an annulus event, NaN
            until events come back (0 = never).
        confidence_events: annulus events per update at which confidence() is 0.5.
        principal_point_px: focus of expansion (centre of the log-polar annulus).

    Params: ``params`` (:class:`SNNConfig`) and ``consts`` (:class:`SNNConsts`); state:
    :class:`SpikingState`.
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, checkpoint: str = "",
                 warmup_steps: int = 5, seed: int = 0, max_silent_steps: int = 10, confidence_events: float = 100.0,
                 principal_point_px=None):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        # the schema's ranges (estimator.snn)
        check_fields(SNNConfig, warmup_steps=warmup_steps, max_silent_steps=max_silent_steps,
                     confidence_events=confidence_events)
        self.params = SNNConfig(checkpoint=str(checkpoint or ""), warmup_steps=int(warmup_steps),
                                max_silent_steps=int(max_silent_steps), confidence_events=float(confidence_events))
        self.model, self.encoder, self.meta = load_checkpoint(checkpoint or None, self.sensor_size, self.dt_s,
                                                              self.device, self.principal_point_px)
        self.consts = snn_consts(self.model, self.encoder, self.batch_size, self.dt_s)
        self._template = self.init_state()
        self.state = self.init_state()

    @property
    def warmup_steps(self) -> int:
        return self.params.warmup_steps

    @property
    def max_silent_steps(self) -> int:
        return self.params.max_silent_steps

    @property
    def confidence_events(self) -> float:
        return self.params.confidence_events

    # ------------------------------------------------------------------ the stage contract
    def init_state(self) -> SpikingState:
        """B descents at rest (:class:`SpikingState`)."""
        return snn_init_state(self.consts, self.device)

    def reset_where(self, state: SpikingState, mask: torch.Tensor) -> SpikingState:
        """``state`` with the descents where ``mask`` (B,) bool is True restarted."""
        return snn_reset_where(self.consts, state, self._mask(mask))

    def step_state(self, state: SpikingState, events, t_us: int, truth: Optional[Truth] = None):
        """Pure step (:func:`snn_step`): (next :class:`SpikingState`, :class:`EstimateOut`)."""
        check_state_like("snn", state, self._template)
        return snn_step(self.params, self.consts, state, events, t_us)

    # ------------------------------------------------------------------ object API
    def diagnostics(self) -> Dict[str, torch.Tensor]:
        """steps_since_reset, silent_steps (B,) int64; spike_rate1 / spike_rate2 (B,) mean spike
        rates; spikes (B,) spikes per step; synops (B,) synaptic operations per step;
        events_in_annulus (B,); dropped_events (events off the sensor ignored this step);
        confidence (B,). The counters are the held state's (also right after a reset), the
        activity the last update's."""
        out = {"steps_since_reset": self.state.steps.clone(), "silent_steps": self.state.silent.clone()}
        last = getattr(self, "_last", None)
        if last is None:
            B, dev = self.batch_size, self.device
            zeros = torch.zeros(B, dtype=torch.float32, device=dev)
            out.update({"spikes": zeros, "synops": zeros.clone(),
                        "events_in_annulus": torch.zeros(B, dtype=torch.int64, device=dev),
                        "dropped_events": torch.tensor(0)})
        else:
            out.update({k: v.clone() for k, v in last.diagnostics.items() if k not in out})
        out["confidence"] = self.confidence()
        return out
