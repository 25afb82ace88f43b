"""Rollout stage: closed-loop generation with the SMART prior (the model's KV-cached step, top-k
sampling, scenes x rollouts in one batch) and the stepping API the environment drives.

``rollout(model_or_checkpoint, scenes, ...) -> RolloutResult`` for whole 8 s futures;
``RolloutState.start(...)`` / ``state.step(forced_tokens)`` for one token step at a time.
"""

from .drawing import FORCED_LATER, Draw
from .engine import (
    LIGHTS, MODES, RolloutResult, RolloutState, StepOutput, TrackFrames, collect_result, rollout, track_frames,
)
from .history import SceneHistory, scene_history
from .sampling import (
    DEFAULT_TOP_K, TEMPERATURE_RANGE, has_prior_logits, no_prior_logits, reference_log_probs, reference_name, sample_tokens,
    temperature_rule, top_k_mask,
)

__all__ = [
    "FORCED_LATER", "Draw", "LIGHTS", "MODES", "RolloutResult", "RolloutState", "SceneHistory", "StepOutput", "TrackFrames", "collect_result", "rollout",
    "DEFAULT_TOP_K", "TEMPERATURE_RANGE", "has_prior_logits", "no_prior_logits", "reference_log_probs", "reference_name",
    "sample_tokens", "scene_history", "temperature_rule", "top_k_mask", "track_frames",
]
