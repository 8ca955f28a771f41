"""Build the configured controller and filter for a batch (the loop's one way in)."""

from __future__ import annotations

import dataclasses
from typing import Optional

import torch

from .efference import EfferenceFilter
from .efference_fit import EfferenceFitFilter
from .filter import MovingAverageFilter
from .params import DescentParams
from .registry import controller_class

#: Filters by name (``controller.filter``); ``auto`` picks ``efference`` for a law that needs an
#: altitude estimate, else ``moving_average`` (the paper's filter).
FILTERS = {"moving_average": MovingAverageFilter, "efference": EfferenceFilter, "efference_fit": EfferenceFitFilter}
FILTER_NAMES = ("auto",) + tuple(FILTERS)


def descent_params(cfg, layout, device="cpu") -> DescentParams:
    """The per-descent parameters of ``layout`` (a :class:`dvsland.sim.BatchLayout`) under ``cfg``."""
    f64 = torch.float64
    z0 = layout.tensor("z0_m", device, f64)
    v0 = layout.tensor("v0_mps", device, f64)
    c = cfg.controller
    return DescentParams(kp=layout.tensor("kp", device, f64), n_bin=layout.tensor("n_bin", device, torch.int64),
                         tau0_s=z0 / v0.abs(), z0_m=z0, v0_mps=v0,
                         m0_kg=torch.full_like(z0, float(cfg.dynamics.mass_kg)), c2=float(c.c2),
                         g_mps2=float(cfg.dynamics.g_mps2), dt_s=float(cfg.dt_s), thrust_min_n=float(c.thrust_min_n),
                         thrust_max_n=None if c.thrust_max_n is None else float(c.thrust_max_n),
                         missing_policy=c.missing_policy)


def controller_options(cfg, name: Optional[str] = None) -> dict:
    """Law options of controller ``name``: its config section for built-ins (``controller.div_p``,
    ``controller.div_gs``), the free-form ``controller.params`` for any other."""
    name = name or cfg.controller.name
    section = getattr(cfg.controller, name, None)
    if dataclasses.is_dataclass(section):
        options = dataclasses.asdict(section)
        if name == "policy" and options.get("base", "none") != "none":  # a residual: its base law's constants
            options["base_options"] = dataclasses.asdict(getattr(cfg.controller, options["base"]))
        return options
    return dict(cfg.controller.params)


def make_controller(cfg, params: DescentParams, name: Optional[str] = None):
    """The configured controller (``controller.name``) for the descents of ``params``."""
    name = name or cfg.controller.name
    return controller_class(name).from_params(params, **controller_options(cfg, name))


def filter_name(cfg, controller=None) -> str:
    """Resolve ``controller.filter`` (``auto`` -> efference when the law needs an altitude)."""
    name = cfg.controller.filter
    if name == "auto":
        return "efference" if getattr(controller, "needs_altitude", False) else "moving_average"
    if name not in FILTERS:
        raise ValueError(f"controller.filter must be one of {list(FILTER_NAMES)}, got {name!r}")
    return name


def make_filter(cfg, params: DescentParams, controller=None):
    """The configured divergence filter; a law that needs an altitude gets one that provides it."""
    name = filter_name(cfg, controller)
    options = dataclasses.asdict(cfg.controller.efference) if name.startswith("efference") else {}
    filt = FILTERS[name].from_params(params, **options)
    if getattr(controller, "needs_altitude", False) and not getattr(filt, "provides_altitude", False):
        raise ValueError(f"controller {cfg.controller.name!r} needs an altitude estimate; controller.filter="
                         f"{name!r} gives none: use 'efference' (or 'auto')")
    if getattr(controller, "needs_doubt", False) and not getattr(filt, "provides_doubt", False):
        raise ValueError(f"controller.policy.observation=efference_doubt needs the filter's doubt; controller.filter="
                         f"{name!r} gives none: use controller.filter=efference_fit")
    if getattr(controller, "needs_velocity_sigma", False) and not getattr(filt, "provides_velocity_sigma", False):
        raise ValueError(f"controller.div_gs.v_min_sigma > 0 needs the filter's velocity standard deviation; "
                         f"controller.filter={name!r} gives none: use efference_fit or efference")
    return filt
