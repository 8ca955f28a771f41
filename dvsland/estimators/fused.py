"""``fused``: several estimators on the same events, one estimate (not in paper).

Estimators fail in different places: through the realistic pixel ``cmax`` abstains over sparse
ground (C, F, G), where a learned network still reads the flow, and the network errs at 10 km, where
``cmax`` is sure. ``fused`` runs its members on every step and combines what they say, by their
confidences read as relative standard errors (``sigma_rel(c) = 0.1 sqrt(1/c - 1)``, the filters'
reading, after each member's own motion-evidence test and calibration):

- ``precision`` (default): the inverse-variance mean of the members' finite estimates, weights
  ``w_i = 1 / sigma_rel_i^2``; the combined ``sigma_rel = 1 / sqrt(sum w_i)``, inflated by the
  Birge ratio ``sqrt(chi^2 / (n - 1))`` when the members disagree by more than their sigmas say
  (``chi^2 = sum w_i ((D_i - D) / |D|)^2``), so that two confident estimates that contradict each
  other give a low confidence, not a confident average;
- ``priority``: the first member (in ``members`` order) whose confidence reaches
  ``min_confidence``; where none does, the most confident one.

The state is the tuple of the members' states (:class:`FusedState`): ``init_state``,
``step_state`` and ``reset_where`` are the members', side by side. Diagnostics: every member's
under ``<member>.<key>``, plus ``confidence`` and ``n_members`` (B,) (members with an estimate).
"""

from __future__ import annotations

import os
from typing import Any, Dict, NamedTuple, Optional, Sequence, Tuple

import torch

from .base import DivergenceEstimator, EstimateOut, Truth, confidence_from_rel_std, confidence_rel_sigma
from .registry import get_estimator, register_estimator

#: the combination rules
RULES = ("precision", "priority")
#: a confidence is read below this (sigma_rel > 0), so no member's weight is infinite
_C_MAX = 1.0 - 1e-6


class FusedState(NamedTuple):
    """State of ``fused``: ``members`` is the tuple of the members' states, in ``members`` order."""

    members: Tuple[Any, ...]


def member_names(members: str) -> Tuple[str, ...]:
    """``"cmax,learned"`` -> ("cmax", "learned"): at least two, none of them ``fused``.

    Raises:
        ValueError: naming ``estimator.fused.members`` and what is allowed.
    """
    names = tuple(m.strip() for m in str(members).split(",") if m.strip())
    if len(names) < 2:
        raise ValueError(f"estimator.fused.members must name at least two estimators, comma-separated "
                         f"(e.g. 'cmax,learned'), got {members!r}")
    if any(n.split("[", 1)[0] == "fused" for n in names):
        raise ValueError(f"estimator.fused.members: 'fused' cannot be its own member, got {members!r}")
    return names


def fuse_precision(d: torch.Tensor, c: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Inverse-variance mean of the members' estimates with Birge-ratio inflation (module doc).

    Args:
        d: (M, B) float32 estimates, 1/s, NaN = none. c: (M, B) float32 confidences in [0, 1].

    Returns:
        (D (B,) float32, NaN where no member has an estimate; confidence (B,) float32).
    """
    ok = torch.isfinite(d) & (c > 0)
    cc = c.clamp(0.0, _C_MAX)
    sig = confidence_rel_sigma(cc)
    w = torch.where(ok, 1.0 / (sig * sig), torch.zeros_like(cc))  # 1 / sigma_rel^2
    w_sum = w.sum(0)
    d0 = torch.where(ok, d, torch.zeros_like(d))
    mean = (w * d0).sum(0) / w_sum.clamp_min(1e-30)
    n = ok.sum(0)
    rel = (d0 - mean) / mean.abs().clamp_min(1e-6)
    chi2 = (w * rel * rel).sum(0)
    birge = torch.where(n > 1, chi2 / (n - 1).clamp_min(1).to(chi2.dtype), torch.ones_like(chi2)).clamp_min(1.0)
    var = birge / w_sum.clamp_min(1e-30)  # sigma_rel^2 of the combined estimate
    d_out = torch.where(n > 0, mean, torch.full_like(mean, float("nan")))
    return d_out, confidence_from_rel_std(var.sqrt(), d_out)


def fuse_priority(d: torch.Tensor, c: torch.Tensor, min_confidence: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """The first member whose confidence reaches ``min_confidence``, else the most confident one.
    Shapes as :func:`fuse_precision`."""
    ok = torch.isfinite(d) & (c > 0)
    score = torch.where(ok, c, torch.full_like(c, -1.0))
    m = torch.arange(d.shape[0], device=d.device).view(-1, 1).to(c.dtype)
    # members that reach the bar rank by order (2 - m / M > 1), the others by confidence (<= 1)
    rank = torch.where(ok & (c >= min_confidence), 2.0 - m / d.shape[0], score)
    pick = rank.argmax(0, keepdim=True)
    d_out, c_out = d.gather(0, pick)[0], c.gather(0, pick)[0]
    none = ~ok.any(0)
    nan = torch.full_like(d_out, float("nan"))
    return torch.where(none, nan, d_out), torch.where(none, torch.zeros_like(c_out), c_out)


@register_estimator("fused")
class FusedEstimator(DivergenceEstimator):
    """Several estimators on the same events, combined (module doc).

    Args:
        members: the member estimators: built (objects for this batch, or (label, object) pairs) or
            by name (built with their defaults by :func:`~.registry.get_estimator`); from a config,
            ``estimator.fused.members`` names them and each is built from its own section
            (``estimator.cmax``, ...).
        rule: ``precision`` or ``priority``.
        min_confidence: the bar of ``priority``, in [0, 1].
        dt_s, seed, principal_point_px: passed to members built by name.
    """

    #: the members run their own motion-evidence tests; the combination needs none of its own
    abstain = None

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1,
                 members: Sequence[Any] = ("cmax", "learned"), rule: str = "precision",
                 min_confidence: float = 0.15, seed: int = 0, principal_point_px=None):
        super().__init__(batch_size, sensor_size, device, dt_s, principal_point_px=principal_point_px)
        if rule not in RULES:
            raise ValueError(f"estimator.fused.rule must be one of {list(RULES)}, got {rule!r}")
        if not 0.0 <= float(min_confidence) <= 1.0:
            raise ValueError(f"estimator.fused.min_confidence must be in [0, 1], got {min_confidence}")
        if isinstance(members, str):
            members = member_names(members)
        if len(members) < 2:
            raise ValueError(f"estimator.fused.members must hold at least two estimators, got {len(members)}")
        self.rule, self.min_confidence = rule, float(min_confidence)
        labelled = [m if isinstance(m, tuple) else (m if isinstance(m, str) else type(m).__name__, m) for m in members]
        #: the members' names, in order: their diagnostics' prefixes
        self.member_labels = tuple(str(lab) for lab, _ in labelled)
        self.members = tuple(self._member(m, seed) for _, m in labelled)
        for m in self.members:
            if not m._has_contract():
                raise ValueError(f"estimator.fused.members: {type(m).__name__} has no pure step (init_state / "
                                 "step_state / reset_where); only such estimators can be members")
        self.needs_events = any(getattr(m, "needs_events", True) for m in self.members)
        self.state = self.init_state()

    @property
    def checkpoint(self):
        """The checkpoint file (str or Path, as the member holds it) of the first member that reads one
        (a run's record names it), else None."""
        for m in self.members:
            ck = getattr(m, "checkpoint", None)
            if isinstance(ck, (str, os.PathLike)) and str(ck) and os.path.isfile(ck):
                return ck
        return None

    def _member(self, m, seed: int) -> DivergenceEstimator:
        if not isinstance(m, str):
            if getattr(m, "batch_size", self.batch_size) != self.batch_size:
                raise ValueError(f"estimator.fused.members: a member built for {m.batch_size} descents, "
                                 f"not {self.batch_size}")
            return m
        return get_estimator(m, self.batch_size, self.sensor_size, self.device, dt_s=self.dt_s, seed=seed,
                             principal_point_px=self.principal_point_px)

    def init_state(self) -> FusedState:
        return FusedState(tuple(m.init_state() for m in self.members))

    def reset_where(self, state: FusedState, mask: torch.Tensor) -> FusedState:
        mask = self._mask(mask)
        return FusedState(tuple(m.reset_where(s, mask) for m, s in zip(self.members, state.members)))

    def step_state(self, state: FusedState, events, t_us: int, truth: Optional[Truth] = None):
        states, outs = [], []
        for m, s in zip(self.members, state.members):  # a few members: not a loop over the batch
            s, out = m.step_state(s, events, t_us, truth)
            states.append(s)
            outs.append(out)
        d = torch.stack([o.d_hat.to(device=self.device, dtype=torch.float32) for o in outs])
        c = torch.stack([o.confidence.to(device=self.device, dtype=torch.float32) for o in outs])
        if self.rule == "precision":
            d_hat, conf = fuse_precision(d, c)
        else:
            d_hat, conf = fuse_priority(d, c, self.min_confidence)
        diag: Dict[str, torch.Tensor] = {f"{lab}.{k}": v for lab, o in zip(self.member_labels, outs)
                                         for k, v in o.diagnostics.items()}
        diag.update(confidence=conf, n_members=(torch.isfinite(d) & (c > 0)).sum(0))
        return FusedState(tuple(states)), EstimateOut(d_hat, conf, diag)


__all__ = ["FusedEstimator", "FusedState", "fuse_precision", "fuse_priority", "member_names", "RULES"]
