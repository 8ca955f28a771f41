"""The training recipe of the learned estimators (docs/learning.md).

Public names: :func:`train`, :class:`RecipeSettings` and the named recipes :data:`RECIPES`,
:func:`recipe` (:mod:`.recipe`), :func:`score` and
:func:`predict` (:mod:`.metrics`: median |relative error| and calibration per site type),
:func:`make_batch` (:mod:`.batches`).
"""

from .batches import Batch, make_batch
from .metrics import predict, score
from .recipe import RECIPES, RecipeSettings, recipe, train

__all__ = ["train", "RecipeSettings", "RECIPES", "recipe", "score", "predict", "make_batch", "Batch"]
