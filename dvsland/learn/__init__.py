"""The training recipe of the learned estimators (docs/learning.md).

Public names: :func:`train` and :class:`RecipeSettings` (:mod:`.recipe`), :func:`score` and
:func:`predict` (:mod:`.metrics`: median |relative error| and calibration per site type),
:func:`make_batch` (:mod:`.batches`).
"""

from .batches import Batch, make_batch
from .metrics import predict, score
from .recipe import RecipeSettings, train

__all__ = ["train", "RecipeSettings", "score", "predict", "make_batch", "Batch"]
