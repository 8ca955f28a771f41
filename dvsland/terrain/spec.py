"""Site specifications: the seeded recipe of one landing site (``configs/sites/<name>.yaml``).

A spec holds every number that shapes a site (sun, albedo, background relief, crater and
boulder populations). :func:`load_spec` reads and validates one; :meth:`SiteSpec.digest` is a
stable hash used as a cache key for prepared render levels.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import yaml

from dvsland.checks import check_fields
from dvsland.config import SITE_NAMES, build, configs_dir
from dvsland.config.schema import opt


@dataclass(frozen=True)
class SunSpec:
    """Sun position. ``azimuth_deg``: compass azimuth TO the sun, clockwise from north (y)."""

    elevation_deg: float = opt(15.0, "sun elevation, degrees", rng=(1.0, 90.0))
    azimuth_deg: float = opt(90.0, "azimuth to the sun, degrees clockwise from north", rng=(-360.0, 360.0))


@dataclass(frozen=True)
class AlbedoSpec:
    """Normal albedo: ``mean`` x exp(``variation`` x fBm) x crater/boulder factors."""

    mean: float = opt(0.12, "mean normal albedo", rng=(1e-3, 1.0))
    variation: float = opt(0.15, "log-albedo std of the fBm patches", rng=(0.0, 2.0))
    ejecta_boost: float = opt(0.35, "relative brightening of the freshest craters' ejecta", rng=(0.0, 5.0))
    boulder_boost: float = opt(0.25, "relative brightening of boulders", rng=(-0.9, 5.0))


@dataclass(frozen=True)
class ReliefSpec:
    """Gentle background relief: fBm of gradient noise, amplitude (lambda / 1 km)^hurst."""

    amplitude_m: float = opt(15.0, "octave amplitude at 1 km wavelength, m", rng=(0.0, 1000.0))
    hurst: float = opt(0.9, "Hurst exponent of the relief", rng=(0.0, 1.5))
    max_wavelength_m: float = opt(40000.0, "longest relief wavelength, m", rng=(1.0, 1e6))
    min_wavelength_m: float = opt(0.1, "shortest relief wavelength, m", rng=(1e-3, 1e6))


@dataclass(frozen=True)
class CraterSpec:
    """Crater population N(>D) = density * D^-exponent per m^2, D in m (simple craters)."""

    density: float = opt(0.05, "N(>1 m) per m^2", rng=(0.0, 10.0))
    exponent: float = opt(2.0, "size-frequency exponent", rng=(0.5, 5.0))
    d_min_m: float = opt(0.2, "smallest crater diameter, m", rng=(1e-3, 1e6))
    d_max_m: float = opt(5000.0, "largest crater diameter, m", rng=(1e-3, 1e6))
    depth_ratio: float = opt(0.2, "bowl depth / D of a fresh crater", rng=(0.0, 1.0))
    rim_ratio: float = opt(0.04, "rim height / D of a fresh crater", rng=(0.0, 1.0))
    freshness_min: float = opt(0.25, "degraded craters keep this fraction of depth and rim", rng=(0.0, 1.0))


@dataclass(frozen=True)
class BoulderSpec:
    """Boulder population N(>D) = density * D^-exponent per m^2, height = D / 2."""

    density: float = opt(0.0, "N(>1 m) per m^2", rng=(0.0, 10.0))
    exponent: float = opt(3.0, "size-frequency exponent", rng=(0.5, 6.0))
    d_min_m: float = opt(0.2, "smallest boulder diameter, m", rng=(1e-3, 1e3))
    d_max_m: float = opt(12.0, "largest boulder diameter, m", rng=(1e-3, 1e3))


@dataclass(frozen=True)
class SiteSpec:
    """One landing site."""

    name: str = opt("A", "site name")
    seed: int = opt(0, "terrain seed", rng=(0, 2**63 - 1))
    description: str = opt("", "one line about the site")
    sun: SunSpec = opt(None, factory=SunSpec)
    albedo: AlbedoSpec = opt(None, factory=AlbedoSpec)
    relief: ReliefSpec = opt(None, factory=ReliefSpec)
    craters: CraterSpec = opt(None, factory=CraterSpec)
    boulders: BoulderSpec = opt(None, factory=BoulderSpec)
    #: Features are generated in a square of side ``region_factor * D`` around (0, 0) per size
    #: octave (the camera only looks near the landing point), capped at ``region_max_m``.
    region_factor: float = opt(256.0, "feature region side / D per size octave", rng=(8.0, 4096.0))
    region_max_m: float = opt(120000.0, "cap of the feature region side, m", rng=(100.0, 1e7))
    #: A landing site is chosen clear: no crater of diameter >= this (m) has the landing point
    #: within 0.75 D of its centre (so the landing point is not in a shadowed bowl).
    landing_clear_d_m: float = opt(25.0, "no crater this large (m) or larger covers the landing point",
                                   rng=(0.0, 1e7))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def digest(self) -> str:
        """Stable 16-hex-digit hash of every field (cache key)."""
        text = json.dumps(self.to_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def with_sun_elevation(self, elevation_deg: Optional[float]) -> "SiteSpec":
        if elevation_deg is None:
            return self
        check_fields(SunSpec, "sun.", elevation_deg=elevation_deg)
        return dataclasses.replace(self, sun=dataclasses.replace(self.sun, elevation_deg=float(elevation_deg)))


def spec_from_dict(data: dict, source: str = "site spec") -> SiteSpec:
    """Build and validate a :class:`SiteSpec` from a nested mapping (YAML), with the same
    validation as the run configs (:func:`dvsland.config.build`: unknown keys, types, the ranges
    declared on the fields). Raises ValueError naming the parameter, the file and the range."""
    spec = build(SiteSpec, data or {}, source=source)
    for part in ("craters", "boulders"):
        sub = getattr(spec, part)
        if sub.d_max_m < sub.d_min_m:
            raise ValueError(f"{part}.d_max_m (in {source}): {sub.d_max_m} must be >= {part}.d_min_m = {sub.d_min_m}")
    return spec


def sites_dir() -> Path:
    """Folder of the site specs (``configs/sites``)."""
    return configs_dir() / "sites"


def available_sites() -> list:
    """Names of the shipped sites (A-I)."""
    return sorted(p.stem for p in sites_dir().glob("*.yaml"))


#: seed offset between consecutive variants of a site (a prime far above the shipped seeds)
VARIANT_SEED_STEP = 1_000_003


def split_site_name(name) -> tuple:
    """``"A"`` -> ("A", 0); ``"A~3"`` -> ("A", 3): site ``A``'s spec with its seed moved by
    3 * VARIANT_SEED_STEP, the same kind of terrain drawn anew (held-out terrain for training
    learned estimators). ValueError for anything else, naming the allowed forms."""
    if isinstance(name, str):
        base, sep, k = name.partition("~")
        if base in SITE_NAMES and (not sep or (k.isdigit() and 1 <= int(k) <= 10**6)):
            return base, int(k) if sep else 0
    raise ValueError(f"unknown site {name!r}: expected one of {', '.join(SITE_NAMES)}, or a variant "
                     f"'<site>~<k>' with k in [1, 1000000] (e.g. 'A~1')")


def is_site_name(name) -> bool:
    """True for a shipped site (A-I) or a variant ``<site>~<k>`` (see :func:`split_site_name`)."""
    try:
        split_site_name(name)
    except ValueError:
        return False
    return True


def load_spec(name: str) -> SiteSpec:
    """Read ``configs/sites/<name>.yaml``; ``<site>~<k>`` is variant k of a site (new seed, same
    parameters; see :func:`split_site_name`). An unknown name is a ValueError listing A-I."""
    base, variant = split_site_name(name)
    path = sites_dir() / f"{base}.yaml"
    if not path.is_file():
        raise ValueError(f"unknown site {name!r}: no spec file {path}")
    data = yaml.safe_load(path.read_text()) or {}
    data.setdefault("name", base)
    spec = spec_from_dict(data, source=str(path))
    if variant:
        spec = dataclasses.replace(spec, name=name, seed=spec.seed + variant * VARIANT_SEED_STEP,
                                   description=f"{spec.description} (variant {variant})")
    return spec
