"""``build_dataset``: fly dispersed descents and write their event windows as resumable shards.

The plan is the campaign's (:func:`dvsland.campaign.make_plan`): shard ``g000-s<k>`` flies every
configured site x controller setting for the seeds ``k .. k + shard_size - 1`` as one batch, and a
seed's dispersions depend only on (``simulation.seed``, site, seed index), never on the shard size.
The campaign's executors are not reused: they map the campaign's own ``run_shard`` (a
``simulate`` that returns run summaries to the driver), while a dataset shard is a file of
hundreds of MB (45 descents x ~1600 steps x 4.7 kB) written where it is flown; shards run here
one after another, or in a local process pool (``workers``).

Each shard is written to a temporary name and renamed when complete, then ``dataset.json`` is
rewritten (atomically) with it marked complete. Re-running the same request in the same folder
skips the complete shards whose file checks out (size and tables), rebuilds a corrupted or missing
one, and removes the temporary files of a killed build.
"""

from __future__ import annotations

import copy
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Union

from dvsland import __version__
from dvsland.config import Config, load_config

from .manifest import SHARDS_DIR, config_hash, load_manifest, manifest_path, same_request, save_manifest, shard_file
from .shardfile import ShardError, ShardWriter, read_index


@dataclass
class BuildResult:
    """What :func:`build_dataset` did.

    Attributes:
        root: the dataset folder.
        manifest: its manifest (dict).
        status: ``complete`` (every shard done) or ``incomplete`` (``max_shards`` stopped it).
        n_shards, n_shards_built: planned shards; shards flown in this call.
        n_samples_built, seconds: samples written and wall seconds of the shards flown in this call.
        samples_per_s: ``n_samples_built / seconds`` (None when nothing was flown).
        bytes_per_sample: shard bytes / samples over the whole dataset (None when empty).
    """

    root: Path
    manifest: dict
    status: str
    n_shards: int
    n_shards_built: int
    n_samples_built: int
    seconds: float
    samples_per_s: Optional[float]
    bytes_per_sample: Optional[float]


def resolve_config(config: Union[Config, str, Path, None], overrides: Sequence[str] = (),
                   sites: Union[None, str, Sequence[str]] = None, estimator: Optional[str] = "oracle") -> Config:
    """The config a build flies: ``config`` (a Config, a YAML path or a shipped name) with
    ``overrides``, restricted to ``sites`` (``"A,D"`` or a list; None = all configured) and with
    ``estimator.name = estimator`` (None keeps the config's).

    Raises:
        ValueError: overrides given with a Config object; a site the config does not define.
    """
    if isinstance(config, Config):
        if overrides:
            raise ValueError("overrides apply to a config file; edit the Config object instead")
        cfg = copy.deepcopy(config)
    else:
        cfg = load_config(config, list(overrides))
    if sites is not None:
        wanted = [s.strip() for s in (sites.split(",") if isinstance(sites, str) else sites) if s and s.strip()]
        known = [s.name for s in cfg.simulation.sites]
        unknown = [s for s in wanted if s not in known]
        if unknown or not wanted:
            raise ValueError(f"--sites must be a non-empty subset of the configured sites {known}, got {wanted}")
        cfg.simulation.sites = [s for s in cfg.simulation.sites if s.name in wanted]
    if estimator is not None:
        cfg.estimator.name = str(estimator)
    return cfg


def camera_fields(camera) -> dict:
    """The camera geometry a dataset records beside ``sensor_size``: ``principal_point_px`` [cx, cy]
    and ``focal_px`` (px; :mod:`dvsland.data.crop`). Datasets written before have neither: the
    readers then take the sensor centre and a 60 degree field of view."""
    from .crop import focal_px, principal_point

    return {"principal_point_px": [float(v) for v in principal_point(camera)], "focal_px": float(focal_px(camera))}


def new_manifest(plan, cfg: Config) -> dict:
    """The manifest of a fresh build of ``plan`` (every shard pending)."""
    disp = cfg.dispersion
    return {"format": "dvsland-event-windows", "format_version": 1, "config": plan.config,
            "config_hash": config_hash(plan.config), "estimator": cfg.estimator.name,
            "sites": [s.name for s in cfg.simulation.sites], "n_seeds": plan.n_seeds,
            "seed_offset": int(cfg.simulation.seed_offset), "shard_size": plan.shard_seeds,
            "sensor_size": [int(cfg.camera.width_px), int(cfg.camera.height_px)], **camera_fields(cfg.camera),
            "dt_s": float(cfg.dt_s), "n_variants": int(disp.terrain_variants) if disp.enabled else 1, "dvsland_version": __version__,
            "shards": [{"id": s.id, "file": f"{SHARDS_DIR}/{s.id}.h5", "seed_offset": s.seed_offset,
                        "n_seeds": s.n_seeds, "status": "pending"} for s in plan.shards]}


def build_dataset(config=None, n_seeds: int = 1, out=None, sites=None, shard_size: int = 5,
                  estimator: Optional[str] = "oracle", overrides: Sequence[str] = (), quiet: bool = False,
                  max_shards: Optional[int] = None, compression: Optional[str] = "gzip",
                  workers: int = 1) -> BuildResult:
    """Build (or resume) a dataset of labelled event windows in folder ``out``.

    Args:
        config: a :class:`Config`, YAML path or shipped name (e.g. ``"montecarlo_efference"``).
        n_seeds: seeds per site (seed indices ``simulation.seed_offset ..`` + n_seeds - 1).
        out: the dataset folder (required; created).
        sites: subset of the configured sites (``"A,D"`` or a list).
        shard_size: seeds per shard (a shard = sites x controller settings x shard_size descents).
        estimator: the estimator that flies (default ``"oracle"``: the truth; None = the config's).
        overrides: ``section.key=value`` strings.
        quiet: no progress bar.
        max_shards: build at most this many missing shards, then stop (status ``incomplete``).
        compression: ``"gzip"`` (default), ``"lzf"`` or None.
        workers: shards flown at once (a local process pool when > 1).

    Raises:
        ValueError: ``out`` missing, or holding a dataset of another request (names what differs).
    """
    from dvsland.campaign import make_plan

    if out is None:
        raise ValueError("out: the dataset folder is required (--out DIR)")
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    cfg = resolve_config(config, overrides, sites, estimator)
    plan = make_plan(cfg, (), n_seeds, shard_size)
    root = Path(out)
    manifest = _open_folder(root, new_manifest(plan, cfg), cfg)
    todo = [e for e in manifest["shards"] if not _shard_ok(root, e, quiet)]
    todo = todo if max_shards is None else todo[:max(0, int(max_shards))]
    shards = {s.id: asdict(s) for s in plan.shards}
    t0, n_built, n_samples = time.perf_counter(), 0, 0
    pbar = None if quiet else _progress(len(manifest["shards"]), len(manifest["shards"]) - len(todo))
    try:
        for entry in _run(plan.config, [shards[e["id"]] for e in todo], root, compression, int(workers)):
            _record(manifest, entry)
            save_manifest(root, manifest)
            n_built, n_samples = n_built + 1, n_samples + entry["n_samples"]
            if pbar is not None:
                pbar.update(1)
                pbar.set_postfix(samples_per_s=f"{n_samples / (time.perf_counter() - t0):.0f}")
    finally:
        if pbar is not None:
            pbar.close()
    return _result(root, manifest, n_built, n_samples, time.perf_counter() - t0)


def _open_folder(root: Path, fresh: dict, cfg: Config) -> dict:
    """The manifest to continue: the folder's own when it asked for the same, else ``fresh``
    (written with config.yaml). Stale temporary files of a killed build are removed."""
    from dvsland.config import dump_config

    if root.exists() and not root.is_dir():
        raise ValueError(f"out={str(root)!r}: exists and is not a folder; a dataset build needs a new or empty "
                         "folder (or its own dataset to resume)")
    if manifest_path(root).is_file():
        old = load_manifest(root, "out")
        diff = same_request(old, fresh)
        if diff is not None:
            raise ValueError(f"out={str(root)!r} holds a dataset of another request ({diff}); "
                             "use a new --out, or the same arguments to resume it")
        fresh = old
    else:
        others = sorted(p.name for p in root.iterdir())[:5] if root.is_dir() else []
        if others:  # another run's files or a user's: never mixed with a dataset
            raise ValueError(f"out={str(root)!r} holds files that are not a dataset ({', '.join(others)}); a dataset "
                             "build needs a new or empty folder (or its own dataset to resume)")
        root.mkdir(parents=True, exist_ok=True)
        (root / "config.yaml").write_text(dump_config(cfg))
        save_manifest(root, fresh)
    if (root / SHARDS_DIR).exists() and not (root / SHARDS_DIR).is_dir():
        raise ValueError(f"out={str(root)!r}: its {SHARDS_DIR!r} entry is a file, not the shards folder; "
                         "use a new --out")
    (root / SHARDS_DIR).mkdir(exist_ok=True)
    for tmp in (root / SHARDS_DIR).glob("*.h5.tmp*"):
        tmp.unlink(missing_ok=True)
    return fresh


def _shard_ok(root: Path, entry: dict, quiet: bool) -> bool:
    """A complete entry whose file exists with the recorded size and readable tables."""
    if entry.get("status") != "complete":
        return False
    path = root / entry["file"]
    try:
        if not path.is_file() or path.stat().st_size != entry.get("bytes"):
            raise ShardError(f"shard {str(path)!r}: missing or not of the recorded size {entry.get('bytes')} bytes")
        read_index(path)
    except ShardError as exc:
        if not quiet:
            print(f"dvsland dataset: {exc}; rebuilding it", file=sys.stderr)
        entry["status"] = "pending"
        return False
    return True


def _record(manifest: dict, entry: dict) -> None:
    for i, e in enumerate(manifest["shards"]):
        if e["id"] == entry["id"]:
            manifest["shards"][i] = {**e, **entry, "status": "complete"}


def _result(root: Path, manifest: dict, n_built: int, n_samples: int, seconds: float) -> BuildResult:
    done = [e for e in manifest["shards"] if e.get("status") == "complete"]
    tot_s = sum(e["n_samples"] for e in done)
    tot_b = sum(e["bytes"] for e in done)
    return BuildResult(root=root, manifest=manifest, n_shards=len(manifest["shards"]), n_shards_built=n_built,
                       status="complete" if len(done) == len(manifest["shards"]) else "incomplete",
                       n_samples_built=n_samples, seconds=seconds,
                       samples_per_s=n_samples / seconds if n_built and seconds > 0 else None,
                       bytes_per_sample=tot_b / tot_s if tot_s else None)


def _progress(total: int, initial: int):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="shard", desc="dataset", file=sys.stderr)


def _run(plan_config: dict, shards: List[dict], root: Path, compression, workers: int) -> Iterator[dict]:
    """Build ``shards`` here one after another, or in a spawned process pool; yield manifest entries."""
    paths = [str(shard_file(root, s["id"])) for s in shards]
    if workers <= 1 or len(shards) <= 1:
        for s, p in zip(shards, paths):
            yield build_shard(plan_config, s, p, compression)
        return
    from concurrent.futures import as_completed

    from dvsland.campaign.executors import make_pool

    pool = make_pool(workers)  # the campaign's pool: its workers die with this driver (SIGKILL included)
    futs = [pool.submit(build_shard, plan_config, s, p, compression) for s, p in zip(shards, paths)]
    try:
        for f in as_completed(futs):
            yield f.result()
    except BaseException:  # Ctrl-C or a failing shard: stop the pool now; finished shards are on disk
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.terminate()
        raise
    pool.shutdown(wait=True)


def build_shard(plan_config: dict, shard: dict, path: str, compression: Optional[str] = "gzip") -> dict:
    """Fly one shard (a :class:`dvsland.campaign.Shard` as a dict) of the plan's config and write
    it to ``path``; returns its manifest entry (without ``status``)."""
    import torch

    from dvsland.campaign import Shard
    from dvsland.campaign.plan import config_from_dict

    from .collect import Flight, descent_table, recording_stages

    sh = Shard(**shard)
    cfg = config_from_dict(plan_config, sh.overrides())
    if cfg.simulation.torch_threads > 0:
        torch.set_num_threads(int(cfg.simulation.torch_threads))
    t0 = time.perf_counter()
    stages, crop = recording_stages(cfg, cfg.simulation.device)
    attrs = {"sensor_size": [int(cfg.camera.width_px), int(cfg.camera.height_px)], **camera_fields(cfg.camera),
             "dt_s": float(cfg.dt_s),
             "shard_id": sh.id, "seed_offset": sh.seed_offset, "n_seeds": sh.n_seeds,
             "config_hash": config_hash(plan_config), "estimator": cfg.estimator.name}
    writer = ShardWriter(path, attrs, compression)
    try:
        flight = Flight(stages, crop=crop)
        for st in flight:
            writer.append(st.events, st.counts, st.samples)
        writer.finish(descent_table(stages.layout, flight.state))
    except BaseException:
        writer.abort()
        raise
    p = Path(path)
    return {"id": sh.id, "n_samples": len(writer.offsets) - 1, "n_events": writer.n_events,
            "n_descents": stages.layout.batch_size, "bytes": p.stat().st_size,
            "seconds": round(time.perf_counter() - t0, 3)}
