"""The model zoo of the ``learned`` estimator: networks from one window's input to (mu, log_var).

Every model takes ``(vox, coords, log_count)``:

- ``vox``: (B, n_bins, h, w) float32 signed voxel grid of one control step (:mod:`.inputs`);
- ``coords``: (1, 2, h, w) float32 cell position about the principal point (:func:`.inputs.coord_channels`);
- ``log_count``: (B,) float32 log(1 + events in the window);

and returns ``(mu, log_var)``, (B,) float32 each: the mean and log-variance of a Gaussian over
log|D| (D in 1/s). The estimate is D_hat = -exp(mu), its relative standard deviation about
exp(log_var / 2).

- :class:`VoxelCNN` (``cnn``): four strided 3x3 convolutions, mean and max pooling, an MLP head.
- :class:`SpikingVoxelNet` (``spiking``): the voxel grid's time bins are the time steps of two
  convolutional LIF layers (:func:`dvsland.estimators.snn.lif.lif_step`, norse-style state); the
  spike counts of layer 2, pooled, feed a linear head. The membranes start from rest at every
  window (no state between control steps).
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from torch import nn

from ..snn.lif import LIFParameters, lif_state, lif_step, lif_step_inference


def _normalise(vox: torch.Tensor) -> torch.Tensor:
    """vox divided by its mean |value| per sample (event-count invariance), (B, n_bins, h, w)."""
    return vox / vox.abs().mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-3)


class VoxelCNN(nn.Module):
    """Conventional CNN: (n_bins + 2) channels -> 4 strided 3x3 convs (width, 2w, 2w, 2w) -> mean
    and max pooling + log_count -> MLP (hidden 32) -> (mu, log_var)."""

    def __init__(self, n_bins: int = 4, width: int = 16):
        super().__init__()
        if not 1 <= int(width) <= 256:
            raise ValueError(f"width must be in [1, 256], got {width}")
        self.n_bins, self.width = int(n_bins), int(width)
        c = self.width
        self.features = nn.Sequential(
            nn.Conv2d(n_bins + 2, c, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(c, 2 * c, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(2 * c, 2 * c, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(2 * c, 2 * c, 3, stride=2, padding=1), nn.ReLU())
        self.head = nn.Sequential(nn.Linear(4 * c + 1, 32), nn.ReLU(), nn.Linear(32, 2))

    def settings(self) -> Dict[str, int]:
        """Constructor keyword arguments that rebuild this network."""
        return {"n_bins": self.n_bins, "width": self.width}

    def forward(self, vox: torch.Tensor, coords: torch.Tensor, log_count: torch.Tensor):
        x = torch.cat([_normalise(vox), coords.expand(vox.shape[0], -1, -1, -1)], dim=1)
        f = self.features(x)
        f = torch.cat([f.mean(dim=(2, 3)), f.amax(dim=(2, 3)), log_count[:, None]], dim=1)
        mu, log_var = self.head(f).unbind(1)
        return mu, log_var.clamp(-12.0, 6.0)


class SpikingVoxelNet(nn.Module):
    """Spiking CNN: per time bin k, current conv1([vox_k, coords]) -> LIF (width) -> conv2 ->
    LIF (2 width) [-> conv3 -> LIF (2 width) when ``depth`` = 3]; the last layer's spike counts over
    the bins, mean-pooled over space and weighted by the radius about the principal point (and
    max-pooled when ``depth`` = 3) -> a linear head (or, with ``hidden`` > 0, one hidden ReLU layer
    of that many units) with log_count -> (mu, log_var).

    ``slice_dt_s``: the LIF step (control interval / n_bins); ``tau_mem_s``, ``tau_syn_s``: time
    constants. ``depth`` 2 and ``hidden`` 0 (the defaults) are the shipped ``spiking`` and
    ``spiking8`` networks. ``delay`` > 0 adds that many earlier bins to each step's input (synaptic
    delays; :meth:`slice_inputs`); ``per_step`` reads the last layer's pooled spikes of every time
    step apart (the head sees when they came) instead of their sum over the window. Activity of
    the last forward pass: :attr:`last_activity` (spikes (B,), synops (B,)).
    """

    def __init__(self, n_bins: int = 8, width: int = 12, slice_dt_s: float = 0.0125, tau_mem_s: float = 0.05,
                 tau_syn_s: float = 0.025, depth: int = 2, hidden: int = 0, delay: int = 0,
                 per_step: bool = False):
        super().__init__()
        if not 1 <= int(width) <= 256:
            raise ValueError(f"width must be in [1, 256], got {width}")
        if int(depth) not in (2, 3):
            raise ValueError(f"depth must be 2 or 3, got {depth}")
        if not 0 <= int(hidden) <= 1024:
            raise ValueError(f"hidden must be in [0, 1024], got {hidden}")
        if not 0 <= int(delay) < int(n_bins):
            raise ValueError(f"delay must be in [0, n_bins - 1 = {int(n_bins) - 1}], got {delay}")
        self.n_bins, self.width, self.slice_dt_s = int(n_bins), int(width), float(slice_dt_s)
        self.depth, self.hidden, self.delay, self.per_step = int(depth), int(hidden), int(delay), bool(per_step)
        self.p = LIFParameters(tau_mem_s=tau_mem_s, tau_syn_s=tau_syn_s, v_th=1.0)
        self.p.check_dt(self.slice_dt_s)
        c = self.width
        self.conv1 = nn.Conv2d(self.in_channels, c, 3, stride=2, padding=1)
        self.conv2 = nn.Conv2d(c, 2 * c, 3, stride=2, padding=1)
        if self.depth == 3:
            self.conv3 = nn.Conv2d(2 * c, 2 * c, 3, stride=2, padding=1)
        n_feat = 4 * c * (self.n_bins if self.per_step else 1) + (2 * c if self.depth == 3 else 0) + 1
        self.head = nn.Linear(n_feat, 2) if not self.hidden else nn.Sequential(
            nn.Linear(n_feat, self.hidden), nn.ReLU(), nn.Linear(self.hidden, 2))
        self.last_activity: Dict[str, torch.Tensor] = {}

    def settings(self) -> Dict[str, float]:
        """Constructor keyword arguments that rebuild this network."""
        out = {"n_bins": self.n_bins, "width": self.width, "slice_dt_s": self.slice_dt_s,
               "tau_mem_s": self.p.tau_mem_s, "tau_syn_s": self.p.tau_syn_s}
        if self.depth != 2 or self.hidden:  # the shipped checkpoints' settings stay as they were
            out.update(depth=self.depth, hidden=self.hidden)
        if self.delay:
            out.update(delay=self.delay)
        if self.per_step:
            out.update(per_step=True)
        return out

    @property
    def in_channels(self) -> int:
        """Input channels per time step: the bin, ``delay`` earlier bins and the two coordinates."""
        return 3 + self.delay

    def slice_inputs(self, vox: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """The network's input per time step: (B, n_bins, 3 + delay, h, w) float32 = [normalised bin k,
        bins k-1 .. k-delay (zeros before the window's first bin), coords]. The delayed copies are
        synaptic delays: a neuron of the first layer sees where events were one step ago beside where
        they are now, so it can respond to motion between bins."""
        B = vox.shape[0]
        xy = coords.expand(B, -1, -1, -1)[:, None].expand(-1, self.n_bins, -1, -1, -1)
        v = _normalise(vox)
        lagged = [nn.functional.pad(v, (0, 0, 0, 0, j, 0))[:, :self.n_bins] for j in range(self.delay + 1)]
        return torch.cat([torch.stack(lagged, dim=2), xy], dim=2)

    def readout(self, count: torch.Tensor, coords: torch.Tensor, log_count: torch.Tensor,
                steps: Optional[torch.Tensor] = None):
        """(mu, log_var) (B,) from the last layer's spike counts of a window, (B, 2 width, h', w'), or
        with ``per_step`` from its spikes at each time step ``steps`` (B, n_bins, 2 width, h', w')."""
        r = coords.norm(dim=1, keepdim=True)  # (1, 1, h, w) radius about the principal point
        r2 = nn.functional.adaptive_avg_pool2d(r, count.shape[-2:])
        src = steps.flatten(1, 2) if self.per_step else count  # per step: when the spikes came, too
        feats = [src.mean(dim=(2, 3)), (src * r2).mean(dim=(2, 3))]
        if self.depth == 3:
            feats.append(count.amax(dim=(2, 3)))
        mu, log_var = self.head(torch.cat([*feats, log_count[:, None]], dim=1)).unbind(1)
        return mu, log_var.clamp(-12.0, 6.0)

    def _layers(self):
        """The convolutions after the first, in order (each feeds a LIF layer)."""
        return (self.conv2, self.conv3) if self.depth == 3 else (self.conv2,)

    def forward(self, vox: torch.Tensor, coords: torch.Tensor, log_count: torch.Tensor):
        B = vox.shape[0]
        cur = self.conv1(self.slice_inputs(vox, coords).flatten(0, 1)).unflatten(0, (B, self.n_bins))
        step = lif_step if torch.is_grad_enabled() else lif_step_inference
        layers = self._layers()
        s1 = lif_state(cur[:, 0].shape, cur.device)
        states = [None] * len(layers)
        count, n_in = 0.0, [0.0] * len(layers)  # n_in[j]: spikes into layers[j] (its synops' source)
        outs = []  # the last layer's spikes per step (``per_step`` read-out)
        for k in range(self.n_bins):  # the time steps of the window (n_bins, a few)
            z, s1 = step(cur[:, k], s1, self.p, self.slice_dt_s)
            for j, conv in enumerate(layers):
                n_in[j] = n_in[j] + z.sum(dim=(1, 2, 3))
                c = conv(z)
                states[j] = lif_state(c.shape, c.device) if states[j] is None else states[j]
                z, states[j] = step(c, states[j], self.p, self.slice_dt_s)
            count = count + z
            if self.per_step:
                outs.append(z)
        n_out = count.sum(dim=(1, 2, 3))
        head_in = self.head.in_features if not self.hidden else self.head[0].in_features
        if self.per_step:  # a spike reaches its own step's block of the read-out's inputs only
            head_in = (head_in - 1) / self.n_bins + 1
        # a spike's targets: 3x3 kernel, stride 2 -> out_channels x 9 / 4 neurons of the next layer
        synops = sum(n * (conv.out_channels * 9 / 4.0) for n, conv in zip(n_in, layers)) + n_out * head_in
        self.last_activity = {"spikes": (sum(n_in) + n_out).detach(), "synops": synops.detach()}
        return self.readout(count, coords, log_count, torch.stack(outs, dim=1) if outs else None)


#: the built-in models by name
MODELS = {"cnn": VoxelCNN, "spiking": SpikingVoxelNet}


def model_class(name: str):
    """The class of model ``name``: a key of :data:`MODELS` or an import path ``package.module:Class``."""
    if name in MODELS:
        return MODELS[name]
    if ":" in str(name):
        import importlib

        mod, _, attr = str(name).rpartition(":")
        try:
            cls = getattr(importlib.import_module(mod), attr)
        except (ImportError, AttributeError) as exc:
            raise ValueError(f"model: cannot import {name!r} ({type(exc).__name__}: {exc})") from None
        return cls
    raise ValueError(f"model: unknown model {name!r}; choose one of {sorted(MODELS)} or 'package.module:Class'")


def build_model(name: str, settings: Dict) -> Tuple[nn.Module, str]:
    """(network, its class path) of model ``name`` built with ``settings`` (constructor kwargs)."""
    cls = model_class(name)
    try:
        net = cls(**settings)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"model settings {settings} do not build {name!r} ({type(exc).__name__}: {exc})") from None
    return net, f"{cls.__module__}:{cls.__qualname__}"
