"""The training recipe of every learned estimator: one function, any model of the zoo or any class.

:func:`train` reads a dataset folder's train and val splits into memory
(:func:`dvsland.data.load_windows`), trains the model on a Gaussian negative log-likelihood of
log|D| (plus ``l1_weight`` |mu - log|D||, which keeps the mean from hiding behind a large
variance), keeps the weights with the lowest median |relative error| on val (early stopping after
``patience`` epochs without improvement), writes a checkpoint after every epoch (best weights
for use, last weights and optimizer for resuming) and TensorBoard curves, and scores the best
weights on the test split at the end. ``echo`` > 1 (data echoing) takes that many optimizer steps on
each batch, the echoes mirrored and transposed anew on the grid: building a batch from events costs
an 8-step, 8-bin input 10-25 times the network's forward and backward pass, so echoes buy steps cheaply. Seeded: the weights and the batch order depend on
``seed`` only; a resumed run continues at the next epoch exactly as an uninterrupted one.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, Optional

import torch

from dvsland.data import Windows, load_manifest_info
from dvsland.estimators.learned.checkpoint import read_checkpoint, save_checkpoint
from dvsland.estimators.state_dict_check import check_optimizer_state, check_state_dict, short_path
from dvsland.estimators.learned.inputs import InputSpec, check_input_spec, coord_channels
from dvsland.estimators.learned.models import build_model

from .batches import make_batch
from .metrics import predict, score
from .resample import load_canvas_split, reference_camera


#: learning-rate schedules: ``cosine`` decays per epoch over ``epochs``; ``budget`` per batch over
#: the run's budget (the largest of its shares of the epochs, of ``max_minutes`` and of
#: ``max_cpu_minutes`` spent), with a short warm-up: a time-capped run ends at the low rate
SCHEDULES = ("cosine", "budget")


@dataclass
class RecipeSettings:
    """The recipe's settings (all stored in the checkpoint's ``train`` field)."""

    model: str = "cnn"
    model_settings: Dict = field(default_factory=dict)
    n_bins: int = 4
    pool_px: int = 2
    coord_scale_px: float = 64.0
    n_windows: int = 1
    epochs: int = 30
    max_minutes: Optional[float] = None
    max_cpu_minutes: Optional[float] = None
    batch_size: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    l1_weight: float = 0.5
    patience: int = 6
    seed: int = 0
    max_drop: float = 0.5
    val_max_samples: int = 6000
    schedule: str = "cosine"
    echo: int = 1
    ema: float = 0.0

    def check(self) -> "RecipeSettings":
        """ValueError naming the setting for a value outside its range (or an empty model name)."""
        if not isinstance(self.model, str) or not self.model.strip():
            raise ValueError(f"model {self.model!r}: empty; expected a model of the zoo (cnn, spiking) or "
                             f"pkg.mod:Class")
        for name, lo, hi in (("epochs", 1, 100000), ("batch_size", 1, 65536), ("patience", 1, 100000),
                             ("val_max_samples", 100, 10 ** 9), ("echo", 1, 16)):
            if not lo <= int(getattr(self, name)) <= hi:
                raise ValueError(f"{name} must be in [{lo}, {hi}], got {getattr(self, name)}")
        for name, lo, hi in (("lr", 0.0, 1.0), ("weight_decay", 0.0, 1.0), ("l1_weight", 0.0, 100.0),
                             ("max_drop", 0.0, 0.95), ("ema", 0.0, 0.99999)):
            v = float(getattr(self, name))
            if not (lo <= v <= hi) or (name == "lr" and v == 0):
                raise ValueError(f"{name} must be in [{lo}, {hi}]{' (> 0)' if name == 'lr' else ''}, got {v}")
        for name in ("max_minutes", "max_cpu_minutes"):
            v = getattr(self, name)
            if v is not None and not float(v) > 0:
                raise ValueError(f"{name} must be > 0 (or None), got {v}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"schedule {self.schedule!r}: expected one of {', '.join(SCHEDULES)}")
        return self


#: named recipes (``dvsland train --recipe NAME``, :func:`recipe`): settings that differ from the
#: defaults. ``quick``: a first model on a small dataset (docs/learning.md, "Your first model in 15
#: minutes"): the last 8 control steps at one bin each on 4 x 4 pixel cells (a 32 x 32 grid), a
#: narrow CNN, a per-batch cosine over a 9 CPU-minute budget, two optimizer steps per batch
RECIPES: Dict[str, Dict] = {
    "quick": {"model": "cnn", "model_settings": {"width": 16}, "n_bins": 8, "n_windows": 8, "pool_px": 4,
              "batch_size": 64, "lr": 3e-3, "schedule": "budget", "max_cpu_minutes": 9.0, "epochs": 30,
              "patience": 30, "val_max_samples": 3000, "echo": 2},
}


def recipe(name: str, **overrides) -> RecipeSettings:
    """The settings of the named recipe ``name`` (:data:`RECIPES`), with ``overrides`` on top.

    Raises:
        ValueError: naming ``--recipe`` for an unknown name (listing the known ones), or a setting
            out of range (:meth:`RecipeSettings.check`).
    """
    if name not in RECIPES:
        raise ValueError(f"--recipe {name!r}: unknown recipe; choose one of {', '.join(sorted(RECIPES))}")
    return RecipeSettings(**{**copy.deepcopy(RECIPES[name]), **overrides}).check()


def _lr(s: RecipeSettings, epoch: int, progress: Optional[float] = None) -> float:
    """The learning rate: cosine decay from lr to lr / 20 over the epochs (``schedule="cosine"``,
    per epoch), or over ``progress`` in [0, 1], the share of the budget spent (``"budget"``, per
    batch, after a warm-up over the first 3 %)."""
    if s.schedule == "budget" and progress is not None:
        p = min(max(float(progress), 0.0), 1.0)
        return s.lr * min(1.0, 0.1 + p / 0.03) * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * p)))
    return s.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(epoch, s.epochs) / s.epochs)))


class Clock:
    """The budget of a run: wall seconds (``time.perf_counter``) and CPU seconds of this process, all
    its threads (``time.process_time``), each counted on from what earlier sessions of the run spent
    (``wall0``, ``cpu0``, s), against ``max_minutes`` (wall) and ``max_cpu_minutes`` (CPU)."""

    def __init__(self, s: RecipeSettings, wall0: float = 0.0, cpu0: float = 0.0):
        self.w0, self.c0 = time.perf_counter() - wall0, time.process_time() - cpu0
        self.caps = (None if s.max_minutes is None else 60.0 * float(s.max_minutes),
                     None if s.max_cpu_minutes is None else 60.0 * float(s.max_cpu_minutes))

    def wall(self) -> float:
        return time.perf_counter() - self.w0

    def cpu(self) -> float:
        return time.process_time() - self.c0

    def share(self, wall: Optional[float] = None, cpu: Optional[float] = None) -> float:
        """The largest share of a cap spent (0 without caps; >= 1: time is up), now or at the readings
        ``wall``, ``cpu`` (s, as recorded)."""
        spent = (self.wall() if wall is None else wall, self.cpu() if cpu is None else cpu)
        return max([x / cap for x, cap in zip(spent, self.caps) if cap] + [0.0])

    def up(self, wall: Optional[float] = None, cpu: Optional[float] = None) -> bool:
        return self.share(wall, cpu) >= 1.0


def _loss(mu, log_var, target, l1_weight: float):
    nll = 0.5 * (log_var + (target - mu) ** 2 * torch.exp(-log_var))
    return (nll + l1_weight * (target - mu).abs()).mean()


def data_dirs(data_dir) -> list:
    """The dataset folders of ``data_dir``: one path, a comma-separated string or a list.

    Raises:
        ValueError: naming ``--data`` when it names no folder (``""``, ``" , "``, an empty list).
    """
    if isinstance(data_dir, (list, tuple)):
        dirs = [Path(d) for d in data_dir if str(d).strip()]
    else:
        dirs = [Path(d.strip()) for d in str(data_dir).split(",") if d.strip()]
    if not dirs:
        raise ValueError(f"--data {data_dir!r}: empty; expected a dataset folder of `dvsland dataset build` "
                         f"(DIR, or DIR,DIR,... of one sensor)")
    return dirs


def input_spec(data_dir, s: "RecipeSettings") -> InputSpec:
    """The model input of ``data_dir``: the canvas of its first folder's camera (sensor size and
    focal length; :mod:`.resample`) with the recipe's bins, cell size and windows."""
    ref = reference_camera([load_manifest_info(d) for d in data_dirs(data_dir)[:1]])
    return check_input_spec(InputSpec(ref["sensor_size"], s.n_bins, s.pool_px, s.coord_scale_px, s.n_windows,
                                      ref["focal_px"]))


def load_split(data_dir, split: str, spec: Optional[InputSpec] = None) -> Windows:
    """The ``split`` of every folder of ``data_dir`` (:func:`data_dirs`) in one Windows, on the
    canvas of ``spec`` (default: the first folder's camera, :func:`input_spec`; folders of another
    camera are resampled onto it, :mod:`.resample`)."""
    dirs = data_dirs(data_dir)
    infos = [load_manifest_info(d) for d in dirs]
    if spec is None:
        spec = check_input_spec(InputSpec(**reference_camera(infos)))
    return load_canvas_split(dirs, split, spec, infos)


def _provenance(data_dir, tr: Windows, va: Windows) -> dict:
    infos = [{"root": str(d.resolve()), **load_manifest_info(d)} for d in data_dirs(data_dir)]
    out = dict(infos[0])
    if len(infos) > 1:
        out["config_hash"] = "+".join(i["config_hash"] for i in infos)
        out["datasets"] = infos
    return {**out, "samples": {"train": tr.n_samples, "val": va.n_samples}}


def _val_subset(va: Windows, n_max: int) -> torch.Tensor:
    """Evenly spaced rows of val (at most n_max), the same every epoch."""
    return torch.linspace(0, va.n_samples - 1, min(n_max, va.n_samples)).round().long().unique()


def _resume_state(out: Path, model_desc: dict, provenance: dict, s: RecipeSettings, net, opt):
    """(the checkpoint at ``out`` to go on from, whether it is a fine-tune), checked against this
    run (ValueError naming ``--resume`` if the model or the settings differ, or if its weights, last
    weights or optimizer state are damaged or diverged: the one checkpoint validation,
    :mod:`dvsland.estimators.state_dict_check`). The same data: the run continues at its next
    epoch. Other data (``--data`` with other folders): a fine-tune, which starts from the
    checkpoint's best weights with a fresh optimizer and epoch count (``lr`` may then differ too)."""
    ck = read_checkpoint(out, "--resume")
    finetune = (ck.get("data") or {}).get("config_hash") != provenance.get("config_hash")
    budget = ("epochs", "max_minutes", "max_cpu_minutes", "patience") + (("lr",) if finetune else ())
    old_train = {**dataclasses.asdict(RecipeSettings()), **(ck.get("train") or {})}  # settings added since: defaults
    old_s = {k: v for k, v in old_train.items() if k not in budget}
    new_s = {k: v for k, v in dataclasses.asdict(s).items() if k not in budget}
    for what, old, new in (("model", ck.get("model"), model_desc), ("settings", old_s, new_s)):
        if old != new:
            raise ValueError(f"--resume: {out} was trained with other {what} ({old!r} vs {new!r}); train to a new "
                             f"--out or pass the same arguments")
    where = f"--resume: {short_path(out)}"
    check_state_dict(ck["state_dict"], net, where)
    if finetune:
        return ck, finetune
    last = ck.get("last")
    if not isinstance(last, dict) or "optimizer" not in last:
        raise ValueError(f"{where} holds no resumable state (a shipped or stripped checkpoint)")
    _check_counters(ck, where)
    check_state_dict(last.get("state_dict"), net, f"{where} (its last weights)")
    check_optimizer_state(last.get("optimizer"), opt, where)
    return ck, finetune


def _check_counters(ck: dict, where: str) -> None:
    """The resumable run's counters: ``epoch`` and ``bad_epochs`` integers >= 0, ``best_val`` a number
    (not NaN; inf before any validation), ``last.seconds`` a finite number >= 0, ``history`` a list."""
    def real(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    for name, v, ok in (("epoch", ck.get("epoch"), lambda v: isinstance(v, int) and v >= 0),
                        ("bad_epochs", ck.get("bad_epochs"), lambda v: isinstance(v, int) and v >= 0),
                        ("best_val", ck.get("best_val"), lambda v: real(v) and not math.isnan(v)),
                        ("last.seconds", ck["last"].get("seconds"), lambda v: real(v) and 0 <= v < math.inf),
                        ("history", ck.get("history"), lambda v: isinstance(v, list))):
        if isinstance(v, bool) or not ok(v):
            raise ValueError(f"{where}: its {name} is {v!r}; expected "
                             f"{'a list' if name == 'history' else 'a number >= 0'} (a damaged checkpoint)")


def _init_state(init, model_desc: dict, spec: InputSpec, net) -> dict:
    """The checkpoint ``init`` (``--init``) to start from, checked: the same model and settings as
    this run, the same bins and windows of the input, finite weights that fit ``net``. The cells may
    differ (``--pool-px``): the built-in networks pool over space, so their weights fit a grid of
    any size, and a model can be refined onto finer cells (a feature then spans more cells than
    the weights learned; the fine-tune adapts them)."""
    ck = read_checkpoint(init, "--init")
    where = f"--init: {short_path(init)}"
    mine = {k: v for k, v in spec._asdict().items() if k in ("n_bins", "n_windows", "coord_scale_px")}
    theirs = {k: ck["input"].get(k) for k in mine} if isinstance(ck["input"], dict) else ck["input"]
    for what, old, new in (("model", ck["model"], model_desc), ("input", theirs, mine)):
        if old != new:
            raise ValueError(f"{where} holds another {what} ({old!r}; this run: {new!r}); pass the same --model, "
                             f"--model-set, --n-bins and --n-windows")
    check_state_dict(ck["state_dict"], net, where)
    return ck


def _start_from(ck: dict, finetune: bool, net, opt, run: dict, log: Callable, src: Path) -> None:
    """Load the resumed (or fine-tuned, or ``--init``) checkpoint ``ck`` of file ``src`` into ``net``,
    ``opt`` and ``run``."""
    if finetune:
        net.load_state_dict(ck["state_dict"])
        run.update(history=list(ck.get("history") or []), best_state=copy.deepcopy(net.state_dict()),
                   finetuned_from=ck.get("data"))
        log(f"fine-tuning {src} (from its best weights, epoch count and optimizer anew)")
        return
    net.load_state_dict(ck["last"]["state_dict"])
    opt.load_state_dict(ck["last"]["optimizer"])
    run.update(epoch=ck["epoch"], history=ck["history"], best_val=ck["best_val"], bad_epochs=ck["bad_epochs"],
               best_state=ck["state_dict"], seconds=ck["last"]["seconds"],
               cpu_seconds=float(ck["last"].get("cpu_seconds", ck["last"]["seconds"])))
    if (ck.get("data") or {}).get("finetuned_from") is not None:
        run["finetuned_from"] = ck["data"]["finetuned_from"]
    log(f"resuming {src} at epoch {run['epoch']}")


def train(data_dir, out, settings: RecipeSettings = RecipeSettings(), resume: bool = False,
          progress: bool = True, tb_dir=None, log: Callable = print, init=None) -> dict:
    """Train ``settings.model`` on dataset folder ``data_dir`` (or several of one sensor, a list or
    comma-separated); write the checkpoint ``out``. ``resume``: go on with the training stored in
    ``out``; ``init``: start from the best weights of that checkpoint file (a fine-tune; not with
    ``resume``). Both are checked before any epoch (ValueError naming ``--resume`` / ``--init``).

    Returns the checkpoint dict (``history``, ``final`` scores on val and test, ...).
    """
    s = settings.check()
    if resume and init is not None:
        raise ValueError("--init and --resume: give one (--resume goes on with the training in --out, --init starts "
                         "a new training from another checkpoint's weights)")
    torch.manual_seed(s.seed)
    spec = input_spec(data_dir, s)
    tr, va = load_split(data_dir, "train", spec), load_split(data_dir, "val", spec)
    coords = coord_channels(spec, ((spec.sensor_size[0] - 1) / 2, (spec.sensor_size[1] - 1) / 2))
    net, cls_path = build_model(s.model, {"n_bins": s.n_bins, **s.model_settings})
    model_desc = {"name": s.model, "class": cls_path, "settings": net.settings()}
    prov = _provenance(data_dir, tr, va)
    opt = torch.optim.AdamW(net.parameters(), lr=s.lr, weight_decay=s.weight_decay)
    avg = _averaged(net, s)
    run = {"epoch": 0, "history": [], "best_val": math.inf, "bad_epochs": 0, "best_state": net.state_dict(),
           "seconds": 0.0, "cpu_seconds": 0.0}
    out = Path(out)
    _start_run(out, resume, init, model_desc, prov, spec, s, net, opt, run, avg, log)
    writer = _writer(tb_dir)
    val_idx = _val_subset(va, s.val_max_samples)
    clock = Clock(s, run["seconds"], run["cpu_seconds"])
    # a new run trains at least one batch; a resumed one whose budget is spent trains none. Between
    # epochs the budget is judged on the time the run records (not on a later reading after the
    # checkpoint's write), so a run stopped by its cap records at least the cap
    while run["epoch"] < s.epochs and run["bad_epochs"] < s.patience and not (
            clock.up(run["seconds"], run["cpu_seconds"]) and run["history"]):
        ep = run["epoch"]
        train_loss, lr = _run_epoch(net, opt, tr, spec, coords, s, ep, clock, progress, avg)
        judged = net if avg is None else avg.module  # with ema: the average is the model
        rec = _validate(judged, va, val_idx, spec, coords, s, ep, train_loss, clock.wall())
        rec.update(lr=lr, cpu_seconds=clock.cpu())
        run["history"].append(rec)
        _tensorboard(writer, rec)
        if rec["val"]["all"]["median_rel_error"] < run["best_val"]:
            run.update(best_val=rec["val"]["all"]["median_rel_error"], bad_epochs=0,
                       best_state=copy.deepcopy(judged.state_dict()))
        else:
            run["bad_epochs"] += 1
        run.update(epoch=ep + 1, seconds=clock.wall(), cpu_seconds=clock.cpu())
        log(f"epoch {ep}: train loss {train_loss:.4f}, val loss {rec['val_loss']:.4f}, val median |rel err| "
            f"{100 * rec['val']['all']['median_rel_error']:.2f} % (best {100 * run['best_val']:.2f} %), "
            f"within 1/2 sigma {100 * rec['val']['all']['within_1sigma']:.0f}/"
            f"{100 * rec['val']['all']['within_2sigma']:.0f} %, {run['seconds']:.0f} s wall, "
            f"{run['cpu_seconds']:.0f} s CPU")
        _save(out, net, opt, spec, model_desc, prov, s, run, final=None, avg=avg)
    if writer is not None:
        writer.close()
    return _finish(out, net, opt, spec, coords, model_desc, prov, s, run, data_dir, va, log, avg)


def _start_run(out: Path, resume: bool, init, model_desc: dict, prov: dict, spec: InputSpec, s: RecipeSettings,
               net, opt, run: dict, avg, log: Callable) -> None:
    """Load what the run starts from into ``net``, ``opt``, ``run`` and ``prov``: ``--resume``'s
    stored run (or, on other data, its best weights), ``--init``'s weights, or nothing; then start the
    weight average ``avg`` from those weights (or go on with a resumed run's own average)."""
    resumed_last: dict = {}
    if resume:
        ck, finetune = _resume_state(out, model_desc, prov, s, net, opt)
        _start_from(ck, finetune, net, opt, run, log, out)
        resumed_last = {} if finetune else ck["last"]
    elif init is not None:
        ck = _init_state(init, model_desc, spec, net)
        _start_from(ck, True, net, opt, run, log, Path(init))
        prov["init"] = str(init)
        if ck["input"].get("pool_px") != spec.pool_px:
            log(f"  its {ck['input'].get('pool_px')}-pixel cells become {spec.pool_px}-pixel ones (--pool-px)")
    if run.get("finetuned_from") is not None:
        prov["finetuned_from"] = run["finetuned_from"]
    if avg is not None:
        _load_average(avg, net, resumed_last)


def _averaged(net, s: RecipeSettings):
    """``ema`` > 0: an exponential moving average of ``net``'s weights, updated after every optimizer
    step (:class:`torch.optim.swa_utils.AveragedModel`); validated, kept and shipped in place of the
    last weights, which move by more from batch to batch than the model improves. Else None."""
    if not s.ema:
        return None
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

    return AveragedModel(net, multi_avg_fn=get_ema_multi_avg_fn(float(s.ema)))


def _load_average(avg, net, last: dict) -> None:
    """Start ``avg`` from a resumed run's average (``last["ema"]``), else from ``net``'s weights."""
    state = last.get("ema")
    if isinstance(state, dict) and "state_dict" in state:
        check_state_dict(state["state_dict"], net, "--resume (its weight average)")
        avg.module.load_state_dict(state["state_dict"])
        avg.n_averaged.fill_(int(state.get("n_averaged", 1)))
    else:
        avg.module.load_state_dict(net.state_dict())
        avg.n_averaged.fill_(1)  # counted as averaged once: the next update blends (not copies) the weights


def _run_epoch(net, opt, tr: Windows, spec, coords, s: RecipeSettings, epoch: int, clock: Clock,
               progress, avg=None) -> tuple:
    """One pass over the train split in batches (seeded order and augmentation), cut short when
    ``clock`` is up; (mean loss, the last learning rate). ``avg``: the weight average to update
    after every optimizer step (:func:`_averaged`)."""
    gen = torch.Generator().manual_seed(s.seed * 100003 + epoch)
    order = torch.randperm(tr.n_samples, generator=gen)
    net.train()
    total, count = 0.0, 0
    batches = range(0, len(order) - s.batch_size + 1, s.batch_size)
    n_batches = max(len(batches), 1)
    lr = _lr(s, epoch, epoch / s.epochs)
    if progress:
        from tqdm import tqdm

        batches = tqdm(batches, desc=f"epoch {epoch}", leave=False, mininterval=2.0)
    for i, start in enumerate(batches):
        lr = _lr(s, epoch, max((epoch + i / n_batches) / s.epochs, clock.share()))
        for g in opt.param_groups:
            g["lr"] = lr
        bt = make_batch(tr, order[start:start + s.batch_size], spec, gen, s.max_drop)
        for r in range(s.echo):  # echoes: the same windows mirrored anew (module doc)
            vox = bt.vox if r == 0 else _mirrored(bt.vox, spec, gen)
            mu, log_var = net(vox, coords, bt.log_count)
            loss = _loss(mu, log_var, bt.target, s.l1_weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
            opt.step()
            if avg is not None:
                avg.update_parameters(net)
            total, count = total + float(loss.detach()), count + 1
        if clock.up():
            break
    return total / max(count, 1), lr


def _mirrored(vox: torch.Tensor, spec: InputSpec, gen: torch.Generator) -> torch.Tensor:
    """``vox`` (B, n_bins, h, w) with each sample mirrored in x and y and transposed at random (each
    with probability 1/2): the grid of the mirrored events when the cells tile the sensor
    symmetrically about its centre (W and H multiples of ``pool_px``; the transpose on a square
    sensor), else ``vox`` unchanged (the coordinate channels are symmetric about the centre)."""
    W, H = spec.sensor_size
    if W % spec.pool_px or H % spec.pool_px:
        return vox
    f = (torch.rand(vox.shape[0], 3, generator=gen) < 0.5)[:, :, None, None, None]
    out = torch.where(f[:, 0], vox.flip(3), vox)
    out = torch.where(f[:, 1], out.flip(2), out)
    if W == H:
        out = torch.where(f[:, 2], out.transpose(2, 3), out)
    return out


def _validate(net, va: Windows, rows, spec, coords, s: RecipeSettings, epoch: int, train_loss: float,
              seconds: float):
    mu, lv = predict(net, va, spec, coords, rows=rows)
    target = torch.log(va.d_true[rows].abs().clamp_min(1e-3))
    val_loss = float(_loss(mu, lv, target, s.l1_weight))
    return {"epoch": epoch, "train_loss": train_loss, "val_loss": val_loss, "lr": _lr(s, epoch),
            "seconds": seconds, "val": score(mu, lv, va, rows)}


def _writer(tb_dir):
    if tb_dir is None:
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(tb_dir))


def _tensorboard(writer, rec: dict) -> None:
    if writer is None:
        return
    ep = rec["epoch"]
    writer.add_scalar("loss/train", rec["train_loss"], ep)
    writer.add_scalar("loss/val", rec["val_loss"], ep)
    for group, v in rec["val"].items():
        writer.add_scalar(f"val_median_rel_error/{group}", v["median_rel_error"], ep)
        writer.add_scalar(f"val_within_1sigma/{group}", v["within_1sigma"], ep)
        writer.add_scalar(f"val_within_2sigma/{group}", v["within_2sigma"], ep)
    writer.flush()


def _save(out, net, opt, spec: InputSpec, model_desc, prov, s, run, final, avg=None) -> None:
    blob = {"model": model_desc, "input": spec._asdict(), "state_dict": run["best_state"], "data": prov,
            "train": dataclasses.asdict(s), "history": run["history"], "epoch": run["epoch"],
            "best_val": run["best_val"], "bad_epochs": run["bad_epochs"],
            "last": {"state_dict": net.state_dict(), "optimizer": opt.state_dict(), "seconds": run["seconds"],
                     "cpu_seconds": run["cpu_seconds"]}}
    if avg is not None:
        blob["last"]["ema"] = {"state_dict": avg.module.state_dict(), "n_averaged": int(avg.n_averaged)}
    if final is not None:
        blob["final"] = final
    blob["input"]["sensor_size"] = list(spec.sensor_size)
    save_checkpoint(out, blob)


def _finish(out, net, opt, spec, coords, model_desc, prov, s, run, data_dir, va, log, avg=None) -> dict:
    """Score the best weights on the whole val and the test split; write the final checkpoint."""
    best = copy.deepcopy(net)
    best.load_state_dict(run["best_state"])
    final = {"val": score(*predict(best, va, spec, coords), va)}
    try:
        te = load_split(data_dir, "test", spec)
        final["test"] = score(*predict(best, te, spec, coords), te)
    except ValueError as exc:  # a dataset without a test split
        final["test_error"] = str(exc)
    final["train_seconds"], final["train_cpu_seconds"] = run["seconds"], run["cpu_seconds"]
    _save(out, net, opt, spec, model_desc, prov, s, run, final, avg=avg)
    for split in ("val", "test"):
        if split in final:
            a = final[split]["all"]
            log(f"{split}: median |rel err| {100 * a['median_rel_error']:.2f} %, within 1/2 sigma "
                f"{100 * a['within_1sigma']:.0f}/{100 * a['within_2sigma']:.0f} % ({a['n']} samples)")
    return read_checkpoint(out)
