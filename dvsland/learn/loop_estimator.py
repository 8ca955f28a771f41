"""``dvsland train-loop --what estimator``: the ``learned`` estimator's weights, fine-tuned on the
landing loss through the closed loop.

The events stay inputs (rendered and emulated along the flown trajectory, no gradient to the state);
the network's forward keeps its graph (:class:`~dvsland.estimators.learned.LearnedConsts` ``grad``),
and the loop runs with ``loop_step(..., grad=True)`` (:func:`~dvsland.learn.loop_loss.gradient_mode`),
so d loss / d D_hat (and d loss / d confidence, through the filter's weights) reaches the weights.

The estimator's fused ring net (:class:`~dvsland.estimators.learned.fast.RingCNN`, the default
``fast="ring"``) copies the first layer's weights; the training estimator therefore runs the model
as trained (``fast=""``: the ring net's reference, equal to float32 rounding). A validation batch
(and ``simulate`` on ``trained.yaml``) flies the trained weights through a ring net rebuilt from them.

The checkpoint (``checkpoint.pt``) is a ``dvsland train`` checkpoint (format ``dvsland-learned``:
``model``, ``input``, ``state_dict``, ``data``, ``train`` of the checkpoint it started from) with the
loop's fields beside (``kind`` = :data:`ESTIMATOR_KIND`, optimizer, counters: ``--resume``), so
``trained.yaml`` names it as ``estimator.learned.checkpoint`` and the ``learned`` estimator loads it.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch
from torch import nn

from dvsland.estimators.learned.checkpoint import FORMAT, FORMAT_VERSION, read_checkpoint
from dvsland.estimators.learned.estimator import LearnedEstimator
from dvsland.estimators.learned.fast import RingCNN
from dvsland.estimators.state_dict_check import check_state_dict

#: ``kind`` of a train-loop checkpoint of the estimator's weights
ESTIMATOR_KIND = "dvsland-loop-estimator"
#: the estimator ``--what estimator`` trains
TRAINED_ESTIMATOR = "learned"
#: fields of the starting ``dvsland train`` checkpoint carried into the trained one
CARRIED = ("model", "input", "data", "train")
#: autograd memory the network's forward holds per descent-step and cell of its input grid, bytes:
#: 73 measured (the shipped CNN, 8 bins on a 64 x 64 grid: 297 KB per descent-step, 70x the rest of
#: the loop's graph); 2x that as margin
GRAPH_BYTES_PER_GRID_CELL = 160


def trained_estimator(stages) -> LearnedEstimator:
    """The ``learned`` estimator of ``stages``; ValueError naming ``--what estimator`` and
    ``estimator.name`` for any other."""
    name = stages.cfg.estimator.name
    est = stages.estimator
    if name != TRAINED_ESTIMATOR or not isinstance(est, LearnedEstimator):
        raise ValueError(f"--what estimator: trains the {TRAINED_ESTIMATOR!r} estimator's network; estimator.name is "
                         f"{name!r} (add --set estimator.name={TRAINED_ESTIMATOR}, and estimator.learned.checkpoint "
                         f"for another network than the shipped CNN)")
    return est


def estimator_graph_bytes(stages) -> int:
    """Bytes of autograd graph the estimator of ``stages`` adds per descent-step: its network's
    forward when it keeps its graph (``consts.grad``), :data:`GRAPH_BYTES_PER_GRID_CELL` per input
    cell; 0 otherwise."""
    c = getattr(stages.estimator, "consts", None)
    if getattr(c, "grad", False) is not True:
        return 0
    h, w = c.spec.grid_hw
    return GRAPH_BYTES_PER_GRID_CELL * int(h) * int(w)


class EstimatorWeights(nn.Module):
    """The ``learned`` estimator's network (shared, not copied: the training estimator flies these
    weights, with its graph kept; module doc). A :class:`~dvsland.learn.loop_trainables.Trainable` by
    its interface (``what``, ``apply``, ``apply_to``, ``describe``); not by inheritance, so that
    :func:`~dvsland.learn.loop_trainables.make_trainable` can build it without an import circle.

    Args:
        stages: the training loop's stages (``estimator.name=learned``).
    """

    what = "estimator"

    def __init__(self, stages):
        super().__init__()
        est = trained_estimator(stages)
        ck = read_checkpoint(est.checkpoint)
        self.source = str(Path(est.checkpoint).resolve())
        self.carried = {k: ck[k] for k in CARRIED if k in ck}
        self.net = est.model.requires_grad_(True)
        self._start = [p.detach().clone() for p in self.net.parameters()]
        self._trained = est  # a plain attribute (not a module): the estimator whose step keeps the graph
        est.ring_net = None
        est.consts = est.consts._replace(model=self.net, ring_net=None, grad=True)

    def apply(self, controller) -> None:  # the law is not trained
        pass

    def apply_to(self, stages) -> None:
        """The trained weights into ``stages``' estimator: the training's keeps its graph (no ring net);
        another (a validation batch) gets no graph and a ring net rebuilt from them if it had one."""
        est = trained_estimator(stages)
        if est is self._trained:
            est.consts = est.consts._replace(model=self.net, ring_net=None, grad=True)
            return
        ring = None
        if est.consts.ring_net is not None:
            ring = RingCNN(self.net, est.coords, est.spec.n_windows, dtype=est.consts.ring_net.dtype)
        est.model, est.ring_net = self.net, ring
        est.consts = est.consts._replace(model=self.net, ring_net=ring, grad=False)

    def weight_change(self) -> float:
        """||w - w_start|| / ||w_start|| over every weight."""
        with torch.no_grad():
            num = sum(float((p - p0).pow(2).sum()) for p, p0 in zip(self.net.parameters(), self._start))
            den = sum(float(p0.pow(2).sum()) for p0 in self._start)
        return (num / max(den, 1e-30)) ** 0.5

    def describe(self) -> dict:
        return {"parameters": sum(p.numel() for p in self.net.parameters()),
                "weight_change": round(self.weight_change(), 6)}

    # ------------------------------------------------------------------ checkpoint and config
    def checkpoint_fields(self) -> dict:
        """The ``dvsland train`` checkpoint fields (format, model, input, weights, provenance)."""
        return {"format": FORMAT, "format_version": FORMAT_VERSION, **self.carried,
                "state_dict": {k: v.detach().clone() for k, v in self.net.state_dict().items()},
                "finetuned_by": {"command": "dvsland train-loop --what estimator", "from": self.source}}

    def load_checkpoint_fields(self, ck: dict, where: str) -> None:
        """The weights of a checkpoint written by :meth:`checkpoint_fields` (``--resume``)."""
        if ck.get("format") != FORMAT or ck.get("model") != self.carried.get("model"):
            raise ValueError(f"{where}: its network ({ck.get('model')!r}) is not the configured estimator's "
                             f"({self.carried.get('model')!r})")
        check_state_dict(ck.get("state_dict"), self.net, where)
        self.net.load_state_dict(ck["state_dict"])

    def trained_config(self, cfg, ckpt: Path):
        """``cfg`` with ``estimator.learned.checkpoint`` = ``ckpt`` by absolute path."""
        e = cfg.estimator
        return replace(cfg, estimator=replace(e, learned=replace(e.learned, checkpoint=str(Path(ckpt).resolve()))))


__all__ = ["EstimatorWeights", "trained_estimator", "estimator_graph_bytes", "ESTIMATOR_KIND", "TRAINED_ESTIMATOR",
           "GRAPH_BYTES_PER_GRID_CELL"]
