"""The evaluation's flights: estimator specs with their variant configs, and the flight config.

Shared by the descents (:mod:`.run`), the hard scenarios (:mod:`.scenario_run`) and recordings.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Sequence

from dvsland.config import Config, build, config_to_dict
from dvsland.config.validate import check_config


def _parse_value(text: str):
    import yaml

    return yaml.safe_load(text)


def parse_estimator_spec(spec) -> tuple:
    """``"dpr"`` -> ("dpr", "dpr", {}); ``"cmax[window_ms=500;n_grid=21]"`` -> (label, "cmax",
    {"window_ms": 500, "n_grid": 21}) with the whole text as label; a tuple (label, name, dict)
    passes through. Values are parsed as YAML scalars; :func:`variant_config` applies them as
    ``--set estimator.cmax.window_ms=500`` would (one override syntax, one validation)."""
    if isinstance(spec, (tuple, list)):
        label, name, over = spec
        return str(label), str(name), dict(over)
    spec = str(spec).strip()
    if "[" not in spec:
        return spec, spec, {}
    if not spec.endswith("]"):
        raise ValueError(f"estimator spec {spec!r}: expected NAME or NAME[key=value;key=value]")
    name, body = spec[:-1].split("[", 1)
    over = {}
    for item in filter(None, (x.strip() for x in body.split(";"))):
        if "=" not in item:
            raise ValueError(f"estimator spec {spec!r}: {item!r} is not key=value")
        k, v = item.split("=", 1)
        over[k.strip()] = _parse_value(v.strip())
    return spec, name.strip(), over


def variant_config(cfg: Config, name: str, overrides: dict, label: str = "") -> Config:
    """``cfg`` with estimator ``name``'s parameters updated by ``overrides``, validated as
    ``--set estimator.<name>.<key>=<value>`` would be (typed by the schema's field, range-checked,
    unknown keys rejected with the allowed ones); an estimator without a config section takes
    them in ``estimator.params``."""
    if not overrides:
        return cfg
    section = name if dataclasses.is_dataclass(getattr(cfg.estimator, name, None)) else "params"
    data = config_to_dict(cfg)
    data["estimator"][section].update(overrides)
    source = f"estimator spec {label or name}"
    return check_config(build(Config, data, source=source), source=source)


def flight_config(cfg: Config, sites: Sequence[str], n_steps: int) -> Config:
    """A copy of ``cfg`` that flies one element per site, in the order of ``sites``, for ``n_steps``
    (+2) steps: the first controller setting, one seed, no dispersion, and no end but the success
    altitude (the evaluation descents end there; ``crash_divergence`` and ``t_max_s`` are lifted)."""
    fc = copy.deepcopy(cfg)
    specs = {s.name: s for s in fc.simulation.sites}
    fc.simulation.sites = [specs[n] for n in sites]
    fc.controller.settings = list(fc.controller.settings)[:1]
    fc.simulation.n_seeds = 1
    if hasattr(fc.simulation, "seed_offset"):
        fc.simulation.seed_offset = 0
    if getattr(fc, "dispersion", None) is not None:
        fc.dispersion.enabled = False
    fc.simulation.crash_divergence = 1e3
    fc.simulation.t_max_s = max(float(fc.simulation.t_max_s), (int(n_steps) + 2) * float(fc.dt_s))
    return fc


__all__ = ["parse_estimator_spec", "variant_config", "flight_config"]
