"""``snn``: the trained spiking divergence estimator behind the common interface.

Each control step, the events since the previous update are encoded in ``n_sub`` log-polar slices
(:class:`~.encoding.LogPolarEncoder`) and fed through :class:`~.model.SpikingDivergenceNet`, whose
membranes carry over between steps. The first ``warmup_steps`` updates after a reset return NaN
(the read-out is still charging).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from dvsland.checks import check_fields
from dvsland.config.schema import SNNConfig

from ..base import DivergenceEstimator, Truth
from ..registry import register_estimator
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


def load_checkpoint(path=None, sensor_size=(128, 128), dt_s: float = 0.1, device="cpu"):
    """(model, encoder, meta) from ``path`` (default: the shipped checkpoint)."""
    path = Path(path) if path else DEFAULT_CHECKPOINT
    if not path.is_file():
        raise ValueError(f"estimator.snn.checkpoint: file not found: {path} (train one with scripts/train_snn.py)")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
        e = ck["encoder"]
        _ = (ck["model"], ck["state_dict"], e["n_rho"], e["n_phi"], e["r_min_px"], e["r_max_px"], e["n_sub"])
    except Exception as exc:  # truncated zip, pickle refusal, wrong layout: not torch's unpickling advice
        raise ValueError(f"estimator.snn.checkpoint: {path} is not a readable dvsland snn checkpoint "
                         f"(truncated, corrupt or of another kind: {type(exc).__name__}); use one written by "
                         f"scripts/train_snn.py, or '' for the shipped one") from None
    if min(sensor_size) < 2 * e["r_max_px"]:
        raise ValueError(f"the snn checkpoint needs a sensor of at least {2 * e['r_max_px']:g} px per side, "
                         f"got {tuple(sensor_size)}")
    enc = LogPolarEncoder(sensor_size, e["n_rho"], e["n_phi"], e["r_min_px"], e["r_max_px"], e["n_sub"], device)
    m = ck["model"]
    trained_dt = m.get("slice_dt_s", 0.1 / e["n_sub"]) * e["n_sub"]
    if m.get("learn_tau", False) and abs(trained_dt - dt_s) > 1e-9:
        raise ValueError(f"the snn checkpoint was trained at a control interval of {trained_dt:g} s (its learned "
                         f"time constants are per slice); got dt_s = {dt_s:g} s (camera.frame_rate_hz)")
    model = SpikingDivergenceNet(e["n_rho"], e["n_phi"], dt_s=dt_s / e["n_sub"], channels=m["channels"],
                                 d_scale=m["d_scale"], learn_tau=m.get("learn_tau", False))
    try:
        model.load_state_dict(ck["state_dict"])
    except (RuntimeError, KeyError, TypeError) as exc:
        raise ValueError(f"estimator.snn.checkpoint: {path}: its weights do not fit the model it describes "
                         f"({str(exc).splitlines()[0]})") from None
    return model.to(device).eval(), enc, ck.get("meta", {})


@register_estimator("snn")
class SpikingEstimator(DivergenceEstimator):
    """Trained spiking estimator (see module doc).

    Args:
        checkpoint: path of a checkpoint from scripts/train_snn.py ("" = the shipped one).
        warmup_steps: updates after a reset that return NaN.
    """

    #: after this many consecutive windows without events an element gives NaN (no data, no estimate)
    max_empty_windows: int = 10

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, checkpoint: str = "",
                 warmup_steps: int = 5, seed: int = 0):
        super().__init__(batch_size, sensor_size, device, dt_s)
        check_fields(SNNConfig, warmup_steps=warmup_steps)  # the schema's range (estimator.snn)
        self.warmup_steps = int(warmup_steps)
        self.model, self.encoder, self.meta = load_checkpoint(checkpoint or None, self.sensor_size, self.dt_s,
                                                              self.device)
        self._state = self.model.initial_state(self.batch_size, self.device)
        self._steps = torch.zeros(self.batch_size, dtype=torch.int64, device=self.device)
        self._empty = torch.zeros(self.batch_size, dtype=torch.int64, device=self.device)  # windows without events
        self._t_prev: Optional[int] = None
        self._rates = {}

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        mask = self._mask(mask)
        self._state = self.model.reset(self._state, mask)
        self._steps[mask] = 0
        self._empty[mask] = 0

    @torch.no_grad()
    def update(self, events, t_us: int, truth: Optional[Truth] = None) -> torch.Tensor:
        t_us = int(t_us)
        t0 = self._t_prev if self._t_prev is not None and self._t_prev < t_us else t_us - int(round(self.dt_s * 1e6))
        self._t_prev = t_us
        x = self.encoder.encode(events, t0, t_us, self.batch_size)
        d, self._state, self._rates = self.model.run_step(x, self._state)
        self._steps += 1
        n_ev = (torch.bincount(events.b, minlength=self.batch_size)[: self.batch_size] if events is not None
                and len(events) else torch.zeros_like(self._empty))
        self._empty = torch.where(n_ev > 0, torch.zeros_like(self._empty), self._empty + 1)
        nan = torch.full_like(d, float("nan"))
        ok = (self._steps > self.warmup_steps) & (self._empty < self.max_empty_windows)
        return torch.where(ok, d, nan).to(torch.float32)

    def diagnostics(self):
        out = {"steps_since_reset": self._steps.clone()}
        out.update({f"spike_{k}": v.clone() for k, v in self._rates.items()})
        return out
