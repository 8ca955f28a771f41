"""The batch layout: B = sites x controller settings x seeds, element order site-major.

Element ``b = (i_site * n_settings + i_setting) * n_seeds + i_seed``. Each element carries its
site, initial conditions, gains, filter length and its own seed (expanded from one master seed).

With ``dispersion.enabled`` each element also carries its dispersed values (drawn per site and
global seed index ``k = simulation.seed_offset + i_seed``, :mod:`dvsland.layout.dispersion`): its
scene (terrain variant, sun), initial conditions and sensor parameters. With dispersions off and
``seed_offset = 0`` the layout is the one of a plain batch (the same element seeds as always).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from dvsland.config import Config
from dvsland.config.validate import setting_label  # noqa: F401 - one definition, checked unique there

from . import dispersion as disp


def expand_seeds(master_seed: int, n: int) -> np.ndarray:
    """``n`` independent 63-bit seeds from one master seed (numpy SeedSequence), int64 (n,)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    state = np.random.SeedSequence(int(master_seed)).generate_state(n, dtype=np.uint64)
    return (state >> np.uint64(1)).astype(np.int64)


@dataclass
class BatchLayout:
    """Who is who in the batch (host-side lists, plus tensors built by :meth:`tensors`).

    Attributes:
        site_names: unique site names, in config order (the renderer's site list).
        site: (B,) site name per element.
        site_idx: (B,) int index into ``site_names``.
        setting_idx, seed_idx: (B,) int.
        label: (B,) setting label per element (``Kp5e6-n5``).
        run_label: (B,) unique run name, ``A/Kp5e6-n5`` (``/s<k>`` appended when n_seeds > 1).
        kp: (B,) float gains, N/s.  n_bin: (B,) int filter lengths.
        z0_m, v0_mps: (B,) float initial conditions.
        seed: (B,) int64 per-element seeds.
        scene: (B,) scene label per element (the site name, or ``E~2@el12`` for a dispersed scene).
        scene_names: unique scene labels (the renderer's list); scene_idx: (B,) int index into it.
        scene_site, scene_sun: per scene, the site (variant) name to load and its sun as
            ``(elevation_deg or None, azimuth_offset_deg)``.
        sensor: {name: (B,) float64} per-element emulator values (``threshold_scale``,
            ``mismatch_sigma``, ``background_rate_hz``, ``refractory_us``); only dispersed ones.
        dispersed: {name: (B,) values} of every dispersed parameter (recorded with each run).
        noise_seed: seed of the batch's emulator and estimator generators.
    """

    site_names: List[str]
    site: List[str]
    site_idx: np.ndarray
    setting_idx: np.ndarray
    seed_idx: np.ndarray
    label: List[str]
    run_label: List[str]
    kp: np.ndarray
    n_bin: np.ndarray
    z0_m: np.ndarray
    v0_mps: np.ndarray
    seed: np.ndarray
    scene: List[str] = field(default_factory=list)
    scene_names: List[str] = field(default_factory=list)
    scene_idx: Optional[np.ndarray] = None
    scene_site: List[str] = field(default_factory=list)
    scene_sun: List[Tuple[Optional[float], float]] = field(default_factory=list)
    sensor: Dict[str, np.ndarray] = field(default_factory=dict)
    dispersed: Dict[str, np.ndarray] = field(default_factory=dict)
    noise_seed: int = 0

    def __post_init__(self):
        if not self.scene:  # no dispersed scene: one scene per site, at its own sun
            self.scene = list(self.site)
            self.scene_names = list(self.site_names)
            self.scene_idx = np.asarray(self.site_idx, np.int64).copy()
            self.scene_site = list(self.site_names)
            self.scene_sun = [(None, 0.0)] * len(self.site_names)

    @property
    def scenes_dispersed(self) -> bool:
        """True when some element flies a scene other than its site's shipped one."""
        return self.scene_names != self.site_names

    @property
    def batch_size(self) -> int:
        return len(self.site)

    def tensor(self, name: str, device, dtype=None) -> torch.Tensor:
        """Attribute ``name`` as a tensor on ``device``."""
        return torch.as_tensor(getattr(self, name), dtype=dtype, device=device)


def build_layout(cfg: Config, sites: Optional[Sequence[str]] = None) -> BatchLayout:
    """Expand ``cfg`` into the batch layout.

    Args:
        cfg: the resolved config (``simulation.sites``, ``controller.settings``, ``simulation.n_seeds``,
            ``simulation.seed``).
        sites: optional subset of site names (in the config's ``simulation.sites``).

    Raises:
        ValueError: no sites / no settings, or a requested site the config does not define.
    """
    site_cfgs = list(cfg.simulation.sites)
    if not site_cfgs:
        raise ValueError("simulation.sites is empty: give at least one site with its z0_m and v0_mps")
    if sites is not None:
        sites = [s.strip() for s in sites if s and s.strip()]
        known = [s.name for s in site_cfgs]
        unknown = [s for s in sites if s not in known]
        if unknown or not sites:
            raise ValueError(f"sites must be a non-empty subset of the configured sites {known}, got {list(sites)}")
        site_cfgs = [s for s in site_cfgs if s.name in sites]
    settings = list(cfg.controller.settings)
    if not settings:
        raise ValueError("controller.settings is empty: give at least one {kp, n_bin}")
    n_seeds = int(cfg.simulation.n_seeds)
    k0 = int(getattr(cfg.simulation, "seed_offset", 0))
    site_names: List[str] = []
    for s in site_cfgs:
        if s.name not in site_names:
            site_names.append(s.name)
    rows = []
    for i, s in enumerate(site_cfgs):
        for j, st in enumerate(settings):
            lab = setting_label(st.kp, st.n_bin, st.label)
            for k in range(k0, k0 + n_seeds):
                tag = f"/s{k}" if (n_seeds > 1 or k0 > 0) else ""
                run = f"{s.name}/{lab}" + tag
                if len(site_cfgs) != len(site_names):  # the same site flown with two ICs
                    run = f"{s.name}{i}/{lab}" + tag
                rows.append((s.name, site_names.index(s.name), j, k, lab, run, st.kp, st.n_bin, s.z0_m, s.v0_mps))
    cols = list(zip(*rows))
    b = len(rows)
    dcfg = getattr(cfg, "dispersion", None)
    enabled = dcfg is not None and dcfg.enabled
    layout = BatchLayout(
        site_names=site_names, site=list(cols[0]), site_idx=np.asarray(cols[1], np.int64),
        setting_idx=np.asarray(cols[2], np.int64), seed_idx=np.asarray(cols[3], np.int64),
        label=list(cols[4]), run_label=list(cols[5]), kp=np.asarray(cols[6], np.float64),
        n_bin=np.asarray(cols[7], np.int64), z0_m=np.asarray(cols[8], np.float64),
        v0_mps=np.asarray(cols[9], np.float64), seed=np.zeros(b, np.int64),
        noise_seed=int(cfg.simulation.seed))
    if not enabled and k0 == 0:  # a plain batch: the element seeds it always had
        layout.seed = expand_seeds(cfg.simulation.seed, b)
        return layout
    # seeds keyed by (site, setting, seed index): independent of the batch and of sharding
    layout.seed = disp.element_seeds(cfg.simulation.seed, layout.site, layout.setting_idx, layout.seed_idx)
    layout.noise_seed = int(layout.seed[0])
    if enabled:
        _apply_dispersions(cfg, layout)
    return layout


def _apply_dispersions(cfg: Config, layout: BatchLayout) -> None:
    """Draw every enabled dispersion per element and write it into ``layout`` (in place)."""
    d = cfg.dispersion
    seed, sites, ks = cfg.simulation.seed, layout.site, layout.seed_idx

    def draw(name):
        vals = disp.sample_elements(getattr(d, name), name, seed, sites, ks)
        if vals is not None:
            layout.dispersed[name] = vals
        return vals

    z0s, v0s = draw("z0_scale"), draw("v0_scale")
    if z0s is not None:
        layout.z0_m = layout.z0_m * z0s
    if v0s is not None:
        layout.v0_mps = layout.v0_mps * v0s
    for name in ("threshold_scale", "mismatch_sigma", "background_rate_hz", "refractory_us"):
        vals = draw(name)
        if vals is not None:
            layout.sensor[name] = vals
    # scene: terrain variant, sun elevation and azimuth offset (rounded to sun_step_deg)
    n_var = int(d.terrain_variants)
    variant = np.asarray(ks, np.int64) % n_var if n_var > 1 else np.zeros(len(sites), np.int64)
    if n_var > 1:
        layout.dispersed["terrain_variant"] = variant
    step = float(d.sun_step_deg)
    el, az = draw("sun_elevation_deg"), draw("sun_azimuth_offset_deg")
    if el is not None:
        el = np.clip(np.round(el / step) * step, 1.0, 90.0)
        layout.dispersed["sun_elevation_deg"] = el
    if az is not None:
        az = np.round(az / step) * step
        layout.dispersed["sun_azimuth_offset_deg"] = az
    if n_var <= 1 and el is None and az is None:
        return
    scene, names, site_of, sun_of = [], [], [], []
    for b, s in enumerate(sites):
        site_name = s if variant[b] == 0 else f"{s}~{int(variant[b])}"
        e = None if el is None else float(el[b])
        a = 0.0 if az is None else float(az[b])
        lab = scene_label(site_name, e, a)
        scene.append(lab)
        if lab not in names:
            names.append(lab)
            site_of.append(site_name)
            sun_of.append((e, a))
    layout.scene, layout.scene_names, layout.scene_site, layout.scene_sun = scene, names, site_of, sun_of
    layout.scene_idx = np.asarray([names.index(x) for x in scene], np.int64)


def scene_label(site_name: str, elevation_deg: Optional[float], azimuth_offset_deg: float) -> str:
    """``E~2``, ``E~2@el12`` or ``E~2@el12@az+5``: a site (variant) under a dispersed sun."""
    lab = site_name
    if elevation_deg is not None:
        lab += f"@el{elevation_deg:g}"
    if azimuth_offset_deg:
        lab += f"@az{azimuth_offset_deg:+g}"
    return lab
