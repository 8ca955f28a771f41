"""A campaign's plan: the grid of swept values x the seeds, split into shards (one batch each).

A shard is one grid point (one value per swept key) and a contiguous range of seed indices
``[seed_offset, seed_offset + n_seeds)``; it flies every configured site x controller setting for
those seeds as one batch. Seed indices are global, so a shard draws the same dispersions whatever
the shard size, and a resumed campaign re-runs exactly the shards that are missing.
"""

from __future__ import annotations

import itertools
import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

from dvsland.config import Config, ConfigError, apply_overrides, build, config_to_dict
from dvsland.config.validate import check_config

PLAN_FILE = "campaign.json"


def parse_sweep(text: str) -> Tuple[str, List[str]]:
    """``"controller.thrust_max_n=8e4,1e5"`` -> ("controller.thrust_max_n", ["8e4", "1e5"]).

    ValueError naming the argument when it has no ``=`` or no value."""
    if "=" not in text:
        raise ValueError(f"--sweep {text!r}: expected key=v1,v2,... (e.g. estimator.name=dpr,oracle)")
    key, raw = text.split("=", 1)
    key = key.strip()
    values = [v.strip() for v in raw.split(",") if v.strip()]
    if not key or not values:
        raise ValueError(f"--sweep {text!r}: expected key=v1,v2,... with at least one value")
    return key, values


@dataclass
class Shard:
    """One batch of the campaign: ``id`` (file name), the grid point ``sweep`` {key: value text},
    and seeds ``seed_offset .. seed_offset + n_seeds - 1``."""

    id: str
    index: int
    sweep: Dict[str, str]
    seed_offset: int
    n_seeds: int

    def overrides(self) -> List[str]:
        """``--set`` strings that turn the campaign config into this shard's config."""
        return [f"{k}={v}" for k, v in self.sweep.items()] + [
            f"simulation.seed_offset={self.seed_offset}", f"simulation.n_seeds={self.n_seeds}",
            "logging.quiet=true", "logging.tensorboard=false", "logging.figures=false"]


@dataclass
class CampaignPlan:
    """The whole campaign: the base config (a plain dict), the sweeps, the seeds and the shards."""

    config: dict
    sweeps: Dict[str, List[str]]
    n_seeds: int
    shard_seeds: int
    shards: List[Shard] = field(default_factory=list)

    def shard_config(self, shard: Shard) -> Config:
        """The validated config of one shard."""
        return config_from_dict(self.config, shard.overrides())

    def to_json(self) -> dict:
        return {"config": self.config, "sweeps": self.sweeps, "n_seeds": self.n_seeds,
                "shard_seeds": self.shard_seeds, "shards": [asdict(s) for s in self.shards]}

    @classmethod
    def from_json(cls, d: dict) -> "CampaignPlan":
        return cls(config=d["config"], sweeps={k: list(v) for k, v in d["sweeps"].items()},
                   n_seeds=int(d["n_seeds"]), shard_seeds=int(d["shard_seeds"]),
                   shards=[Shard(**s) for s in d["shards"]])

    def save(self, folder) -> Path:
        """Write ``campaign.json`` into ``folder`` atomically."""
        path = Path(folder) / PLAN_FILE
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1))
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, folder) -> "CampaignPlan":
        path = Path(folder) / PLAN_FILE
        if not path.is_file():
            raise ValueError(f"--resume {folder}: no {PLAN_FILE} there (not a campaign folder)")
        return cls.from_json(json.loads(path.read_text()))


def config_from_dict(data: dict, overrides: Sequence[str] = ()) -> Config:
    """Build and validate a Config from a plain dict plus ``--set`` overrides."""
    d = apply_overrides(data, overrides)
    source = "campaign config" + (" with overrides" if overrides else "")
    return check_config(build(Config, d, source=source), source=source)


def make_plan(cfg: Config, sweeps: Sequence[str] = (), n_seeds: int = None, shard_seeds: int = 5) -> CampaignPlan:
    """Plan a campaign of ``cfg`` over the cartesian product of ``sweeps`` (``key=v1,v2`` strings)
    and ``n_seeds`` seeds (default ``simulation.n_seeds``), ``shard_seeds`` seeds per shard.

    Every grid point's config is validated here, so a bad swept value fails before any work."""
    n_seeds = int(cfg.simulation.n_seeds if n_seeds is None else n_seeds)
    if n_seeds < 1:
        raise ValueError(f"n_seeds must be >= 1, got {n_seeds}")
    if shard_seeds < 1:
        raise ValueError(f"shard_seeds must be >= 1, got {shard_seeds}")
    sw: Dict[str, List[str]] = {}
    for text in sweeps:
        k, vals = parse_sweep(text)
        if k in sw:
            raise ValueError(f"--sweep {k} given twice")
        if k.startswith(("simulation.seed_offset", "simulation.n_seeds")):
            raise ValueError(f"--sweep {k}: the campaign sets the seeds; use --n-seeds")
        sw[k] = vals
    first = int(cfg.simulation.seed_offset)  # --set simulation.seed_offset=K: seeds K .. K + n_seeds - 1
    base = config_to_dict(cfg)
    base["simulation"]["n_seeds"] = 1
    base["simulation"]["seed_offset"] = 0
    plan = CampaignPlan(config=base, sweeps=sw, n_seeds=n_seeds, shard_seeds=int(shard_seeds))
    keys = list(sw)
    for g, values in enumerate(itertools.product(*(sw[k] for k in keys)) if keys else [()]):
        point = dict(zip(keys, values))
        try:
            from dvsland.stages import check_names

            check_names(config_from_dict(base, [f"{k}={v}" for k, v in point.items()]))
        except ConfigError as exc:
            raise ValueError(f"--sweep {point}: {exc}") from None
        for k0 in range(first, first + n_seeds, shard_seeds):
            n = min(shard_seeds, first + n_seeds - k0)
            idx = len(plan.shards)
            plan.shards.append(Shard(id=f"g{g:03d}-s{k0:05d}", index=idx, sweep=point, seed_offset=k0, n_seeds=n))
    return plan
