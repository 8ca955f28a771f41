"""The loss of a flight, differentiated through the closed loop (``dvsland train-loop``).

One window flies ``window`` steps of every descent from a detached state with the loop's own
controller and ``loop_step(..., grad=True)``; the loss is the batch mean of, per descent:

- ``track`` x sum over steps of ((D - D*(t)) / 0.01 1/s)^2 dt (clipped at 30), D the true divergence
  after the step and D*(t) = -1 / max(tau0 - c2 t, 2 / crash_divergence) the paper's TTC profile
  (dense shaping; 0 to leave the law its own target);
- ``landing`` x (v / 2 m/s)^2 at the step a descent ends (landing or crash: the faster, the worse);
  a landing's v is read where the step crosses the success altitude (:func:`crossing_speed`);
- ``fail`` (a constant) when it ends other than landed (crash, ascent, timeout);
- ``fuel`` x the propellant burnt, in % of the initial mass;
- ``track_gs`` x sum over steps of ((D - D*_gs) / 0.01 1/s)^2 dt (clipped at 30), D and z the true
  divergence and altitude after the step and D*_gs = div_gs's target at the true altitude (its TTC
  profile, then -max(d_final, v_min / z); ``controller.div_gs``'s constants): dense shaping towards
  the descent ``div_gs`` would fly with perfect sensing (0 by default);
- ``filter`` x sum over steps of ((D_f - D) / 0.01 1/s)^2 dt (clipped at 30), D_f the filter's output
  and D the true divergence at the step's start (dense: how well the filter knows the divergence the
  loop flies; ``--what filter``'s default beside the landing terms, 0 otherwise);
- ``residual`` x sum over steps of r^2 dt, r = tanh(net) in [-1, 1] the residual policy's correction
  as a share of its reach (``controller.policy.base=div_gs``; 0 by default): a price on moving the
  base law's command, so that a constant offset, which a feedback base law cancels, is not pushed
  to the bound.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Tuple

import torch

from dvsland.control.div_gs import floored_target
from dvsland.pytree import tree_map
from dvsland.sim import loop_step
from dvsland.sim.termination import SUCCESS

#: tracking-error scale, 1/s
ERR_SCALE = 0.01


@dataclass(frozen=True)
class LossWeights:
    """Weights of the loss terms (module doc); each finite and >= 0."""

    track: float = 1.0
    landing: float = 1.0
    fail: float = 25.0
    fuel: float = 0.0
    filter: float = 0.0
    track_gs: float = 0.0
    residual: float = 0.0

    def check(self) -> "LossWeights":
        for name, v in vars(self).items():
            if not (isinstance(v, (int, float)) and v >= 0 and v < float("inf")):
                raise ValueError(f"--loss {name}={v!r}: each weight must be a finite number >= 0")
        return self

    @classmethod
    def parse(cls, text: str, base: "LossWeights" = None) -> "LossWeights":
        """``"track=0,fuel=0.1"`` over ``base`` (the defaults); ValueError naming --loss."""
        vals = dict(vars(base or cls()))
        for item in filter(None, (s.strip() for s in str(text).split(","))):
            key, sep, v = item.partition("=")
            if not sep or key.strip() not in vals:
                raise ValueError(f"--loss {item!r}: expected NAME=WEIGHT with NAME one of {list(vals)}")
            try:
                vals[key.strip()] = float(v)
            except ValueError:
                raise ValueError(f"--loss {item!r}: the weight must be a number") from None
        return cls(**vals).check()


def ttc_target(stages, t_s: torch.Tensor) -> torch.Tensor:
    """D*(t) (B,) float64 1/s: the paper's TTC profile of each descent at flight time ``t_s`` (B,) s."""
    p = stages.params
    return -1.0 / (p.tau0_s - p.c2 * t_s).clamp_min(2.0 / stages.settings.crash_divergence)


def div_gs_target(stages, t_s: torch.Tensor, z_m: torch.Tensor) -> torch.Tensor:
    """D*_gs (B,) float64 1/s: ``div_gs``'s target (``controller.div_gs``'s constants) at flight time
    ``t_s`` (B,) s and altitude ``z_m`` (B,) m (the true one, for the ``track_gs`` term)."""
    o, p = stages.cfg.controller.div_gs, stages.params
    return floored_target(t_s, p.tau0_s, p.c2, float(o.d_final_per_s), float(o.v_min_mps), z_m.clamp_min(1.0))[0]


def crossing_speed(before, after, z_s: float) -> torch.Tensor:
    """(B,) float64 m/s: the speed where the step from ``before`` to ``after`` crosses altitude ``z_s``
    (linear in the step). Its gradient counts the change of the crossing time: the termination
    step is a constant of the graph, so the speed read at the step's end would be differentiated
    at a fixed time, not at the fixed altitude where a landing is judged."""
    dz = before.z_m - after.z_m
    frac = ((before.z_m - z_s) / torch.where(dz.abs() > 1e-12, dz, torch.ones_like(dz))).clamp(0.0, 1.0)
    return before.v_mps + frac * (after.v_mps - before.v_mps)


def step_terms(stages, before, after, out, w: LossWeights) -> Dict[str, torch.Tensor]:
    """The loss terms (B,) float64 of one step from ``before`` to ``after`` (LoopStates)."""
    flying, dt = before.active, stages.settings.dt_s
    zero = torch.zeros_like(after.z_m)
    d = after.v_mps / after.z_m
    err = (d - ttc_target(stages, out.t_flight_s + dt)) / ERR_SCALE
    ended = flying & ~after.active
    landed = ended & (after.outcome == SUCCESS)
    m0 = stages.params.m0_kg
    v_end = torch.where(landed, crossing_speed(before, after, stages.settings.success_altitude_m), after.v_mps)
    terms = {"track": w.track * torch.where(flying, err.clamp(-30, 30) ** 2 * dt, zero),
            "landing": w.landing * torch.where(ended, (v_end / 2.0) ** 2, zero),
            "fail": w.fail * (ended & ~landed).to(zero.dtype),
            "fuel": w.fuel * 100.0 * torch.where(flying, before.m_kg - after.m_kg, zero) / m0,
            "_landed": landed.to(zero.dtype), "_ended": ended.to(zero.dtype)}
    if w.track_gs:
        e_gs = (d - div_gs_target(stages, out.t_flight_s + dt, after.z_m)) / ERR_SCALE
        terms["track_gs"] = w.track_gs * torch.where(flying, e_gs.clamp(-30, 30) ** 2 * dt, zero)
    if w.residual:
        r = out.control_residual
        if r is None:
            raise ValueError(f"--loss residual={w.residual}: the law has no residual; use controller.name=policy "
                             "with controller.policy.base=div_gs")
        terms["residual"] = w.residual * torch.where(flying, r.to(zero.dtype) ** 2 * dt, zero)
    if w.filter:  # only when weighted: a missing output (NaN) must not reach the graph as 0 x NaN
        f_err = (out.d_filtered - out.d_true) / ERR_SCALE
        ok = flying & torch.isfinite(f_err)
        terms["filter"] = w.filter * torch.where(ok, torch.where(ok, f_err, 0.0).clamp(-30, 30) ** 2 * dt, zero)
    return terms


def gradient_mode(stages):
    """``grad`` of :func:`dvsland.sim.loop_step` for training: True for an estimator without events
    (the oracle: a function of the state) and for one whose step keeps its own graph (``--what
    estimator``: the learned estimator's ``consts.grad``, the gradient to its weights), else
    ``"straight_through"`` (the true divergence's gradient)."""
    if stages.events is None or getattr(getattr(stages.estimator, "consts", None), "grad", False) is True:
        return True
    return "straight_through"


def window_loss(stages, state, window: int, w: LossWeights) -> Tuple[torch.Tensor, Dict[str, float], object]:
    """Fly ``window`` steps (0: until every descent has ended or ``t_max``) from ``state`` detached,
    with the gradient of :func:`gradient_mode`.

    Returns:
        (loss: 0-dim float64 with its graph; terms: name -> batch-mean float, plus ``landed``,
        ``ended`` counts and ``steps`` flown; the state after the window).
    """
    state = tree_map(lambda t: t.detach(), state)
    sums: Dict[str, torch.Tensor] = {}
    n, grad, limit = 0, gradient_mode(stages), window or stages.settings.n_steps_max
    while n < limit:
        nxt, out = loop_step(stages, state, grad=grad)
        for k, v in step_terms(stages, state, nxt, out, w).items():
            sums[k] = sums[k] + v if k in sums else v
        state, n = nxt, n + 1
        if not window and not bool(state.active.any()):
            break
    B = state.batch_size
    loss = sum(v.sum() for k, v in sums.items() if not k.startswith("_")) / B
    terms = {k: float(v.detach().sum()) / B for k, v in sums.items() if not k.startswith("_")}
    terms.update(landed=int(sums["_landed"].sum()), ended=int(sums["_ended"].sum()), steps=n * B)
    return loss, terms, state


__all__ = ["LossWeights", "window_loss", "gradient_mode", "step_terms", "crossing_speed", "ttc_target", "div_gs_target",
           "ERR_SCALE"]
