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
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import torch

from dvsland.checks import check_fields
from dvsland.config.schema import SNNConfig

from ..base import DivergenceEstimator, Truth
from ..registry import register_estimator
from ..state_dict_check import check_state_dict as check_weights
from .encoding import LogPolarEncoder
from .model import SpikingDivergenceNet

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


def _short(path) -> str:
    text = str(path)
    return text if len(text) <= 120 else f"{text[:60]}...{text[-40:]} ({len(text)} characters)"


def _check_path(path: Path) -> None:
    """ValueError naming estimator.snn.checkpoint for a path the OS refuses (too long) or a missing file."""
    try:
        found = path.is_file()
    except (OSError, ValueError) as exc:  # ENAMETOOLONG, a NUL byte, ...
        raise ValueError(f"estimator.snn.checkpoint: {_short(path)}: {getattr(exc, 'strerror', None) or exc}; expected "
                         f"the path of a checkpoint file (at most 4096 characters, each folder or file name at "
                         f"most 255 bytes)") from None
    if not found:
        raise ValueError(f"estimator.snn.checkpoint: file not found: {_short(path)} (train one with "
                         f"scripts/train_snn.py)")


def check_state_dict(path, state: dict, model: torch.nn.Module) -> None:
    """Every tensor of a checkpoint's ``state`` against ``model`` (names, shapes, floating dtypes,
    finite values): :func:`dvsland.estimators.state_dict_check.check_state_dict`, the messages
    naming ``estimator.snn.checkpoint`` and the file."""
    check_weights(state, model, f"estimator.snn.checkpoint: {_short(path)}")


def load_checkpoint(path=None, sensor_size=(128, 128), dt_s: float = 0.1, device="cpu", principal_point_px=None):
    """(model, encoder, meta) from ``path`` (default: the shipped checkpoint). Raises ValueError with
    the path for a missing, corrupt or foreign file, a path the OS refuses, and tensors of the wrong
    name, shape or dtype or with NaN / inf values (:func:`check_state_dict`, naming the tensor)."""
    path = Path(path) if path else DEFAULT_CHECKPOINT
    _check_path(path)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # any failure to read untrusted bytes (the unpickler raises KeyError, IndexError, ...)
        raise ValueError(f"estimator.snn.checkpoint: {path} is not a readable dvsland snn checkpoint (corrupt, "
                         f"truncated or another kind of file). Re-train it with scripts/train_snn.py or leave "
                         f"estimator.snn.checkpoint empty for the shipped one") from None
    missing = [k for k in ("state_dict", "encoder", "model") if not isinstance(ck, dict) or k not in ck]
    if missing:
        raise ValueError(f"estimator.snn.checkpoint: {path} is not a readable dvsland snn checkpoint (it has no "
                         f"{missing}). Re-train it with scripts/train_snn.py or leave estimator.snn.checkpoint "
                         f"empty for the shipped one")
    e = ck["encoder"]
    try:
        _ = (e["n_rho"], e["n_phi"], e["r_min_px"], e["r_max_px"], e["n_sub"], ck["model"]["channels"])
    except (KeyError, TypeError):
        raise ValueError(f"estimator.snn.checkpoint: {path} is not a readable dvsland snn checkpoint (its encoder "
                         f"or model description is incomplete)") from None
    m = ck["model"]
    try:
        trained_dt = m.get("slice_dt_s", 0.1 / e["n_sub"]) * e["n_sub"]
        learn_tau = m.get("learn_tau", False)
    except Exception:
        trained_dt, learn_tau = None, None
    if learn_tau and trained_dt is not None and abs(trained_dt - dt_s) > 1e-9:
        raise ValueError(f"the snn checkpoint was trained at a control interval of {trained_dt:g} s (its learned "
                         f"time constants are per slice); got dt_s = {dt_s:g} s (camera.frame_rate_hz)")
    try:  # a damaged description (a flipped byte in a number) must fail here, clearly, whatever breaks
        enc = LogPolarEncoder(sensor_size, e["n_rho"], e["n_phi"], e["r_min_px"], e["r_max_px"], e["n_sub"], device,
                              principal_point_px=principal_point_px)
        model = SpikingDivergenceNet(e["n_rho"], e["n_phi"], dt_s=dt_s / e["n_sub"], channels=m["channels"],
                                     d_scale=m["d_scale"], learn_tau=learn_tau)
    except Exception as exc:
        first = (str(exc).splitlines() or [""])[0][:200]
        raise ValueError(f"estimator.snn.checkpoint: {path}: its encoder or model description does not make a "
                         f"network ({type(exc).__name__}: {first})") from None
    check_state_dict(path, ck["state_dict"], model)
    try:
        model.load_state_dict(ck["state_dict"])
    except Exception as exc:
        first = (str(exc).splitlines() or [""])[0][:200]
        raise ValueError(f"estimator.snn.checkpoint: {path}: its weights or description do not fit the network "
                         f"it describes ({type(exc).__name__}: {first})") from None
    return model.to(device).eval(), enc, ck.get("meta", {})


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
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, checkpoint: str = "",
                 warmup_steps: int = 5, seed: int = 0, max_silent_steps: int = 10, confidence_events: float = 100.0,
                 principal_point_px=None):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        # the schema's ranges (estimator.snn)
        check_fields(SNNConfig, warmup_steps=warmup_steps, max_silent_steps=max_silent_steps,
                     confidence_events=confidence_events)
        self.warmup_steps = int(warmup_steps)
        self.max_silent_steps = int(max_silent_steps)
        self.confidence_events = float(confidence_events)
        self.model, self.encoder, self.meta = load_checkpoint(checkpoint or None, self.sensor_size, self.dt_s,
                                                              self.device, self.principal_point_px)
        B, dev = self.batch_size, self.device
        self._state = self.model.initial_state(B, dev)
        self._steps = torch.zeros(B, dtype=torch.int64, device=dev)
        self._silent = torch.zeros(B, dtype=torch.int64, device=dev)
        self._ev_avg = torch.zeros(B, dtype=torch.float32, device=dev)
        self._d = torch.full((B,), float("nan"), dtype=torch.float32, device=dev)
        self._t_prev: Optional[int] = None
        self._rates = {}
        self._spikes = torch.zeros(B, dtype=torch.float32, device=dev)
        self._synops = torch.zeros(B, dtype=torch.float32, device=dev)
        c1, c2 = self.model.channels
        n_sub = self.encoder.n_sub
        kh, kw = self.model.conv1.kernel_size
        # fan-out of one input bin / one spike (output channels x kernel taps / stride)
        self._fan_in = float(c1 * kh * kw)
        kh2, kw2 = self.model.conv2.kernel_size
        self._fan1 = float(c2 * kh2 * kw2) / float(self.model.conv2.stride[0] * self.model.conv2.stride[1])
        self._n1 = float(c1 * self.model.n_rho * self.model.n_phi) * n_sub
        self._n2 = float(c2 * self.model.n_rho2 * self.model.n_phi) * n_sub

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        mask = self._mask(mask)
        self._state = self.model.reset(self._state, mask)
        self._steps[mask] = 0
        self._silent[mask] = 0
        self._ev_avg[mask] = 0.0
        self._d[mask] = float("nan")

    @torch.no_grad()
    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        t_us = int(t_us)
        t0 = self._t_prev if self._t_prev is not None and self._t_prev < t_us else t_us - int(round(self.dt_s * 1e6))
        self._t_prev = t_us
        x = self.encoder.encode(events, t0, t_us, self.batch_size)
        d, self._state, self._rates = self.model.run_step(x, self._state)
        self._steps += 1
        n_ev = self.encoder.events_in_annulus
        self._silent = torch.where(n_ev > 0, torch.zeros_like(self._silent), self._silent + 1)
        a = 1.0 - math.exp(-self.dt_s / 1.0)  # 1 s exponential average
        self._ev_avg = self._ev_avg + a * (n_ev.to(torch.float32) - self._ev_avg)
        # activity: spikes of the step (rates are means over neurons and slices) and synaptic ops
        s1 = self._rates["rate1"] * self._n1
        s2 = self._rates["rate2"] * self._n2
        nnz = (x > 0).flatten(1).sum(1).to(torch.float32)
        self._spikes = s1 + s2
        self._synops = nnz * self._fan_in + s1 * self._fan1 + s2
        ok = self._steps > self.warmup_steps
        if self.max_silent_steps > 0:
            ok &= self._silent < self.max_silent_steps
        self._d = torch.where(ok, d, torch.full_like(d, float("nan"))).to(torch.float32)
        return self._d.clone()

    def confidence(self) -> torch.Tensor:
        """(B,) float32: n / (n + confidence_events) of the averaged annulus events, 0 where NaN."""
        c = self._ev_avg / (self._ev_avg + self.confidence_events)
        return torch.where(torch.isfinite(self._d), c, torch.zeros_like(c))

    def diagnostics(self):
        """steps_since_reset, silent_steps (B,) int64; spike_rate1 / spike_rate2 (B,) mean spike
        rates; spikes (B,) spikes per step; synops (B,) synaptic operations per step;
        events_in_annulus (B,); dropped_events (events off the sensor ignored this step);
        confidence (B,)."""
        out = {"steps_since_reset": self._steps.clone(), "silent_steps": self._silent.clone()}
        out.update({f"spike_{k}": v.clone() for k, v in self._rates.items()})
        out.update({"spikes": self._spikes.clone(), "synops": self._synops.clone(),
                    "events_in_annulus": self.encoder.events_in_annulus.clone(),
                    "dropped_events": torch.tensor(self.encoder.dropped), "confidence": self.confidence()})
        return out
