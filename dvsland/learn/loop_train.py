"""Training through the closed loop (``dvsland train-loop``): a law's constants, the ``efference_fit``
filter's constants or a policy network learn from the loss of the flight itself (:mod:`.loop_loss`), by truncated backpropagation in time.

A batch of B descents (the config's sites x settings x seeds) flies window after window; at each
window's start the state is detached, and descents that have ended restart from a new dispersed
start (counter-based draws of (seed, descent, episode): the same on every device). Every
``val_every`` windows, and at the end, the trained values fly a validation batch (another seed,
whole descents, no gradient): landings, landing speed, fuel.

What is written into the run folder: ``checkpoint.pt`` (the trained values, the optimizer, the
counters: ``--resume`` goes on from it), ``trained.yaml`` (the config that flies the result by
path), ``train_loop.json`` (settings, history, final validation) and TensorBoard scalars (``tb/``).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

from dvsland.checks import check_range
from dvsland.control.policy import POLICY_KIND
from dvsland.report.stats import median
from dvsland.sim import dispersed_start, init_state, loop_step, reset_where
from dvsland.sim.termination import SUCCESS

from .loop_estimator import ESTIMATOR_KIND, estimator_graph_bytes
from .loop_loss import LossWeights, step_terms, window_loss
from .loop_trainables import WHATS, Trainable

#: ``kind`` of a law checkpoint (a policy's is :data:`dvsland.control.policy.POLICY_KIND`)
LAW_KIND = "dvsland-loop-law"
#: ``kind`` of a filter checkpoint (``--what filter``)
FILTER_KIND = "dvsland-loop-filter"
#: autograd memory a window holds per descent-step, bytes: about 1 KB measured with the oracle,
#: ``div_gs`` or ``policy`` and the efference filter (scripts/bench_loop_grad.py); 4x that as margin
GRAPH_BYTES_PER_DESCENT_STEP = 4096
#: the ``efference_fit`` filter re-fits every row of its history each step: its graph holds about
#: 1.6 KB per descent-step and history row (measured: 1.59 MB per descent-step after 1,000 steps,
#: B = 1, oracle, div_gs); 2 KB as margin. A whole descent of n steps holds about n^2 / 2 of them.
FIT_GRAPH_BYTES_PER_ROW = 2048


@dataclass(frozen=True)
class TrainLoopSettings:
    """Settings of one training (each checked by :meth:`check`, naming the option).

    Attributes:
        what: ``policy``, ``law`` or ``filter``.
        params: law or filter constants to train (() = the default set).
        window: steps per truncated-backpropagation window (0 = whole descents).
        lr: Adam's learning rate.
        seed: the training starts' seed (torch's too).
        dispersion: relative std. dev. of the restarted descents' altitude (speed: half of it).
        cpu_minutes: budget of process CPU time, minutes.
        max_windows: stop after this many windows (0 = the CPU budget alone).
        val_every: validate every this many windows (0 = only at the end).
        loss: the loss weights.
    """

    what: str = "policy"
    params: Sequence[str] = ()
    window: int = 40
    lr: float = 3e-3
    seed: int = 0
    dispersion: float = 0.05
    cpu_minutes: float = 1.0
    max_windows: int = 0
    val_every: int = 50
    loss: LossWeights = field(default_factory=LossWeights)

    def check(self) -> "TrainLoopSettings":
        if self.what not in WHATS:
            raise ValueError(f"--what {self.what!r}: choose one of {list(WHATS)}")
        for name, lo, hi, integer in (("window", 0, 100000, True), ("max_windows", 0, 10**9, True),
                                      ("val_every", 0, 10**9, True), ("lr", 0.0, 10.0, False),
                                      ("dispersion", 0.0, 0.5, False), ("cpu_minutes", 0.0, 1e6, False)):
            v, flag = getattr(self, name), "--" + name.replace("_", "-")
            if integer and not isinstance(v, int):
                raise ValueError(f"{flag}: {v!r} is not an integer")
            check_range(flag, v, lo, hi, open_lo=name == "lr")
        self.loss.check()
        return self


@dataclass
class TrainLoopRun:
    """Counters of a training (what ``--resume`` restores)."""

    windows: int = 0
    steps: int = 0
    cpu_s: float = 0.0
    landed: int = 0
    ended: int = 0
    history: list = field(default_factory=list)


def restart_ended(stages, state, episode: torch.Tensor, seed: int, dispersion: float):
    """Ended descents restart from a new dispersed start keyed by (seed, descent, episode):
    (state, episode (B,) int64). No copy when none has ended."""
    done = ~state.active
    if not bool(done.any()):
        return state, episode
    episode = episode + done.to(torch.int64)
    b = torch.arange(state.batch_size, device=state.z_m.device)
    z0, v0 = dispersed_start(stages, (seed, b, episode), dispersion, 0.5 * dispersion, (0.7, 1.3), (0.8, 1.2))
    return reset_where(stages, state, done, z_m=z0, v_mps=v0), episode


@torch.no_grad()
def validate(stages, trainable: Trainable, loss: Optional[LossWeights] = None) -> dict:
    """Fly every descent of ``stages`` once, whole, with the trained values: landings, landing speed, fuel
    (medians as the reports compute them: :func:`dvsland.report.stats.median`, the mean of the two
    middle values for an even count); with ``loss``, also the training's loss of these whole flights
    (``loss``: the batch mean of :func:`~.loop_loss.step_terms` summed over the descent, and each term)."""
    trainable.apply_to(stages)
    state = init_state(stages)
    sums = {}
    while bool(state.active.any()) and state.step < stages.settings.n_steps_max:
        nxt, out = loop_step(stages, state)
        if loss is not None:
            for k, v in step_terms(stages, state, nxt, out, loss).items():
                if not k.startswith("_"):
                    sums[k] = sums[k] + v if k in sums else v
        state = nxt
    landed = state.outcome == SUCCESS
    terms = {k: round(float(v.mean()), 4) for k, v in sums.items()}
    extra = {"loss": round(sum(float(v.mean()) for v in sums.values()), 4), "loss_terms": terms} if sums else {}
    v = median(state.v_mps[landed].abs().tolist())
    fuel = median((stages.params.m0_kg - state.m_kg)[landed].tolist())
    return {"n": state.batch_size, "landed": int(landed.sum()), "success_rate": float(landed.double().mean()),
            "median_landing_speed_mps": round(v, 3) if v is not None else None,
            "median_fuel_kg": round(fuel, 1) if fuel is not None else None, **extra,
            "outcomes": state.outcome.tolist()}


def fit_history_rows(stages, window: int) -> int:
    """History rows the ``efference_fit`` filter re-fits per step in a window, at most (0 for another
    filter): the rows of a whole descent (half on average for ``window`` 0: every descent starts
    afresh), or the rows its ``forget_s`` window reads."""
    from dvsland.control.efference_fit import EfferenceFitParams

    p = getattr(stages.filter, "params", None)
    if not isinstance(p, EfferenceFitParams):
        return 0
    n = stages.settings.n_steps_max
    rows = n // 2 if window == 0 else n
    forget = float(p.cfg.forget_s)
    if forget > 0:
        rows = min(rows, int(math.ceil(p.cut_forget * forget / p.dt_s)))
    return rows


def check_horizon_fits(stages, window: int, available_bytes: float) -> int:
    """Bytes the graph of one window holds (``window`` steps, 0 = ``t_max``, of B descents; with the
    ``efference_fit`` filter, :data:`FIT_GRAPH_BYTES_PER_ROW` per row of its history too; with
    ``--what estimator``, the network's graph, :func:`~.loop_estimator.estimator_graph_bytes`); ValueError
    naming ``--window`` when that passes half of ``available_bytes``."""
    steps = window or stages.settings.n_steps_max
    est = estimator_graph_bytes(stages)
    per_step = GRAPH_BYTES_PER_DESCENT_STEP + est + FIT_GRAPH_BYTES_PER_ROW * fit_history_rows(stages, window)
    need = steps * stages.batch_size * per_step
    if need > 0.5 * available_bytes:
        per_window_step = GRAPH_BYTES_PER_DESCENT_STEP + est + FIT_GRAPH_BYTES_PER_ROW * fit_history_rows(stages, 1)
        most = int(0.5 * available_bytes / (stages.batch_size * per_window_step))
        raise ValueError(f"--window {window}: a window of {steps} steps x {stages.batch_size} descents holds about "
                         f"{need / 2**30:.1f} GiB of autograd graph; {available_bytes / 2**30:.1f} GiB is available: "
                         f"use a window of at most {most} steps, or fewer seeds or sites")
    return need


def check_finite_loss(loss: torch.Tensor, trainable: Trainable, windows: int) -> None:
    """ValueError when a window's loss or gradient is not finite (nothing is saved from it)."""
    grads = [p.grad for p in trainable.parameters() if p.grad is not None]
    if not math.isfinite(float(loss.detach())) or not all(bool(torch.isfinite(g).all()) for g in grads):
        raise ValueError(f"train-loop: the loss or its gradient is not finite in window {windows + 1} "
                         f"(try a smaller --lr or a shorter --window); the last checkpoint is kept")


def train_windows(stages, trainable: Trainable, opt, s: TrainLoopSettings, run: TrainLoopRun,
                  episode: torch.Tensor, on_window: Optional[Callable[[dict], None]] = None) -> torch.Tensor:
    """Train until the CPU budget or ``max_windows`` is spent; returns the episode counters."""
    state = init_state(stages)
    state, episode = restart_ended(stages, state._replace(active=torch.zeros_like(state.active)), episode,
                                   s.seed, s.dispersion)
    c0, budget = time.process_time() - run.cpu_s, s.cpu_minutes * 60.0
    while time.process_time() - c0 < budget and not (s.max_windows and run.windows >= s.max_windows):
        trainable.apply_to(stages)
        loss, terms, state = window_loss(stages, state, s.window, s.loss)
        opt.zero_grad()
        loss.backward()
        check_finite_loss(loss, trainable, run.windows)
        torch.nn.utils.clip_grad_norm_(trainable.parameters(), 1.0)
        opt.step()
        state, episode = restart_ended(stages, state, episode, s.seed, s.dispersion)
        run.windows, run.steps, run.cpu_s = run.windows + 1, run.steps + terms["steps"], time.process_time() - c0
        run.landed, run.ended = run.landed + terms["landed"], run.ended + terms["ended"]
        rec = {"window": run.windows, "loss": float(loss.detach()), **terms, "cpu_s": round(run.cpu_s, 2),
               "values": trainable.describe() if trainable.what != "policy" else None}
        if on_window is not None:
            on_window(rec)
    return episode


def checkpoint_kind(what: str) -> str:
    """``kind`` of a checkpoint of ``what`` (policy, law, filter or estimator)."""
    return {"policy": POLICY_KIND, "filter": FILTER_KIND, "estimator": ESTIMATOR_KIND}.get(what, LAW_KIND)


def save_checkpoint(path: Path, trainable: Trainable, opt, s: TrainLoopSettings, run: TrainLoopRun,
                    episode: torch.Tensor, law: str) -> None:
    """The training's checkpoint (atomic: a temporary file renamed over ``path``)."""
    ck = {"kind": checkpoint_kind(trainable.what), "controller": law,
          "settings": {**asdict(s), "params": list(s.params)}, "run": asdict(run), "episode": episode.cpu(),
          "optimizer": opt.state_dict(), "values": trainable.describe()}
    ck.update(trainable.checkpoint_fields())  # --what estimator: a `dvsland train` checkpoint too
    tmp = path.with_name(path.name + ".tmp")
    torch.save(ck, tmp)
    tmp.replace(path)


__all__ = ["TrainLoopSettings", "TrainLoopRun", "restart_ended", "validate", "train_windows", "save_checkpoint",
           "check_finite_loss", "check_horizon_fits", "checkpoint_kind", "LAW_KIND", "FILTER_KIND", "GRAPH_BYTES_PER_DESCENT_STEP",
           "FIT_GRAPH_BYTES_PER_ROW", "fit_history_rows"]
