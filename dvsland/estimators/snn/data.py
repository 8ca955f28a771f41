"""Training sequences for the spiking estimator: short constant-divergence descents rendered on
held-out terrain (site variants ``<site>~<k>``, never the nine evaluation sites), turned into
events by the configured emulator and encoded in log-polar slices.

A sequence has ``n_steps`` control steps of ``cfg.dt_s``: z_k = z0 exp(D t_k), D constant,
|D| log-uniform in [d_min, d_max], a fraction ``ascent_fraction`` of them with D > 0 (the loop
can climb), z0 log-uniform so that the sequence stays within [z_min_m, z_max_m].
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from dvsland.config import Config
from dvsland.events import EventEmulator

from .encoding import LogPolarEncoder


def training_sites(variants: Sequence[int] = (1, 2), sites: str = "ABCDEFGHI") -> list:
    """Names of the held-out training terrains, e.g. ["A~1", ..., "I~2"]."""
    return [f"{s}~{k}" for k in variants for s in sites]


def make_sequences(cfg: Config, encoder: LogPolarEncoder, sites: Sequence[str], n_seq: int, n_steps: int,
                   seed: int = 0, d_min: float = 0.01, d_max: float = 0.5, ascent_fraction: float = 0.15,
                   z_min_m: float = 60.0, z_max_m: float = 9000.0, batch: int = 64, device="cpu",
                   progress: bool = True) -> dict:
    """Render, emulate and encode ``n_seq`` sequences (see module doc).

    Returns a dict of CPU tensors: ``x`` (N, n_steps, n_sub, 2, n_rho, n_phi) float16 events per
    pixel; ``d`` (N, n_steps) float32 true D, 1/s; ``z`` (N, n_steps) float32 altitude, m;
    ``site`` (N,) int64 index into ``sites``; and ``sites``.
    """
    from dvsland.render import get_renderer

    if n_seq < 1 or n_steps < 1:
        raise ValueError(f"n_seq and n_steps must be >= 1, got {n_seq}, {n_steps}")
    if not 0 < d_min < d_max:
        raise ValueError(f"need 0 < d_min < d_max, got {d_min}, {d_max}")
    rng = np.random.default_rng(seed)
    renderer = get_renderer("fast", list(sites), cfg.camera, cfg.render, device=device)
    dt = cfg.dt_s
    span_s = n_steps * dt
    d_abs = np.exp(rng.uniform(math.log(d_min), math.log(d_max), n_seq))
    sign = np.where(rng.uniform(size=n_seq) < ascent_fraction, 1.0, -1.0)
    d = sign * d_abs
    # z stays in [z_min, z_max] over the sequence: z0 in [z_min e^{|D| T}, z_max] when descending
    lo = np.where(d < 0, z_min_m * np.exp(d_abs * span_s), z_min_m)
    hi = np.where(d < 0, z_max_m, z_max_m * np.exp(-d_abs * span_s))
    z0 = np.exp(rng.uniform(np.log(lo), np.log(np.maximum(hi, lo * 1.01))))
    site = rng.integers(0, len(sites), n_seq)
    t = np.arange(n_steps + 1) * dt
    z = z0[:, None] * np.exp(d[:, None] * t[None, :])  # (N, n_steps + 1)
    x_all = torch.empty((n_seq, n_steps, encoder.n_sub, 2, encoder.n_rho, encoder.n_phi), dtype=torch.float16)
    emu = EventEmulator.from_config(cfg.emulator, device=device, seed=seed)
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
        emu.reset(renderer.render(zz[:, 0], idx), int(t_us[0]))
        for k in range(n_steps):
            ev = emu.step(renderer.render(zz[:, k + 1], idx), int(t_us[k + 1]))
            x_all[sl, k] = encoder.encode(ev, int(t_us[k]), int(t_us[k + 1]), b).to("cpu", torch.float16)
        if bar is not None:
            bar.update(b)
    if bar is not None:
        bar.close()
    d_t = torch.as_tensor(np.repeat(d[:, None], n_steps, axis=1), dtype=torch.float32)
    return {"x": x_all, "d": d_t, "z": torch.as_tensor(z[:, 1:], dtype=torch.float32),
            "site": torch.as_tensor(site), "sites": list(sites)}
