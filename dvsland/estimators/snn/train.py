"""Training of :class:`SpikingDivergenceNet` by back-propagation through time (surrogate spikes).

Loss per sequence step after ``warmup_steps``: the squared relative error
((D_hat - D) / max(|D|, d_floor))^2, so that the slow high-altitude descents (|D| ~ 0.02 1/s)
count as much as the last metres. Adam, gradient-norm clipping, cosine learning-rate decay.
"""

from __future__ import annotations

import math
import time
from typing import Optional

import torch

from ..metrics import divergence_metrics

from .model import SpikingDivergenceNet


def sequence_loss(model: SpikingDivergenceNet, x: torch.Tensor, d: torch.Tensor, warmup_steps: int,
                  d_floor: float = 0.02):
    """x (B, K, n_sub, 2, n_rho, n_phi) events per pixel, d (B, K) true D, 1/s. Returns (loss,
    d_hat (B, K) float32 1/s)."""
    b, k = d.shape
    state = model.initial_state(b, x.device)
    outs = []
    for s in range(k):
        dh, state, _ = model.run_step(x[:, s].float(), state)
        outs.append(dh)
    d_hat = torch.stack(outs, 1)
    rel = (d_hat - d)[:, warmup_steps:] / d[:, warmup_steps:].abs().clamp(min=d_floor)
    return (rel ** 2).mean(), d_hat


def train(model: SpikingDivergenceNet, data: dict, epochs: int = 10, batch: int = 32, lr: float = 3e-3,
          warmup_steps: int = 5, val_fraction: float = 0.1, seed: int = 0, log=print,
          max_minutes: Optional[float] = None, crop_steps: Optional[int] = None) -> dict:
    """Train in place on ``data`` (``x``, ``d``; made above this layer, e.g. by
    :func:`dvsland.data.snn_sequences.make_sequences`); the last ``val_fraction`` of the sequences
    is held out. ``crop_steps``: train on a random window of this
    many steps of each batch (the network starts from rest at the window's start: short sequences
    cut from long ones, a cheap curriculum); validation always runs the whole sequences. Returns the
    history (per-epoch loss and validation median |relative error|)."""
    x, d = data["x"], data["d"]
    n, k_all = x.shape[0], x.shape[1]
    if crop_steps is not None and not warmup_steps < int(crop_steps) <= k_all:
        raise ValueError(f"crop_steps must be in ({warmup_steps}, {k_all}] (warm-up, sequence length), got {crop_steps}")
    n_val = max(1, int(round(n * val_fraction)))
    tr, va = torch.arange(n - n_val), torch.arange(n - n_val, n)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    steps_total = epochs * math.ceil(len(tr) / batch)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps_total, 1))
    g = torch.Generator().manual_seed(seed)
    hist = {"epoch": [], "train_loss": [], "val_median_rel_err": [], "val_within_20": [], "seconds": []}
    t0 = time.perf_counter()
    for ep in range(epochs):
        model.train()
        perm = tr[torch.randperm(len(tr), generator=g)]
        tot, nb = 0.0, 0
        for a in range(0, len(perm), batch):
            idx = perm[a:a + batch]
            xb, db = x[idx], d[idx]
            if crop_steps is not None and int(crop_steps) < k_all:
                s0 = int(torch.randint(0, k_all - int(crop_steps) + 1, (1,), generator=g))
                xb, db = xb[:, s0:s0 + int(crop_steps)], db[:, s0:s0 + int(crop_steps)]
            loss, _ = sequence_loss(model, xb, db, warmup_steps)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            sched.step()
            tot += float(loss.detach())
            nb += 1
        med, w20 = evaluate(model, x[va], d[va], warmup_steps)
        hist["epoch"].append(ep + 1)
        hist["train_loss"].append(tot / max(nb, 1))
        hist["val_median_rel_err"].append(med)
        hist["val_within_20"].append(w20)
        hist["seconds"].append(time.perf_counter() - t0)
        log(f"epoch {ep + 1}/{epochs}: train loss {tot / max(nb, 1):.4f}, val median |rel err| {med:.3f}, "
            f"within 20 % {w20:.2f} ({time.perf_counter() - t0:.0f} s)")
        if max_minutes is not None and time.perf_counter() - t0 > 60 * max_minutes:
            log(f"stopping: time budget of {max_minutes} min reached")
            break
    return hist


@torch.no_grad()
def evaluate(model: SpikingDivergenceNet, x: torch.Tensor, d: torch.Tensor, warmup_steps: int,
             batch: int = 64):
    """(median |relative error|, fraction within 20 %) over the steps after the warm-up, by
    :func:`dvsland.estimators.metrics.divergence_metrics` (the open-loop evaluation's metrics)."""
    model.eval()
    d_hat = torch.cat([sequence_loss(model, x[a:a + batch], d[a:a + batch], warmup_steps)[1]
                       for a in range(0, x.shape[0], batch)])
    m = divergence_metrics(d_hat[:, warmup_steps:].numpy(), d[:, warmup_steps:].numpy())
    return m["median_abs_rel_err"], m["within_20"]
