"""SMART model: named configs' parameter counts, causality in time, batch alignment, checkpoints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from smart_marl.model.batch import SmartBatch, collate_scenes, scene_road, scene_tensors
from smart_marl.model.checkpoint import VocabularyMismatchError, load_checkpoint, save_checkpoint
from smart_marl.model.layers import knn_within, relative_pose_features
from smart_marl.model.smart import NAMED_CONFIGS, PAPER_PARAMS, SMART, ModelConfigError, get_config, model_parameter_count
from smart_marl.scenario import AgentType
from smart_marl.synthetic import synthetic_scenario
from smart_marl.tokens import MotionVocabulary, TypeVocab, tokenize_motion
from smart_marl.tokens.motion import BOX_SIZE_M
from smart_marl.tokens.road import RoadVocabulary


def tiny_config(**kw):
    base = dict(hidden_dim=16, num_heads=2, head_dim=8, num_road_layers=1, num_agent_blocks=2, motion_vocab_sizes=(8, 8, 8),
                road_vocab_size=8, num_freq_bands=4, dropout=0.0, agent_neighbours=4, map_neighbours=4, road_neighbours=4)
    base.update(kw)
    return get_config("smart-1m", **base)


def random_batch(b=2, n=5, s=8, r=12, seed=0) -> SmartBatch:
    g = torch.Generator().manual_seed(seed)
    pose = torch.cat([torch.rand(b, n, s, 2, generator=g) * 40, torch.rand(b, n, s, 1, generator=g) * 6 - 3], -1)
    start = pose + torch.randn(b, n, s, 3, generator=g) * 0.5
    valid = torch.rand(b, n, s, generator=g) > 0.2
    rpose = torch.cat([torch.rand(b, r, 2, generator=g) * 40, torch.rand(b, r, 1, generator=g) * 6 - 3], -1)
    e = 6
    return SmartBatch(
        agent_tokens=torch.randint(0, 8, (b, n, s), generator=g), agent_valid=valid, agent_type=torch.randint(0, 3, (b, n), generator=g),
        agent_shape=torch.rand(b, n, 3, generator=g) * 4, agent_start_pose=start, agent_pose=pose,
        target_tokens=torch.randint(0, 8, (b, n, s), generator=g), target_valid=valid,
        road_points=torch.randn(b, r, 11, 2, generator=g), road_pose=rpose, road_type=torch.randint(0, 60, (b, r), generator=g),
        road_light=torch.randint(0, 10, (b, r), generator=g), road_valid=torch.ones(b, r, dtype=torch.bool),
        road_token=torch.randint(0, 8, (b, r), generator=g), road_masked=torch.rand(b, r, generator=g) < 0.3,
        road_pairs=torch.randint(0, r, (b, e, 2), generator=g), road_pair_valid=torch.ones(b, e, dtype=torch.bool))


@pytest.mark.parametrize("name", list(NAMED_CONFIGS))
def test_named_config_parameter_count_is_within_10_percent_of_the_paper(name):
    n = model_parameter_count(get_config(name))
    assert abs(n / PAPER_PARAMS[name] - 1.0) < 0.10, (name, n)


def test_named_configs_carry_table6_hyperparameters():
    c = get_config("smart-101m")
    assert (c.hidden_dim, c.num_heads, c.head_dim, c.num_road_layers, c.num_agent_blocks) == (512, 8, 64, 3, 6)
    assert c.motion_vocab_sizes == (2048, 2048, 2048) and c.road_vocab_size == 1024
    assert (c.agent_radius_m, c.map_radius_m, c.road_radius_m, c.temporal_window_tokens) == (60.0, 30.0, 10.0, 6)


def test_unknown_config_name_and_field_are_clear_errors():
    with pytest.raises(ModelConfigError, match="unknown model config 'smart-3m'.*smart-1m"):
        get_config("smart-3m")
    with pytest.raises(ModelConfigError, match="unknown model config field.*hiden_dim"):
        get_config("smart-1m", hiden_dim=3)


def test_knn_within_matches_brute_force():
    g = torch.Generator().manual_seed(1)
    q, k = torch.rand(1, 30, 2, generator=g) * 50, torch.rand(1, 40, 2, generator=g) * 50
    kv = torch.rand(1, 40, generator=g) > 0.3
    idx, mask = knn_within(q, k, 15.0, 6, torch.ones(1, 30, dtype=torch.bool), kv)
    d = torch.cdist(q[0], k[0]).numpy()
    for i in range(30):
        cand = [j for j in np.argsort(d[i]) if kv[0, j] and d[i, j] <= 15.0][:6]
        assert sorted(idx[0, i][mask[0, i]].tolist()) == sorted(cand)


def test_relative_pose_features_bearing_is_in_the_query_frame():
    q = torch.tensor([1.0, 2.0, np.pi / 2])  # facing +y
    k = torch.tensor([1.0, 5.0, 0.0])  # 3 m straight ahead, heading -pi/2 relative
    dist, bearing, dh = relative_pose_features(q, k).tolist()
    assert dist == pytest.approx(3.0) and bearing == pytest.approx(0.0, abs=1e-6) and dh == pytest.approx(-np.pi / 2)


def test_motion_features_of_a_step_do_not_depend_on_later_steps():
    torch.manual_seed(0)
    model = SMART(tiny_config()).eval()
    batch = random_batch()
    with torch.no_grad():
        feats, _ = model(batch)
        t = 4
        changed = random_batch(seed=5)
        b2 = SmartBatch(**vars(batch))
        for name in ("agent_tokens", "agent_valid", "agent_start_pose", "agent_pose"):
            x = getattr(batch, name).clone()
            x[:, :, t + 1:] = getattr(changed, name)[:, :, t + 1:]
            setattr(b2, name, x)
        feats2, _ = model(b2)
        logits = [torch.stack(model.motion_logits(f, batch.agent_type)) for f in (feats, feats2)]
    valid = batch.agent_valid[:, :, : t + 1]
    assert torch.allclose(logits[0][:, :, :, : t + 1][:, valid], logits[1][:, :, :, : t + 1][:, valid], atol=1e-5)
    # a batch cut after step t gives the same features: step t needs nothing later (incremental inference)
    cut = SmartBatch(**{k: (v[:, :, : t + 1] if k.startswith(("agent_", "target_")) and v.dim() >= 3 else v) for k, v in vars(batch).items()})
    with torch.no_grad():
        feats_cut, _ = model(cut)
    assert torch.allclose(feats_cut[valid], feats[:, :, : t + 1][valid], atol=1e-5)
    # and the later steps did change (the test is not vacuous)
    later = batch.agent_valid[:, :, t + 1:] & b2.agent_valid[:, :, t + 1:]
    assert not torch.allclose(feats[:, :, t + 1:][later], feats2[:, :, t + 1:][later])


def _grid_vocab(size=8) -> MotionVocabulary:
    """A small deterministic vocabulary: straight motions at ``size`` speeds (0 .. 15 m/s)."""
    types = {}
    for t in (AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST):
        speeds = np.linspace(0.0, 15.0, size)
        poses = np.zeros((size, 6, 3), np.float32)
        poses[:, :, 0] = speeds[:, None] * np.arange(6)[None] * 0.1
        types[t] = TypeVocab.from_poses(poses, *BOX_SIZE_M[t])
    return MotionVocabulary(types=types, method="uniform_grid")


def _road_vocab(size=8) -> RoadVocabulary:
    pts = np.zeros((size, 11, 2), np.float32)
    pts[:, :, 0] = np.linspace(0, 1, 11)[None] * np.linspace(1, 5, size)[:, None]
    return RoadVocabulary(points=pts, tolerance_m=0.0, requested_size=size)


def test_batch_targets_are_the_next_steps_nearest_tokens():
    sc = synthetic_scenario(0)
    mv, rv = _grid_vocab(), _road_vocab()
    mt = tokenize_motion(sc, mv)
    arr = scene_tensors(sc, mv, scene_road(sc, rv), rng=0)
    keep = np.flatnonzero(mt.valid.any(1))
    assert np.array_equal(arr["agent_tokens"], mt.ids[keep])
    both = mt.valid[keep][:, :-1] & mt.valid[keep][:, 1:]
    assert np.array_equal(arr["target_valid"][:, :-1], both) and not arr["target_valid"][:, -1].any()
    assert np.array_equal(arr["target_tokens"][:, :-1][both], mt.nearest_ids[keep][:, 1:][both])
    assert np.allclose(arr["agent_pose"], mt.reached[keep][:, 1:])
    b = collate_scenes([arr, scene_tensors(synthetic_scenario(1), mv, scene_road(synthetic_scenario(1), rv), rng=1)])
    assert b.agent_tokens.shape[0] == 2 and b.target_valid[0].sum() == both.sum()


def test_road_crop_radius_changes_no_agent_feature():
    sc = synthetic_scenario(0)
    mv, rv = _grid_vocab(), _road_vocab()
    cfg = tiny_config(motion_vocab_sizes=(8, 8, 8), road_vocab_size=8)
    model = SMART(cfg, [torch.from_numpy(mv[t].contour) for t in range(3)]).eval()
    road = scene_road(sc, rv)
    full = collate_scenes([scene_tensors(sc, mv, road, rng=0, road_mask_prob=0.0)])
    radius = cfg.map_radius_m + cfg.num_road_layers * cfg.road_radius_m
    crop = collate_scenes([scene_tensors(sc, mv, road, rng=0, road_mask_prob=0.0, road_keep_radius_m=radius)])
    with torch.no_grad():
        f1, _ = model(full)
        f2, _ = model(crop)
    assert torch.allclose(f1, f2, atol=1e-5)


def test_checkpoint_round_trip_and_vocabulary_mismatch(tmp_path):
    mv, rv = _grid_vocab(), _road_vocab()
    torch.manual_seed(0)
    model = SMART(tiny_config(), [torch.from_numpy(mv[t].contour) for t in range(3)])
    save_checkpoint(tmp_path / "ck", model, mv, rv, step=7, metrics={"loss": 1.5})
    ck = load_checkpoint(tmp_path / "ck", motion_vocab=mv)
    assert ck.step == 7 and ck.meta["vocabularies"]["motion"]["content_hash"] == mv.content_hash()
    for k, v in model.state_dict().items():
        assert torch.equal(v, ck.model.state_dict()[k])
    other = _grid_vocab()
    poses = other[AgentType.VEHICLE].poses.copy()
    poses[1, :, 0] *= 1.1
    other.types[AgentType.VEHICLE] = TypeVocab.from_poses(poses, *BOX_SIZE_M[AgentType.VEHICLE])
    with pytest.raises(VocabularyMismatchError, match="not the one this model was trained with"):
        load_checkpoint(tmp_path / "ck", motion_vocab=other)
