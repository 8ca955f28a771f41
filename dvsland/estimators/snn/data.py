"""Training sequences for the spiking estimator: short constant-divergence descents rendered on
held-out terrain (site variants ``<site>~<k>``, never the nine evaluation sites), turned into
events by the configured emulator and encoded in log-polar slices.

A sequence has ``n_steps`` control steps of ``cfg.dt_s``. Its initial |D| is log-uniform in
[d_min, d_max]; a fraction ``ascent_fraction`` climb at constant D > 0 (the loop can climb); the
others descend on the paper's law tau(t) = tau0 - c2 t with c2 uniform in [0, c2_max] (0 =
constant D), so |D| grows as in a real descent. z0 is log-uniform so that the sequence stays
within [z_min_m, z_max_m].

Dispersed scenes (``dispersion``, a :class:`~dvsland.config.schema.DispersionConfig` such as the
``dispersion:`` section of configs/montecarlo.yaml): each sequence draws its own sun elevation
(rounded to ``sun_step_deg``: each distinct (terrain, sun) pair costs one terrain preparation)
and its own sensor: contrast-threshold scale, per-pixel mismatch, background rate and refractory
period, exactly as a Monte Carlo campaign draws them per seed (distributions from the config,
draws from the sequence's own generator).

Held-out site type: :data:`SITE_TYPES` groups the nine sites by kind; ``training_sites(...,
hold_out_type=...)`` leaves one kind out entirely, so that its sites measure generalisation to a
kind of terrain never seen in training.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np
import torch

from dvsland.config import Config

from .encoding import LogPolarEncoder


#: the site types of the nine evaluation sites (configs/sites/)
SITE_TYPES = {"craters": "ABC", "craters_rocks": "DE", "rocky": "FG", "featureless": "HI"}

#: the sensor parameters a dispersion draws per sequence (emulator.set_element_params)
SENSOR_DISPERSIONS = ("threshold_scale", "mismatch_sigma", "background_rate_hz", "refractory_us")


def training_sites(variants: Sequence[int] = (1, 2), sites: str = "ABCDEFGHI",
                   hold_out_type: Optional[str] = None) -> list:
    """Names of the held-out training terrains, e.g. ["A~1", ..., "I~2"], without the sites of
    ``hold_out_type`` (a key of :data:`SITE_TYPES`) when given."""
    if hold_out_type is not None:
        if hold_out_type not in SITE_TYPES:
            raise ValueError(f"hold_out_type must be one of {sorted(SITE_TYPES)}, got {hold_out_type!r}")
        sites = "".join(c for c in sites if c not in SITE_TYPES[hold_out_type])
    return [f"{s}~{k}" for k in variants for s in sites]


def _draw_dispersions(dispersion, n_seq: int, rng: np.random.Generator, sun_step_deg: Optional[float]) -> dict:
    """{name: (n_seq,) float64} draws of the enabled scene and sensor dispersions (sun elevation
    rounded to the step, clipped to [1, 90] deg)."""
    from dvsland.layout.dispersion import sample_one

    out = {}
    if dispersion is None or not dispersion.enabled:
        return out
    for name in ("sun_elevation_deg",) + SENSOR_DISPERSIONS:
        dist = getattr(dispersion, name)
        if dist.kind == "off":
            continue
        out[name] = np.asarray([sample_one(dist, rng) for _ in range(n_seq)], dtype=np.float64)
    if "sun_elevation_deg" in out:
        step = float(sun_step_deg if sun_step_deg is not None else dispersion.sun_step_deg)
        if not step > 0:
            raise ValueError(f"sun_step_deg must be > 0, got {step}")
        out["sun_elevation_deg"] = np.clip(np.round(out["sun_elevation_deg"] / step) * step, 1.0, 90.0)
    return out


def make_sequences(cfg: Config, encoder: LogPolarEncoder, sites: Sequence[str], n_seq: int, n_steps: int,
                   seed: int = 0, d_min: float = 0.01, d_max: float = 0.5, ascent_fraction: float = 0.15,
                   c2_max: float = 0.0,
                   z_min_m: float = 60.0, z_max_m: float = 9000.0, batch: int = 64, device="cpu",
                   progress: bool = True, dispersion=None, sun_step_deg: Optional[float] = None) -> dict:
    """Render, emulate and encode ``n_seq`` sequences (see module doc).

    Returns a dict of CPU tensors: ``x`` (N, n_steps, n_sub, 2, n_rho, n_phi) float16 events per
    pixel; ``d`` (N, n_steps) float32 true D, 1/s; ``z`` (N, n_steps) float32 altitude, m;
    ``site`` (N,) int64 index into ``sites``; ``sites``; and ``dispersed``: {name: (N,) float64}
    the per-sequence draws of ``dispersion`` (empty when it is None or disabled).
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
    drawn = _draw_dispersions(dispersion, n_seq, np.random.default_rng([seed, 7]), sun_step_deg)
    if "sun_elevation_deg" in drawn:  # one scene per (site, sun): the renderer's site list
        pairs = sorted(set(zip(site.tolist(), drawn["sun_elevation_deg"].tolist())))
        scene_of = {p: i for i, p in enumerate(pairs)}
        scene = np.asarray([scene_of[p] for p in zip(site.tolist(), drawn["sun_elevation_deg"].tolist())])
        source = build_event_source(cfg, [sites[a] for a, _ in pairs], device, renderer="fast", seed=seed,
                                    suns=[(e, 0.0) for _, e in pairs],
                                    altitude_ranges=[(float(z_min_m), float(z_max_m))] * len(pairs))
    else:
        scene = site
        source = build_event_source(cfg, list(sites), device, renderer="fast", seed=seed)
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
        idx = torch.as_tensor(scene[sl], device=device)
        zz = torch.as_tensor(z[sl], dtype=torch.float32, device=device)
        sensor = {n: drawn[n][sl] for n in SENSOR_DISPERSIONS if n in drawn}
        if sensor:  # per-sequence sensor of this chunk (takes effect at the reset below); own mismatch maps
            source.emulator.set_element_params(**sensor, element_seeds=seed * 1_000_003 + np.arange(sl.start, sl.stop))
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
            "site": torch.as_tensor(site), "sites": list(sites), "dispersed": drawn}
