"""Training sequences for the spiking estimator: short constant-divergence descents rendered on
held-out terrain (site variants ``<site>~<k>``, never the nine evaluation sites), turned into
events by the configured emulator and encoded in log-polar slices.

A sequence has ``n_steps`` control steps of ``cfg.dt_s``. Its initial |D| is log-uniform in
[d_min, d_max]; a fraction ``ascent_fraction`` climb at constant D > 0 (the loop can climb); the
others descend on the paper's law tau(t) = tau0 - c2 t with c2 uniform in [0, c2_max] (0 =
constant D), so |D| grows as in a real descent. z0 is log-uniform so that the sequence stays
within [z_min_m, z_max_m].
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from dvsland.config import Config

from .encoding import LogPolarEncoder


def training_sites(variants: Sequence[int] = (1, 2), sites: str = "ABCDEFGHI") -> list:
    """Names of the held-out training terrains, e.g. ["A~1", ..., "I~2"]."""
    return [f"{s}~{k}" for k in variants for s in sites]


def make_sequences(cfg: Config, encoder: LogPolarEncoder, sites: Sequence[str], n_seq: int, n_steps: int,
                   seed: int = 0, d_min: float = 0.01, d_max: float = 0.5, ascent_fraction: float = 0.15,
                   c2_max: float = 0.0,
                   z_min_m: float = 60.0, z_max_m: float = 9000.0, batch: int = 64, device="cpu",
                   progress: bool = True) -> dict:
    """Render, emulate and encode ``n_seq`` sequences (see module doc).

    Returns a dict of CPU tensors: ``x`` (N, n_steps, n_sub, 2, n_rho, n_phi) float16 events per
    pixel; ``d`` (N, n_steps) float32 true D, 1/s; ``z`` (N, n_steps) float32 altitude, m;
    ``site`` (N,) int64 index into ``sites``; and ``sites``.
    """
    from dvsland.stages import build_event_source

    if n_seq < 1 or n_steps < 1:
        raise ValueError(f"n_seq and n_steps must be >= 1, got {n_seq}, {n_steps}")
    if not 0 < d_min < d_max:
        raise ValueError(f"need 0 < d_min < d_max, got {d_min}, {d_max}")
    if not 0.0 <= c2_max < 1.0:
        raise ValueError(f"c2_max must be in [0, 1), got {c2_max}")
    if not 0.0 <= ascent_fraction <= 1.0:
        raise ValueError(f"ascent_fraction must be in [0, 1], got {ascent_fraction}")
    if not 0 < z_min_m < z_max_m:
        raise ValueError(f"need 0 < z_min_m < z_max_m, got {z_min_m}, {z_max_m}")
    rng = np.random.default_rng(seed)
    source = build_event_source(cfg, list(sites), device, renderer="fast", seed=seed)
    dt = cfg.dt_s
    span_s = n_steps * dt
    d_abs = np.exp(rng.uniform(math.log(d_min), math.log(d_max), n_seq))
    sign = np.where(rng.uniform(size=n_seq) < ascent_fraction, 1.0, -1.0)
    t = np.arange(n_steps + 1) * dt
    # descents follow the paper's law tau(t) = tau0 - c2 t (D = -1 / tau: |D| grows), c2 drawn in
    # [0, c2_max] and capped so that tau halves at most; climbs keep D constant
    tau0 = 1.0 / d_abs
    c2 = np.where(sign < 0, np.minimum(rng.uniform(0.0, c2_max, n_seq), 0.5 * tau0 / span_s), 0.0)
    tau = tau0[:, None] - c2[:, None] * t[None, :]
    d = np.where(sign[:, None] < 0, -1.0 / tau, d_abs[:, None] * np.ones_like(tau))  # (N, n_steps + 1)
    safe_c2 = np.where(c2 > 0, c2, 1.0)
    log_ratio = np.where(sign[:, None] < 0,
                         np.where(c2[:, None] > 0, np.log(tau / tau0[:, None]) / safe_c2[:, None],
                                  -t[None, :] / tau0[:, None]),
                         d_abs[:, None] * t[None, :])  # log z(t) - log z0
    # z stays in [z_min, z_max] over the sequence
    lo = np.maximum(z_min_m * np.exp(-log_ratio.min(axis=1)), z_min_m)
    hi = np.minimum(z_max_m * np.exp(-log_ratio.max(axis=1)), z_max_m)
    z0 = np.exp(rng.uniform(np.log(lo), np.log(np.maximum(hi, lo * 1.01))))
    site = rng.integers(0, len(sites), n_seq)
    z = z0[:, None] * np.exp(log_ratio)  # (N, n_steps + 1)
    x_all = torch.empty((n_seq, n_steps, encoder.n_sub, 2, encoder.n_rho, encoder.n_phi), dtype=torch.float16)
    t_us = np.round(t * 1e6).astype(np.int64)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_seq, desc="snn data", unit="seq")
    for a in range(0, n_seq, batch):
        sl = slice(a, min(a + batch, n_seq))
        b = sl.stop - sl.start
        idx = torch.as_tensor(site[sl], device=device)
        zz = torch.as_tensor(z[sl], dtype=torch.float32, device=device)
        source.reset(zz[:, 0], idx, int(t_us[0]))
        for k in range(n_steps):
            _, ev = source.step(zz[:, k + 1], idx, int(t_us[k + 1]))
            x_all[sl, k] = encoder.encode(ev, int(t_us[k]), int(t_us[k + 1]), b).to("cpu", torch.float16)
        if bar is not None:
            bar.update(b)
    if bar is not None:
        bar.close()
    # the truth of a step is D at the end of its interval (as in dvsland.evaluate)
    return {"x": x_all, "d": torch.as_tensor(d[:, 1:], dtype=torch.float32),
            "z": torch.as_tensor(z[:, 1:], dtype=torch.float32),
            "site": torch.as_tensor(site), "sites": list(sites)}
