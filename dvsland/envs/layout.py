"""The batch of a :class:`~dvsland.envs.LandingVectorEnv`: B descents chosen from a config."""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Sequence

import numpy as np

from dvsland.layout import BatchLayout, build_layout

#: the per-element fields of a BatchLayout (lists or (B,) arrays)
_ELEMENT_FIELDS = ("site", "site_idx", "setting_idx", "seed_idx", "label", "run_label", "kp", "n_bin", "z0_m",
                   "v0_mps", "seed", "scene", "scene_idx")


def fit_layout(cfg, sites: Optional[Sequence[str]], num_envs: Optional[int]) -> BatchLayout:
    """The layout of ``cfg`` (``sites`` subset) with ``num_envs`` elements.

    None, or the layout's own size: the config's layout as :func:`dvsland.layout.build_layout`
    gives it (the batch :func:`dvsland.simulate` flies). Otherwise ``simulation.n_seeds`` becomes
    ceil(num_envs / (sites x settings)) (``cfg`` is changed) and the first ``num_envs`` elements in
    seed-major order are kept (seed 0 of every site and setting, then seed 1, ...), in layout order.
    """
    layout = build_layout(cfg, sites)
    if num_envs is None or num_envs == layout.batch_size:
        return layout
    per_seed = layout.batch_size // int(cfg.simulation.n_seeds)
    cfg.simulation.n_seeds = int(math.ceil(num_envs / per_seed))
    layout = build_layout(cfg, sites)
    order = sorted(range(layout.batch_size), key=lambda b: (int(layout.seed_idx[b]), b))
    return subset_layout(layout, sorted(order[:num_envs]))


def subset_layout(layout: BatchLayout, idx: Sequence[int]) -> BatchLayout:
    """The elements ``idx`` of ``layout`` (its site and scene lists unchanged)."""
    idx = [int(i) for i in idx]

    def pick(v):
        return [v[i] for i in idx] if isinstance(v, list) else np.asarray(v)[idx]

    fields = {k: pick(getattr(layout, k)) for k in _ELEMENT_FIELDS}
    fields["sensor"] = {k: pick(v) for k, v in layout.sensor.items()}
    fields["dispersed"] = {k: pick(v) for k, v in layout.dispersed.items()}
    return dataclasses.replace(layout, **fields)
