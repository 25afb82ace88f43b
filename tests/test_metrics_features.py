"""smart_marl.metrics on synthetic scenes: features, estimators and the edge cases (short tracks,
no road edges, no traffic lights, NaN-padded ends, one evaluated agent, bad rollouts)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from smart_marl.geometry import RoadEdgeSegments
from smart_marl.metrics import RolloutError, Rollouts, compute_features, logged_scene, score_rollouts
from smart_marl.metrics.baselines import constant_velocity, log_replay, noisy_log_replay, random_rollouts
from smart_marl.metrics.features import kinematic_features, kinematic_validity
from smart_marl.metrics.likelihood import bernoulli_log_likelihood, histogram_bins, histogram_log_likelihood
from smart_marl.metrics.config import get_rules
from smart_marl.scenario import RoadMap, TrafficLights, Tracks
from smart_marl.synthetic import synthetic_scenario


@pytest.fixture(scope="module")
def scenario():
    return synthetic_scenario(0)


def _with_tracks(scenario, **changes):
    tr = scenario.tracks
    fields = {f.name: getattr(tr, f.name) for f in dataclasses.fields(tr)}
    fields.update(changes)
    return dataclasses.replace(scenario, tracks=Tracks(**fields))


def test_kinematics_of_a_circle_at_constant_speed():
    t = np.arange(91) * 0.1
    omega, radius = 0.3, 20.0
    x, y = radius * np.cos(omega * t), radius * np.sin(omega * t)
    heading = omega * t + np.pi / 2
    speed, accel, dh, d2h = kinematic_features(x, y, np.zeros_like(x), heading)
    chord = 2 * radius * np.sin(omega * 0.1) / 0.2  # central difference of a circle
    np.testing.assert_allclose(speed[1:-1], chord, rtol=1e-12)
    np.testing.assert_allclose(dh[1:-1], omega, rtol=1e-12)
    np.testing.assert_allclose(accel[2:-2], 0.0, atol=1e-9)
    np.testing.assert_allclose(d2h[2:-2], 0.0, atol=1e-9)
    # NaN-padded ends: one step for speeds, two for accelerations
    assert np.isnan(speed[[0, -1]]).all() and np.isnan(accel[[0, 1, -2, -1]]).all()
    assert np.isnan(dh[[0, -1]]).all() and np.isnan(d2h[[0, 1, -2, -1]]).all()


def test_angular_speed_wraps_across_pi():
    heading = np.array([np.pi - 0.05, np.pi - 0.01, -np.pi + 0.03])
    _, _, dh, _ = kinematic_features(np.zeros(3), np.zeros(3), np.zeros(3), heading)
    assert dh[1] == pytest.approx(0.08 / 2 / 0.1)  # the raw difference is 0.08 - 2 pi


def test_kinematic_validity_needs_both_neighbours():
    valid = np.array([True, True, True, False, True, True, True, True])
    speed_valid, accel_valid = kinematic_validity(valid)
    assert speed_valid.tolist() == [False, True, False, True, False, True, True, False]
    assert accel_valid.tolist() == [False, False, True, False, True, False, False, False]


def test_histogram_bins_clip_close_the_last_bin_and_send_nan_to_it():
    edges = get_rules("2024").features["linear_speed"].edges()
    bins = histogram_bins(np.array([-3.0, 0.0, 2.4999, 2.5, 24.9, 25.0, 99.0, np.nan]), edges)
    assert bins.tolist() == [0, 0, 0, 1, 9, 9, 9, 9]


def test_histogram_likelihood_is_the_smoothed_frequency_of_the_logged_bin():
    edges = np.array([0.0, 1.0, 2.0], np.float32)
    sim = np.array([[[0.5, 0.5, 1.5]], [[0.5, 1.5, 1.5]]])  # 2 rollouts, 1 agent, 3 steps: 3 x bin0, 3 x bin1
    ll = histogram_log_likelihood(np.array([[0.2, 1.2, 0.2]]), sim, edges, 0.1)
    np.testing.assert_allclose(np.exp(ll), [[3.1 / 6.2] * 3])
    ll = bernoulli_log_likelihood(np.array([True, False]), np.array([[True, False], [False, False]]), 0.001)
    np.testing.assert_allclose(np.exp(ll), [1.001 / 2.002, 2.001 / 2.002])


def test_log_replay_scores_better_than_random_rollouts_and_recovers_the_log(scenario):
    scene = logged_scene(scenario)
    replay = score_rollouts(scene, log_replay(scenario, 4), "2025")
    rand = score_rollouts(scene, random_rollouts(scenario, 4, seed=0), "2025")
    assert replay.min_ade == pytest.approx(0.0, abs=1e-4)  # float32 source rounding only
    assert replay.meta_metric > rand.meta_metric
    assert rand.min_ade > 1.0
    assert 0.0 < rand.meta_metric < 1.0


def test_rollouts_are_vectorised_per_rollout(scenario):
    """Each rollout's features do not depend on the other rollouts in the batch."""
    scene = logged_scene(scenario)
    from smart_marl.metrics import align_rollouts, metric_frame_rollouts

    ro = metric_frame_rollouts(scene, align_rollouts(scene, random_rollouts(scenario, 4, seed=3)))
    batch = compute_features(scene, ro)
    one = compute_features(scene, Rollouts(ro.object_ids, ro.x[2:3], ro.y[2:3], ro.z[2:3], ro.heading[2:3]))
    for name in ("linear_speed", "distance_to_nearest_object", "time_to_collision", "distance_to_road_edge"):
        np.testing.assert_array_equal(getattr(batch, name)[2], getattr(one, name)[0])


def test_agent_valid_on_fewer_than_three_frames_is_left_out_of_kinematic_scores(scenario):
    predicted = int(scenario.predict_indices[0])
    valid = scenario.tracks.valid.copy()
    valid[predicted] = False
    valid[predicted, 10:12] = True  # valid on 2 frames only: no speed can be measured
    short = _with_tracks(scenario, valid=valid)
    scene = logged_scene(short)
    log = compute_features(scene, None)
    k = int(np.flatnonzero(scene.object_ids == scenario.tracks.ids[predicted])[0])
    e = int(np.flatnonzero(scene.evaluated == k)[0])
    speed_valid, accel_valid = kinematic_validity(log.valid[0])
    assert not speed_valid[e].any() and not accel_valid[e].any()
    m = score_rollouts(scene, constant_velocity(short, 4), "2025")
    assert all(np.isfinite(v) for v in m.likelihoods.values())


def test_scene_without_road_edges_or_traffic_lights_scores_those_features_as_matching(scenario):
    bare = dataclasses.replace(scenario, road_map=RoadMap.empty(), traffic_lights=TrafficLights.empty(scenario.num_frames))
    scene = logged_scene(bare)
    assert scene.road_edges.num_segments == 0 and scene.lanes is None and scene.signals is None
    m = score_rollouts(scene, random_rollouts(bare, 8, seed=1), "2025")
    r, bins = 8, 10
    assert m.likelihoods["distance_to_road_edge"] == pytest.approx((r * 80 + 0.1) / (r * 80 + 0.1 * bins), rel=1e-6)
    assert m.likelihoods["offroad_indication"] == pytest.approx((r + 0.001) / (r + 0.002), rel=1e-6)
    assert m.likelihoods["traffic_light_violation"] == pytest.approx((r + 0.001) / (r + 0.002), rel=1e-6)
    # the same when only the pure-array scene lacks them
    scene2 = dataclasses.replace(logged_scene(scenario), road_edges=RoadEdgeSegments.from_polylines([]), signals=None)
    m2 = score_rollouts(scene2, random_rollouts(scenario, 8, seed=1), "2025")
    assert m2.likelihoods["offroad_indication"] == m.likelihoods["offroad_indication"]


def test_single_evaluated_agent(scenario):
    solo = dataclasses.replace(scenario, predict_indices=np.zeros(0, np.int64), predict_difficulty=np.zeros(0, np.int8))
    scene = logged_scene(solo)
    assert scene.evaluated_ids.tolist() == [solo.sdc_id]
    m = score_rollouts(scene, noisy_log_replay(solo, 4, seed=0), "2024")
    assert m.num_evaluated == 1
    assert all(np.isfinite(v) for v in m.likelihoods.values())


def test_wrong_rollouts_raise_errors_naming_scenario_and_object(scenario):
    scene = logged_scene(scenario)
    ro = constant_velocity(scenario, 2)
    with pytest.raises(RolloutError, match="80 steps"):
        score_rollouts(scene, Rollouts(ro.object_ids, ro.x[..., :79], ro.y[..., :79], ro.z[..., :79], ro.heading[..., :79]))
    missing = int(ro.object_ids[-1])
    with pytest.raises(RolloutError, match=rf"{scenario.scenario_id}.*agent {missing} is missing"):
        score_rollouts(scene, Rollouts(ro.object_ids[:-1], ro.x[:, :-1], ro.y[:, :-1], ro.z[:, :-1], ro.heading[:, :-1]))
    extra_ids = np.concatenate([ro.object_ids, [987654]])
    cat = lambda v: np.concatenate([v, v[:, :1]], axis=1)
    with pytest.raises(RolloutError, match="object 987654 is not a simulated agent"):
        score_rollouts(scene, Rollouts(extra_ids, cat(ro.x), cat(ro.y), cat(ro.z), cat(ro.heading)), where="f.binproto")


def test_lane_matching_with_pruning_equals_brute_force_official_distance():
    from smart_marl.metrics import features as F
    from smart_marl.metrics.inputs import lane_map

    rng = np.random.default_rng(0)
    pts = [np.cumsum(rng.normal(0, 1, (int(rng.integers(2, 40)), 2)), 0) + rng.uniform(-50, 50, 2) for _ in range(60)]
    lanes = lane_map(pts, list(range(60)), np.array([-3000.0, 500.0]))  # far padding point, as in WOMD
    q = rng.uniform(-60, 60, (3000, 2))
    start, end = lanes.points[:, :-1].reshape(-1, 2), lanes.points[:, 1:].reshape(-1, 2)
    d = F._quirky_lane_distance(q[:, None], start[None], end[None])
    d = np.where(lanes.point_valid[:, :-1].reshape(-1)[None], d, 1e10)
    np.testing.assert_array_equal(F._nearest_lane(q, lanes), np.argmin(d, 1) // (lanes.points.shape[1] - 1))


def test_nearest_object_distance_with_pruning_equals_all_pairs():
    from smart_marl.metrics.features import distance_to_nearest_object

    rng = np.random.default_rng(5)
    b, a, t = 3, 40, 6
    xy = rng.uniform(-30, 30, (b, a, t, 2)) + 5000.0  # source-frame magnitudes
    length, width = rng.uniform(0.5, 6, (b, a, t)), rng.uniform(0.5, 2.5, (b, a, t))
    heading = rng.uniform(-np.pi, np.pi, (b, a, t))
    valid = rng.random((b, a, t)) > 0.2
    evaluated = np.array([0, 7, 13])
    pruned = distance_to_nearest_object(xy, length, width, heading, valid, evaluated, candidates=3)
    full = distance_to_nearest_object(xy, length, width, heading, valid, evaluated, candidates=a)
    np.testing.assert_array_equal(pruned, full)
    assert (full[~valid[:, evaluated]] == 1e10).all()
