"""Model stage: the SMART model (RoadNet + factorised MotionNet + next-token heads), its named
configs (Table 6: smart-1m, smart-7m, smart-26m, smart-101m), batch tensors, losses and checkpoints.

Read top to bottom: :mod:`.layers` (Fourier RPE, dense K-nearest neighbourhoods, attention),
:mod:`.roadnet`, :mod:`.motionnet`, :mod:`.smart` (the model and configs), :mod:`.batch` (tokenized
scenes -> padded tensors), :mod:`.losses`, :mod:`.checkpoint`.
"""

from .batch import SmartBatch, collate_scenes, scene_road, scene_tensors
from .checkpoint import Checkpoint, CheckpointError, VocabularyMismatchError, load_checkpoint, save_checkpoint
from .losses import NextTokenLoss
from .smart import NAMED_CONFIGS, SMART, ModelConfigError, SmartConfig, get_config, model_parameter_count

__all__ = [
    "Checkpoint", "CheckpointError", "ModelConfigError", "NAMED_CONFIGS", "NextTokenLoss", "SMART", "SmartBatch", "SmartConfig",
    "VocabularyMismatchError", "collate_scenes", "get_config", "load_checkpoint", "model_parameter_count", "save_checkpoint",
    "scene_road", "scene_tensors",
]
