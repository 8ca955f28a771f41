"""Scores of a model on a split: median |relative error| and calibration, overall and per site type.

The error of a sample is |D_hat - D| / |D| with D_hat = -exp(mu); calibration is the share of
samples whose |log|D_hat| - log|D|| lies within 1 and 2 predicted standard deviations
(sigma = exp(log_var / 2); ideal 68.3 % and 95.4 %).
"""

from __future__ import annotations

from typing import Dict

import torch

from dvsland.data import Windows
from dvsland.data.splits import site_types
from dvsland.estimators.learned.inputs import InputSpec

from .batches import make_batch


@torch.no_grad()
def predict(model, w: Windows, spec: InputSpec, coords: torch.Tensor, batch_size: int = 256, rows=None):
    """(mu, log_var), (n,) float32 each, of ``model`` on the samples ``rows`` (n,) int64 of ``w``
    (default all)."""
    model.eval()
    rows = torch.arange(w.n_samples) if rows is None else rows
    mus, lvs = [], []
    for start in range(0, len(rows), batch_size):  # batches of samples, not single samples
        idx = rows[start:start + batch_size]
        bt = make_batch(w, idx, spec)
        mu, lv = model(bt.vox, coords, bt.log_count)
        mus.append(mu)
        lvs.append(lv)
    return torch.cat(mus), torch.cat(lvs)


def _summary(rel: torch.Tensor, z: torch.Tensor) -> Dict[str, float]:
    return {"n": int(rel.numel()), "median_rel_error": float(rel.median()) if rel.numel() else float("nan"),
            "within_1sigma": float((z <= 1).float().mean()) if rel.numel() else float("nan"),
            "within_2sigma": float((z <= 2).float().mean()) if rel.numel() else float("nan")}


def score(mu: torch.Tensor, log_var: torch.Tensor, w: Windows, rows=None) -> Dict[str, Dict[str, float]]:
    """{"all" | site type | site: {n, median_rel_error, within_1sigma, within_2sigma}} of predictions
    (n,) of the samples ``rows`` of ``w`` (default all) against their ``d_true``. Only groups with
    samples are listed."""
    rows = torch.arange(w.n_samples) if rows is None else rows
    d = w.d_true[rows].double()
    site = w.site[rows]
    rel = (-torch.exp(mu.double()) - d).abs() / d.abs()
    z = (mu.double() - torch.log(d.abs().clamp_min(1e-3))).abs() / torch.exp(0.5 * log_var.double())
    out = {"all": _summary(rel, z)}
    names = list(w.sites)
    for tname, letters in site_types().items():
        m = torch.tensor([names[int(s)].split("~")[0] in letters for s in range(len(names))])[site]
        if bool(m.any()):
            out[tname] = _summary(rel[m], z[m])
    for s, name in enumerate(names):
        m = site == s
        if bool(m.any()):
            out[name] = _summary(rel[m], z[m])
    return out
