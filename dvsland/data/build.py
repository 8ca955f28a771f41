"""``build_dataset``: fly dispersed descents and write their event windows as resumable shards.

The plan is the campaign's (:func:`dvsland.campaign.make_plan`): shard ``g000-s<k>`` flies every
configured site x controller setting for the seeds ``k .. k + shard_size - 1`` as one batch, and a
seed's dispersions depend only on (``simulation.seed``, site, seed index), never on the shard size.
A dataset shard is a file of hundreds of MB (45 descents x ~1600 steps x 4.7 kB) written where it
is flown (not sent to the driver as a campaign's shard result is); shards run here one after
another, or in the campaign's process pool (``workers``: :func:`dvsland.campaign.executors.map_pool`,
whose workers die with the driver). The progress bar counts loop steps inside the shards.

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
    from dvsland.runs import open_folder

    if out is None:
        raise ValueError("out: the dataset folder is required (--out DIR)")
    root = open_folder(out, "--out", create=False)  # empty, too long a name, a file: refused first
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    cfg = resolve_config(config, overrides, sites, estimator)
    plan = make_plan(cfg, (), n_seeds, shard_size)
    manifest, lock = _open_folder(root, new_manifest(plan, cfg), cfg)
    try:
        return _build(plan, root, manifest, quiet, max_shards, compression, int(workers))
    finally:
        if lock is not None:
            lock.close()


def _build(plan, root: Path, manifest: dict, quiet: bool, max_shards, compression, workers: int) -> BuildResult:
    """Fly the shards of ``manifest`` that have no good file (at most ``max_shards``)."""
    todo = [e for e in manifest["shards"] if not _shard_ok(root, e, quiet)]
    todo = todo if max_shards is None else todo[:max(0, int(max_shards))]
    shards = {s.id: asdict(s) for s in plan.shards}
    t0, n_built, n_samples = time.perf_counter(), 0, 0
    to_fly = [shards[e["id"]] for e in todo]
    bar = None if quiet else _progress(plan, to_fly, workers)
    try:
        for i, entry in _run(plan.config, to_fly, root, compression, workers, bar):
            _record(manifest, entry)
            save_manifest(root, manifest)
            n_built, n_samples = n_built + 1, n_samples + entry["n_samples"]
            if bar is not None:
                bar.shard_done(i, f"{n_samples / (time.perf_counter() - t0):.0f} samples/s")
    finally:
        if bar is not None:
            bar.close()
    return _result(root, manifest, n_built, n_samples, time.perf_counter() - t0)


#: the lock a running build holds in its folder (a second build into the same folder is refused)
LOCK_FILE = ".dataset.lock"


def _open_folder(root: Path, fresh: dict, cfg: Config):
    """(manifest to continue, the folder's lock): the folder's own manifest when it asked for the
    same, else ``fresh`` (written with config.yaml). A folder holding anything but a dataset is
    refused before anything is written; a build already running there is refused
    (:func:`dvsland.runs.lock_folder`). Stale temporary files of a killed build are removed."""
    from dvsland.runs import lock_folder, open_folder

    if not manifest_path(root).is_file():
        others = sorted(p.name for p in root.iterdir() if p.name != LOCK_FILE)[:5] if root.is_dir() else []
        if others:  # another run's files or a user's: never mixed with a dataset
            raise ValueError(f"out={str(root)!r} holds files that are not a dataset ({', '.join(others)}); a dataset "
                             "build needs a new or empty folder (or its own dataset to resume)")
    _same_request(root, fresh)
    open_folder(root, "--out")
    lock = lock_folder(root, LOCK_FILE, "dvsland dataset build")
    try:
        fresh = _continue_or_start(root, fresh, cfg)
    except BaseException:
        if lock is not None:
            lock.close()
        raise
    return fresh, lock


def _same_request(root: Path, fresh: dict):
    """The folder's manifest when it asked for the same as ``fresh``; None when it has none;
    ValueError (naming what differs) otherwise."""
    if not manifest_path(root).is_file():
        return None
    old = load_manifest(root, "out", check_entries=False)  # damaged entries are repaired below
    diff = same_request(old, fresh)
    if diff is not None:
        raise ValueError(f"out={str(root)!r} holds a dataset of another request ({diff}); "
                         "use a new --out, or the same arguments to resume it")
    return old


def _continue_or_start(root: Path, fresh: dict, cfg: Config) -> dict:
    """Under the folder's lock: its manifest (read again: a build may have ended meanwhile) or
    ``fresh`` written with config.yaml; the shards folder made and its temporary files removed."""
    from dvsland.config import dump_config
    from dvsland.report.results import atomic_write_text

    old = _same_request(root, fresh)
    if old is not None:
        fresh = _checked_entries(root, old, fresh)
    else:
        save_manifest(root, fresh)
    atomic_write_text(root / "config.yaml", dump_config(cfg))  # resumed: a damaged copy is rewritten
    if (root / SHARDS_DIR).exists() and not (root / SHARDS_DIR).is_dir():
        raise ValueError(f"out={str(root)!r}: its {SHARDS_DIR!r} entry is a file, not the shards folder; "
                         "use a new --out")
    (root / SHARDS_DIR).mkdir(exist_ok=True)
    for tmp in (root / SHARDS_DIR).glob("*.h5.tmp*"):
        tmp.unlink(missing_ok=True)
    return fresh


def _checked_entries(root: Path, old: dict, fresh: dict) -> dict:
    """``old`` (the folder's manifest) with each shard entry checked against the plan's in
    ``fresh``: an entry that is missing, not an object, or names another file (a damaged or
    hand-edited manifest: a path outside the folder was kept and read) is reported on stderr and
    replaced by the plan's, so its shard is rebuilt."""
    have = {e.get("id"): e for e in old["shards"] if isinstance(e, dict)}
    entries = []
    for want in fresh["shards"]:
        got = have.get(want["id"])
        if got is None or got.get("file") != want["file"]:
            print(f"dvsland dataset: {manifest_path(root)}: the entry of shard {want['id']} is missing or names "
                  f"another file ({None if got is None else got.get('file')!r}, expected {want['file']!r}); "
                  "rebuilding that shard", file=sys.stderr)
            got = dict(want)
        entries.append(got)
    return {**old, "shards": entries}


def _shard_ok(root: Path, entry: dict, quiet: bool) -> bool:
    """A complete entry whose file exists with the recorded size and readable tables."""
    if entry.get("status") != "complete":
        return False
    path = root / entry["file"]
    try:
        if not all(isinstance(entry.get(k), int) for k in ("bytes", "n_samples", "n_events")):
            raise ShardError(f"shard {str(path)!r}: its manifest entry lacks its size or counts")
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


def _progress(plan, to_fly: List[dict], workers: int):
    """The build's bar over the loop steps of the shards to fly (:class:`dvsland.campaign.progress.StepBar`)."""
    from dvsland.campaign.progress import StepBar, shard_steps

    ids = {s["id"] for s in to_fly}
    before = [asdict(s) for s in plan.shards if s.id not in ids]
    return StepBar(shard_steps(plan.config, to_fly), "dataset", len(plan.shards), len(before),
                   steps_before=sum(shard_steps(plan.config, before)), shared=workers > 1 and len(to_fly) > 1)


def _run(plan_config: dict, shards: List[dict], root: Path, compression, workers: int, bar=None
         ) -> Iterator[tuple]:
    """Build ``shards`` here one after another, or in the campaign's process pool
    (:func:`dvsland.campaign.executors.map_pool`: workers that die with this driver, stopped at
    once on Ctrl-C); yield (index in ``shards``, manifest entry). ``bar`` follows their steps."""
    from dvsland.campaign import progress

    paths = [str(shard_file(root, s["id"])) for s in shards]
    slot = (lambda i: i) if bar is not None else (lambda i: None)
    if workers <= 1 or len(shards) <= 1:
        progress.install(bar.slots if bar is not None else None, bar.refresh if bar is not None else None)
        try:
            for i, (s, p) in enumerate(zip(shards, paths)):
                yield i, build_shard(plan_config, s, p, compression, slot(i))
        finally:
            progress.install(None)
        return
    from dvsland.campaign.executors import map_pool

    calls = [(plan_config, s, p, compression, slot(i)) for i, (s, p) in enumerate(zip(shards, paths))]
    yield from map_pool(build_shard, calls, workers, tick=bar.refresh if bar is not None else None,
                        slots=bar.slots if bar is not None else None,
                        hint="run the same `dvsland dataset build` command again to resume, with fewer --workers "
                             "or a smaller --shard-size")


def build_shard(plan_config: dict, shard: dict, path: str, compression: Optional[str] = "gzip",
                progress_slot: Optional[int] = None) -> dict:
    """Fly one shard (a :class:`dvsland.campaign.Shard` as a dict) of the plan's config and write
    it to ``path``; returns its manifest entry (without ``status``). ``progress_slot``: report the
    steps flown there after each step (:mod:`dvsland.campaign.progress`)."""
    import torch

    from dvsland.campaign import Shard, progress
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
            progress.report(progress_slot, flight.state.step)
        writer.finish(descent_table(stages.layout, flight.state))
    except BaseException:
        writer.abort()
        raise
    p = Path(path)
    return {"id": sh.id, "n_samples": len(writer.offsets) - 1, "n_events": writer.n_events,
            "n_descents": stages.layout.batch_size, "bytes": p.stat().st_size,
            "seconds": round(time.perf_counter() - t0, 3)}
