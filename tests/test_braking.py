"""Scenes edited so that a leader brakes (smart_marl.braking): the stop follows the logged path at the
asked deceleration and stays; only the braking leaders change; draws are seeded."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from smart_marl.braking import brake_along_log, braking_leaders, leader_follower_pairs, with_braking_leaders
from smart_marl.scenario import DT_S


@pytest.fixture(scope="module")
def pair_scene(sample_scenes):
    sc = sample_scenes[2]  # four leader / follower pairs
    return sc, leader_follower_pairs(sc)


def _distance_to_path(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    a, b = path[:-1, None], path[1:, None]  # [S, 1, 2] segments
    ab = b - a
    t = np.clip(((points[None] - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
    return np.linalg.norm(a + t[..., None] * ab - points[None], axis=-1).min(0)


def test_a_braking_leader_slows_at_the_asked_rate_on_its_logged_path_and_stays(pair_scene):
    sc, pairs = pair_scene
    leader = pairs[0][0]
    onset, decel = sc.current_frame + 3, 6.0
    out = brake_along_log(sc, leader, onset, decel)
    tr, log = out.tracks, sc.tracks
    p = tr.position[leader, onset - 1 :, :2].astype(np.float64)
    speed = np.linalg.norm(np.diff(p, axis=0), axis=-1) / DT_S  # speeds over frames onset .. end
    v0 = np.linalg.norm(log.position[leader, onset - 1, :2] - log.position[leader, onset - 2, :2]) / DT_S
    moving = speed > 0.05
    assert moving.sum() >= 5 and not moving[moving.argmin():].any()  # slows down, stops, stays stopped
    stop_s = v0 / decel
    assert abs(moving.sum() * DT_S - stop_s) < 2 * DT_S
    mid = np.flatnonzero(moving)[1:-1]
    np.testing.assert_allclose(np.diff(speed)[mid[:-1]], -decel * DT_S, atol=0.05 * decel * DT_S + 1e-3)
    on_path = _distance_to_path(p, log.position[leader, onset - 1 :, :2].astype(np.float64))
    assert on_path.max() < 0.05
    np.testing.assert_array_equal(tr.position[leader, :onset], log.position[leader, :onset])  # before the onset: the log
    others = np.arange(sc.num_tracks) != leader
    np.testing.assert_array_equal(tr.position[others], log.position[others])
    np.testing.assert_array_equal(tr.valid, log.valid)
    assert not np.shares_memory(tr.position, log.position)  # the input scene is not modified


def test_brake_along_log_refuses_an_onset_outside_the_scene_or_a_track_with_a_gap(pair_scene):
    sc, pairs = pair_scene
    with pytest.raises(ValueError, match="onset frame"):
        brake_along_log(sc, pairs[0][0], sc.num_frames, 6.0)
    with pytest.raises(ValueError, match="decel_mps2"):
        brake_along_log(sc, pairs[0][0], sc.current_frame + 1, 0.0)
    valid = sc.tracks.valid.copy()
    valid[pairs[0][0], sc.current_frame + 20] = False  # a frame missing after the onset
    gappy = dataclasses.replace(sc, tracks=dataclasses.replace(sc.tracks, valid=valid))
    with pytest.raises(ValueError, match=r"track \d+ \(id \d+\) is not valid without a gap"):
        brake_along_log(gappy, pairs[0][0], sc.current_frame + 1, 6.0)
    assert brake_along_log(gappy, pairs[0][0], sc.current_frame + 22, 6.0).num_frames == sc.num_frames  # after it: fine


def test_braking_leaders_are_drawn_per_leader_and_seeded(pair_scene):
    sc, pairs = pair_scene
    leaders = sorted({p[0] for p in pairs})
    assert braking_leaders(sc, np.random.default_rng(0), 0.0) == []
    edits = braking_leaders(sc, np.random.default_rng(0), 1.0)
    assert sorted(e[0] for e in edits) == leaders
    assert all(sc.current_frame < frame <= sc.current_frame + 31 and 4.0 <= decel <= 9.0 for _, frame, decel in edits)
    every = with_braking_leaders(sc, edits)
    after = slice(sc.current_frame + 1, None)
    changed = [i for i in range(sc.num_tracks) if not np.array_equal(every.tracks.position[i, after], sc.tracks.position[i, after])]
    assert changed == leaders
    assert braking_leaders(sc, np.random.default_rng(0), 1.0) == edits
    assert braking_leaders(sc, np.random.default_rng(1), 1.0) != edits  # other decelerations and onsets
    half = [len(braking_leaders(sc, np.random.default_rng(s), 0.5)) for s in range(40)]
    assert 0 < np.mean(half) < len(leaders)


def test_dropped_tokens_are_no_targets_and_the_rest_are_kept(pair_scene, sample_vocab):
    """without_targets (a scripted leader from its onset, a drifted CAT-K token): token k of a track is the
    target at position k - 1, masked; nothing else moves."""
    from smart_marl.model.batch import scene_tensors
    from smart_marl.tokens import tokenize_motion
    from smart_marl.train_data import without_targets

    sc, pairs = pair_scene
    leader, follower = pairs[0][0], pairs[0][1]
    mt = tokenize_motion(sc, sample_vocab)
    arrays = scene_tensors(sc, sample_vocab, _empty_road(), road_mask_prob=0.0, rng=0, motion_tokens=mt)
    k = 4
    drop = np.zeros(mt.ids.shape, bool)
    drop[leader, k:] = True
    out = without_targets(arrays, mt, drop)
    rows = list(np.flatnonzero(mt.valid.any(1)))
    lr, fr = rows.index(leader), rows.index(follower)
    assert arrays["target_valid"][lr, k - 1] and not out["target_valid"][lr, k - 1:].any()
    np.testing.assert_array_equal(out["target_valid"][lr, : k - 1], arrays["target_valid"][lr, : k - 1])
    others = np.arange(len(rows)) != lr
    np.testing.assert_array_equal(out["target_valid"][others], arrays["target_valid"][others])  # the follower still learns
    assert without_targets(arrays, mt, np.zeros_like(drop)) is arrays


def test_drifted_flags_the_tokens_that_start_far_from_the_log(pair_scene, sample_vocab):
    from smart_marl.catk import drifted
    from smart_marl.tokens import tokenize_motion

    sc, pairs = pair_scene
    mt = tokenize_motion(sc, sample_vocab)
    assert not drifted(sc, mt, 2.0).any()  # the log's own rolling matching stays within centimetres
    leader, k = pairs[0][0], 6
    mt.start_pose[leader, k, 1] += 3.0  # a CAT-K rollout that went 3 m sideways by token k
    got = drifted(sc, mt, 2.0)
    assert got[leader, k] and got.sum() == 1
    assert not drifted(sc, mt, 3.5).any()


def _empty_road():
    from smart_marl.model.batch import RoadArrays

    return RoadArrays(local=np.zeros((0, 0, 2), np.float32), pose=np.zeros((0, 3), np.float32), type_id=np.zeros(0, np.int64),
                      light=np.zeros(0, np.int64), token=np.zeros(0, np.int64), pairs=np.zeros((0, 2), np.int64),
                      light_index=np.zeros(0, np.int64))


def test_behind_in_lane_holds_each_leaders_followers_and_grows_with_the_distance(pair_scene):
    sc, pairs = pair_scene
    from smart_marl.braking import FOLLOW_GAP_M, behind_in_lane

    leaders = sorted({p[0] for p in pairs})
    assert not behind_in_lane(sc, [], 60.0).any()
    near = behind_in_lane(sc, leaders, FOLLOW_GAP_M)
    assert all(near[f] for _, f, _ in pairs)  # every nearest follower is in the queue
    far = behind_in_lane(sc, leaders, 200.0)
    assert (far >= near).all()
    assert not behind_in_lane(sc, leaders, 0.5).any()  # nobody's centre half a metre behind
