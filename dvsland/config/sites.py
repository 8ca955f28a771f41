"""Cut a config to some of its sites (``--sites`` of simulate, campaign, evaluate and bench).

The names themselves (A-I, variants ``<site>~<k>``) are parsed by the command line
(:func:`dvsland.cli.common.parse_sites`); here they are checked against ``simulation.sites``.
"""

from __future__ import annotations

from typing import Optional, Sequence

from .schema import Config


def check_configured_sites(cfg: Config, sites: Optional[Sequence[str]], param: str = "--sites") -> None:
    """Commands that fly the config's descents (simulate, campaign, evaluate, bench) take only sites
    of ``simulation.sites``; ValueError naming ``param``, the site and the configured ones."""
    if sites is None:
        return
    known = list(dict.fromkeys(s.name for s in cfg.simulation.sites))
    for n in sites:
        if n not in known:
            why = (" (a terrain variant: render and events take variants; campaigns fly them through "
                   "dispersion.terrain_variants)" if "~" in n else "")
            raise ValueError(f"{param}: site {n!r} is not in the config's simulation.sites {known}{why}")


def restrict_sites(cfg: Config, sites: Optional[Sequence[str]], param: str = "--sites") -> Config:
    """``cfg`` with ``simulation.sites`` cut to ``sites`` (in the config's order), after
    :func:`check_configured_sites`; ``cfg`` unchanged for None."""
    if sites is None:
        return cfg
    check_configured_sites(cfg, sites, param)
    cfg.simulation.sites = [s for s in cfg.simulation.sites if s.name in set(sites)]
    return cfg
