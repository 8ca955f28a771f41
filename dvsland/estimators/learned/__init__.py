"""The ``learned`` estimator and its model zoo (docs/learning.md).

Public names: :class:`LearnedEstimator` (registered as ``learned``; its stage: :class:`LearnedState`,
:class:`LearnedConsts`, :func:`learned_step`), :class:`InputSpec`,
:func:`voxel_grid`, :func:`coord_channels`, :data:`MODELS`, :func:`build_model`,
:func:`save_checkpoint`, :func:`load_checkpoint`.
"""

from .checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from .estimator import LearnedConsts, LearnedEstimator, LearnedState, learned_step
from .inputs import InputSpec, check_input_spec, coord_channels, events_voxel_grid, voxel_grid
from .models import MODELS, SpikingVoxelNet, VoxelCNN, build_model, model_class

__all__ = ["LearnedEstimator", "LearnedState", "LearnedConsts", "learned_step", "InputSpec", "check_input_spec",
           "coord_channels", "events_voxel_grid", "voxel_grid", "MODELS", "SpikingVoxelNet", "VoxelCNN", "build_model",
           "model_class", "load_checkpoint", "read_checkpoint", "save_checkpoint"]
