"""The closed-loop driver: :class:`ClosedLoop` flies a batch to the end on :func:`loop_step`.

It holds the current :class:`LoopState`, records every :class:`StepOutput` into the traces and
times the stages; the step itself (render -> emulate -> estimate -> filter -> control -> dynamics)
is :func:`dvsland.sim.step.loop_step`. Finished descents stay in the batch, frozen by the
``active`` mask (their state, outcome and summary never change again).
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from typing import Callable, Dict, List, Optional

import numpy as np
import torch

from dvsland.control.gain import loop_gain_fields
from dvsland.estimators.registry import estimator_label
from dvsland.report.checkpoint import estimator_checkpoint

from .result import TraceRecorder
from .state import LoopState
from .step import D_HAT_ABS_MAX, StepOutput, init_state, loop_step
from .termination import INTERRUPTED, OUTCOMES

STAGES = ("render", "emulate", "estimate", "control", "dynamics", "record", "logging")

_log = logging.getLogger("dvsland.sim")


class StageTimer:
    """Accumulates wall seconds (``seconds``) and process CPU seconds (``cpu_seconds``: every
    thread of the process; on a shared machine the CPU time is the cost a stage would have alone,
    the wall time includes waiting for a core) per stage; ``sync=True`` synchronises CUDA around
    each stage."""

    def __init__(self, device, sync: bool = False):
        self.seconds: Dict[str, float] = {k: 0.0 for k in STAGES}
        self.cpu_seconds: Dict[str, float] = {k: 0.0 for k in STAGES}
        self.sync = bool(sync) and torch.device(device).type == "cuda"

    @contextmanager
    def __call__(self, stage: str):
        if self.sync:
            torch.cuda.synchronize()
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            if self.sync:
                torch.cuda.synchronize()
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0
            self.cpu_seconds[stage] = self.cpu_seconds.get(stage, 0.0) + time.process_time() - c0


class ClosedLoop:
    """Flies B descents to the end on :func:`loop_step` and records them: the driver of
    :func:`dvsland.simulate` and the campaigns.

    Args:
        stages: :class:`dvsland.stages.Stages` from :func:`dvsland.stages.build_stages` (the loop
            builds nothing itself).
        state: the state to start from (default :func:`init_state`); read, never written.
        sync_timers: synchronise CUDA around stage timers (profiling only).

    Attributes:
        stages, layout: what it flies.
        state: the current :class:`LoopState` (its pixel buffers are moved in place by the next step:
            copy it to keep it).
        traces: :class:`TraceRecorder` of every step's :class:`StepOutput` and the final state.
        timer: :class:`StageTimer` (seconds per stage).
        n_steps_max: steps in ``simulation.t_max_s``.
    """

    def __init__(self, stages, state: Optional[LoopState] = None, sync_timers: bool = False):
        self.stages = stages
        self.layout = stages.layout
        self.B = stages.layout.batch_size
        self.n_steps_max = stages.settings.n_steps_max
        self.state = init_state(stages) if state is None else state
        # the states the loop made itself are donated to the next step (loop_step(donate=True)); one
        # given by the caller is only read
        self._owned = state is None
        self.traces = TraceRecorder(self.n_steps_max + 1, self.B, torch.device(stages.device))
        self.timer = StageTimer(stages.device, sync_timers)

    @property
    def step_index(self) -> int:
        """Control steps flown so far."""
        return self.state.step

    @property
    def done(self) -> bool:
        """True when no element is active or the step budget is spent (one host sync)."""
        return self.state.step >= self.n_steps_max or self.state.done

    def step(self) -> StepOutput:
        """Fly one control step (finished descents stay frozen) and record it. The step is handed the
        state the loop made (:func:`loop_step` ``donate``): a :class:`LoopState` read from ``state``
        must be copied to be stepped from again after the loop moved on."""
        self.state, out = loop_step(self.stages, self.state, timer=self.timer, donate=self._owned)
        self._owned = True
        with self.timer("record"):
            self.traces.record_output(out)
        return out

    def run(self, on_step: Optional[Callable[["ClosedLoop", StepOutput], None]] = None) -> None:
        """Step until every element has finished or ``t_max_s`` is reached; ``on_step(self, out)``
        after each step."""
        while not self.done:
            out = self.step()
            if on_step is not None:
                with self.timer("logging"):
                    on_step(self, out)
        self.record_final()
        n_bad = int(self.state.n_sanitised.sum())
        if n_bad:
            _log.warning("estimator %r returned %d estimates that were +-inf or |D_hat| > %g 1/s in %d of %d "
                         "descents; they were treated as missing (results: sanitised_estimates)",
                         self.stages.settings.estimator_name, n_bad, D_HAT_ABS_MAX,
                         int((self.state.n_sanitised > 0).sum()), self.B)

    def record_final(self) -> None:
        """Write the final state as the last trace row (thrust NaN)."""
        self.traces.record_final(self.state, self.stages.settings.dt_s)

    def mark_interrupted(self) -> None:
        """Mark still-flying elements as interrupted (after an exception or Ctrl-C)."""
        st = self.state
        self.state = st._replace(outcome=torch.where(st.active, torch.full_like(st.outcome, INTERRUPTED), st.outcome))

    def summaries(self) -> List[dict]:
        """One dict per element (the ``runs`` of results.json), from the state so far."""
        return run_summaries(self.stages, self.state)

    def traces_numpy(self) -> Dict[str, np.ndarray]:
        """Recorded traces (rows, B) plus ``run_label``, ``site``, ``label`` (B,) string arrays."""
        out = self.traces.numpy()
        out["run_label"] = np.asarray(self.layout.run_label)
        out["site"] = np.asarray(self.layout.site)
        out["label"] = np.asarray(self.layout.label)
        return out


def run_summaries(stages, state: LoopState) -> List[dict]:
    """One dict per element (the ``runs`` of results.json) of ``state``."""
    L, cfg = stages.layout, stages.cfg
    st = {k: v.cpu().numpy() for k, v in state._asdict().items()
          if k in ("outcome", "t_end_s", "z_m", "v_mps", "m_kg", "lowest_m", "max_thrust_n", "n_held", "n_missing",
                   "n_sanitised", "n_positive")}
    m0 = stages.settings.mass_kg
    gains = loop_gain_fields(stages.controller, state.m_kg, state.z_m)
    ctl_name = getattr(stages.controller, "controller_name", type(stages.controller).__name__)
    est_label = estimator_label(cfg.estimator.name)  # an alias (mine=pkg.mod:Class) is shown as the alias
    ckpt = estimator_checkpoint(cfg, cfg.estimator.name, stages.estimator)  # a trained estimator's file and hash
    runs = []
    for b in range(L.batch_size):
        runs.append({
            "run": L.run_label[b], "site": L.site[b], "label": L.label[b], "kp": float(L.kp[b]),
            "n_bin": int(L.n_bin[b]), "seed": int(L.seed[b]), "seed_index": int(L.seed_idx[b]),
            "estimator": est_label, "controller": ctl_name, "filter": type(stages.filter).__name__,
            "outcome": OUTCOMES[int(st["outcome"][b])],
            "t_end_s": round(float(st["t_end_s"][b]), 6), "z_end_m": float(st["z_m"][b]), "v_end_mps": float(st["v_mps"][b]),
            "lowest_altitude_m": float(st["lowest_m"][b]), "fuel_used_kg": float(m0 - st["m_kg"][b]),
            "max_thrust_n": float(st["max_thrust_n"][b]),
            **{k: (val if val is None or isinstance(val, str) else float(val[b])) for k, val in gains.items()},
            "z0_m": float(L.z0_m[b]), "v0_mps": float(L.v0_mps[b]),
            "held_steps": int(st["n_held"][b]), "missing_estimates": int(st["n_missing"][b]),
            "sanitised_estimates": int(st["n_sanitised"][b]), "positive_estimates": int(st["n_positive"][b]),
        })
        if ckpt is not None:
            runs[-1]["checkpoint"] = ckpt
        if est_label != cfg.estimator.name:  # the whole import path, to repeat the run
            runs[-1]["estimator_spec"] = cfg.estimator.name
        if L.dispersed:  # a Monte Carlo batch: the element's scene and dispersed values
            runs[-1]["scene"] = L.scene[b]
            runs[-1]["dispersion"] = {k: (int(v[b]) if v.dtype.kind == "i" else float(v[b]))
                                      for k, v in L.dispersed.items()}
    return runs
