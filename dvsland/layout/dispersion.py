"""Per-seed dispersions of a Monte Carlo batch: the maths (sampling), no simulation state.

A :class:`~dvsland.config.schema.Dispersion` is one parameter's distribution: ``off`` (the
nominal value of the config, not dispersed), ``fixed`` (one value for every element), ``uniform``
on ``[low, high]`` or ``normal`` (``mean``, ``std``) clipped to ``[low, high]``. The draws of an
element depend only on the master seed, its site name and its seed index ``k`` (never on the
controller setting, the batch size or how a campaign is split into shards), so every controller
setting and every estimator flies the same dispersed scenes for the same ``k`` (common random
numbers: paired comparisons), and a shard re-run on another machine draws the same values.

Each parameter draws from its own stream (:func:`element_rng` with a per-parameter key), so
switching one dispersion on or off never changes the values drawn for another.
"""

from __future__ import annotations

import zlib
from typing import Dict, Optional, Sequence

import numpy as np

#: parameter name -> stream key (fixed forever: changing one changes every campaign's draws)
STREAM_KEYS: Dict[str, int] = {
    "z0_scale": 1, "v0_scale": 2, "sun_elevation_deg": 3, "sun_azimuth_offset_deg": 4,
    "terrain_variant": 5, "threshold_scale": 6, "mismatch_sigma": 7, "background_rate_hz": 8,
    "refractory_us": 9, "element_seed": 10,
}

from dvsland.config.dispersion import KINDS, check_dispersion_config, check_distribution  # noqa: F401 (re-export)


def site_key(site: str) -> int:
    """A stable 31-bit integer for a site name (crc32; ``A``, ``A~3`` ... all differ)."""
    return zlib.crc32(str(site).encode()) & 0x7FFFFFFF


def element_rng(master_seed: int, site: str, seed_index: int, stream: str) -> np.random.Generator:
    """The numpy generator of one (site, seed index, parameter) draw.

    Args:
        master_seed: ``simulation.seed`` (>= 0).
        site: site name (``A`` ... ``I`` or a variant ``A~k``).
        seed_index: global seed index k >= 0 (``simulation.seed_offset + i``).
        stream: a key of :data:`STREAM_KEYS`.
    """
    if stream not in STREAM_KEYS:
        raise ValueError(f"stream must be one of {sorted(STREAM_KEYS)}, got {stream!r}")
    if int(seed_index) < 0:
        raise ValueError(f"seed_index must be >= 0, got {seed_index}")
    ss = np.random.SeedSequence(int(master_seed), spawn_key=(site_key(site), int(seed_index), STREAM_KEYS[stream]))
    return np.random.default_rng(ss)


def sample_one(dist, rng: np.random.Generator) -> Optional[float]:
    """One draw of ``dist`` (None for ``off``). Normal draws are clipped to ``[low, high]``."""
    kind = dist.kind
    if kind == "off":
        return None
    if kind == "fixed":
        return float(dist.value)
    if kind == "uniform":
        return float(rng.uniform(dist.low, dist.high))
    if kind == "normal":
        return float(np.clip(rng.normal(dist.mean, dist.std), dist.low, dist.high))
    raise ValueError(f"distribution kind must be one of {list(KINDS)}, got {kind!r}")


def sample_elements(dist, name: str, master_seed: int, sites: Sequence[str],
                    seed_index: Sequence[int]) -> Optional[np.ndarray]:
    """Draws of parameter ``name`` for B elements, float64 (B,), or None when ``dist`` is off.

    Args:
        dist: the Dispersion of the parameter.
        name: parameter name (a key of :data:`STREAM_KEYS`).
        master_seed: ``simulation.seed``.
        sites: (B,) site names.  seed_index: (B,) global seed indices.
    """
    if dist.kind == "off":
        return None
    return np.asarray([sample_one(dist, element_rng(master_seed, s, k, name))
                       for s, k in zip(sites, seed_index)], dtype=np.float64)


def element_seeds(master_seed: int, sites: Sequence[str], setting_idx: Sequence[int],
                  seed_index: Sequence[int]) -> np.ndarray:
    """(B,) int64 63-bit per-element seeds keyed by (site, setting, seed index): the seeds of the
    emulator's and the estimators' own randomness, independent of batch size and sharding."""
    out = []
    for s, j, k in zip(sites, setting_idx, seed_index):
        ss = np.random.SeedSequence(int(master_seed),
                                    spawn_key=(site_key(s), int(k), STREAM_KEYS["element_seed"], int(j)))
        out.append(int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1)))
    return np.asarray(out, dtype=np.int64)

