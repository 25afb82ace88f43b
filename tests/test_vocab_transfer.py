"""Warm start across motion vocabularies (smart_marl.model.transfer): a new token takes the head row of
the old token nearest it, and the probability of an old token is split among the new tokens sharing it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from smart_marl.model.checkpoint import Checkpoint
from smart_marl.model.transfer import nearest_tokens, transfer_motion_vocabulary
from smart_marl.tokens import MotionVocabulary
from smart_marl.tokens.motion import TypeVocab
from smart_marl.tokens.road import RoadVocabulary


def test_nearest_tokens_picks_the_closest_contour():
    old = torch.zeros(3, 6, 4, 2)
    old[1] += 1.0
    old[2] += 5.0
    new = torch.stack([old[2] + 0.1, old[0] - 0.2, old[1] + 0.3, old[1] - 0.4])
    assert nearest_tokens(old, new).tolist() == [2, 0, 1, 1]


def test_transfer_to_a_vocabulary_holding_each_old_token_twice_splits_its_probability(sample_vocab, tiny_smart):
    model = tiny_smart(sample_vocab)
    order = {t: np.concatenate([np.arange(v.size)[::-1], np.arange(v.size)]) for t, v in sample_vocab.types.items()}
    doubled = MotionVocabulary(types={t: TypeVocab.from_poses(v.poses[order[t]], v.length_m, v.width_m)
                                      for t, v in sample_vocab.types.items()})
    road = RoadVocabulary(points=np.zeros((8, 11, 2), np.float32), tolerance_m=0.0, requested_size=8)
    new = transfer_motion_vocabulary(Checkpoint(model=model, motion_vocab=sample_vocab, road_vocab=road), doubled).model.eval()

    features = torch.randn(50, model.config.hidden_dim, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        old_logits = model.motion_logits(features, None)
        new_logits = new.motion_logits(features, None)
    for t in range(3):
        pick = torch.as_tensor(order[t])
        torch.testing.assert_close(new_logits[t], old_logits[t][:, pick] - math.log(2))
        # the two new tokens of an old one carry together exactly the old token's probability
        p_old, p_new = old_logits[t].softmax(-1), new_logits[t].softmax(-1)
        v = p_old.shape[1]
        torch.testing.assert_close(p_new[:, :v].flip(-1) + p_new[:, v:], p_old)
        # token inputs come from the contours: the new token embeds as its old twin
        torch.testing.assert_close(new.motion_contours[t], model.motion_contours[t][pick])
    shared = {k: v for k, v in model.state_dict().items() if not k.startswith("motion_contour")
              and not k.startswith(tuple(f"motion_heads.{t}.{len(model.motion_heads[t]) - 1}." for t in range(3)))}
    for k, v in shared.items():
        torch.testing.assert_close(new.state_dict()[k], v)


def test_vocab_transfer_command_writes_a_checkpoint_that_loads_with_the_new_vocabulary(tiny_prior, sample_vocab, tmp_path, capsys):
    from smart_marl.cli import main
    from smart_marl.model.checkpoint import load_checkpoint
    from smart_marl.tokens import save_motion_vocabulary

    npz, _ = save_motion_vocabulary(sample_vocab, tmp_path / "motion_32")
    assert main(["vocab", "transfer", str(tiny_prior), "--motion-vocab", str(npz), "--out", str(tmp_path / "moved")]) == 0
    ck = load_checkpoint(tmp_path / "moved.json", motion_vocab=sample_vocab)
    assert tuple(ck.model.config.motion_vocab_sizes) == tuple(sample_vocab[t].size for t in range(3))
    assert ck.meta["data"]["transferred_from"].endswith(".json")
    assert '"motion_sizes"' in capsys.readouterr().out


def test_transfer_of_one_type_keeps_the_other_types_tokens_and_head_rows_exactly(sample_vocab, tiny_smart, tiny_prior, tmp_path, capsys):
    """types=["pedestrian"]: vehicles and cyclists keep their vocabularies and logits bit for bit; only
    the pedestrian tokens and head rows change (here to a reversed copy of another vocabulary)."""
    from smart_marl.cli import main
    from smart_marl.model.checkpoint import load_checkpoint
    from smart_marl.model.transfer import merge_vocabularies
    from smart_marl.scenario import AgentType
    from smart_marl.tokens import save_motion_vocabulary

    model = tiny_smart(sample_vocab)
    road = RoadVocabulary(points=np.zeros((8, 11, 2), np.float32), tolerance_m=0.0, requested_size=8)
    other = MotionVocabulary(types={t: TypeVocab.from_poses(v.poses[::-1][: v.size // 2], v.length_m, v.width_m)
                                    for t, v in sample_vocab.types.items()})
    moved = transfer_motion_vocabulary(Checkpoint(model=model, motion_vocab=sample_vocab, road_vocab=road), other, ["pedestrian"])
    assert moved.motion_vocab[AgentType.VEHICLE] is sample_vocab[AgentType.VEHICLE]
    assert moved.motion_vocab[AgentType.CYCLIST] is sample_vocab[AgentType.CYCLIST]
    assert moved.motion_vocab[AgentType.PEDESTRIAN] is other[AgentType.PEDESTRIAN]
    features = torch.randn(20, model.config.hidden_dim, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        old_logits, new_logits = model.eval().motion_logits(features, None), moved.model.eval().motion_logits(features, None)
    for t in (AgentType.VEHICLE, AgentType.CYCLIST):
        assert torch.equal(new_logits[t], old_logits[t])
    assert new_logits[AgentType.PEDESTRIAN].shape[1] == other[AgentType.PEDESTRIAN].size
    with pytest.raises(ValueError, match="no tokens for pedestrian"):
        merge_vocabularies(sample_vocab, MotionVocabulary(types={AgentType.VEHICLE: sample_vocab[AgentType.VEHICLE]}), ["pedestrian"])

    npz, _ = save_motion_vocabulary(other, tmp_path / "motion_other")
    assert main(["vocab", "transfer", str(tiny_prior), "--motion-vocab", str(npz), "--types", "pedestrian",
                 "--out", str(tmp_path / "moved")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["motion_sizes"]["pedestrian"] == other[AgentType.PEDESTRIAN].size
    assert out["motion_sizes"]["vehicle"] == load_checkpoint(tiny_prior).motion_vocab[AgentType.VEHICLE].size
    with pytest.raises(SystemExit) as exit_info:
        main(["vocab", "transfer", str(tiny_prior), "--motion-vocab", str(npz), "--types", "walker", "--out", str(tmp_path / "bad")])
    assert exit_info.value.code == 2
    assert "argument --types: expected a comma-separated list of vehicle, pedestrian, cyclist" in capsys.readouterr().err
