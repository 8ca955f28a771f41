"""The batch layout: B = sites x controller settings x seeds, element order site-major.

Element ``b = (i_site * n_settings + i_setting) * n_seeds + i_seed``. Each element carries its
site, initial conditions, gains, filter length and its own seed (expanded from one master seed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence

import numpy as np
import torch

from dvsland.config import Config
from dvsland.config.validate import setting_label  # noqa: F401 - one definition, checked unique there


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
    site_names: List[str] = []
    for s in site_cfgs:
        if s.name not in site_names:
            site_names.append(s.name)
    rows = []
    for i, s in enumerate(site_cfgs):
        for j, st in enumerate(settings):
            lab = setting_label(st.kp, st.n_bin, st.label)
            for k in range(n_seeds):
                run = f"{s.name}/{lab}" + (f"/s{k}" if n_seeds > 1 else "")
                if len(site_cfgs) != len(site_names):  # the same site flown with two ICs
                    run = f"{s.name}{i}/{lab}" + (f"/s{k}" if n_seeds > 1 else "")
                rows.append((s.name, site_names.index(s.name), j, k, lab, run, st.kp, st.n_bin, s.z0_m, s.v0_mps))
    cols = list(zip(*rows))
    b = len(rows)
    return BatchLayout(
        site_names=site_names, site=list(cols[0]), site_idx=np.asarray(cols[1], np.int64),
        setting_idx=np.asarray(cols[2], np.int64), seed_idx=np.asarray(cols[3], np.int64),
        label=list(cols[4]), run_label=list(cols[5]), kp=np.asarray(cols[6], np.float64),
        n_bin=np.asarray(cols[7], np.int64), z0_m=np.asarray(cols[8], np.float64),
        v0_mps=np.asarray(cols[9], np.float64), seed=expand_seeds(cfg.simulation.seed, b))
