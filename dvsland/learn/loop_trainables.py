"""What ``dvsland train-loop`` trains, by name: a built-in law's constants or the ``policy`` law's network.

A :class:`Trainable` is an ``nn.Module`` (its parameters are what the optimizer moves) that knows how
to put its current values into a controller of its law (:meth:`Trainable.apply`): the training
loop's controller before each window (so the window's graph reaches the parameters), and a
validation batch's controller before it flies.

Law constants are positive and trained in log space: value = exp(raw). ``kp_scale`` multiplies every
setting's gain Kp of ``tau_p`` and ``div_p``; ``div_gs`` trains ``lambda_per_s`` and ``d_final_per_s``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Dict, Sequence, Tuple

import torch
from torch import nn

#: law -> constants that can be trained by name (the first ones are the default set)
LAW_CONSTANTS: Dict[str, Tuple[str, ...]] = {"div_gs": ("lambda_per_s", "d_final_per_s"),
                                             "tau_p": ("kp_scale",), "div_p": ("kp_scale",)}
#: what ``--what`` accepts
WHATS = ("policy", "law")


class Trainable(nn.Module):
    """Base: ``apply(controller)`` puts the current values into a controller of the trained law."""

    what = ""

    def apply(self, controller) -> None:
        raise NotImplementedError

    def describe(self) -> dict:
        """What a checkpoint and train_loop.json record of the current values (plain numbers)."""
        return {}


class LawConstants(Trainable):
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
        self.law, self.names = law, names
        self.base = controller.params
        start = {n: 1.0 if n == "kp_scale" else float(getattr(self.base.options, n)) for n in names}
        self.raw = nn.ParameterDict({n: nn.Parameter(torch.tensor(math.log(v), dtype=torch.float64))
                                     for n, v in start.items()})

    def values(self) -> Dict[str, torch.Tensor]:
        """name -> 0-dim float64 tensor (with its graph to ``raw``)."""
        return {n: torch.exp(self.raw[n]) for n in self.names}

    def apply(self, controller) -> None:
        vals = self.values()
        p = controller.params
        if "kp_scale" in vals:
            p = p._replace(kp=self.base.kp.to(p.kp.device) * vals.pop("kp_scale"))
        if vals:
            p = p._replace(options=dataclasses.replace(p.options, **vals))
        controller.params = p

    def describe(self) -> dict:
        return {n: float(v.detach()) for n, v in self.values().items()}

    def config_overrides(self) -> Dict[str, float]:
        """``controller.<law>.<name>`` -> value for the constants of the law's config section
        (``kp_scale`` is not one: it scales the gains of ``controller.settings``)."""
        return {f"controller.{self.law}.{n}": v for n, v in self.describe().items() if n != "kp_scale"}


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
        return {"hidden": self.net.hidden, "parameters": sum(p.numel() for p in self.net.parameters())}


def make_trainable(stages, what: str, names: Sequence[str] = ()) -> Trainable:
    """The :class:`Trainable` of ``what`` (``policy`` or ``law``) for the loop's controller.

    Raises:
        ValueError: naming ``--what`` / ``--params``: an unknown kind, a law without trainable
            constants, a constant the law does not have, ``--params`` with ``--what policy``, or a
            plug-in law (whose maths the loop cannot differentiate).
    """
    if what not in WHATS:
        raise ValueError(f"--what {what!r}: choose one of {list(WHATS)}")
    ctl, law = stages.controller, stages.cfg.controller.name
    if not hasattr(getattr(ctl, "params", None), "_replace"):
        raise ValueError(f"--what {what}: controller {law!r} is a plug-in law without the stage contract's "
                         f"params; train-loop trains built-in laws ({sorted(LAW_CONSTANTS)}) and 'policy'")
    if what == "policy":
        if names:
            raise ValueError("--params: only with --what law (the policy trains its whole network)")
        if law != "policy":
            raise ValueError(f"--what policy: needs controller.name=policy (got {law!r}); add "
                             f"--set controller.name=policy")
        return PolicyWeights(ctl)
    return LawConstants(ctl, law, names)


__all__ = ["Trainable", "LawConstants", "PolicyWeights", "make_trainable", "LAW_CONSTANTS", "WHATS"]
