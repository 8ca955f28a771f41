"""``build_zoom_dataset``: event windows of procedural textures zoomed at known divergences.

The closed-loop datasets (:mod:`.build`) are flown by landing laws over the nine terrains, so their
divergence spans what those laws fly (about -0.01 to -0.1 1/s, twice that with the recipe's time
stretch) and their scenes are the terrains. A model trained on them alone reads the terrains'
statistics and under-reads |D| beyond that range. This builder writes, in the same shard format
(one sample per control step and descent, :mod:`.shardfile`), descents that no lander flies:

- the ground is a :class:`dvsland.render.textures.TextureRenderer` texture, a new one per descent
  (1/f^beta fields and sharp ellipses: none of the terrains, and not the random blobs of
  :class:`dvsland.evaluate.ZoomTextureFrames` that the generalisation check flies);
- the divergence goes linearly in time from D0 to D1 over the descent, both log-uniform in
  |D| in [``d_min``, ``d_max``] (D1 within a factor ``d_ratio`` of D0), and the altitude follows
  z(t) = z0 exp(integral of D) exactly, from z0 log-uniform in [``z_min``, ``z_max``] (raised
  where the descent would end below 20 m);
- the events come from the config's emulator (``emulator`` section: the ideal pixel of
  ``montecarlo_efference``, or the noisy one of ``realistic_sensor``), at the config's nominal
  sensor values (no per-descent sensor dispersion).

Descent i (global index) gets scene ``T~i``, site ``T`` and terrain variant ``i mod 5``, so the
split rule (:mod:`.splits`) puts a fifth of the descents in test (variant 0), a fifth in val
(variant 4) and the rest in train. Everything depends on ``seed`` only: the same request writes
the same shards. Shards of ``shard_size`` descents are written one after another; the same
command again resumes (complete shards are kept).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Dict, NamedTuple, Optional

import numpy as np
import torch

from dvsland import __version__
from dvsland.config import Config

from .manifest import SHARDS_DIR, config_hash, save_manifest, shard_file
from .shardfile import DESCENT_FIELDS, SAMPLE_FIELDS, ShardWriter

#: terrain variants of the split rule (test 0, val 4, train 1-3)
N_VARIANTS = 5
#: lowest altitude a descent may reach, m
Z_FLOOR_M = 20.0


class ZoomRequest(NamedTuple):
    """What a zoom dataset holds (module doc); every field is recorded in the manifest.

    Attributes:
        n_descents: descents (>= 1).
        steps: control steps per descent after the first frame (>= 2).
        d_min, d_max: range of |D|, 1/s (0 < d_min < d_max <= 5).
        d_ratio: |D1| / |D0| within [1 / d_ratio, d_ratio] (>= 1).
        z_min, z_max: range of the start altitude, m (20 <= z_min < z_max).
        seed: the draws' and the textures' seed.
        shard_size: descents per shard (>= 1).
    """

    n_descents: int
    steps: int = 40
    d_min: float = 0.004
    d_max: float = 0.6
    d_ratio: float = 3.0
    z_min: float = 150.0
    z_max: float = 6000.0
    seed: int = 0
    shard_size: int = 50

    def check(self) -> "ZoomRequest":
        """``self``; ValueError naming the field and its range when one is out of it."""
        rules = (("n_descents", 1, 10_000_000), ("steps", 2, 100_000), ("shard_size", 1, 100_000))
        for k, lo, hi in rules:
            v = getattr(self, k)
            if not (isinstance(v, (int, np.integer)) and lo <= v <= hi):
                raise ValueError(f"{k} must be an integer in [{lo}, {hi}], got {v!r}")
        if not (0 < self.d_min < self.d_max <= 5.0):
            raise ValueError(f"d_min, d_max must satisfy 0 < d_min < d_max <= 5 1/s, got {self.d_min}, {self.d_max}")
        if not (1.0 <= self.d_ratio <= 100.0):
            raise ValueError(f"d_ratio must be in [1, 100], got {self.d_ratio}")
        if not (Z_FLOOR_M <= self.z_min < self.z_max <= 20000.0):
            raise ValueError(f"z_min, z_max must satisfy {Z_FLOOR_M} <= z_min < z_max <= 20000 m, got "
                             f"{self.z_min}, {self.z_max}")
        return self


def descent_profiles(req: ZoomRequest, first: int, n: int, dt_s: float) -> Dict[str, np.ndarray]:
    """The profiles of descents ``first .. first + n - 1``: ``d`` and ``z`` (n, steps + 1) float64
    (1/s, m) at the control steps, and ``z0`` (n,). Descent i's draws depend on (seed, i) only."""
    K = req.steps
    t = np.arange(K + 1) * dt_s
    d, z = np.empty((n, K + 1)), np.empty((n, K + 1))
    for j in range(n):  # set-up only, n draws: not on a hot path
        rng = np.random.default_rng([int(req.seed), first + j])
        a0 = math.exp(rng.uniform(math.log(req.d_min), math.log(req.d_max)))
        a1 = float(np.clip(a0 * math.exp(rng.uniform(-1, 1) * math.log(req.d_ratio)), req.d_min, req.d_max))
        z0 = math.exp(rng.uniform(math.log(req.z_min), math.log(req.z_max)))
        d[j] = -(a0 + (a1 - a0) * t / t[-1])
        integral = -(a0 * t + 0.5 * (a1 - a0) * t ** 2 / t[-1])  # of D from 0 to t
        z0 = max(z0, Z_FLOOR_M * math.exp(-integral[-1]))
        z[j] = z0 * np.exp(integral)
    return {"d": d, "z": z, "z0": z[:, 0].copy()}


def _samples(ev, k: int, dt_s: float, prof: dict) -> tuple:
    """(events, counts, samples) of step ``k`` for every descent of the shard (all active)."""
    n = prof["d"].shape[0]
    t_us, t0_us = int(round(k * dt_s * 1e6)), int(round((k - 1) * dt_s * 1e6))
    b = ev.b.numpy()
    counts = np.bincount(b, minlength=n).astype(np.int64)
    events = {"x": ev.x.numpy().astype(np.uint16), "y": ev.y.numpy().astype(np.uint16),
              "dt_us": (ev.t.numpy() - t0_us).astype(np.int32), "p": ev.p.numpy().astype(np.int8)}
    d, z = prof["d"][:, k], prof["z"][:, k]
    s = {"descent": np.arange(n), "step": np.full(n, k), "t0_us": np.full(n, t0_us), "t_us": np.full(n, t_us),
         "t_s": np.full(n, k * dt_s), "d_true": d, "tau_s": -1.0 / d, "z_m": z, "v_mps": d * z, "d_est": d,
         "thrust_n": np.full(n, np.nan), "valid": np.ones(n, bool)}
    return events, counts, {f: np.asarray(s[f], dtype=SAMPLE_FIELDS[f][0]) for f in SAMPLE_FIELDS}


def _descents(first: int, prof: dict) -> Dict[str, np.ndarray]:
    n = prof["d"].shape[0]
    idx = np.arange(first, first + n)
    nan = np.full(n, np.nan)
    out = {"site": ["T"] * n, "scene": [f"T~{i}" for i in idx], "setting": ["zoom"] * n,
           "variant": idx % N_VARIANTS, "seed": idx, "seed_index": idx, "z0_m": prof["z0"],
           "v0_mps": prof["d"][:, 0] * prof["z0"], "sun_elevation_deg": nan, "threshold_scale": nan,
           "mismatch_sigma": nan, "background_rate_hz": nan, "refractory_us": nan, "outcome": ["zoom"] * n}
    return {k: (np.asarray(v, dtype=object) if DESCENT_FIELDS[k] is str else np.asarray(v, DESCENT_FIELDS[k]))
            for k, v in out.items()}


def build_zoom_shard(cfg: Config, req: ZoomRequest, first: int, n: int, path, attrs: dict,
                     compression: Optional[str] = "gzip") -> dict:
    """Render, emulate and write descents ``first .. first + n - 1`` to ``path``; the manifest entry."""
    from dvsland.events import EventEmulator
    from dvsland.render.textures import TextureRenderer

    t_wall = time.perf_counter()
    dt_s = float(cfg.dt_s)
    prof = descent_profiles(req, first, n, dt_s)
    rend = TextureRenderer([f"A~{i + 1}" for i in range(first, first + n)], cfg.camera, cfg.render, seed=req.seed,
                           altitude_range_m=(Z_FLOOR_M, req.z_max))
    emu = EventEmulator.from_config(cfg.emulator, "cpu", seed=int(req.seed) * 1_000_003 + first)
    idx = torch.arange(n)
    emu.reset(rend.render(torch.as_tensor(prof["z"][:, 0]), idx), 0)
    writer = ShardWriter(path, attrs, compression)
    try:
        for k in range(1, req.steps + 1):
            ev = emu.step(rend.render(torch.as_tensor(prof["z"][:, k]), idx), int(round(k * dt_s * 1e6)))
            writer.append(*_samples(ev.to("cpu"), k, dt_s, prof))
        writer.finish(_descents(first, prof))
    except BaseException:
        writer.abort()
        raise
    return {"n_samples": len(writer.offsets) - 1, "n_events": writer.n_events, "n_descents": n,
            "bytes": Path(path).stat().st_size, "seconds": round(time.perf_counter() - t_wall, 3)}


def _manifest(cfg: Config, req: ZoomRequest) -> dict:
    from .build import camera_fields

    conf = dataclasses.asdict(cfg)
    conf["zoom"] = req._asdict()  # the request is part of what the shards hold
    shards = [{"id": f"z{i:06d}", "file": f"{SHARDS_DIR}/z{i:06d}.h5", "seed_offset": i,
               "n_seeds": min(req.shard_size, req.n_descents - i), "status": "pending"}
              for i in range(0, req.n_descents, req.shard_size)]
    return {"format": "dvsland-event-windows", "format_version": 1, "config": conf, "config_hash": config_hash(conf),
            "estimator": "oracle", "sites": ["T"], "n_seeds": req.n_descents, "seed_offset": 0,
            "shard_size": req.shard_size, "sensor_size": [int(cfg.camera.width_px), int(cfg.camera.height_px)],
            **camera_fields(cfg.camera), "dt_s": float(cfg.dt_s), "n_variants": N_VARIANTS,
            "dvsland_version": __version__, "source": "zoom_textures", "shards": shards}


def build_zoom_dataset(cfg: Config, req: ZoomRequest, out, quiet: bool = True,
                       compression: Optional[str] = "gzip") -> dict:
    """Build (or resume) a zoom dataset (module doc) in folder ``out``; returns its manifest. The folder
    is handled as ``dataset build`` handles its own (:func:`dvsland.data.build.build_dataset`: a
    folder of other files or of another request refused, a lock, config.yaml, damaged entries and
    shards rebuilt).

    Raises:
        ValueError: a field of ``req`` out of range (named); ``out`` holding other files or another
            request (naming what differs).
    """
    from dvsland.runs import open_folder

    from .build import _open_folder, _shard_ok

    req = req.check()
    root = open_folder(out, "--out", create=False)
    fresh = _manifest(cfg, req)
    manifest, lock = _open_folder(root, fresh, cfg)
    try:
        attrs = {"sensor_size": fresh["sensor_size"], "principal_point_px": fresh["principal_point_px"],
                 "focal_px": fresh["focal_px"], "dt_s": fresh["dt_s"], "config_hash": fresh["config_hash"],
                 "estimator": "oracle"}
        for e in manifest["shards"]:
            if _shard_ok(root, e, quiet):
                continue
            entry = build_zoom_shard(cfg, req, e["seed_offset"], e["n_seeds"], shard_file(root, e["id"]),
                                     {**attrs, "shard_id": e["id"], "seed_offset": e["seed_offset"],
                                      "n_seeds": e["n_seeds"]}, compression)
            e.update(entry, status="complete")
            save_manifest(root, manifest)
            if not quiet:
                print(f"shard {e['id']}: {entry['n_descents']} descents, {entry['n_samples']} samples, "
                      f"{entry['n_events']} events, {entry['seconds']:.1f} s", flush=True)
    finally:
        if lock is not None:
            lock.close()
    return manifest


__all__ = ["ZoomRequest", "build_zoom_dataset", "build_zoom_shard", "descent_profiles", "N_VARIANTS"]
