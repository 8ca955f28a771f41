"""The loop body: the one pure step ``loop_step(stages, state, thrust=None)`` and its parts.

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
estimator (:func:`active_events`).

The step is a composition of public pure parts over the :class:`LoopState` (none of them changes
its inputs; each stage's state goes in and comes out, :mod:`dvsland.pytree`):
:func:`render` (frames), :func:`sense` (events), :func:`estimate` (D_hat), :func:`act` (filter
and law) and :func:`advance` (dynamics and termination). :func:`sense_step` runs the first four and
:func:`act_step` the last, for callers that choose the thrust after seeing the estimates (an
environment's agent).
"""

from __future__ import annotations

from contextlib import nullcontext
from typing import Any, Callable, NamedTuple, Optional, Tuple

import torch

from dvsland.estimators import Truth
from dvsland.events import EventEmulator
from dvsland.events.emulator import compiled_pixel_step
from dvsland.events.emulator_rows import emulator_step_rows
from dvsland.plugins import call_plugin, check_batch_tensor
from dvsland.pytree import ObjectStage

from .contracts import check_loop_state, check_no_nan_thrust, checked_thrust_out, stage_fns
from .reset import init_state, reset_where
from .state import LoopState, StageStates
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
        diagnostics: zero-argument callable returning the estimator's diagnostics dict for this
            step (``{}`` when it has none).
        t_flight_s: (B,) float64 flight time of each descent at the step's start, s (``t_s``
            unless a descent was restarted by :func:`dvsland.sim.reset_where`).
        control_residual: (B,) float64 a residual law's correction as a share of its reach
            (:attr:`dvsland.control.base.ControlOutput.residual`; None for other laws).
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
    t_flight_s: Optional[torch.Tensor] = None
    control_residual: Optional[torch.Tensor] = None


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



def confidence_of(conf: torch.Tensor, d_hat: torch.Tensor) -> torch.Tensor:
    """An estimator's confidence (B,) as float64 in [0, 1]; 0 where ``d_hat`` is NaN (missing or
    sanitised) or the confidence is not finite."""
    c = conf.to(dtype=torch.float64)
    ok = torch.isfinite(d_hat) & torch.isfinite(c)
    return torch.where(ok, c.clamp(0.0, 1.0), torch.zeros_like(c))


class Estimate(NamedTuple):
    """What :func:`estimate` returns besides the estimator's next state; (B,) tensors.

    Attributes:
        d_hat: float64 D_hat, 1/s, sanitised (NaN = none).
        confidence: float64 in [0, 1].
        bad: bool, estimates replaced by NaN at this step.
        diagnostics: the estimator's diagnostics dict.
    """

    d_hat: torch.Tensor
    confidence: torch.Tensor
    bad: torch.Tensor
    diagnostics: dict


class Command(NamedTuple):
    """What :func:`act` returns besides the filter's and the law's next states.

    Attributes:
        control: the law's :class:`dvsland.control.ControlOutput` (thrust checked).
        d_filtered: (B,) float64 filtered D, 1/s.
        n_used: (B,) estimates the filter used.
        z_est_m: (B,) float64 the filter's altitude estimate, m, or None.
    """

    control: Any
    d_filtered: torch.Tensor
    n_used: torch.Tensor
    z_est_m: Optional[torch.Tensor]


class Sensed(NamedTuple):
    """A step that has sensed but not yet acted (:func:`sense_step`), for callers that choose the
    thrust after seeing the step's estimates (an environment's agent). Plain data: it can be acted
    on any number of times.

    Attributes:
        state: the state the step started from (unchanged).
        out: the :class:`StepOutput` so far; ``thrust_n`` is the law's command (0 for finished
            descents) and ``ended`` is all False until :func:`act_step`.
        bad: (B,) bool, estimates replaced by NaN at this step.
        stage_state: the :class:`StageStates` after sensing, estimating, filtering and the law.
    """

    state: LoopState
    out: StepOutput
    bad: torch.Tensor
    stage_state: StageStates


# ------------------------------------------------------------------ the parts
def flight_time_s(stages, state: LoopState) -> torch.Tensor:
    """(B,) float64 flight time of each descent at the state's step, s."""
    return state.flight_step.to(torch.float64) * stages.settings.dt_s


def render(stages, state: LoopState, all_active: Optional[bool] = None,
           rows: Optional[torch.Tensor] = None) -> Optional[torch.Tensor]:
    """Frames (B, H, W) float32 at the current altitudes of the active descents (finished ones keep
    their last frame); None when the estimator needs no events. ``all_active``: whether every
    descent flies (read from ``state.active`` when None: one host sync); ``rows``: the active
    descents' indices (K,) int64 when the caller has them."""
    if stages.events is None:
        return None
    s = stages.settings
    # frames are inputs (no gradient); clamped (NaN too), the altitudes are in the renderer's range and
    # the scene indices come from the layout, so the renderer need not check them (no host sync)
    alt = state.z_m.detach().nan_to_num(s.render_max_altitude_m).clamp(s.render_min_altitude_m,
                                                                       s.render_max_altitude_m)
    if all_active is None:
        all_active = bool(state.active.all())
    if state.last_frames is None or all_active:
        return stages.events.render(alt, state.scene_idx, in_range=True)
    idx = state.active.nonzero().squeeze(1) if rows is None else rows
    new = stages.events.render(alt.index_select(0, idx), state.scene_idx.index_select(0, idx), in_range=True)
    return state.last_frames.index_copy(0, idx, new.to(state.last_frames.dtype))  # one pass: copy and put


#: the built-in emulator steps only the flying descents once they are at most this share of the batch
#: (0: never). Taking their rows out and putting them back copies the state, so that pays only when
#: most of the batch has finished: on this project's CPU, B = 90, 20.4 ms for the whole batch's step
#: against 12.9 / 9.4 / 6.6 ms for 22 / 11 / 2 rows, and 77.7 ms for all 90 (benchmarks.md)
EMULATOR_ROWS_SHARE = 0.25
#: the same where the compiled pixel kernel runs (CPU): its whole-batch step over the finished rows'
#: unchanged frames is one memory pass, so the copies pay only below this share: B = 63, 3.9 ms for
#: the whole batch against 3.2 / 3.6-3.9 / 3.9-4.6 / 5.9 ms for 4 / 6 / 8 / 15 rows (benchmarks.md)
EMULATOR_ROWS_SHARE_COMPILED = 0.1


def sense(stages, state: LoopState, frames: Optional[torch.Tensor], t_us: int, compact: bool = False,
          rows: Optional[torch.Tensor] = None, donate: bool = False):
    """The emulator's step to ``t_us`` on ``frames``: (emulator state, Events of (t_prev, t_us] or None).

    The first frame (and a batch without events) gives no events. Descents restarted since the last
    step (``state.restarted``) restart their pixels on these frames: their events are dropped.
    Finished descents' events are dropped when ``compact``; given ``rows`` (K,) int64, the active
    descents' indices, and at most :data:`EMULATOR_ROWS_SHARE` of the batch flying
    (:data:`EMULATOR_ROWS_SHARE_COMPILED` where the compiled pixel kernel runs), the built-in
    emulator steps only those (:func:`emulator_step_rows`: the same events, and a finished
    descent's pixels cost nothing). ``donate``: the built-in emulator updates the state's pixel
    buffers in place (:func:`~dvsland.events.emulator.emulator_step`), so ``state`` must not be
    stepped from again.
    """
    if frames is None:
        return None, None
    emu, st = stage_fns(stages).emulator, state.stage_state.emulator
    if st is None:
        return emu.init_state(frames, t_us, state.noise_seed), None
    if compact and rows is not None and isinstance(emu, EventEmulator) and rows.numel() <= frames.shape[0] * (
            EMULATOR_ROWS_SHARE_COMPILED if compiled_pixel_step(emu.params, st) else EMULATOR_ROWS_SHARE):
        st, events = emulator_step_rows(emu.params, st, frames, t_us, rows)
    else:  # only the built-in emulator takes donate (a plug-in's step_state may not)
        kw = {"donate": True} if donate and isinstance(emu, EventEmulator) else {}
        st, events = emu.step_state(st, frames, t_us, **kw)
    keep = state.active if compact else None
    if state.restarted is not None:
        st = emu.reset_where(st, state.restarted, frames, t_us, state.noise_seed)
        keep = ~state.restarted if keep is None else keep & ~state.restarted
    if keep is not None:
        events = active_events(events, keep)
    return st, events


def estimate(stages, state: LoopState, events, t_us: int, grad: bool = False,
             donate: bool = False) -> Tuple[Any, Estimate]:
    """The estimator's step on ``events``: (estimator state, :class:`Estimate`).

    Event estimators give no estimate on the first frame and for descents restarted at this step.
    ``grad=True`` keeps the estimate's autograd graph (otherwise it is detached at this boundary);
    ``grad="straight_through"`` makes D_hat = D_true(z, v) + (D_hat - D_true) held fixed: the
    estimate's value, with the gradient of the true divergence (events are inputs, not functions
    of the state, so an event estimator's output has no other path back to the state).
    ``donate``: an estimator that ``accepts_donate`` may work in the state's buffers (see
    :func:`loop_step`).
    """
    fns = stage_fns(stages)
    B, dev, name = state.batch_size, state.z_m.device, fns.estimator_name
    st = state.stage_state.estimator
    if stages.events is not None and events is None:  # first frame: no events yet
        d = torch.full((B,), float("nan"), dtype=torch.float64, device=dev)
        return st, Estimate(d, torch.zeros_like(d), torch.zeros(B, dtype=torch.bool, device=dev), {})
    truth = Truth(altitude_m=state.z_m, velocity_mps=state.v_mps)
    kw = {"donate": True} if donate and getattr(fns.estimator, "accepts_donate", False) else {}
    st, out = call_plugin(name, "update", fns.estimator.step_state, st, events, t_us, truth, **kw)
    d_hat = check_batch_tensor(out.d_hat, B, dev, name, "update", detach=not grad).to(dtype=torch.float64)
    if stages.events is not None and state.restarted is not None:
        # a restarted descent leaves this step as a new one leaves its first frame: no estimate, and
        # an estimator state that has seen nothing (so its first window starts on the next step)
        st = fns.estimator.reset_where(st, state.restarted)
        d_hat = torch.where(state.restarted, torch.full_like(d_hat, float("nan")), d_hat)
    d_hat, bad = sanitise_estimates(d_hat)  # +-inf or absurd |D_hat| -> NaN, counted
    if grad == "straight_through":
        d_true = truth.divergence.to(torch.float64)
        d_hat = d_true + (d_hat - d_true).detach()
    conf = check_batch_tensor(out.confidence, B, dev, name, "confidence", detach=not grad)
    return st, Estimate(d_hat, confidence_of(conf, d_hat), bad, out.diagnostics)


def act(stages, state: LoopState, est: Estimate) -> Tuple[Any, Any, Command]:
    """Filter the estimate (with the efference copy) and run the law at each descent's flight time:
    (filter state, law state, :class:`Command`)."""
    fns = stage_fns(stages)
    accel = thrust_accel = None
    if state.last_thrust_n is not None:  # the craft knows the acceleration it applied
        thrust_accel = state.last_thrust_n / state.last_mass_kg
        accel = thrust_accel - stages.settings.g_mps2
    if state.restarted is not None and accel is not None:  # a restarted descent has no efference copy yet
        nan = torch.full_like(accel, float("nan"))
        accel, thrust_accel = torch.where(state.restarted, nan, accel), torch.where(state.restarted, nan, thrust_accel)
    f_st, f_out = fns.filter.step_state(state.stage_state.filter, est.d_hat, state.active, accel, thrust_accel,
                                        est.confidence)
    d_f, n_used, z_hat = f_out[0], f_out[1], f_out[2]
    kw = {"estimate": (est.d_hat, est.confidence)} if getattr(fns.controller, "needs_estimate", False) else {}
    if getattr(fns.controller, "needs_doubt", False):  # make_filter checked that the filter gives it
        kw["doubt"] = f_out[3]
    if getattr(fns.controller, "needs_velocity_sigma", False):  # make_filter checked that the filter gives it
        kw["velocity_sigma_mps"] = f_out[4]
    c_st, ctl = call_plugin(fns.controller_name, "__call__", fns.controller.step_state, state.stage_state.controller,
                            flight_time_s(stages, state), d_f, state.m_kg, state.active, z_hat, **kw)
    checked_thrust_out(ctl, state.batch_size, state.z_m.device, fns.controller_name)
    if isinstance(fns.controller, ObjectStage):  # a plug-in law: its command is checked (one host sync)
        check_no_nan_thrust(ctl.thrust_n, fns.controller_name)
    return f_st, c_st, Command(ctl, d_f, n_used, z_hat)


def advance(stages, state: LoopState, thrust: torch.Tensor, held: torch.Tensor, est: Estimate,
            frames: Optional[torch.Tensor], stage_state: StageStates,
            terminate: bool = True) -> Tuple[LoopState, torch.Tensor]:
    """Dynamics over dt with ``thrust`` (B,) N held, bookkeeping and termination: (next state with
    ``stage_state``, ended (B,) bool). ``terminate=False`` ends no descent (a prescribed profile
    that climbs or goes below the success altitude keeps flying)."""
    s, act_ = stages.settings, state.active
    z, v, m, _ = stages.dynamics.step(state.z_m, state.v_mps, state.m_kg, thrust, s.dt_s)
    z = torch.where(act_, z, state.z_m)
    v = torch.where(act_, v, state.v_mps)
    m = torch.where(act_, m, state.m_kg)
    t_next = (state.flight_step + 1).to(torch.float64) * s.dt_s
    code = termination_code(z, v, t_next, s.success_altitude_m, s.crash_divergence, s.t_max_s)
    ended = act_ & (code != RUNNING) if terminate else torch.zeros_like(act_)
    i64, d_hat = torch.int64, est.d_hat
    nxt = state._replace(
        step=state.step + 1, flight_step=state.flight_step + 1, z_m=z, v_mps=v, m_kg=m, active=act_ & ~ended,
        outcome=torch.where(ended, code, state.outcome), t_end_s=torch.where(act_, t_next, state.t_end_s),
        lowest_m=torch.where(act_, torch.minimum(state.lowest_m, z), state.lowest_m),
        max_thrust_n=torch.where(act_, torch.maximum(state.max_thrust_n, thrust), state.max_thrust_n),
        n_held=state.n_held + held.to(i64), n_missing=state.n_missing + (torch.isnan(d_hat) & act_).to(i64),
        n_sanitised=state.n_sanitised + (est.bad & act_).to(i64),
        n_positive=state.n_positive + ((d_hat > 0) & act_).to(i64),
        last_thrust_n=thrust, last_mass_kg=state.m_kg, last_frames=frames if frames is not None else state.last_frames,
        restarted=None, stage_state=stage_state)
    return nxt, ended


# ------------------------------------------------------------------ the step
def loop_step(stages, state: LoopState, thrust: Optional[torch.Tensor] = None,
              timer: Optional[Callable[[str], Any]] = None, terminate: bool = True,
              grad: bool = False, donate: bool = False) -> Tuple[LoopState, StepOutput]:
    """Fly one control step of every active descent: :func:`sense_step` then :func:`act_step`.

    Pure: ``state`` is not changed and can be stepped from again (the same outputs).

    Args:
        stages: :class:`dvsland.stages.Stages` (built by :func:`dvsland.stages.build_stages`).
        state: the state to step from.
        thrust: None (the controller's command) or (B,) thrust in N to apply instead (open loop,
            a learned controller, an environment's action); must be finite and >= 0. The filter and
            controller still run (their outputs are reported), the given thrust is what flies.
        timer: optional ``timer(stage_name)`` context manager factory (per-stage timing).
        terminate: end descents that meet a termination condition (False: none ends, see
            :func:`advance`).
        grad: keep the autograd graph through the estimate (the dynamics, filter and law are
            differentiable torch maths; termination masks are constants; a thrust given in ``thrust``
            keeps its graph too). With the ``oracle`` the estimate is a function of (z, v), so the
            gradient runs through the whole closed loop. ``"straight_through"``: the estimate's value
            with the true divergence's gradient (any estimator; see :func:`estimate`). Off by default
            (the estimate is detached).
        donate: hand ``state``'s per-pixel buffers to the step (JAX's donated arguments): the
            built-in emulator then moves its pixels' reference and last-event times in place
            instead of writing new arrays (a third of its pass on this project's CPU), an estimator
            that ``accepts_donate`` (``dpr``, ``learned``) its window, and ``state`` must not be
            stepped from again (its flight values stay valid). The loop runners that made their
            state donate it (:class:`~dvsland.sim.ClosedLoop`, the fleet, the evaluation's
            ``fly_profile``, ``dvsland bench``). Off by default: the step is then pure.

    Returns:
        (the next :class:`LoopState`, the :class:`StepOutput` of this step).

    Raises:
        ValueError: ``thrust`` of the wrong shape, NaN or negative; a ``state`` that does not fit the
            stages (:func:`dvsland.sim.contracts.check_loop_state`: names the stage and the field).
        PluginError: the estimator or the law broke its contract (:mod:`dvsland.plugins`).
    """
    thrust = _checked_thrust(thrust, state.z_m)  # before sensing: a bad thrust costs nothing
    return act_step(stages, sense_step(stages, state, timer, grad, donate), thrust, timer, terminate)


def fly_steps(stages, state: LoopState, n: int, **kwargs) -> Tuple[LoopState, list]:
    """``n`` calls of :func:`loop_step` (``kwargs`` passed on): (the state after them, their
    :class:`StepOutput` s)."""
    outs = []
    for _ in range(int(n)):
        state, out = loop_step(stages, state, **kwargs)
        outs.append(out)
    return state, outs


def sense_step(stages, state: LoopState, timer: Optional[Callable[[str], Any]] = None, grad: bool = False,
               donate: bool = False) -> Sensed:
    """The first half of a step: render, emulate, estimate, filter and run the law at ``t_k``;
    finish the step with :func:`act_step`. ``state`` is not changed (unless ``donate``: see
    :func:`loop_step`)."""
    tm = timer or (lambda name: nullcontext())
    if state.stage_state is not getattr(stages, "_last_stage_state", None):  # a state the loop did not just make
        check_loop_state(stages, state)
    k = state.step
    t_s = k * stages.settings.dt_s
    t_us = int(round(t_s * 1e6))
    all_active = bool(state.active.all())  # the loop body's one host sync: which path the batch takes
    compact = bool(getattr(stages.settings, "compact", True)) and not all_active
    frames = events = emu_st = None
    if stages.events is not None:  # an estimator without events: no frame, no emulation, no timer
        rows = state.active.nonzero().squeeze(1) if compact else None  # the batch's one read on that path
        with tm("render"):
            frames = render(stages, state, all_active, rows)
        with tm("emulate"):
            emu_st, events = sense(stages, state, frames, t_us, compact, rows, donate)
    with tm("estimate"):
        est_st, est = estimate(stages, state, events, t_us, grad, donate)
    with tm("control"):
        f_st, c_st, cmd = act(stages, state, est)
        u = _applied_thrust(cmd.control.thrust_n, None, state.active)
    ctl, diag = cmd.control, est.diagnostics
    out = StepOutput(step=k, t_s=t_s, t_us=t_us, z_m=state.z_m, v_mps=state.v_mps, m_kg=state.m_kg,
                     d_true=Truth(state.z_m, state.v_mps).divergence, d_est=est.d_hat, d_conf=est.confidence,
                     d_filtered=cmd.d_filtered, n_used=cmd.n_used.to(torch.float64), thrust_n=u,
                     held=ctl.held & state.active, tau_target_s=ctl.tau_target_s, tau_hat_s=ctl.tau_hat_s,
                     z_est_m=cmd.z_est_m, active=state.active, ended=torch.zeros_like(state.active), frames=frames,
                     events=events, diagnostics=lambda: dict(diag or {}), t_flight_s=flight_time_s(stages, state),
                     control_residual=ctl.residual)
    return Sensed(state, out, est.bad, StageStates(emu_st, est_st, f_st, c_st))


def act_step(stages, sensed: Sensed, thrust: Optional[torch.Tensor] = None,
             timer: Optional[Callable[[str], Any]] = None, terminate: bool = True) -> Tuple[LoopState, StepOutput]:
    """The second half of a step: fly ``dt`` with the law's command (``thrust=None``) or ``thrust``
    (B,) N held, then bookkeeping and termination (unless ``terminate=False``); returns (next
    state, the step's StepOutput).

    Raises:
        ValueError: ``thrust`` of the wrong shape, NaN or negative.
    """
    tm = timer or (lambda name: nullcontext())
    state, out = sensed.state, sensed.out
    u = _applied_thrust(out.thrust_n, _checked_thrust(thrust, state.z_m), state.active)
    est = Estimate(out.d_est, out.d_conf, sensed.bad, {})
    with tm("dynamics"):
        nxt, ended = advance(stages, state, u, out.held, est, out.frames, sensed.stage_state, terminate)
    stages._last_stage_state = nxt.stage_state  # a check cache only: the next step trusts what it made
    return nxt, out._replace(thrust_n=u, ended=ended)


def active_events(events, active: torch.Tensor):
    """``events`` without those of finished descents: ``active`` (B,) bool indexed by each event's
    ``b``; the order (sorted by (b, t)) is kept. None stays None."""
    if events is None or len(events) == 0:
        return events
    keep = active[events.b]
    if bool(keep.all()):
        return events
    sub = events[keep]  # a subset in the same order: as checked as the events it came from
    mark = getattr(events, "checked", None)  # None too for events unpickled from before the mark
    return sub if mark is None else sub.marked_checked(*mark)


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


__all__ = ["StepOutput", "Sensed", "Estimate", "Command", "init_state", "reset_where", "loop_step", "fly_steps",
           "sense_step",
           "act_step", "render", "sense", "estimate", "act", "advance", "flight_time_s", "sanitise_estimates",
           "confidence_of", "active_events", "D_HAT_ABS_MAX"]
