"""The batched closed loop: renderer -> emulator -> estimator -> filter -> controller -> dynamics.

One :class:`ClosedLoop` flies B descents at once. Finished descents stay in the batch, frozen
by the ``active`` mask (their state, outcome and summary never change again). Estimators that
need no events (``needs_events = False``, e.g. ``oracle``) skip rendering and emulation.
"""

from __future__ import annotations

import logging
import math
import time
from contextlib import contextmanager
from typing import Callable, Dict, List, Optional

import numpy as np
import torch

from dvsland.config import Config
from dvsland.control import descent_params, make_filter
from dvsland.control.gain import loop_gain_fields
from dvsland.dynamics import LanderDynamics
from dvsland.estimators import Truth

from dvsland.layout import BatchLayout
from .result import TraceRecorder
from .termination import INTERRUPTED, OUTCOMES, RUNNING, termination_code

STAGES = ("render", "emulate", "estimate", "control", "dynamics", "record", "logging")

#: an estimate with |D_hat| above this (1/s) is not a divergence (a descent crashes at |D| = 0.5 1/s
#: by default): like +-inf it is replaced by NaN ("no estimate") and counted per descent
D_HAT_ABS_MAX = 10.0

_log = logging.getLogger("dvsland.sim")


def sanitise_estimates(d_hat: torch.Tensor, abs_max: float = D_HAT_ABS_MAX):
    """Replace estimates that cannot be a divergence by NaN.

    Args:
        d_hat: (B,) float estimates, 1/s (NaN = no estimate).
        abs_max: largest accepted |D_hat|, 1/s.

    Returns:
        (d_clean (B,) same dtype, bad (B,) bool): ``bad`` marks +-inf and |D_hat| > abs_max, now NaN.
        NaN stays NaN and is not counted; a positive (wrong-sign) estimate is kept (the controller's
        ``missing_policy`` handles a non-negative filtered estimate) and counted by the loop.
    """
    bad = torch.isinf(d_hat) | (d_hat.abs() > abs_max)
    return torch.where(bad, torch.full_like(d_hat, float("nan")), d_hat), bad



def _estimator_confidence(estimator, d_hat: torch.Tensor) -> torch.Tensor:
    """The estimator's ``confidence()`` (B,) as float64 in [0, 1] on ``d_hat``'s device; 1 where an
    estimator has no ``confidence()`` and its estimate is finite; 0 where ``d_hat`` is NaN (missing
    or sanitised) or the confidence is not finite."""
    fn = getattr(estimator, "confidence", None)
    c = None if fn is None else fn()
    if c is None:
        c = torch.ones_like(d_hat)
    c = torch.as_tensor(c).to(device=d_hat.device, dtype=torch.float64).reshape(d_hat.shape)
    ok = torch.isfinite(d_hat) & torch.isfinite(c)
    return torch.where(ok, c.clamp(0.0, 1.0), torch.zeros_like(c))


def _nominal_params(params, layout):
    """``params`` with the sites' undispersed initial state (z0, v0): the efference filter's prior
    (a craft knows its planned start, not its dispersion). Unchanged when nothing is dispersed."""
    import dataclasses

    scale = {k: layout.dispersed.get(k) for k in ("z0_scale", "v0_scale")}
    if all(v is None for v in scale.values()):
        return params
    z0, v0 = params.z0_m, params.v0_mps
    if scale["z0_scale"] is not None:
        z0 = z0 / torch.as_tensor(scale["z0_scale"], dtype=z0.dtype, device=z0.device)
    if scale["v0_scale"] is not None:
        v0 = v0 / torch.as_tensor(scale["v0_scale"], dtype=v0.dtype, device=v0.device)
    return dataclasses.replace(params, z0_m=z0, v0_mps=v0)


class StageTimer:
    """Accumulates wall seconds per stage; ``sync=True`` synchronises CUDA around each stage."""

    def __init__(self, device, sync: bool = False):
        self.seconds: Dict[str, float] = {k: 0.0 for k in STAGES}
        self.sync = bool(sync) and torch.device(device).type == "cuda"

    @contextmanager
    def __call__(self, stage: str):
        if self.sync:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self.sync:
                torch.cuda.synchronize()
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0


class ClosedLoop:
    """State and step of the batched closed-loop descent.

    Args:
        cfg: resolved config.
        layout: :class:`BatchLayout` (B elements).
        estimator: a :class:`dvsland.estimators.DivergenceEstimator` for B elements.
        renderer: object with ``render(altitude_m (B,), site_idx (B,) long) -> (B, H, W)``;
            needed only when ``estimator.needs_events``.
        emulator: event emulator with ``reset(frames, t_us)`` and ``step(frames, t_us) -> Events``;
            needed only when ``estimator.needs_events``.
        device: torch device of the state.
        sync_timers: synchronise CUDA around stage timers (profiling only).
        controller: optional :class:`dvsland.control.Controller` for the B elements, replacing
            the configured law ``controller.name`` (it gets the filtered divergence, see ``Controller``).
    """

    def __init__(self, cfg: Config, layout: BatchLayout, estimator, renderer=None, emulator=None,
                 device="cpu", sync_timers: bool = False, controller=None):
        self.cfg = cfg
        self.layout = layout
        self.device = torch.device(device)
        self.estimator = estimator
        self.needs_events = bool(getattr(estimator, "needs_events", True))
        if self.needs_events and (renderer is None or emulator is None):
            raise ValueError(f"estimator {cfg.estimator.name!r} needs events: a renderer and an emulator are required")
        self.renderer = renderer
        self.emulator = emulator
        B = layout.batch_size
        self.B = B
        self.dt_s = float(cfg.dt_s)
        dev = self.device
        f64 = torch.float64
        self.site_idx = layout.tensor("scene_idx", dev, torch.int64)  # the renderer's row (= site unless dispersed)
        self.z0_m = layout.tensor("z0_m", dev, f64)
        self.v0_mps = layout.tensor("v0_mps", dev, f64)
        self.m0_kg = torch.full((B,), float(cfg.dynamics.mass_kg), dtype=f64, device=dev)
        self.kp = layout.tensor("kp", dev, f64)
        self.dynamics = LanderDynamics.from_config(cfg.dynamics)
        self.params = descent_params(cfg, layout, dev)
        if controller is None:
            from dvsland.stages import build_controller

            controller = build_controller(cfg, layout, dev)
        self.controller = controller
        self.filter = make_filter(cfg, self.params if cfg.controller.efference.prior_state == "dispersed"
                                  else _nominal_params(self.params, layout), controller)
        self._needs_altitude = bool(getattr(controller, "needs_altitude", False))
        sim = cfg.simulation
        self.n_steps_max = int(math.ceil(sim.t_max_s / self.dt_s - 1e-9))
        self.traces = TraceRecorder(self.n_steps_max + 1, B, dev)
        self.timer = StageTimer(dev, sync_timers)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Put every element back at its initial conditions."""
        B, dev, f64 = self.B, self.device, torch.float64
        self.z_m = self.z0_m.clone()
        self.v_mps = self.v0_mps.clone()
        self.m_kg = self.m0_kg.clone()
        self.active = torch.ones(B, dtype=torch.bool, device=dev)
        self.outcome = torch.full((B,), RUNNING, dtype=torch.int8, device=dev)
        self.t_end_s = torch.zeros(B, dtype=f64, device=dev)
        self.lowest_m = self.z0_m.clone()
        self.max_thrust_n = torch.zeros(B, dtype=f64, device=dev)
        self.n_held = torch.zeros(B, dtype=torch.int64, device=dev)
        self.n_missing = torch.zeros(B, dtype=torch.int64, device=dev)
        self.n_sanitised = torch.zeros(B, dtype=torch.int64, device=dev)
        self.n_positive = torch.zeros(B, dtype=torch.int64, device=dev)
        self.last_thrust_n: Optional[torch.Tensor] = None  # efference copy: the command held over the last step
        self.last_mass_kg: Optional[torch.Tensor] = None
        self.step_index = 0
        self.estimator.reset(None)
        self.filter.reset(None)
        self.controller.reset(None)
        self.last_frames: Optional[torch.Tensor] = None
        self.last_events = None

    @property
    def t_s(self) -> float:
        """Flight time of the current step, s."""
        return self.step_index * self.dt_s

    @property
    def done(self) -> bool:
        """True when no element is active or the step budget is spent (one host sync)."""
        return self.step_index >= self.n_steps_max or not bool(self.active.any())

    # ------------------------------------------------------------------ one step
    def _render(self) -> torch.Tensor:
        """Frames (B, H, W): rendered for active elements; finished ones keep their last frame
        (so they emit no events and cost no rendering)."""
        r = self.cfg.render
        alt = self.z_m.clamp(r.min_altitude_m, r.max_altitude_m)
        if self.last_frames is None or bool(self.active.all()):
            return self.renderer.render(alt, self.site_idx)
        idx = self.active.nonzero().squeeze(1)
        frames = self.last_frames.clone()
        frames[idx] = self.renderer.render(alt[idx], self.site_idx[idx]).to(frames.dtype)
        return frames

    def step(self) -> None:
        """Fly one control step for all active elements (finished ones stay frozen)."""
        k, dt, tm = self.step_index, self.dt_s, self.timer
        t_s = k * dt
        t_us = int(round(t_s * 1e6))
        truth = Truth(altitude_m=self.z_m, velocity_mps=self.v_mps)
        events = None
        if self.needs_events:
            with tm("render"):
                frames = self._render()
            with tm("emulate"):
                if k == 0:
                    self.emulator.reset(frames, t_us)
                else:
                    events = self.emulator.step(frames, t_us)
            self.last_frames, self.last_events = frames, events
        with tm("estimate"):
            if self.needs_events and events is None:  # first frame: no events yet
                d_hat = torch.full((self.B,), float("nan"), dtype=torch.float32, device=self.device)
            else:
                d_hat = self.estimator.update(events, t_us, truth=truth)
            d_hat = d_hat.to(device=self.device, dtype=torch.float64)
            d_hat, bad = sanitise_estimates(d_hat)  # +-inf or absurd |D_hat| -> NaN, counted
            conf = _estimator_confidence(self.estimator, d_hat)  # (B,) float64, 0 where no estimate
            self.n_sanitised += (bad & self.active).to(torch.int64)
            self.n_positive += ((d_hat > 0) & self.active).to(torch.int64)
        with tm("control"):
            accel = thrust_accel = None
            if self.last_thrust_n is not None:  # the craft knows the acceleration it applied
                thrust_accel = self.last_thrust_n / self.last_mass_kg
                accel = thrust_accel - float(self.cfg.dynamics.g_mps2)
            d_f, n_used = self.filter.update(d_hat, mask=self.active, accel_mps2=accel,
                                             thrust_accel_mps2=thrust_accel, confidence=conf)
            z_hat = getattr(self.filter, "altitude_m", None)
            if self._needs_altitude:
                ctl = self.controller(t_s, d_f, self.m_kg, self.active, altitude_m=z_hat)
            else:
                ctl = self.controller(t_s, d_f, self.m_kg, self.active)
            thrust = torch.where(self.active, ctl.thrust_n, torch.zeros_like(ctl.thrust_n))
            held = ctl.held & self.active
            self.n_held += held.to(torch.int64)
            self.n_missing += (torch.isnan(d_hat) & self.active).to(torch.int64)
        with tm("record"):
            self.traces.record(k, t_s=t_s, z_m=self.z_m, v_mps=self.v_mps, m_kg=self.m_kg, thrust_n=thrust,
                               d_true=truth.divergence, d_est=d_hat, d_filtered=d_f,
                               tau_target_s=ctl.tau_target_s, tau_hat_s=ctl.tau_hat_s,
                               n_used=n_used.to(torch.float64), d_conf=conf, active=self.active, held=held,
                               **({} if z_hat is None else {"z_est_m": z_hat}))
        with tm("dynamics"):
            self.last_thrust_n, self.last_mass_kg = thrust, self.m_kg
            z, v, m, _ = self.dynamics.step(self.z_m, self.v_mps, self.m_kg, thrust, dt)
            act = self.active
            self.z_m = torch.where(act, z, self.z_m)
            self.v_mps = torch.where(act, v, self.v_mps)
            self.m_kg = torch.where(act, m, self.m_kg)
            self.max_thrust_n = torch.where(act, torch.maximum(self.max_thrust_n, thrust), self.max_thrust_n)
            self.lowest_m = torch.where(act, torch.minimum(self.lowest_m, self.z_m), self.lowest_m)
            t_next = (k + 1) * dt
            sim = self.cfg.simulation
            code = termination_code(self.z_m, self.v_mps, t_next, sim.success_altitude_m,
                                    sim.crash_divergence, sim.t_max_s)
            ended = act & (code != RUNNING)
            self.outcome = torch.where(ended, code, self.outcome)
            self.t_end_s = torch.where(act, torch.full_like(self.t_end_s, t_next), self.t_end_s)
            self.active = act & ~ended
        self.step_index = k + 1

    def record_final(self) -> None:
        """Write the final state as the last trace row (thrust NaN)."""
        k = self.step_index
        if k < self.traces.n_rows:
            truth = Truth(self.z_m, self.v_mps)
            self.traces.record(k, t_s=k * self.dt_s, z_m=self.z_m, v_mps=self.v_mps, m_kg=self.m_kg,
                               d_true=truth.divergence, active=self.active)

    def mark_interrupted(self) -> None:
        """Mark still-flying elements as interrupted (after an exception or Ctrl-C)."""
        self.outcome = torch.where(self.active, torch.full_like(self.outcome, INTERRUPTED), self.outcome)

    # ------------------------------------------------------------------ summaries
    def summaries(self) -> List[dict]:
        """One dict per element (the ``runs`` of results.json), from the state so far."""
        L, cfg = self.layout, self.cfg
        outcome = self.outcome.cpu().numpy()
        t_end = self.t_end_s.cpu().numpy()
        z, v, m = self.z_m.cpu().numpy(), self.v_mps.cpu().numpy(), self.m_kg.cpu().numpy()
        low, umax = self.lowest_m.cpu().numpy(), self.max_thrust_n.cpu().numpy()
        held, miss = self.n_held.cpu().numpy(), self.n_missing.cpu().numpy()
        san, pos = self.n_sanitised.cpu().numpy(), self.n_positive.cpu().numpy()
        m0 = float(cfg.dynamics.mass_kg)
        gains = loop_gain_fields(self.controller, self.m_kg, self.z_m)
        runs = []
        for b in range(self.B):
            runs.append({
                "run": L.run_label[b], "site": L.site[b], "label": L.label[b], "kp": float(L.kp[b]),
                "n_bin": int(L.n_bin[b]), "seed": int(L.seed[b]), "seed_index": int(L.seed_idx[b]),
                "estimator": cfg.estimator.name, "controller": getattr(self.controller, "controller_name",
                                                                    type(self.controller).__name__), "filter": type(self.filter).__name__, "outcome": OUTCOMES[int(outcome[b])],
                "t_end_s": round(float(t_end[b]), 6), "z_end_m": float(z[b]), "v_end_mps": float(v[b]),
                "lowest_altitude_m": float(low[b]), "fuel_used_kg": float(m0 - m[b]),
                "max_thrust_n": float(umax[b]),
                **{k: (val if val is None or isinstance(val, str) else float(val[b])) for k, val in gains.items()},
                "z0_m": float(L.z0_m[b]), "v0_mps": float(L.v0_mps[b]),
                "held_steps": int(held[b]), "missing_estimates": int(miss[b]),
                "sanitised_estimates": int(san[b]), "positive_estimates": int(pos[b]),
            })
            if L.dispersed:  # a Monte Carlo batch: the element's scene and dispersed values
                runs[-1]["scene"] = L.scene[b]
                runs[-1]["dispersion"] = {k: (int(v[b]) if v.dtype.kind == "i" else float(v[b]))
                                          for k, v in L.dispersed.items()}
        return runs

    def traces_numpy(self) -> Dict[str, np.ndarray]:
        """Recorded traces (rows, B) plus ``run_label``, ``site``, ``label`` (B,) string arrays."""
        out = self.traces.numpy()
        out["run_label"] = np.asarray(self.layout.run_label)
        out["site"] = np.asarray(self.layout.site)
        out["label"] = np.asarray(self.layout.label)
        return out

    def run(self, on_step: Optional[Callable[["ClosedLoop"], None]] = None) -> None:
        """Step until every element has finished or ``t_max_s`` is reached; ``on_step`` after each step."""
        while not self.done:
            self.step()
            if on_step is not None:
                with self.timer("logging"):
                    on_step(self)
        self.record_final()
        n_bad = int(self.n_sanitised.sum())
        if n_bad:
            _log.warning("estimator %r returned %d estimates that were +-inf or |D_hat| > %g 1/s in %d of %d "
                         "descents; they were treated as missing (results: sanitised_estimates)",
                         self.cfg.estimator.name, n_bad, D_HAT_ABS_MAX, int((self.n_sanitised > 0).sum()), self.B)
