"""What ``dvsland train-loop`` trains, by name: a built-in law's constants or the ``policy`` law's network.

A :class:`Trainable` is an ``nn.Module`` (its parameters are what the optimizer moves) that knows how
to put its current values into a controller of its law (:meth:`Trainable.apply`): the training
loop's controller before each window (so the window's graph reaches the parameters), and a
validation batch's controller before it flies.

Law constants are positive and trained in log space: value = exp(raw). ``kp_scale`` multiplies every
setting's gain Kp of ``tau_p`` and ``div_p``; ``div_gs`` trains ``lambda_per_s`` and ``d_final_per_s``.
The ``efference_fit`` filter's constants (:class:`FilterConstants`, ``--what filter``) are trained the
same way. Its gate ``gate_sigma`` trains through a straight-through surrogate (the hard gate's values,
a sigmoid gate's gradient: :func:`dvsland.control.efference_fit.gate_surrogate`); ``min_confidence``,
a hard gate applied before the estimate enters the history, has a zero gradient almost everywhere
and is refused by name.

:meth:`Trainable.apply_to` puts the values into a :class:`~dvsland.stages.Stages` (the law's
controller, or the filter).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Dict, Sequence, Tuple

import torch
from torch import nn

from dvsland.control.policy import checkpoint_observation_base
from dvsland.estimators.state_dict_check import check_state_dict

#: law -> constants that can be trained by name (the first ones are the default set)
LAW_CONSTANTS: Dict[str, Tuple[str, ...]] = {"div_gs": ("lambda_per_s", "d_final_per_s"),
                                             "tau_p": ("kp_scale",), "div_p": ("kp_scale",)}
#: ``efference_fit`` constants that can be trained by name (the first four are the default set)
FILTER_CONSTANTS: Tuple[str, ...] = ("meas_sigma_rel", "meas_sigma_abs", "cauchy_c", "prior_rel_sigma",
                                     "prior_rel_sigma_v", "gate_sigma")
FILTER_DEFAULT: Tuple[str, ...] = FILTER_CONSTANTS[:4]
#: ``efference_fit`` constants whose gradient is zero almost everywhere (hard gates: a threshold moved by
#: a little changes no weight), refused by ``--what filter``
FILTER_ZERO_GRADIENT: Dict[str, str] = {
    "min_confidence": "a hard gate on the estimator's confidence",
    "iterations": "an integer (Gauss-Newton rounds)",
    "forget_s": "the rows the fit reads are an integer cut of it (and 0, never, cannot start a log)",
}
#: the filter ``--what filter`` trains
TRAINED_FILTER = "efference_fit"
#: what ``--what`` accepts
WHATS = ("policy", "law", "filter", "estimator")


class Trainable(nn.Module):
    """Base: ``apply(controller)`` puts the current values into a controller of the trained law."""

    what = ""

    def apply(self, controller) -> None:
        raise NotImplementedError

    def apply_to(self, stages) -> None:
        """Put the current values into ``stages`` (its controller; :class:`FilterConstants`: its filter)."""
        self.apply(stages.controller)

    def describe(self) -> dict:
        """What a checkpoint and train_loop.json record of the current values (plain numbers)."""
        return {}

    def checkpoint_fields(self) -> dict:
        """The fields of the training checkpoint that hold the trained values."""
        raise NotImplementedError

    def load_checkpoint_fields(self, ck: dict, where: str) -> None:
        """Load the values that :meth:`checkpoint_fields` wrote into ``ck``; ValueError naming
        ``where`` where they do not fit."""
        raise NotImplementedError

    def trained_config(self, cfg, ckpt: Path):
        """``cfg`` (the training config) with the trained values in place, so that it flies them;
        ``ckpt`` is the training's checkpoint (named by absolute path where the values live there)."""
        raise NotImplementedError


class LogConstants(Trainable):
    """Base of named positive constants trained in log space: ``raw[name]`` = log(value)."""

    def _start(self, start: Dict[str, float]) -> None:
        """The constants ``start`` (name -> value > 0), in this order, as the trained parameters."""
        self.names = tuple(start)
        self.raw = nn.ParameterDict({n: nn.Parameter(torch.tensor(math.log(v), dtype=torch.float64))
                                     for n, v in start.items()})

    def values(self) -> Dict[str, torch.Tensor]:
        """name -> 0-dim float64 tensor (with its graph to ``raw``)."""
        return {n: torch.exp(self.raw[n]) for n in self.names}

    def describe(self) -> dict:
        return {n: float(v.detach()) for n, v in self.values().items()}

    def checkpoint_fields(self) -> dict:
        return {"raw": {k: v.detach().clone() for k, v in self.raw.items()}}

    def load_checkpoint_fields(self, ck: dict, where: str) -> None:
        check_state_dict(ck.get("raw"), self.raw, where)
        self.raw.load_state_dict(ck["raw"])


class LawConstants(LogConstants):
    """A built-in law's positive constants, log-parameterised.

    Args:
        controller: the training loop's controller (its current values are the start).
        law: its name (a key of :data:`LAW_CONSTANTS`).
        names: the constants to train (() = the law's default set).
    """

    what = "law"

    def __init__(self, controller, law: str, names: Sequence[str] = ()):
        super().__init__()
        if law not in LAW_CONSTANTS:
            raise ValueError(f"--what law: controller.name {law!r} has no trainable constants; choose one of "
                             f"{sorted(LAW_CONSTANTS)} (or --what policy with controller.name=policy)")
        names = tuple(names) or LAW_CONSTANTS[law]
        bad = [n for n in names if n not in LAW_CONSTANTS[law]]
        if bad:
            raise ValueError(f"--params {','.join(bad)}: not a trainable constant of {law!r}; choose from "
                             f"{list(LAW_CONSTANTS[law])}")
        self.law = law
        self.base = controller.params
        self._start({n: 1.0 if n == "kp_scale" else float(getattr(self.base.options, n)) for n in names})

    def apply(self, controller) -> None:
        vals = self.values()
        p = controller.params
        if "kp_scale" in vals:
            p = p._replace(kp=self.base.kp.to(p.kp.device) * vals.pop("kp_scale"))
        if vals:
            p = p._replace(options=dataclasses.replace(p.options, **vals))
        controller.params = p

    def trained_config(self, cfg, ckpt: Path):
        """The law's constants into ``controller.<law>``; ``kp_scale`` scales every setting's Kp."""
        c, vals = cfg.controller, self.describe()
        if "kp_scale" in vals:
            c = dataclasses.replace(c, settings=[dataclasses.replace(x, kp=x.kp * vals.pop("kp_scale"))
                                                 for x in c.settings])
        if vals:
            c = dataclasses.replace(c, **{self.law: dataclasses.replace(getattr(c, self.law), **vals)})
        return dataclasses.replace(cfg, controller=c)


class PolicyWeights(Trainable):
    """The ``policy`` law's network (shared, not copied: the controller flies these weights)."""

    what = "policy"

    def __init__(self, controller):
        super().__init__()
        net = getattr(getattr(controller.params, "options", None), "net", None)
        if net is None:
            raise ValueError("--what policy: the controller has no network; use controller.name=policy")
        self.net = net.requires_grad_(True)

    def apply(self, controller) -> None:
        controller.params = controller.params._replace(options=controller.params.options._replace(net=self.net))

    def describe(self) -> dict:
        return {"hidden": self.net.hidden, "observation": self.net.observation, "base": self.net.base,
                "authority": self.net.authority, "parameters": sum(p.numel() for p in self.net.parameters())}

    def checkpoint_fields(self) -> dict:
        """``hidden``, ``observation``, ``base``, ``authority`` and the weights (a checkpoint without
        ``observation`` / ``base`` / ``authority`` is ``basic`` / ``none`` / 1)."""
        return {"hidden": self.net.hidden, "observation": self.net.observation, "base": self.net.base,
                "authority": self.net.authority, "state_dict": self.net.state_dict()}

    def load_checkpoint_fields(self, ck: dict, where: str) -> None:
        if ck.get("hidden") != self.net.hidden:
            raise ValueError(f"{where}: hidden {ck.get('hidden')!r} != controller.policy.hidden {self.net.hidden}")
        checkpoint_observation_base(ck, where, self.net.observation, self.net.base, self.net.authority)
        check_state_dict(ck.get("state_dict"), self.net, where)
        self.net.load_state_dict(ck["state_dict"])

    def trained_config(self, cfg, ckpt: Path):
        """``controller.policy.checkpoint`` = ``ckpt`` by absolute path."""
        c = cfg.controller
        return dataclasses.replace(cfg, controller=dataclasses.replace(
            c, policy=dataclasses.replace(c.policy, checkpoint=str(Path(ckpt).resolve()))))


class FilterConstants(LogConstants):
    """The ``efference_fit`` filter's positive constants (``controller.efference``), log-parameterised.

    ``prior_rel_sigma`` and ``prior_rel_sigma_v`` act through the prior's std. devs. ``sz0`` =
    prior_rel_sigma |z0| and ``sv0`` = prior_rel_sigma_v max(|v0|, 1e-3), recomputed from the target
    filter's own planned start (a validation batch has its own); the others are fields of its ``cfg``.

    Args:
        filt: the training loop's ``efference_fit`` filter (its current values are the start).
        names: the constants to train (() = :data:`FILTER_DEFAULT`).
    """

    what = "filter"

    def __init__(self, filt, names: Sequence[str] = ()):
        super().__init__()
        names = tuple(names) or FILTER_DEFAULT
        gated = [n for n in names if n in FILTER_ZERO_GRADIENT]
        if gated:
            raise ValueError("--params " + ", ".join(f"{n}: {FILTER_ZERO_GRADIENT[n]}" for n in gated)
                             + f"; its gradient is zero almost everywhere, so --what filter does not train it. "
                             f"Choose from {list(FILTER_CONSTANTS)}")
        bad = [n for n in names if n not in FILTER_CONSTANTS]
        if bad:
            raise ValueError(f"--params {','.join(bad)}: not a trainable constant of the {TRAINED_FILTER} filter; "
                             f"choose from {list(FILTER_CONSTANTS)}")
        cfg = filt.params.cfg
        start = {n: float(getattr(cfg, n)) for n in names}
        zero = [n for n, v in start.items() if not v > 0]
        if zero:
            raise ValueError(f"--params {','.join(zero)}: controller.efference.{zero[0]} is {start[zero[0]]!r}; a "
                             f"constant trained in log space must start > 0 (add --set "
                             f"controller.efference.{zero[0]}=...)")
        self._start(start)

    def apply(self, filt) -> None:
        vals = self.values()
        p = filt.params
        if "prior_rel_sigma" in vals:
            p = p._replace(sz0=vals["prior_rel_sigma"] * p.z0_m.abs())
        if "prior_rel_sigma_v" in vals:
            p = p._replace(sv0=vals["prior_rel_sigma_v"] * p.v0_mps.abs().clamp_min(1e-3))
        filt.params = p._replace(cfg=dataclasses.replace(p.cfg, **vals))

    def apply_to(self, stages) -> None:
        self.apply(stages.filter)

    def trained_config(self, cfg, ckpt: Path):
        """The constants into ``controller.efference``. With ``prior_rel_sigma`` trained and the
        config's ``prior_rel_sigma_v`` null (= prior_rel_sigma), the velocity prior is written out as
        flown, so that the trained altitude prior does not move it."""
        e, opts = cfg.controller.efference, self.describe()
        if "prior_rel_sigma" in opts and "prior_rel_sigma_v" not in opts and e.prior_rel_sigma_v is None:
            opts["prior_rel_sigma_v"] = float(e.prior_rel_sigma)
        c = dataclasses.replace(cfg.controller, efference=dataclasses.replace(e, **opts))
        return dataclasses.replace(cfg, controller=c)


def make_trainable(stages, what: str, names: Sequence[str] = ()) -> Trainable:
    """The :class:`Trainable` of ``what`` (``policy``, ``law`` or ``filter``) for the loop's stages.

    Raises:
        ValueError: naming ``--what`` / ``--params``: an unknown kind, a law without trainable
            constants, a constant the law does not have, ``--params`` with ``--what policy``, a
            plug-in law (whose maths the loop cannot differentiate); ``--what filter`` without
            ``controller.filter=efference_fit``, or a filter constant that is not trainable.
    """
    if what not in WHATS:
        raise ValueError(f"--what {what!r}: choose one of {list(WHATS)}")
    if what == "estimator":  # the learned estimator's network (dvsland.learn.loop_estimator)
        if names:
            raise ValueError("--params: only with --what law or --what filter (--what estimator trains the whole "
                             "network)")
        from .loop_estimator import EstimatorWeights

        return EstimatorWeights(stages)
    if what == "filter":
        filt = stages.cfg.controller.filter
        if filt != TRAINED_FILTER or not hasattr(getattr(stages.filter, "params", None), "sz0"):
            raise ValueError(f"--what filter: trains the {TRAINED_FILTER!r} filter's constants; controller.filter is "
                             f"{filt!r} (add --set controller.filter={TRAINED_FILTER})")
        return FilterConstants(stages.filter, names)
    ctl, law = stages.controller, stages.cfg.controller.name
    if not hasattr(getattr(ctl, "params", None), "_replace"):
        raise ValueError(f"--what {what}: controller {law!r} is a plug-in law without the stage contract's "
                         f"params; train-loop trains built-in laws ({sorted(LAW_CONSTANTS)}) and 'policy'")
    if what == "policy":
        if names:
            raise ValueError("--params: only with --what law or --what filter (the policy trains its whole network)")
        if law != "policy":
            raise ValueError(f"--what policy: needs controller.name=policy (got {law!r}); add "
                             f"--set controller.name=policy")
        return PolicyWeights(ctl)
    return LawConstants(ctl, law, names)


__all__ = ["Trainable", "LawConstants", "PolicyWeights", "FilterConstants", "make_trainable", "LAW_CONSTANTS",
           "FILTER_CONSTANTS", "FILTER_DEFAULT", "FILTER_ZERO_GRADIENT", "TRAINED_FILTER", "WHATS"]
