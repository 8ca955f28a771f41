"""Site specifications: the seeded recipe of one landing site (``configs/sites/<name>.yaml``).

A spec holds every number that shapes a site (sun, albedo, background relief, crater and
boulder populations). :func:`load_spec` reads and validates one; :meth:`SiteSpec.digest` is a
stable hash used as a cache key for prepared render levels.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import yaml

from dvsland.config import SITE_NAMES, configs_dir


@dataclass(frozen=True)
class SunSpec:
    """Sun position. ``azimuth_deg``: compass azimuth TO the sun, clockwise from north (y)."""

    elevation_deg: float = 15.0
    azimuth_deg: float = 90.0


@dataclass(frozen=True)
class AlbedoSpec:
    """Normal albedo: ``mean`` x exp(``variation`` x fBm) x crater/boulder factors."""

    mean: float = 0.12
    variation: float = 0.15          # log-albedo std of the fBm patches
    ejecta_boost: float = 0.35        # relative brightening of the freshest craters' ejecta
    boulder_boost: float = 0.25       # relative brightening of boulders


@dataclass(frozen=True)
class ReliefSpec:
    """Gentle background relief: fBm of gradient noise, amplitude (lambda / 1 km)^hurst."""

    amplitude_m: float = 15.0         # octave amplitude at 1 km wavelength, m
    hurst: float = 0.9
    max_wavelength_m: float = 40000.0
    min_wavelength_m: float = 0.1


@dataclass(frozen=True)
class CraterSpec:
    """Crater population N(>D) = density * D^-exponent per m^2, D in m (simple craters)."""

    density: float = 0.05
    exponent: float = 2.0
    d_min_m: float = 0.2
    d_max_m: float = 5000.0
    depth_ratio: float = 0.2          # bowl depth / D of a fresh crater
    rim_ratio: float = 0.04           # rim height / D of a fresh crater
    freshness_min: float = 0.25       # degraded craters keep this fraction of depth and rim


@dataclass(frozen=True)
class BoulderSpec:
    """Boulder population N(>D) = density * D^-exponent per m^2, height = D / 2."""

    density: float = 0.0
    exponent: float = 3.0
    d_min_m: float = 0.2
    d_max_m: float = 12.0


@dataclass(frozen=True)
class SiteSpec:
    """One landing site."""

    name: str = "A"
    seed: int = 0
    description: str = ""
    sun: SunSpec = field(default_factory=SunSpec)
    albedo: AlbedoSpec = field(default_factory=AlbedoSpec)
    relief: ReliefSpec = field(default_factory=ReliefSpec)
    craters: CraterSpec = field(default_factory=CraterSpec)
    boulders: BoulderSpec = field(default_factory=BoulderSpec)
    #: Features are generated in a square of side ``region_factor * D`` around (0, 0) per size
    #: octave (the camera only looks near the landing point), capped at ``region_max_m``.
    region_factor: float = 256.0
    region_max_m: float = 120000.0
    #: A landing site is chosen clear: no crater of diameter >= this (m) has the landing point
    #: within 0.75 D of its centre (so the landing point is not in a shadowed bowl).
    landing_clear_d_m: float = 25.0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def digest(self) -> str:
        """Stable 16-hex-digit hash of every field (cache key)."""
        text = json.dumps(self.to_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def with_sun_elevation(self, elevation_deg: Optional[float]) -> "SiteSpec":
        if elevation_deg is None:
            return self
        _check("sun.elevation_deg", elevation_deg, 1.0, 90.0)
        return dataclasses.replace(self, sun=dataclasses.replace(self.sun, elevation_deg=float(elevation_deg)))


_RANGES = {
    "sun.elevation_deg": (1.0, 90.0), "sun.azimuth_deg": (-360.0, 360.0),
    "albedo.mean": (1e-3, 1.0), "albedo.variation": (0.0, 2.0), "albedo.ejecta_boost": (0.0, 5.0),
    "albedo.boulder_boost": (-0.9, 5.0),
    "relief.amplitude_m": (0.0, 1000.0), "relief.hurst": (0.0, 1.5),
    "relief.max_wavelength_m": (1.0, 1e6), "relief.min_wavelength_m": (1e-3, 1e6),
    "craters.density": (0.0, 10.0), "craters.exponent": (0.5, 5.0), "craters.d_min_m": (1e-3, 1e6),
    "craters.d_max_m": (1e-3, 1e6), "craters.depth_ratio": (0.0, 1.0), "craters.rim_ratio": (0.0, 1.0),
    "craters.freshness_min": (0.0, 1.0),
    "boulders.density": (0.0, 10.0), "boulders.exponent": (0.5, 6.0), "boulders.d_min_m": (1e-3, 1e3),
    "boulders.d_max_m": (1e-3, 1e3),
    "region_factor": (8.0, 4096.0), "landing_clear_d_m": (0.0, 1e7), "region_max_m": (100.0, 1e7), "seed": (0, 2**63 - 1),
}


def _check(name: str, value, lo, hi) -> None:
    if not (lo <= value <= hi):
        raise ValueError(f"site spec: {name} = {value} is out of range [{lo}, {hi}]")


def spec_from_dict(data: dict, source: str = "site spec") -> SiteSpec:
    """Build and validate a :class:`SiteSpec` from a nested mapping (YAML)."""
    sub = {"sun": SunSpec, "albedo": AlbedoSpec, "relief": ReliefSpec, "craters": CraterSpec,
           "boulders": BoulderSpec}
    kwargs = {}
    known = {f.name for f in dataclasses.fields(SiteSpec)}
    for key, value in (data or {}).items():
        if key not in known:
            raise ValueError(f"{source}: unknown key '{key}'; known keys: {sorted(known)}")
        if key in sub:
            cls = sub[key]
            names = {f.name for f in dataclasses.fields(cls)}
            bad = set(value or {}) - names
            if bad:
                raise ValueError(f"{source}: unknown key(s) {sorted(bad)} in '{key}'; known: {sorted(names)}")
            kwargs[key] = cls(**{k: float(v) for k, v in (value or {}).items()})
        elif key == "seed":
            kwargs[key] = int(value)
        elif key in ("name", "description"):
            kwargs[key] = str(value)
        else:
            kwargs[key] = float(value)
    spec = SiteSpec(**kwargs)
    flat = spec.to_dict()
    for dotted, (lo, hi) in _RANGES.items():
        node = flat
        for k in dotted.split("."):
            node = node[k]
        _check(dotted, node, lo, hi)
    if spec.craters.d_max_m < spec.craters.d_min_m:
        raise ValueError(f"{source}: craters.d_max_m must be >= craters.d_min_m")
    if spec.boulders.d_max_m < spec.boulders.d_min_m:
        raise ValueError(f"{source}: boulders.d_max_m must be >= boulders.d_min_m")
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
