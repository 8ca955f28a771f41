"""One ``dvsland train-loop`` run: build the training and validation batches, restore a checkpoint
to resume, train (:mod:`.loop_train`) with a progress bar and TensorBoard scalars, validate, and
write ``checkpoint.pt``, ``trained.yaml`` and ``train_loop.json`` into the run folder.
"""

from __future__ import annotations

import json
from dataclasses import asdict, fields, replace
from pathlib import Path
from typing import Optional

import torch

from dvsland.campaign.plan import available_memory_bytes
from dvsland.config import dump_config
from dvsland.estimators.state_dict_check import (check_finite_numbers, check_optimizer_state,
                                                 read_checkpoint_file)
from dvsland.report.results import atomic_write_text
from dvsland.report.tensorboard import summary_writer
from dvsland.stages import build_stages

from .loop_loss import LossWeights
from .loop_train import (TrainLoopRun, TrainLoopSettings, check_horizon_fits, checkpoint_kind, save_checkpoint,
                         train_windows, validate)
from .loop_trainables import Trainable, make_trainable

#: files of a train-loop run folder
CHECKPOINT, TRAINED_CONFIG, SUMMARY = "checkpoint.pt", "trained.yaml", "train_loop.json"


def validation_config(cfg, val_seed: int, val_seeds: Optional[int] = None):
    """The training config with another ``simulation.seed`` (and ``val_seeds`` seeds per site and
    setting, None: the training's): the validation descents."""
    n = cfg.simulation.n_seeds if val_seeds is None else int(val_seeds)
    return replace(cfg, simulation=replace(cfg.simulation, seed=int(val_seed), n_seeds=n))


def restore(path: Path, trainable: Trainable, opt, law: str) -> tuple:
    """(TrainLoopRun, episode (B,) or None, settings dict) of a checkpoint, loaded into ``trainable``
    and ``opt``; ValueError naming ``--resume`` and the file for a missing, foreign or damaged one."""
    where = f"--resume {path}"
    kind = checkpoint_kind(trainable.what)
    ck = read_checkpoint_file(path, "--resume", f"dvsland train-loop checkpoint ({kind})")
    if ck.get("kind") != kind or ck.get("controller") != law:
        raise ValueError(f"{where}: a {ck.get('kind')!r} checkpoint of controller {ck.get('controller')!r}; this "
                         f"training is --what {trainable.what} of {law!r}")
    check_finite_numbers(ck.get("run", {}), where, "run")
    trainable.load_checkpoint_fields(ck, where)
    check_optimizer_state(ck.get("optimizer"), opt, where)
    opt.load_state_dict(ck["optimizer"])
    run = TrainLoopRun(**{k: v for k, v in ck.get("run", {}).items() if k in TrainLoopRun.__dataclass_fields__})
    return run, ck.get("episode"), ck.get("settings", {})


def trained_config(cfg, trainable: Trainable, ckpt: Path):
    """The config that flies the trained result: the training config with the trained values in
    place (:meth:`~.loop_trainables.Trainable.trained_config`: the law's or the filter's constants,
    or the policy's or the estimator's checkpoint by absolute path)."""
    flown = trainable.trained_config(cfg, ckpt)
    return replace(flown, logging=replace(flown.logging, quiet=False))  # --quiet was the training's


def _tensorboard(writer, rec: dict, what: str = "law") -> None:
    step = rec["window"]
    for k in ("loss", *(f.name for f in fields(LossWeights))):  # the total, then each term
        if k in rec:
            writer.add_scalar(f"loss/{k}", rec[k], step)
    writer.add_scalar("train/landed", rec["landed"], step)
    for k, v in (rec.get("values") or {}).items():
        writer.add_scalar(f"{'filter' if what == 'filter' else 'law'}/{k}", v, step)
    val = rec.get("val")
    if val:
        writer.add_scalar("val/success_rate", val["success_rate"], step)
        if val.get("loss") is not None:
            writer.add_scalar("val/loss", val["loss"], step)
        if val["median_landing_speed_mps"] is not None:
            writer.add_scalar("val/median_landing_speed_mps", val["median_landing_speed_mps"], step)


def train_loop(cfg, run_dir: Path, settings: TrainLoopSettings, sites=None, val_seed: int = 999,
               val_seeds: Optional[int] = None, resume: bool = False, progress: bool = True) -> dict:
    """Train ``settings.what`` through the loop of ``cfg`` into ``run_dir``; returns train_loop.json's dict.

    Args:
        cfg: the resolved config (its controller is the one trained).
        run_dir: the run folder (made, with ``config.yaml``, by the caller).
        settings: :class:`TrainLoopSettings` (checked).
        sites: the sites flown (None: the config's).
        val_seed: ``simulation.seed`` of the validation batch.
        val_seeds: its seeds per site and setting (None: the config's ``simulation.n_seeds``).
        resume: go on from ``run_dir/checkpoint.pt``.
    """
    s = settings.check()
    torch.manual_seed(s.seed)
    stages = build_stages(cfg, sites)
    trainable = make_trainable(stages, s.what, s.params)
    check_horizon_fits(stages, s.window, available_memory_bytes())
    opt = torch.optim.Adam(trainable.parameters(), lr=s.lr)
    run, episode = TrainLoopRun(), torch.zeros(stages.batch_size, dtype=torch.int64)
    ckpt = run_dir / CHECKPOINT
    if resume:
        run, ep, _ = restore(ckpt, trainable, opt, cfg.controller.name)
        if isinstance(ep, torch.Tensor) and ep.shape == episode.shape:
            episode = ep
        s = replace(s, cpu_minutes=s.cpu_minutes + run.cpu_s / 60.0)  # the budget is this call's
    val_stages = build_stages(validation_config(cfg, val_seed, val_seeds), sites)
    writer, bar = summary_writer(run_dir / "tb"), _bar(progress, s, run)

    def on_window(rec: dict) -> None:
        if s.val_every and rec["window"] % s.val_every == 0:
            rec["val"] = {k: v for k, v in validate(val_stages, trainable, s.loss).items()
                          if k != "outcomes"}
        run.history.append(rec)
        _tensorboard(writer, rec, s.what)
        if bar is not None:
            bar.update(max(0.0, round(min(run.cpu_s, bar.total) - bar.n, 1)))
            bar.set_postfix(loss=f"{rec['loss']:.3g}", landed=run.landed)

    try:
        episode = train_windows(stages, trainable, opt, s, run, episode, on_window)
    finally:  # an interrupt keeps what was trained so far, and the curves written so far
        save_checkpoint(ckpt, trainable, opt, s, run, episode, cfg.controller.name)
        writer.flush()
        if bar is not None:
            bar.close()
    final = validate(val_stages, trainable, s.loss)
    summary = {"what": s.what, "controller": cfg.controller.name, "settings": {**asdict(s), "params": list(s.params)},
               "batch": stages.batch_size, "windows": run.windows, "simulated_steps": run.steps,
               "cpu_s": round(run.cpu_s, 1), "train_landed": run.landed, "train_ended": run.ended,
               "values": trainable.describe(), "val_seed": val_seed, "val_batch": val_stages.batch_size,
               "validation": final, "history": run.history}
    atomic_write_text(run_dir / TRAINED_CONFIG, dump_config(trained_config(cfg, trainable, ckpt)))
    atomic_write_text(run_dir / SUMMARY, json.dumps(summary, indent=1) + "\n")
    _tensorboard(writer, {"window": run.windows, "landed": run.landed, "val": final})
    writer.close()
    return summary


def _bar(progress: bool, s: TrainLoopSettings, run: TrainLoopRun):
    if not progress:
        return None
    import sys

    from tqdm.auto import tqdm

    return tqdm(total=round(s.cpu_minutes * 60.0, 1), initial=round(run.cpu_s, 1), unit="cpu-s",
                desc=f"train-loop {s.what}", file=sys.stderr, mininterval=2.0,
                bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} cpu-s [{elapsed}<{remaining}{postfix}]")


__all__ = ["train_loop", "restore", "trained_config", "validation_config", "CHECKPOINT", "TRAINED_CONFIG", "SUMMARY",
           "LossWeights"]
