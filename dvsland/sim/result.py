"""What a simulation returns: per-run summaries, per-step traces, where the outputs are."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch

#: Per-step trace fields, each (steps, B). Row k holds the state at t_k and the command held
#: over [t_k, t_k + dt); the last row is the final state (thrust NaN).
TRACE_FIELDS = ("t_s", "z_m", "v_mps", "m_kg", "thrust_n", "d_true", "d_est", "d_filtered",
                "tau_target_s", "tau_hat_s", "n_used", "z_est_m", "d_conf")
TRACE_FLAGS = ("active", "held")


class TraceRecorder:
    """Preallocated device buffers (n_rows, B) filled one row per step (no host sync).

    Args:
        n_rows: maximum number of rows (steps + 1).
        batch_size: B.
        device: torch device.
    """

    def __init__(self, n_rows: int, batch_size: int, device):
        self.n_rows = int(n_rows)
        self.rows = 0
        self.buf = {k: torch.full((self.n_rows, batch_size), float("nan"), dtype=torch.float64, device=device)
                    for k in TRACE_FIELDS}
        self.flags = {k: torch.zeros((self.n_rows, batch_size), dtype=torch.bool, device=device)
                      for k in TRACE_FLAGS}

    def record(self, row: int, **values) -> None:
        """Write ``values`` (each (B,) or scalar) into row ``row``."""
        if not 0 <= row < self.n_rows:
            raise ValueError(f"row must be in [0, {self.n_rows}), got {row}")
        for k, v in values.items():
            target = self.buf[k] if k in self.buf else self.flags[k]
            target[row] = v
        self.rows = max(self.rows, row + 1)

    def record_output(self, out) -> None:
        """Write one :class:`dvsland.sim.StepOutput` into row ``out.step``."""
        extra = {} if out.z_est_m is None else {"z_est_m": out.z_est_m}
        self.record(out.step, t_s=out.t_s, z_m=out.z_m, v_mps=out.v_mps, m_kg=out.m_kg, thrust_n=out.thrust_n,
                    d_true=out.d_true, d_est=out.d_est, d_filtered=out.d_filtered, tau_target_s=out.tau_target_s,
                    tau_hat_s=out.tau_hat_s, n_used=out.n_used, d_conf=out.d_conf, active=out.active,
                    held=out.held, **extra)

    def record_final(self, state, dt_s: float) -> None:
        """Write the final :class:`dvsland.sim.LoopState` as row ``state.step`` (thrust NaN), if it fits."""
        k = state.step
        if k < self.n_rows:
            self.record(k, t_s=k * dt_s, z_m=state.z_m, v_mps=state.v_mps, m_kg=state.m_kg,
                        d_true=state.v_mps / state.z_m, active=state.active)

    def numpy(self, start: int = 0, stop: Optional[int] = None) -> Dict[str, np.ndarray]:
        """Rows [start, stop) (default all recorded) as numpy arrays."""
        stop = self.rows if stop is None else stop
        out = {k: v[start:stop].cpu().numpy() for k, v in self.buf.items()}
        out.update({k: v[start:stop].cpu().numpy() for k, v in self.flags.items()})
        return out


@dataclass
class SimulationResult:
    """The outcome of :func:`dvsland.simulate`.

    Attributes:
        runs: one dict per batch element (site, label, kp, n_bin, estimator, outcome, t_end_s,
            z_end_m, v_end_mps, lowest_altitude_m, fuel_used_kg, max_thrust_n, loop_gain, ...).
        traces: per-step numpy arrays (steps, B), see :data:`TRACE_FIELDS`, plus ``run_label``.
        run_dir: the run folder (config.yaml, results.json, traces.npz, tb/, figures/).
        wall_time_s: wall time of the closed loop (excluding figures), s.
        status: ``"complete"``, ``"interrupted"`` or ``"error"``.
        timings_s: seconds spent per stage (render, emulate, estimate, control, dynamics, logging, ...).
        n_steps: control steps flown.
        sim_time_s: descent-seconds simulated (sum over runs of t_end_s).
    """

    runs: List[dict]
    traces: Dict[str, np.ndarray]
    run_dir: Optional[Path]
    wall_time_s: float
    status: str = "complete"
    timings_s: Dict[str, float] = field(default_factory=dict)
    n_steps: int = 0
    sim_time_s: float = 0.0
    error: Optional[str] = None

    @property
    def real_time_factor(self) -> float:
        """Descent-seconds simulated per wall second (all runs together)."""
        return self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else float("inf")

    def outcome_counts(self) -> Dict[str, int]:
        """How many runs ended in each outcome."""
        out: Dict[str, int] = {}
        for r in self.runs:
            out[r["outcome"]] = out.get(r["outcome"], 0) + 1
        return out
