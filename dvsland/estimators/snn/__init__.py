"""``snn``: a trained spiking divergence estimator (docs/estimators_snn.md).

Public names: :class:`SpikingEstimator` (registered as "snn"; its stage: :class:`SpikingState`,
:class:`SNNConsts`, :func:`snn_step`), :class:`SpikingDivergenceNet`,
:class:`LogPolarEncoder`, the LIF primitives (:mod:`.lif`), :func:`load_checkpoint`,
:func:`save_checkpoint`, ``DEFAULT_CHECKPOINT``. Training: :mod:`.train`, the ``dvsland train``
command (:mod:`dvsland.cli.cmd_train`).
"""

from .encoding import LogPolarEncoder
from .estimator import (DEFAULT_CHECKPOINT, SNNConsts, SpikingEstimator, SpikingState, load_checkpoint,
                        save_checkpoint, snn_step)
from .lif import LIFParameters, LIFState, LIState, li_step, lif_step, spike
from .model import SpikingDivergenceNet

__all__ = ["SpikingEstimator", "SpikingState", "SNNConsts", "snn_step", "SpikingDivergenceNet", "LogPolarEncoder",
           "LIFParameters", "LIFState", "LIState", "lif_step", "li_step", "spike", "load_checkpoint", "save_checkpoint", "DEFAULT_CHECKPOINT"]
