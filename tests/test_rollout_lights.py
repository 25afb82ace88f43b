"""Light states that follow the clock in closed loop (RolloutState(lights="log"), issue 33): before every step the
road pieces carry the scene's logged light states of the frame that step starts at; "current" (the default) holds
the current frame's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from smart_marl.model.batch import light_codes, scene_road
from smart_marl.rollout import RolloutState
from smart_marl.tokens.road import RoadVocabulary

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def test_logged_lights_follow_the_frames_of_the_steps_and_reach_the_logits(model, vocab, scenes):
    scene = scenes[0]  # 637f20cafde22ff8: lane 431's signal goes from unknown (0) to ARROW_STOP (1) at frame 20
    any_vocab = RoadVocabulary(points=np.zeros((1, 11, 2), np.float32), tolerance_m=0.0, requested_size=1)  # tokens unused
    index = scene_road(scene, any_vocab, model.config.road_settings).light_index
    assert (index >= 0).any()
    held = RolloutState.start(model, scene, num_rollouts=2, seed=0, motion_vocab=vocab)
    follow = RolloutState.start(model, scene, num_rollouts=2, seed=0, motion_vocab=vocab, lights="log")
    start = held.road_light.clone()
    torch.testing.assert_close(follow.road_light, start)  # both start from the current frame's lights
    changed_at = []
    for k in range(1, 5):
        forced = torch.zeros(held.num_groups, held.num_slots, dtype=torch.long)  # the same tokens in both
        held.step(forced)
        follow.step(forced)
        want = light_codes(scene.traffic_lights, index, scene.current_frame + 5 * k)
        assert follow.road_light[0, : len(index)].tolist() == want.tolist()
        assert torch.equal(held.road_light, start)
        if not np.array_equal(want, start[0, : len(index)].numpy()):
            changed_at.append(k)
            assert not torch.allclose(follow.logits(), held.logits())  # the model sees the new lights
    assert changed_at  # the scene's lights do change within these steps


def test_unknown_lights_mode_is_refused(model, vocab, scenes):
    with pytest.raises(ValueError, match="lights must be one of"):
        RolloutState.start(model, scenes[0], num_rollouts=1, motion_vocab=vocab, lights="future")
