"""Training sequences of the spiking estimator ('snn'), flown on the loop.

Short constant-divergence descents and climbs rendered on held-out terrain (site variants
``<site>~<k>``, never the nine evaluation sites, :func:`training_sites`), turned into events by the
configured emulator and encoded in log-polar slices by the model's encoder. Every sequence flies
on :func:`dvsland.sim.loop_step` (the stages of :func:`dvsland.stages.build_stages`: the fast
renderer, the configured emulator and dynamics) with the thrust that tracks its altitude profile
(:func:`dvsland.evaluate.reference.tracking_thrust`); the events of each step are the
``StepOutput``'s. Data generation lives here, above the loop; the model side (encoder, network,
training) stays in :mod:`dvsland.estimators.snn`, and ``scripts/train_snn.py`` wires the two.

A sequence has ``n_steps`` control steps of ``cfg.dt_s``. Its initial |D| is log-uniform in
[d_min, d_max]; a fraction ``ascent_fraction`` climb at constant D > 0 (the loop can climb); the
others descend on the paper's law tau(t) = tau0 - c2 t with c2 uniform in [0, c2_max] (0 =
constant D), so |D| grows as in a real descent. z0 is log-uniform so that the sequence stays
within [z_min_m, z_max_m]. The labels (``d``, ``z``) are the profile's, at the end of each step.

Dispersed scenes (``dispersion``, a :class:`~dvsland.config.schema.DispersionConfig` such as the
``dispersion:`` section of configs/montecarlo.yaml): each sequence draws its own sun elevation
(rounded to ``sun_step_deg``: each distinct (terrain, sun) pair costs one terrain preparation)
and its own sensor: contrast-threshold scale, per-pixel mismatch, background rate and refractory
period, exactly as a Monte Carlo campaign draws them per seed (distributions from the config,
draws from the sequence's own generator).
"""

from __future__ import annotations

import copy
import math
from typing import Optional, Sequence

import numpy as np
import torch

from dvsland.config import Config
from dvsland.estimators.snn.data import SITE_TYPES, training_sites  # noqa: F401 - re-exported

#: the sensor parameters a dispersion draws per sequence (emulator.set_element_params)
SENSOR_DISPERSIONS = ("threshold_scale", "mismatch_sigma", "background_rate_hz", "refractory_us")


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


def _profiles(rng: np.random.Generator, n_seq: int, n_t: int, dt: float, d_min: float, d_max: float,
              ascent_fraction: float, c2_max: float, z_min_m: float, z_max_m: float):
    """(d (N, n_t), z (N, n_t), d_abs (N,)) of the sequences at t = k dt, k = 0 .. n_t - 1; draws in
    the order of the sequences' generator (d_abs, sign, c2, z0)."""
    span_s = (n_t - 3) * dt  # the sequence itself; two samples beyond for the tracking thrust
    d_abs = np.exp(rng.uniform(math.log(d_min), math.log(d_max), n_seq))
    sign = np.where(rng.uniform(size=n_seq) < ascent_fraction, 1.0, -1.0)
    t = np.arange(n_t) * dt
    # descents follow the paper's law tau(t) = tau0 - c2 t (D = -1 / tau: |D| grows), c2 drawn in
    # [0, c2_max] and capped so that tau halves at most over the sequence; climbs keep D constant
    tau0 = 1.0 / d_abs
    c2 = np.where(sign < 0, np.minimum(rng.uniform(0.0, c2_max, n_seq), 0.5 * tau0 / span_s), 0.0)
    tau = np.maximum(tau0[:, None] - c2[:, None] * t[None, :], 1e-3 * tau0[:, None])  # (> tau0 / 2 within)
    d = np.where(sign[:, None] < 0, -1.0 / tau, d_abs[:, None] * np.ones_like(tau))
    safe_c2 = np.where(c2 > 0, c2, 1.0)
    log_ratio = np.where(sign[:, None] < 0,
                         np.where(c2[:, None] > 0, np.log(tau / tau0[:, None]) / safe_c2[:, None],
                                  -t[None, :] / tau0[:, None]),
                         d_abs[:, None] * t[None, :])  # log z(t) - log z0
    # z stays in [z_min, z_max] over the sequence (its n_steps + 1 frames)
    seq = log_ratio[:, :n_t - 2]
    lo = np.maximum(z_min_m * np.exp(-seq.min(axis=1)), z_min_m)
    hi = np.minimum(z_max_m * np.exp(-seq.max(axis=1)), z_max_m)
    z0 = np.exp(rng.uniform(np.log(lo), np.log(np.maximum(hi, lo * 1.01))))
    return d, z0[:, None] * np.exp(log_ratio), d_abs


def sequence_config(cfg: Config, n_steps: int) -> Config:
    """A copy of ``cfg`` for recording training sequences: no timeout within the sequence, one
    controller setting, and the ``oracle`` as the loop's estimator (what the loop estimates is not
    recorded; :func:`make_sequences` records the camera with ``build_stages(record_events=True)``
    and flies the profile with ``terminate=False``, so no sequence ends early)."""
    fc = copy.deepcopy(cfg)
    fc.simulation.success_altitude_m = 0.0
    fc.simulation.crash_divergence = 1e3
    fc.simulation.t_max_s = max(float(fc.simulation.t_max_s), (int(n_steps) + 3) * float(fc.dt_s))
    fc.controller.settings = list(fc.controller.settings)[:1]
    fc.estimator.name = "oracle"  # what the loop estimates is not recorded: the cheapest estimator
    return fc


def _layout(names, scene, z0, d0, seeds, sensor, noise_seed, kp, n_bin):
    """The batch layout of one chunk of sequences: element i flies renderer scene ``scene[i]``."""
    from dvsland.layout import BatchLayout

    b = len(scene)
    return BatchLayout(site_names=list(names), site=[names[i] for i in scene], site_idx=np.asarray(scene, np.int64),
                       setting_idx=np.zeros(b, np.int64), seed_idx=np.arange(b, dtype=np.int64), label=["snn"] * b,
                       run_label=[f"seq{int(s)}" for s in seeds], kp=np.full(b, float(kp)),
                       n_bin=np.full(b, int(n_bin), np.int64), z0_m=np.asarray(z0, np.float64),
                       # the controller's plan (its output is not flown): a descent at the start's |D|
                       v0_mps=-np.abs(np.asarray(d0, np.float64)) * np.asarray(z0, np.float64),
                       seed=np.asarray(seeds, np.int64), sensor=dict(sensor), noise_seed=int(noise_seed))


def make_sequences(cfg: Config, encoder, sites: Sequence[str], n_seq: int, n_steps: int,
                   seed: int = 0, d_min: float = 0.01, d_max: float = 0.5, ascent_fraction: float = 0.15,
                   c2_max: float = 0.0,
                   z_min_m: float = 60.0, z_max_m: float = 9000.0, batch: int = 64, device="cpu",
                   progress: bool = True, dispersion=None, sun_step_deg: Optional[float] = None) -> dict:
    """Render, emulate and encode ``n_seq`` sequences (see module doc) on :func:`dvsland.sim.loop_step`.

    Args:
        cfg: config (camera, render, emulator, dynamics, controller; ``dt_s``).
        encoder: :class:`dvsland.estimators.snn.LogPolarEncoder` (``encode(events, t0_us, t1_us, B)``).
        sites: the renderer's terrains (e.g. :func:`training_sites`).
        n_seq, n_steps: sequences and control steps per sequence.
        seed: seed of the draws and of the emulator.
        batch: sequences flown together (one loop each).

    Returns a dict of CPU tensors: ``x`` (N, n_steps, n_sub, 2, n_rho, n_phi) float16 events per
    pixel; ``d`` (N, n_steps) float32 true D, 1/s; ``z`` (N, n_steps) float32 altitude, m;
    ``site`` (N,) int64 index into ``sites``; ``sites``; and ``dispersed``: {name: (N,) float64}
    the per-sequence draws of ``dispersion`` (empty when it is None or disabled).
    """
    from dvsland.evaluate.reference import fly_profile
    from dvsland.render import get_renderer
    from dvsland.stages import build_stages

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
    device = torch.device(device)
    rng = np.random.default_rng(seed)
    dt = cfg.dt_s
    d, z, d_abs = _profiles(rng, n_seq, n_steps + 3, dt, d_min, d_max, ascent_fraction, c2_max, z_min_m, z_max_m)
    site = rng.integers(0, len(sites), n_seq)
    drawn = _draw_dispersions(dispersion, n_seq, np.random.default_rng([seed, 7]), sun_step_deg)
    if "sun_elevation_deg" in drawn:  # one scene per (site, sun): the renderer's site list
        pairs = sorted(set(zip(site.tolist(), drawn["sun_elevation_deg"].tolist())))
        scene_of = {p: i for i, p in enumerate(pairs)}
        scene = np.asarray([scene_of[p] for p in zip(site.tolist(), drawn["sun_elevation_deg"].tolist())])
        names = [sites[a] for a, _ in pairs]
        renderer = get_renderer("fast", names, cfg.camera, cfg.render, device=device, suns=[(e, 0.0) for _, e in pairs],
                                altitude_ranges=[(float(z_min_m), float(z_max_m))] * len(pairs))
    else:
        scene, names = site, list(sites)
        renderer = get_renderer("fast", names, cfg.camera, cfg.render, device=device)  # shared by the chunks
    fcfg = sequence_config(cfg, n_steps)
    first = fcfg.controller.settings[0]
    f64 = dict(dtype=torch.float64, device=device)
    x_all = torch.empty((n_seq, n_steps, encoder.n_sub, 2, encoder.n_rho, encoder.n_phi), dtype=torch.float16)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_seq, desc="snn data", unit="seq")
    for a in range(0, n_seq, batch):
        sl = slice(a, min(a + batch, n_seq))
        b = sl.stop - sl.start
        sensor = {n: drawn[n][sl] for n in SENSOR_DISPERSIONS if n in drawn}
        # per-sequence sensor of this chunk, each with its own mismatch map (set by build_stages)
        seeds = seed * 1_000_003 + np.arange(sl.start, sl.stop)
        layout = _layout(names, scene[sl], z[sl, 0], d_abs[sl], seeds, sensor, seed, first.kp, first.n_bin)
        stages = build_stages(fcfg, layout, device, renderer=renderer, record_events=True)
        m0 = torch.full((b,), 1e3 * float(fcfg.dynamics.dry_mass_kg) + 1.0, **f64)  # fuel never runs out
        flight = fly_profile(stages, z[sl], d[sl, 0] * z[sl, 0], m0, keep_flying=True)  # climbs too
        for k, out in enumerate(flight):
            if k > 0:  # the events of (t_{k-1}, t_k]
                x_all[sl, k - 1] = encoder.encode(out.events, _t_us(k - 1, dt), out.t_us, b).to("cpu", torch.float16)
        if bar is not None:
            bar.update(b)
    if bar is not None:
        bar.close()
    # the truth of a step is D at the end of its interval (as in dvsland.evaluate)
    return {"x": x_all, "d": torch.as_tensor(d[:, 1:n_steps + 1], dtype=torch.float32),
            "z": torch.as_tensor(z[:, 1:n_steps + 1], dtype=torch.float32),
            "site": torch.as_tensor(site), "sites": list(sites), "dispersed": drawn}


def _t_us(k: int, dt: float) -> int:
    """The loop's time of step ``k``, int µs (as :func:`dvsland.sim.loop_step` computes it)."""
    return int(round(k * dt * 1e6))


__all__ = ["make_sequences", "training_sites", "SITE_TYPES", "SENSOR_DISPERSIONS", "sequence_config"]
