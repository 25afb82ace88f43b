"""Model stage: the SMART model (RoadNet + factorised MotionNet + next-token heads), its named
configs (Table 6: smart-1m, smart-7m, smart-26m, smart-101m), batch tensors, losses and checkpoints.

The model, including the path inference takes, is four files, read top to bottom: :mod:`.layers`
(Fourier RPE, dense K-nearest neighbourhoods, attention), :mod:`.roadnet`, :mod:`.motionnet` (its
forward over every step and the KV-cached step beside it) and :mod:`.smart` (the model, its heads
and configs; ``forward`` for training, ``encode_road`` / ``start_cache`` / ``step`` /
``next_token_logits`` for inference). Around it: :mod:`.batch` (tokenized scenes -> padded tensors),
:mod:`.losses`, :mod:`.checkpoint` (files, and :func:`~.checkpoint.load_prior`).
"""

from .batch import RoadSettings, SmartBatch, collate_scenes, scene_road, scene_tensors
from .checkpoint import (
    Checkpoint, CheckpointError, Prior, VocabularyMismatchError, load_checkpoint, load_prior, save_checkpoint,
)
from .losses import NextTokenLoss
from .motionnet import MotionCache
from .smart import NAMED_CONFIGS, SMART, ModelConfigError, SmartConfig, get_config, model_parameter_count

__all__ = [
    "Checkpoint", "CheckpointError", "ModelConfigError", "MotionCache", "NAMED_CONFIGS", "NextTokenLoss", "Prior", "RoadSettings", "SMART", "SmartBatch",
    "SmartConfig", "VocabularyMismatchError", "collate_scenes", "get_config", "load_checkpoint", "load_prior",
    "model_parameter_count", "save_checkpoint",
    "scene_road", "scene_tensors",
]
