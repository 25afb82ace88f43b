"""CAT-K closed-loop targets (smart_marl.catk): the chosen token is the closest among the model's
top-K, a rollout allowed every token is the log's own rolling matching, and the training mode runs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from smart_marl.catk import catk_tokens, first_future_step
from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors
from smart_marl.tokens import box_contour, compose_poses, tokenize_motion
from smart_marl.tokens.road import RoadVocabulary, road_pieces

from model_variants import TINY_TRAIN_MODEL


@pytest.fixture(scope="module")
def road_vocab(sample_scenes):
    pieces = road_pieces(sample_scenes[0].road_map).local
    return RoadVocabulary(points=pieces[np.random.default_rng(0).choice(len(pieces), 8)], tolerance_m=0.0, requested_size=8)


def test_catk_with_every_token_allowed_is_the_logged_rolling_matching(sample_scenes, sample_vocab, tiny_smart, road_vocab,
                                                                       one_torch_thread):
    model = tiny_smart(sample_vocab)
    scenes = sample_scenes
    roads = [scene_road(sc, road_vocab) for sc in scenes]
    got = catk_tokens(model, scenes, roads, sample_vocab, top_k=max(v.size for v in sample_vocab.types.values()))
    for sc, mt in zip(scenes, got):
        log = tokenize_motion(sc, sample_vocab)
        assert mt.valid.sum() > 100
        np.testing.assert_array_equal(mt.valid, log.valid)
        np.testing.assert_array_equal(mt.ids[mt.valid], log.ids[log.valid])
        np.testing.assert_array_equal(mt.nearest_ids, log.nearest_ids)  # the targets are the log's tokens
        np.testing.assert_allclose(mt.reached, log.reached, atol=1e-5)


def test_catk_token_is_the_closest_of_the_models_top_k(sample_scenes, sample_vocab, tiny_smart, road_vocab, one_torch_thread):
    """Checked independently: the full (not incremental) forward over the CAT-K sequence gives the
    top-K at each future step; among them, the token whose placed box contours are nearest the logged
    boxes (mean corner distance over the token's frames) is the one taken."""
    top_k = 3
    model = tiny_smart(sample_vocab)
    sc = sample_scenes[2]  # 43 agents valid at the current frame
    road = scene_road(sc, road_vocab)
    mt = catk_tokens(model, [sc], [road], sample_vocab, top_k=top_k)[0]
    batch = collate_scenes([scene_tensors(sc, sample_vocab, road, road_mask_prob=0.0, rng=0, motion_tokens=mt)])
    with torch.no_grad():
        feats, _ = model(batch)
    keep = np.flatnonzero(mt.valid.any(1))
    tr = sc.tracks
    kc = first_future_step(sc)
    checked, differs_from_nearest = 0, 0
    for k in range(kc, mt.num_steps):
        b0, b1 = mt.boundaries[k], mt.boundaries[k + 1]
        for j, row in enumerate(keep):
            if not (mt.valid[row, k] and mt.valid[row, k - 1]):
                continue
            t = int(tr.types[row])
            v = sample_vocab[t]
            logits = model.motion_heads[t](feats[0, j, k - 1])
            top = logits.topk(top_k).indices.numpy()
            frames = np.arange(b0 + 1, b1 + 1)
            ok = tr.valid[row, frames]
            gt = np.concatenate([tr.position[row, frames, :2], tr.heading[row, frames, None]], -1)[ok]
            gt_box = box_contour(gt.astype(np.float64), v.length_m, v.width_m)  # [F, 4, 2]
            dists = []
            for tok in top:
                placed = compose_poses(mt.start_pose[row, k].astype(np.float64), v.poses[tok, 1:].astype(np.float64))[ok]
                dists.append(np.linalg.norm(box_contour(placed, v.length_m, v.width_m) - gt_box, axis=-1).mean())
            assert mt.ids[row, k] == top[int(np.argmin(dists))]
            checked += 1
            differs_from_nearest += int(mt.ids[row, k] != mt.nearest_ids[row, k])
    assert checked > 200
    assert differs_from_nearest > 0  # the top-K restriction binds somewhere (else this test proves little)


class _StopsAtRead(list):
    """Scenes that raise on their ``n``-th read: a training run stopped between two checkpoints."""

    def __init__(self, scenes, n):
        super().__init__(scenes)
        self.reads, self.n = 0, n

    def __getitem__(self, i):
        self.reads += 1
        if self.reads == self.n:
            raise KeyboardInterrupt("stopped")
        return super().__getitem__(i)


def test_catk_training_mode_trains_on_its_rollouts_and_resumes_exactly(sample_scenes, sample_vocab, tmp_path, one_torch_thread):
    from smart_marl.model.checkpoint import load_checkpoint
    from smart_marl.tokens.vocab_io import save_motion_vocabulary, save_road_vocabulary
    from smart_marl.train import load_train_config, train

    scenes = sample_scenes[3:]  # one scene, 10 tracks
    pieces = road_pieces(scenes[0].road_map).local
    save_motion_vocabulary(sample_vocab, tmp_path / "mv")
    save_road_vocabulary(RoadVocabulary(points=pieces[:16], tolerance_m=0.0, requested_size=16), tmp_path / "rv")
    base = {"motion_vocab": str(tmp_path / "mv"), "road_vocab": str(tmp_path / "rv"), "batch_size": 1, "num_workers": 0,
            "max_steps": 4, "lr": 1e-3, "log_every": 1, "val_every": 0, "ckpt_every": 2, "tensorboard": False, "progress": False,
            "catk_top_k": 3, "dropout": 0.1, "road_keep_radius_m": 20.0,
            "model_overrides": TINY_TRAIN_MODEL}
    full = train(load_train_config(base, {"out_dir": str(tmp_path / "full")}), scenes=scenes)
    assert full.step == 4 and np.isfinite(full.last_train["loss"])
    train(load_train_config(base, {"out_dir": str(tmp_path / "forced"), "catk_top_k": 0, "token_noise_topk": 0,
                                   "max_steps": 1}), scenes=scenes)
    first = lambda run: (tmp_path / run / "train.csv").read_text().splitlines()[1].split(",")[1]  # noqa: E731  step 1's loss
    assert first("full") != first("forced")  # same weights at step 1: only the token sequences differ
    train(load_train_config(base, {"out_dir": str(tmp_path / "kept"), "catk_avoid": True, "brake_leaders": 1.0,
                                   "max_steps": 1}), scenes=scenes)
    assert first("kept") != first("full")  # the scene's leader brakes, its follower's targets keep the gap
    train(load_train_config(base, {"out_dir": str(tmp_path / "near"), "catk_max_drift_m": 0.01, "max_steps": 1}), scenes=scenes)
    assert first("near") != first("full")  # the tokens that drifted off the log are no targets
    with pytest.raises(KeyboardInterrupt):
        train(load_train_config(base, {"out_dir": str(tmp_path / "stopped")}), scenes=_StopsAtRead(scenes, 3))
    resumed = train(load_train_config(base, {"out_dir": str(tmp_path / "stopped")}), scenes=scenes)
    assert resumed.resumed_from == 2 and resumed.step == 4
    a = load_checkpoint(tmp_path / "full" / "checkpoints" / "final").model.state_dict()
    b = load_checkpoint(tmp_path / "stopped" / "checkpoints" / "final").model.state_dict()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def _token_end_gap(mt, sc, a: int, b: int) -> np.ndarray:
    """[S + 1] rounded-box distance of tracks a and b at the rollout's token ends (NaN where either is absent)."""
    from smart_marl.geometry import rounded_box_signed_distance

    sz = sc.tracks.size[:, sc.current_frame]
    p, q = mt.reached[a], mt.reached[b]
    gap = rounded_box_signed_distance(p[:, 0], p[:, 1], sz[a, 0], sz[a, 1], p[:, 2], q[:, 0], q[:, 1], sz[b, 0], sz[b, 1], q[:, 2])
    return np.where(mt.reached_valid[a] & mt.reached_valid[b], gap, np.nan)


def test_catk_that_keeps_gaps_brakes_behind_a_braking_leader(sample_scenes, sample_vocab, tiny_smart, road_vocab, one_torch_thread):
    """The follower's log drives on while its leader brakes at 8 m/s2: CAT-K over the whole vocabulary
    follows that log into the leader; keeping gaps, the follower stops behind it, and its targets are
    the tokens it took wherever the log's would have run into the leader."""
    from smart_marl.braking import brake_along_log, leader_follower_pairs

    sc0 = sample_scenes[2]
    leader, follower, _ = leader_follower_pairs(sc0)[0]
    sc = brake_along_log(sc0, leader, sc0.current_frame + 1, 8.0)
    model, road = tiny_smart(sample_vocab), scene_road(sc, road_vocab)
    every = max(v.size for v in sample_vocab.types.values())
    plain = catk_tokens(model, [sc], [road], sample_vocab, top_k=every)[0]
    kept = catk_tokens(model, [sc], [road], sample_vocab, top_k=every, avoid=True)[0]
    assert np.nanmin(_token_end_gap(plain, sc, follower, leader)) < -1.0  # the log runs into the stopped leader
    assert np.nanmin(_token_end_gap(kept, sc, follower, leader)) > -0.1
    kc = first_future_step(sc)
    relabelled = np.flatnonzero(kept.nearest_ids[follower, kc:] != plain.nearest_ids[follower, kc:]) + kc
    steps = kept.valid[follower, kc:]
    assert len(relabelled) >= 2
    relabelled = [k for k in relabelled if steps[k - kc]]
    np.testing.assert_array_equal(kept.nearest_ids[follower, relabelled], kept.ids[follower, relabelled])
    np.testing.assert_array_equal(kept.ids[:, :kc], plain.ids[:, :kc])  # the history is the log's either way


def test_keeping_gaps_and_braking_leaders_need_catk(sample_vocab):
    from smart_marl.train_config import TrainConfigError, load_train_config

    with pytest.raises(TrainConfigError, match="catk_avoid=true .* needs catk_top_k > 0"):
        load_train_config({"catk_avoid": True})
    with pytest.raises(TrainConfigError, match="brake_leaders=0.5 .* needs catk_avoid=true"):
        load_train_config({"catk_top_k": 8, "brake_leaders": 0.5})
    with pytest.raises(TrainConfigError, match="catk_max_drift_m=2.0 .* needs catk_top_k > 0"):
        load_train_config({"catk_max_drift_m": 2.0})
    with pytest.raises(TrainConfigError, match="brake_leaders"):
        load_train_config({"catk_top_k": 8, "catk_avoid": True, "brake_leaders": 1.5})
    assert load_train_config({"catk_top_k": 8, "catk_avoid": True, "brake_leaders": 0.5}).brake_leaders == 0.5


def test_a_closed_loop_batch_over_the_whole_vocabulary_is_the_teacher_forced_batch(sample_scenes, sample_vocab, tiny_smart,
                                                                                     road_vocab, one_torch_thread):
    """The training path of CAT-K (items -> closed_loop_batch) builds, with K = every token, the batch the
    teacher-forced path builds: whatever CAT-K changes in training comes from the top-K restriction alone."""
    from smart_marl.model.batch import collate_scenes
    from smart_marl.train_data import TokenizedScenes, closed_loop_batch

    model = tiny_smart(sample_vocab)
    args = dict(seed=0, noise_topk=0, road_mask_prob=0.15, road_keep_radius_m=30.0)
    keys = [(i, 7 + i) for i in range(len(sample_scenes))]
    forced = collate_scenes([TokenizedScenes(sample_scenes, sample_vocab, road_vocab, **args)[k] for k in keys])
    items = [TokenizedScenes(sample_scenes, sample_vocab, road_vocab, closed_loop=True, **args)[k] for k in keys]
    every = max(v.size for v in sample_vocab.types.values())
    closed = closed_loop_batch(model, items, sample_vocab, every, 0.15, 30.0, 0, torch.device("cpu"))
    for name, value in vars(forced).items():
        if isinstance(value, torch.Tensor):
            assert value.shape == getattr(closed, name).shape, name
            assert torch.allclose(value.float(), getattr(closed, name).float(), atol=1e-5), name
    assert forced.target_valid.sum() > 100
