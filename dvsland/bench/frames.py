"""Frames for the event benchmarks: the fast renderer along the oracle descent of every site.

They need the renderer and the closed-form descent, so they sit here, above the stages, and not
in :mod:`dvsland.events.benchmark` (which times the emulator on any frames it is given).
"""

from __future__ import annotations

import torch

from dvsland.config import PAPER_INITIAL_CONDITIONS, SITE_NAMES, CameraConfig
from dvsland.dynamics import closed_form_state, closed_form_time_to_altitude
from dvsland.events.benchmark import DT_US
from dvsland.render import get_renderer


def descent_frames(B: int, n: int, camera=None, sites=None) -> torch.Tensor:
    """Fast-renderer frames along the oracle descent, (n, B, H, W) float32: sites A-I cycled over
    the batch, element b started at fraction b / B of its descent."""
    camera = camera or CameraConfig()
    names = list(sites or SITE_NAMES)
    r = get_renderer("fast", names, camera)
    site_idx = torch.arange(B) % len(names)
    c2 = 0.5
    ics = [PAPER_INITIAL_CONDITIONS[names[i].split("~")[0]] for i in site_idx.tolist()]
    t_end = torch.tensor([closed_form_time_to_altitude(50.0, z0, v0, c2) for z0, v0 in ics])  # time to 50 m
    t_start = (torch.arange(B, dtype=torch.float64) / B) * (t_end - n * DT_US * 1e-6).clamp(min=0)
    out = []
    for k in range(n):
        t = (t_start + k * DT_US * 1e-6).tolist()
        z = torch.tensor([float(closed_form_state(tb, z0, v0, c2)[0]) for tb, (z0, v0) in zip(t, ics)])
        out.append(r.render(z.float(), site_idx))
    return torch.stack(out)


__all__ = ["descent_frames"]
