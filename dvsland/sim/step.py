"""The loop body: ``init_state`` and the one pure step ``loop_step(stages, state, thrust=None)``.

Everything that flies descents runs on :func:`loop_step`: :func:`dvsland.simulate` and the
campaigns, the open-loop evaluation (``thrust`` given), the bench, the training data of
:mod:`dvsland.data` and the gymnasium environment of :mod:`dvsland.envs`::

    stages = build_stages(cfg, "A,D")
    state = init_state(stages)                     # or init_state(stages, z_m=..., v_mps=..., m_kg=...)
    while not state.done and state.step < stages.settings.n_steps_max:
        state, out = loop_step(stages, state)      # out: StepOutput (frames, events, D_hat, thrust, ...)

Within one step: render the frames at the current altitude (active descents only), emulate the
events since the last step, estimate D, filter, command a thrust (the controller's, or ``thrust``),
advance the dynamics over ``dt`` with the thrust held, and end descents that met a termination
condition. Finished descents stay in the state, frozen by ``active``, and leave the hot path
(``simulation.compact``): they are not rendered again and their events are dropped before the
estimator (:func:`compacted`, :func:`active_events`).
"""

from __future__ import annotations

from contextlib import nullcontext
from typing import Any, Callable, NamedTuple, Optional, Tuple

import torch

from dvsland.estimators import Truth
from dvsland.plugins import PluginError, call_plugin, check_batch_tensor

from .state import LiveStages, LoopState, StaleStateError, adopt_state, advance_generation, live_handle
from .termination import RUNNING, termination_code

#: an estimate with |D_hat| above this (1/s) is not a divergence (a descent crashes at |D| = 0.5 1/s
#: by default): like +-inf it is replaced by NaN ("no estimate") and counted per descent
D_HAT_ABS_MAX = 10.0


class StepOutput(NamedTuple):
    """What one :func:`loop_step` observed and commanded; tensors (B,) float64 unless said.

    Row semantics follow the traces: the values at the step's start time ``t_s`` and the command
    held over ``[t_s, t_s + dt)``.

    Attributes:
        step: index of the step (0 for the first).
        t_s: flight time at the step's start, s.
        t_us: the same, int µs (the events' time base).
        z_m, v_mps, m_kg: true state at ``t_s``.
        d_true: true divergence v/z at ``t_s``, 1/s.
        d_est: the estimator's D_hat (NaN = none, also where sanitised), 1/s.
        d_conf: the estimator's confidence in [0, 1] (0 where no estimate).
        d_filtered: the filter's output, 1/s.
        n_used: estimates the filter used (float64).
        thrust_n: thrust held over the step, N (0 for finished descents).
        held: bool, the controller held its last command (missing or non-negative estimate).
        tau_target_s, tau_hat_s: the law's target and estimated time to contact, s (NaN if none).
        z_est_m: the filter's altitude estimate, m (None unless the filter provides one).
        active: bool, flying during this step.
        ended: bool, ended at this step's end (``outcome`` of the returned state tells how).
        frames: (B, H, W) float32 frames rendered at ``t_s`` (None without events).
        events: :class:`dvsland.events.Events` of ``(t_prev, t_s]`` (None at step 0 or without events).
        diagnostics: zero-argument callable returning the estimator's ``diagnostics()`` dict for this
            step (valid until the next step; ``{}`` when it has none).
    """

    step: int
    t_s: float
    t_us: int
    z_m: torch.Tensor
    v_mps: torch.Tensor
    m_kg: torch.Tensor
    d_true: torch.Tensor
    d_est: torch.Tensor
    d_conf: torch.Tensor
    d_filtered: torch.Tensor
    n_used: torch.Tensor
    thrust_n: torch.Tensor
    held: torch.Tensor
    tau_target_s: Any
    tau_hat_s: Any
    z_est_m: Optional[torch.Tensor]
    active: torch.Tensor
    ended: torch.Tensor
    frames: Optional[torch.Tensor]
    events: Any
    diagnostics: Callable[[], dict]


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


def estimator_confidence(estimator, d_hat: torch.Tensor, name: str = "estimator") -> torch.Tensor:
    """The estimator's ``confidence()`` (B,) as float64 in [0, 1] on ``d_hat``'s device; 1 where an
    estimator has no ``confidence()`` (or it returns None) and its estimate is finite; 0 where
    ``d_hat`` is NaN (missing or sanitised) or the confidence is not finite.

    Raises:
        PluginError: ``confidence()`` raised or returned something other than None or a (B,)
            floating tensor on the loop's device (``name`` is the plug-in's name in the message).
    """
    fn = getattr(estimator, "confidence", None)
    c = None if not callable(fn) else call_plugin(name, "confidence", fn)
    c = check_batch_tensor(c, d_hat.shape[0], d_hat.device, name, "confidence", allow_none=True)
    if c is None:
        c = torch.ones_like(d_hat)
    c = c.to(dtype=torch.float64)
    ok = torch.isfinite(d_hat) & torch.isfinite(c)
    return torch.where(ok, c.clamp(0.0, 1.0), torch.zeros_like(c))


# ------------------------------------------------------------------ initial state
def init_state(stages, z_m=None, v_mps=None, m_kg=None) -> LoopState:
    """The state at step 0: every descent at its initial conditions, every stage reset.

    Args:
        stages: :class:`dvsland.stages.Stages`.
        z_m, v_mps, m_kg: optional initial altitude (m, > 0), velocity (m/s) and mass (kg, > 0):
            scalars or (B,) values; default the layout's z0, v0 and ``dynamics.mass_kg``. The
            controller's target and the filter's prior keep the configured (planned) start.

    Raises:
        ValueError: a start value of the wrong shape, not finite, or out of range (names it).
    """
    L, dev, f64 = stages.layout, torch.device(stages.device), torch.float64
    B = L.batch_size
    z = _start("z_m", L.tensor("z0_m", dev, f64) if z_m is None else z_m, B, dev, positive=True)
    v = _start("v_mps", L.tensor("v0_mps", dev, f64) if v_mps is None else v_mps, B, dev)
    m = _start("m_kg", stages.settings.mass_kg if m_kg is None else m_kg, B, dev, positive=True)
    names = (stages.settings.estimator_name, "filter", _controller_name(stages))
    for name, stage in zip(names, (stages.estimator, stages.filter, stages.controller)):
        call_plugin(name, "reset", stage.reset, None)
    zeros_i = torch.zeros(B, dtype=torch.int64, device=dev)
    zeros_f = torch.zeros(B, dtype=f64, device=dev)
    state = LoopState(step=0, z_m=z, v_mps=v, m_kg=m, active=torch.ones(B, dtype=torch.bool, device=dev),
                      outcome=torch.full((B,), RUNNING, dtype=torch.int8, device=dev), t_end_s=zeros_f,
                      lowest_m=z.clone(), max_thrust_n=zeros_f.clone(), n_held=zeros_i, n_missing=zeros_i.clone(),
                      n_sanitised=zeros_i.clone(), n_positive=zeros_i.clone(), last_thrust_n=None,
                      last_mass_kg=None, last_frames=None, stage_state=advance_generation(stages))
    return state


def _controller_name(stages) -> str:
    ctl = stages.controller
    return str(getattr(ctl, "controller_name", None) or stages.cfg.controller.name)


def _start(name: str, value, B: int, dev, positive: bool = False) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=torch.float64).to(dev)
    if t.dim() == 0:
        t = t.expand(B).clone()
    if t.shape != (B,):
        raise ValueError(f"{name} must be a scalar or of shape ({B},), got shape {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()) or (positive and not bool((t > 0).all())):
        raise ValueError(f"{name} must be finite{' and > 0' if positive else ''}, got {t.tolist()}")
    return t


# ------------------------------------------------------------------ the step
class Sensed(NamedTuple):
    """A step that has sensed but not yet acted (:func:`sense_step`), for callers that choose the
    thrust after seeing the step's estimates (an environment's agent).

    Attributes:
        state: the state the step started from (consumed: its stage state moved on).
        out: the :class:`StepOutput` so far; ``thrust_n`` is the law's command (0 for finished
            descents) and ``ended`` is all False until :func:`act_step`.
        bad: (B,) bool, estimates replaced by NaN at this step.
        handle: the stages' state right after sensing (checked by :func:`act_step`).
    """

    state: LoopState
    out: StepOutput
    bad: torch.Tensor
    handle: LiveStages


def loop_step(stages, state: LoopState, thrust: Optional[torch.Tensor] = None,
              timer: Optional[Callable[[str], Any]] = None) -> Tuple[LoopState, StepOutput]:
    """Fly one control step of every active descent: :func:`sense_step` then :func:`act_step`.

    Args:
        stages: :class:`dvsland.stages.Stages` (built by :func:`dvsland.stages.build_stages`).
        state: the state to step from. A live state (as returned by the previous call) is consumed;
            a cloned one (:func:`dvsland.sim.clone_state`) can be stepped from again.
        thrust: None (the controller's command) or (B,) thrust in N to apply instead (open loop,
            a learned controller, an environment's action); must be finite and >= 0. The filter and
            controller still run (their outputs are reported), the given thrust is what flies.
        timer: optional ``timer(stage_name)`` context manager factory (per-stage timing).

    Returns:
        (the next :class:`LoopState`, the :class:`StepOutput` of this step).

    Raises:
        StaleStateError: ``state`` was already consumed.
        ValueError: ``thrust`` of the wrong shape, NaN or negative.
        PluginError: the estimator or the law broke its contract (:mod:`dvsland.plugins`).
    """
    thrust = _checked_thrust(thrust, state.z_m)  # before sensing: a bad thrust consumes nothing
    return act_step(stages, sense_step(stages, state, timer), thrust, timer)


def sense_step(stages, state: LoopState, timer: Optional[Callable[[str], Any]] = None) -> Sensed:
    """The first half of a step: render, emulate, estimate, filter and run the law at ``t_k``.

    Consumes ``state`` like :func:`loop_step`; finish the step with :func:`act_step`.
    """
    tm = timer or (lambda name: nullcontext())
    adopt_state(stages, state)
    k = state.step
    t_s = k * stages.settings.dt_s
    t_us = int(round(t_s * 1e6))
    compact = compacted(stages, state)
    frames, events = _sense(stages, state, t_us, tm, compact)
    with tm("estimate"):
        d_hat, conf, bad = _estimate(stages, state, events, t_us)
    with tm("control"):
        ctl, d_f, n_used, z_hat = _control(stages, state, d_hat, conf, t_s)
        u = _applied_thrust(ctl.thrust_n, None, state.active)
    diag = getattr(stages.estimator, "diagnostics", None)
    out = StepOutput(step=k, t_s=t_s, t_us=t_us, z_m=state.z_m, v_mps=state.v_mps, m_kg=state.m_kg,
                     d_true=Truth(state.z_m, state.v_mps).divergence, d_est=d_hat, d_conf=conf, d_filtered=d_f,
                     n_used=n_used.to(torch.float64), thrust_n=u, held=ctl.held & state.active,
                     tau_target_s=ctl.tau_target_s, tau_hat_s=ctl.tau_hat_s, z_est_m=z_hat, active=state.active,
                     ended=torch.zeros_like(state.active), frames=frames, events=events,
                     diagnostics=(lambda: (diag() or {})) if callable(diag) else dict)
    return Sensed(state, out, bad, advance_generation(stages))


def act_step(stages, sensed: Sensed, thrust: Optional[torch.Tensor] = None,
             timer: Optional[Callable[[str], Any]] = None) -> Tuple[LoopState, StepOutput]:
    """The second half of a step: fly ``dt`` with the law's command (``thrust=None``) or ``thrust``
    (B,) N held, then bookkeeping and termination; returns (next state, the step's StepOutput).

    Raises:
        StaleStateError: ``sensed`` is not the stages' latest sensing (acted on already).
        ValueError: ``thrust`` of the wrong shape, NaN or negative.
    """
    if sensed.handle != live_handle(stages):
        raise StaleStateError(f"step {sensed.out.step} was already acted on (or the stages moved on): "
                              "sense again from the newest state")
    tm = timer or (lambda name: nullcontext())
    state, out = sensed.state, sensed.out
    u = _applied_thrust(out.thrust_n, _checked_thrust(thrust, state.z_m), state.active)
    with tm("dynamics"):
        nxt, ended = _advance(stages, state, u, out.held, out.d_est, sensed.bad, out.frames)
    return nxt, out._replace(thrust_n=u, ended=ended)


def _sense(stages, state: LoopState, t_us: int, tm, compact: bool = False):
    """Render (active descents; finished ones keep their last frame) and emulate; (frames, events)."""
    if stages.events is None:
        return None, None
    with tm("render"):
        frames = _render(stages, state)
    with tm("emulate"):
        if state.step == 0:
            stages.emulator.reset(frames, t_us)
            return frames, None
        events = stages.emulator.step(frames, t_us)
        if compact:  # finished descents' events never reach the estimator
            events = active_events(events, state.active)
    return frames, events


def compacted(stages, state: LoopState) -> bool:
    """True when finished descents leave this step's hot path (``simulation.compact`` and at least
    one descent has finished): their events are dropped before the estimator, which then has
    nothing new to work on for them (their frames are never rendered again either way). One host
    sync."""
    return bool(getattr(stages.settings, "compact", True)) and not bool(state.active.all())


def active_events(events, active: torch.Tensor):
    """``events`` without those of finished descents: ``active`` (B,) bool indexed by each event's
    ``b``; the order (sorted by (b, t)) is kept. None stays None."""
    if events is None or len(events) == 0:
        return events
    keep = active[events.b]
    return events if bool(keep.all()) else events[keep]


def _render(stages, state: LoopState) -> torch.Tensor:
    s = stages.settings
    alt = state.z_m.clamp(s.render_min_altitude_m, s.render_max_altitude_m)
    site_idx = stages.scene_idx
    if state.last_frames is None or bool(state.active.all()):
        return stages.events.render(alt, site_idx)
    idx = state.active.nonzero().squeeze(1)
    frames = state.last_frames.clone()
    frames[idx] = stages.events.render(alt[idx], site_idx[idx]).to(frames.dtype)
    return frames


def _estimate(stages, state: LoopState, events, t_us: int):
    """(d_hat (B,) float64 sanitised, confidence (B,) float64, bad (B,) bool)."""
    B, dev, name = state.batch_size, state.z_m.device, stages.settings.estimator_name
    if stages.events is not None and events is None:  # first frame: no events yet
        d_hat = torch.full((B,), float("nan"), dtype=torch.float32, device=dev)
    else:
        truth = Truth(altitude_m=state.z_m, velocity_mps=state.v_mps)
        d_hat = call_plugin(name, "update", stages.estimator.update, events, t_us, truth=truth)
        d_hat = check_batch_tensor(d_hat, B, dev, name, "update")
    d_hat = d_hat.to(dtype=torch.float64)
    d_hat, bad = sanitise_estimates(d_hat)  # +-inf or absurd |D_hat| -> NaN, counted
    return d_hat, estimator_confidence(stages.estimator, d_hat, name), bad


def _control(stages, state: LoopState, d_hat, conf, t_s: float):
    """Filter the estimate (with the efference copy) and run the law; (ControlOutput, d_f, n_used, z_hat)."""
    accel = thrust_accel = None
    if state.last_thrust_n is not None:  # the craft knows the acceleration it applied
        thrust_accel = state.last_thrust_n / state.last_mass_kg
        accel = thrust_accel - stages.settings.g_mps2
    d_f, n_used = stages.filter.update(d_hat, mask=state.active, accel_mps2=accel,
                                       thrust_accel_mps2=thrust_accel, confidence=conf)
    z_hat = getattr(stages.filter, "altitude_m", None)
    ctl, name = stages.controller, _controller_name(stages)
    kw = {"altitude_m": z_hat} if getattr(ctl, "needs_altitude", False) else {}
    out = call_plugin(name, "__call__", ctl, t_s, d_f, state.m_kg, state.active, **kw)
    thrust = getattr(out, "thrust_n", None)
    thrust = check_batch_tensor(thrust, state.batch_size, state.z_m.device, name, "__call__ (thrust_n)")
    if bool(torch.isnan(thrust).any()):
        raise PluginError(name, "__call__", "thrust_n is NaN; a law must command a number (hover or hold when "
                                            "its input is missing)")
    return out, d_f, n_used, z_hat


def _checked_thrust(thrust, like: torch.Tensor) -> Optional[torch.Tensor]:
    """``thrust`` as a (B,) float64 tensor on ``like``'s device (None stays None).

    Raises:
        ValueError: the wrong shape, not finite or negative (names ``thrust`` and the range).
    """
    if thrust is None:
        return None
    u = torch.as_tensor(thrust).to(device=like.device, dtype=torch.float64)
    if u.dim() == 0:
        u = u.expand_as(like)
    if u.shape != like.shape:
        raise ValueError(f"thrust must be of shape {tuple(like.shape)}, got {tuple(u.shape)}")
    if not bool(torch.isfinite(u).all()) or bool((u < 0).any()):
        raise ValueError(f"thrust must be finite and >= 0 N, got {u.tolist()}")
    return u


def _applied_thrust(ctl_thrust: torch.Tensor, thrust: Optional[torch.Tensor], active: torch.Tensor) -> torch.Tensor:
    """The thrust that flies: the controller's or the given (checked) one, 0 for finished descents."""
    u = ctl_thrust if thrust is None else thrust
    return torch.where(active, u, torch.zeros_like(u))


def _advance(stages, state: LoopState, u, held, d_hat, bad, frames) -> Tuple[LoopState, torch.Tensor]:
    """Dynamics over dt with ``u`` held, bookkeeping and termination; (next state, ended (B,) bool)."""
    s, act = stages.settings, state.active
    z, v, m, _ = stages.dynamics.step(state.z_m, state.v_mps, state.m_kg, u, s.dt_s)
    z = torch.where(act, z, state.z_m)
    v = torch.where(act, v, state.v_mps)
    m = torch.where(act, m, state.m_kg)
    t_next = (state.step + 1) * s.dt_s
    code = termination_code(z, v, t_next, s.success_altitude_m, s.crash_divergence, s.t_max_s)
    ended = act & (code != RUNNING)
    i64 = torch.int64
    nxt = state._replace(
        step=state.step + 1, z_m=z, v_mps=v, m_kg=m, active=act & ~ended,
        outcome=torch.where(ended, code, state.outcome),
        t_end_s=torch.where(act, torch.full_like(state.t_end_s, t_next), state.t_end_s),
        lowest_m=torch.where(act, torch.minimum(state.lowest_m, z), state.lowest_m),
        max_thrust_n=torch.where(act, torch.maximum(state.max_thrust_n, u), state.max_thrust_n),
        n_held=state.n_held + held.to(i64), n_missing=state.n_missing + (torch.isnan(d_hat) & act).to(i64),
        n_sanitised=state.n_sanitised + (bad & act).to(i64), n_positive=state.n_positive + ((d_hat > 0) & act).to(i64),
        last_thrust_n=u, last_mass_kg=state.m_kg, last_frames=frames if frames is not None else state.last_frames,
        stage_state=advance_generation(stages))
    return nxt, ended


__all__ = ["StepOutput", "Sensed", "init_state", "loop_step", "sense_step", "act_step", "sanitise_estimates",
           "estimator_confidence", "D_HAT_ABS_MAX"]
