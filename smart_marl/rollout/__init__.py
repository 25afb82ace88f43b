"""Rollout stage: closed-loop generation with the SMART prior (KV-cached incremental decoding,
top-k sampling, scenes x rollouts in one batch) and the stepping API the environment drives.

``rollout(model_or_checkpoint, scenes, ...) -> RolloutResult`` for whole 8 s futures;
``RolloutState.start(...)`` / ``state.step(forced_tokens)`` for one token step at a time.
"""

from .engine import (
    MODES, RolloutResult, RolloutState, SceneHistory, StepOutput, collect_result, motion_vocabulary_from_model, resolve_model,
    rollout, scene_history, token_poses_from_contours,
)
from .incremental import IncrementalMotionNet
from .sampling import pad_type_logits, sample_tokens

__all__ = [
    "MODES", "IncrementalMotionNet", "RolloutResult", "RolloutState", "SceneHistory", "StepOutput", "collect_result",
    "motion_vocabulary_from_model", "pad_type_logits", "resolve_model", "rollout", "sample_tokens", "scene_history",
    "token_poses_from_contours",
]
