"""A campaign's plan: the grid of swept values x the seeds, split into shards (one batch each).

A shard is one grid point (one value per swept key) and a contiguous range of seed indices
``[seed_offset, seed_offset + n_seeds)``; it flies every configured site x controller setting for
those seeds as one batch. Seed indices are global, so a shard draws the same dispersions whatever
the shard size, and a resumed campaign re-runs exactly the shards that are missing.

Limits: a plan holds at most :data:`MAX_SHARDS` shards (``campaign.json``, the merge and the report
hold every one) and :data:`MAX_GRID_POINTS` grid points, checked by arithmetic before anything is
built; each grid point's first shard must fit :func:`dvsland.config.validate.check_memory`. Each shard result carries
:func:`shard_hash` of what it flew, so a resumed campaign never merges a shard of another config.
A damaged ``campaign.json`` is one ValueError naming the file and the field.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

from dvsland.config import Config, ConfigError, apply_overrides, build, config_to_dict
from dvsland.config.schema import SimulationConfig
from dvsland.config.validate import check_config

PLAN_FILE = "campaign.json"
#: the most shards one campaign may plan: campaign.json (~250 B per shard, 25 MB at the limit),
#: the merge and the report hold every shard
MAX_SHARDS = 100_000
#: the most grid points (combinations of swept values): each is validated before the plan is saved
#: (about 25 ms each: 4 minutes at the limit, Ctrl-C stops it at once)
MAX_GRID_POINTS = 10_000
#: the most seeds one shard (one batch) may fly: the range of ``simulation.n_seeds``
MAX_SHARD_SEEDS = int(SimulationConfig.__dataclass_fields__["n_seeds"].metadata["rng"][1])
#: the fields of campaign.json and what each must be
PLAN_FIELDS = {"config": (dict, "a mapping (the base config)"), "sweeps": (dict, "a mapping {key: [values]}"),
               "n_seeds": (int, "an integer >= 1"), "shard_seeds": (int, "an integer >= 1"),
               "shards": (list, "a list of shards")}
SHARD_FIELDS = {"id": str, "index": int, "sweep": dict, "seed_offset": int, "n_seeds": int}


def config_digest(plan_config: dict) -> str:
    """sha256 of a campaign's base config (canonical JSON)."""
    return hashlib.sha256(json.dumps(plan_config, sort_keys=True, default=str).encode()).hexdigest()


def shard_hash(plan_config_or_digest, shard: dict) -> str:
    """16 hex digits naming what a shard flies: the base config (or its :func:`config_digest`),
    the grid point and the seeds. Stored in each shard file and compared on resume."""
    digest = (plan_config_or_digest if isinstance(plan_config_or_digest, str)
              else config_digest(plan_config_or_digest))
    key = json.dumps([digest, shard["sweep"], shard["seed_offset"], shard["n_seeds"]], sort_keys=True)
    return hashlib.sha256(key.encode()).hexdigest()[:16]


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
        """Write ``campaign.json`` into ``folder`` atomically (RunWriteError names a failed path)."""
        from dvsland.report.results import atomic_write_text

        return atomic_write_text(Path(folder) / PLAN_FILE, json.dumps(self.to_json(), indent=1))

    @classmethod
    def load(cls, folder) -> "CampaignPlan":
        """Read and check ``folder/campaign.json``: a missing, empty, truncated or damaged file, or a
        base config or grid point that does not validate, is one ValueError naming the file and
        the field."""
        path = Path(folder) / PLAN_FILE
        if not path.is_file():
            raise ValueError(f"--resume {folder}: no {PLAN_FILE} there (not a campaign folder)")
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            reason = getattr(exc, "strerror", None) or exc
            raise ValueError(f"--resume {folder}: cannot read {path}: {reason}") from None
        plan = cls.from_json(_parse_plan(text, path))
        for point in plan.grid_points():
            check_grid_point(plan.config, point, f"{path} field 'config'" + (f" with sweep {point}" if point else ""))
        return plan

    def grid_points(self) -> List[Dict[str, str]]:
        """The distinct grid points of the shards, in plan order."""
        seen = {}
        for sh in self.shards:
            seen.setdefault(json.dumps(sh.sweep, sort_keys=True), sh.sweep)
        return list(seen.values())


def _plan_damaged(path, field: str, expected: str, got) -> ValueError:
    text = repr(got)
    text = text if len(text) <= 80 else text[:77] + "..."
    return ValueError(f"{path}: field '{field}': expected {expected}, got {text}; the campaign plan is damaged: "
                      f"restore it or start a new campaign (the shard files in shards/ are kept)")


def _parse_plan(text: str, path) -> dict:
    """campaign.json text -> a dict whose fields have the right types (ValueError naming the field)."""
    expected = "a JSON object with the fields " + ", ".join(PLAN_FIELDS)
    if not text.strip():
        raise ValueError(f"{path}: the file is empty; expected {expected} (the campaign plan is damaged: restore it "
                         f"or start a new campaign; the shard files in shards/ are kept)")
    try:
        d = json.loads(text)
    except ValueError as exc:
        pos = getattr(exc, "pos", len(text))
        keys = re.findall(r'\n "([^"]+)":', text[:pos])
        where = f"field '{keys[-1]}'" if keys else "the top level"
        raise ValueError(f"{path}: not valid JSON in {where} ({exc}): the file is truncated or overwritten; "
                         f"expected {expected} (restore it or start a new campaign; the shard files in shards/ "
                         f"are kept)") from None
    if not isinstance(d, dict):
        raise _plan_damaged(path, "(top level)", expected, d)
    for key, (tp, what) in PLAN_FIELDS.items():
        v = d.get(key, _MISSING)
        if v is _MISSING or not isinstance(v, tp) or isinstance(v, bool) or (tp is int and v < 1):
            raise _plan_damaged(path, key, what, "nothing (missing)" if v is _MISSING else v)
    for k, vals in d["sweeps"].items():
        if not isinstance(vals, list) or not vals or not all(isinstance(v, str) for v in vals):
            raise _plan_damaged(path, f"sweeps.{k}", "a non-empty list of value strings", vals)
    if not d["shards"] or len(d["shards"]) > MAX_SHARDS:
        raise _plan_damaged(path, "shards", f"1 to {MAX_SHARDS} shards", f"{len(d['shards'])} shards")
    ids = set()
    for i, sh in enumerate(d["shards"]):
        _check_shard_entry(sh, i, path)
        if sh["id"] in ids:
            raise _plan_damaged(path, f"shards[{i}].id", "an id used once", sh["id"])
        ids.add(sh["id"])
    return d


_MISSING = object()


def _check_shard_entry(sh, i: int, path) -> None:
    if not isinstance(sh, dict):
        raise _plan_damaged(path, f"shards[{i}]", "an object with the fields " + ", ".join(SHARD_FIELDS), sh)
    for key, tp in SHARD_FIELDS.items():
        v = sh.get(key, _MISSING)
        if v is _MISSING or not isinstance(v, tp) or isinstance(v, bool):
            got = "nothing (missing)" if v is _MISSING else v
            raise _plan_damaged(path, f"shards[{i}].{key}", f"a {tp.__name__}", got)
    if not re.fullmatch(r"[A-Za-z0-9_.+-]{1,100}", sh["id"]) or sh["id"].startswith("."):
        raise _plan_damaged(path, f"shards[{i}].id", "a plain file name ([A-Za-z0-9_.+-], 1-100 characters)", sh["id"])
    if sh["seed_offset"] < 0 or not 1 <= sh["n_seeds"] <= MAX_SHARD_SEEDS:
        raise _plan_damaged(path, f"shards[{i}]", f"seed_offset >= 0 and n_seeds in [1, {MAX_SHARD_SEEDS}]",
                            {"seed_offset": sh["seed_offset"], "n_seeds": sh["n_seeds"]})
    if sorted(sh) != sorted(SHARD_FIELDS):
        raise _plan_damaged(path, f"shards[{i}]", "exactly the fields " + ", ".join(SHARD_FIELDS), sorted(sh))


def config_from_dict(data: dict, overrides: Sequence[str] = (), source: str = "") -> Config:
    """Build and validate a Config from a plain dict plus ``--set`` overrides (errors name ``source``)."""
    d = apply_overrides(data, overrides)
    source = source or "campaign config" + (" with overrides" if overrides else "")
    return check_config(build(Config, d, source=source), source=source)


def check_grid_point(base: dict, point: Dict[str, str], source: str, shard_seeds: int = 0) -> Config:
    """Validate the config of one grid point (and, with ``shard_seeds``, that a shard of that
    many seeds fits :func:`dvsland.config.validate.check_memory`); returns it.

    Raises:
        ValueError: naming the swept point and the parameter (a ConfigError inside)."""
    from dvsland.stages import check_names

    try:
        cfg = config_from_dict(base, [f"{k}={v}" for k, v in point.items()], source)
        check_names(cfg)
        if shard_seeds:
            _check_shard_memory(cfg, shard_seeds, source)
    except ConfigError as exc:
        raise ValueError(f"--sweep {point}: {exc}" if point else str(exc)) from None
    return cfg


def _check_shard_memory(cfg: Config, shard_seeds: int, source: str) -> None:
    from dvsland.config.validate import check_memory
    from dvsland.layout import build_layout

    cfg.simulation.n_seeds = int(shard_seeds)
    layout = build_layout(cfg)
    check_memory(cfg, len(layout.scene_names), layout.batch_size, source=source)


def shard_bytes(cfg: Config, shard_seeds: int) -> float:
    """Estimated peak memory of one shard of ``shard_seeds`` seeds of ``cfg``, bytes
    (:func:`dvsland.config.validate.estimate_run_bytes` on the shard's layout: its scenes and B)."""
    import copy

    from dvsland.config.validate import estimate_run_bytes
    from dvsland.layout import build_layout

    c = copy.deepcopy(cfg)
    c.simulation.n_seeds = int(shard_seeds)
    layout = build_layout(c)
    return estimate_run_bytes(c, len(layout.scene_names), layout.batch_size)


def available_memory_bytes() -> float:
    """Memory the system can give a new process now (``MemAvailable`` of /proc/meminfo), bytes;
    inf where that cannot be read (not Linux)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return math.inf


def auto_shard_seeds(cfg: Config, n_seeds: int, workers: int = 1) -> int:
    """Seeds per shard chosen from the memory estimate: the most seeds (at most
    ``ceil(n_seeds / workers)``, so that every worker gets a shard, and at most
    :data:`MAX_SHARD_SEEDS`) whose shard fits ``simulation.max_memory_gb`` divided among the
    ``workers`` processes that hold a shard each. At the default ``max_memory_gb = 0`` the budget
    is 80 % of the memory available now (:func:`available_memory_bytes`), at most 80 % of the
    machine's: other processes on a shared machine keep theirs (on this 23 GB machine two workers
    took 14-seed shards of 4-6 GB each while other jobs held 9 GB, and the system killed one). Finished
    descents cost almost nothing (``simulation.compact``), so one large shard per worker wastes
    little on the descents that end first. 1 when not even one seed fits (the plan's memory check
    then names the parts).

    Raises:
        ValueError: ``n_seeds`` or ``workers`` < 1.
    """
    from dvsland.config.validate import memory_limit_bytes

    if int(n_seeds) < 1 or int(workers) < 1:
        raise ValueError(f"n_seeds and workers must be >= 1, got {n_seeds} and {workers}")
    budget = memory_limit_bytes(cfg)
    if not float(getattr(cfg.simulation, "max_memory_gb", 0.0) or 0.0):  # the default: what is free now
        budget = min(budget, 0.8 * available_memory_bytes())
    budget /= int(workers)
    lo, hi = 1, min(MAX_SHARD_SEEDS, math.ceil(int(n_seeds) / int(workers)))
    if shard_bytes(cfg, hi) <= budget:
        return hi
    while lo < hi:  # largest s in [lo, hi) that fits; the estimate grows with s
        mid = (lo + hi + 1) // 2
        if shard_bytes(cfg, mid) <= budget:
            lo = mid
        else:
            hi = mid - 1
    return lo


def check_plan_size(n_seeds: int, shard_seeds: int, n_points: int) -> int:
    """The number of shards of ``n_points`` grid points x ``n_seeds`` seeds in shards of
    ``shard_seeds``; ValueError (up front, by arithmetic) beyond :data:`MAX_SHARDS`."""
    if not 1 <= n_seeds:
        raise ValueError(f"--n-seeds must be >= 1, got {n_seeds}")
    if not 1 <= shard_seeds <= MAX_SHARD_SEEDS:
        raise ValueError(f"--shard-seeds must be in [1, {MAX_SHARD_SEEDS}] (one shard is one batch), got {shard_seeds}")
    if n_points > MAX_GRID_POINTS:
        raise ValueError(f"--sweep: {n_points:,} combinations of swept values; a campaign holds at most "
                         f"{MAX_GRID_POINTS:,} grid points (each is validated before the plan is saved): "
                         f"sweep fewer values")
    n = n_points * math.ceil(n_seeds / shard_seeds)
    if n > MAX_SHARDS:
        points = f"{n_points:,} grid point" + ("s" if n_points != 1 else "")
        raise ValueError(f"--n-seeds {n_seeds}: the plan would hold {n:,} shards ({points} x "
                         f"{math.ceil(n_seeds / shard_seeds):,} shards of --shard-seeds {shard_seeds}); a campaign "
                         f"holds at most {MAX_SHARDS:,} (campaign.json, the merge and the report keep every shard): "
                         f"use fewer seeds or sweep values, or more --shard-seeds")
    return n


def _parse_sweeps(sweeps: Sequence[str]) -> Dict[str, List[str]]:
    sw: Dict[str, List[str]] = {}
    for text in sweeps:
        k, vals = parse_sweep(text)
        if k in sw:
            raise ValueError(f"--sweep {k} given twice")
        if k.startswith(("simulation.seed_offset", "simulation.n_seeds")):
            raise ValueError(f"--sweep {k}: the campaign sets the seeds; use --n-seeds")
        sw[k] = vals
    return sw


def make_plan(cfg: Config, sweeps: Sequence[str] = (), n_seeds: int = None, shard_seeds: int = 5) -> CampaignPlan:
    """Plan a campaign of ``cfg`` over the cartesian product of ``sweeps`` (``key=v1,v2`` strings)
    and ``n_seeds`` seeds (default ``simulation.n_seeds``), ``shard_seeds`` seeds per shard.

    The plan's size is checked first (:func:`check_plan_size`), then every grid point's config
    and the memory of its largest shard, so a bad swept value fails before any work. Plain
    Python throughout: Ctrl-C stops it at once."""
    n_seeds = int(cfg.simulation.n_seeds if n_seeds is None else n_seeds)
    shard_seeds = int(shard_seeds)
    sw = _parse_sweeps(sweeps)
    check_plan_size(n_seeds, shard_seeds, math.prod(len(v) for v in sw.values()))
    first = int(cfg.simulation.seed_offset)  # --set simulation.seed_offset=K: seeds K .. K + n_seeds - 1
    base = config_to_dict(cfg)
    base["simulation"]["n_seeds"] = 1
    base["simulation"]["seed_offset"] = 0
    plan = CampaignPlan(config=base, sweeps=sw, n_seeds=n_seeds, shard_seeds=shard_seeds)
    keys = list(sw)
    for g, values in enumerate(itertools.product(*(sw[k] for k in keys)) if keys else [()]):
        point = dict(zip(keys, values))
        check_grid_point(base, point, "campaign config" + (f" with sweep {point}" if point else ""),
                         shard_seeds=min(shard_seeds, n_seeds))
        for k0 in range(first, first + n_seeds, shard_seeds):
            n = min(shard_seeds, first + n_seeds - k0)
            idx = len(plan.shards)
            plan.shards.append(Shard(id=f"g{g:03d}-s{k0:05d}", index=idx, sweep=point, seed_offset=k0, n_seeds=n))
    return plan
