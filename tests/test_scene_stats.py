"""Scene statistics (smart_marl.sources.scene_stats) on hand-made scenes whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest

from smart_marl.scenario import AgentType, LaneType, MapFeatureType, RoadMap, Scenario, TrafficLights, Tracks
from smart_marl.sources.scene_stats import (
    STATISTICS, StatisticsAccumulator, central_difference, count_lane_changes, lane_curvatures_per_m, lane_widths_m,
    leader_gaps, match_lanes, scene_samples, speed_from_positions_mps, yaw_rate_radps,
)

T = 91
t_s = np.arange(T) * 0.1


def make_scene(xy: np.ndarray, heading: np.ndarray | None = None, types=None, lengths=None, valid=None,
               lanes: list[np.ndarray] = (), sdc_index: int = 0) -> Scenario:
    """Tracks from positions [N, T, 2] (velocities from the same motion, though the statistics use
    positions), lanes from centre lines [n, 2]."""
    xy = np.asarray(xy, np.float64)
    n = xy.shape[0]
    if heading is None:
        d = np.gradient(xy, axis=1)
        heading = np.arctan2(d[..., 1], d[..., 0])
    pos = np.concatenate([xy, np.zeros((n, T, 1))], axis=-1)
    lengths = np.full(n, 4.0) if lengths is None else np.asarray(lengths, np.float64)
    size = np.broadcast_to(np.stack([lengths, np.full(n, 2.0), np.full(n, 1.5)], -1)[:, None], (n, T, 3))
    features = [dict(id=k + 1, type=MapFeatureType.LANE, subtype=LaneType.SURFACE_STREET, speed_limit_mph=30.0,
                     points=np.concatenate([np.asarray(p, np.float64), np.zeros((len(p), 1))], axis=1))
                for k, p in enumerate(lanes)]
    return Scenario(
        scenario_id="hand-made", source="test", timestamps_s=t_s, current_frame=10,
        tracks=Tracks(ids=np.arange(n) + 1, types=np.zeros(n, np.int8) if types is None else np.asarray(types, np.int8),
                      position=pos, heading=heading, velocity=np.gradient(xy, axis=1) / 0.1, size=size,
                      valid=np.ones((n, T), bool) if valid is None else valid),
        road_map=RoadMap.from_features(features), traffic_lights=TrafficLights.empty(T), sdc_index=sdc_index)


def straight(x0: float, y0: float, speed_mps: float) -> np.ndarray:
    return np.stack([x0 + speed_mps * t_s, np.full(T, y0)], axis=-1)


def test_constant_speed_vehicle_has_its_speed_no_acceleration_and_never_stops():
    s = make_scene([straight(0, 0, 10.0)])
    out = scene_samples(s)
    assert np.allclose(out["vehicle_speed_mps"], 10.0)
    assert np.allclose(out["vehicle_accel_mps2"], 0.0, atol=1e-9)
    assert np.allclose(out["vehicle_abs_jerk_mps3"], 0.0, atol=1e-9)
    assert not out["vehicle_stopped_time_share"].any()
    assert np.allclose(out["fast_vehicle_speed_ratio_4s"], 1.0) and np.allclose(out["fast_vehicle_speed_ratio_8s"], 1.0)
    assert not out["fast_vehicle_slows_20pct_8s_share"].any() and not out["fast_vehicle_stops_within_8s_share"].any()
    assert not out["fast_vehicle_speeds_up_20pct_8s_share"].any()
    assert np.allclose(out["sdc_speed_mps"], 10.0)
    assert np.allclose(out["vehicle_abs_yaw_rate_radps"], 0.0)


def test_uniform_braking_gives_its_deceleration_and_a_stop():
    """10 m/s braking at 2 m/s^2 from the current frame (1 s) to a stop at 6 s, then standing."""
    tb = np.clip(t_s - 1.0, 0.0, 5.0)
    x = np.where(t_s < 1.0, 10.0 * t_s, 10.0 + 10.0 * tb - tb ** 2)
    s = make_scene([np.stack([x, np.zeros(T)], -1)], heading=np.zeros((1, T)))
    out = scene_samples(s)
    speed = speed_from_positions_mps(s.tracks.position[..., :2], s.tracks.valid)
    accel, ok = central_difference(speed, s.tracks.valid)
    steady = ok[0] & (t_s > 1.5) & (t_s < 5.5)  # away from the kinks, where smoothing blurs them
    assert np.allclose(accel[0, steady], -2.0, atol=1e-6)
    assert np.allclose(out["fast_vehicle_speed_ratio_8s"], 0.0, atol=1e-9)
    assert out["fast_vehicle_stops_within_8s_share"].tolist() == [True]
    assert out["fast_vehicle_slows_50pct_8s_share"].tolist() == [True]
    # below 0.5 m/s from 5.75 s on (10 - 2 (t - 1) < 0.5): 33 of the 91 frames, give or take the smoothing
    assert abs(out["vehicle_stopped_time_share"].sum() - 33) <= 2
    assert out["vehicle_moving_then_stops_share"].tolist() == [True]


def test_a_vehicle_pulling_away_speeds_up_and_does_not_slow():
    """6 m/s at the current frame (1 s), then 0.5 m/s^2 to 10 m/s at 9 s."""
    ta = np.clip(t_s - 1.0, 0.0, None)
    x = np.where(t_s < 1.0, 6.0 * t_s, 6.0 + 6.0 * ta + 0.25 * ta ** 2)
    out = scene_samples(make_scene([np.stack([x, np.zeros(T)], -1)], heading=np.zeros((1, T))))
    assert out["fast_vehicle_speeds_up_20pct_8s_share"].tolist() == [True]
    assert out["fast_vehicle_slows_20pct_8s_share"].tolist() == [False]
    assert abs(float(out["fast_vehicle_speed_ratio_8s"][0]) - 10.0 / 6.0) < 0.02


def test_a_parked_vehicle_is_stopped_and_parked():
    s = make_scene([straight(0, 0, 10.0), straight(50, 5, 0.0)], heading=np.zeros((2, T)))
    out = scene_samples(s)
    assert out["vehicle_parked_share"].tolist() == [False, True]
    assert out["vehicle_stopped_time_share"].mean() == pytest.approx(0.5)
    assert not out["vehicle_stopped_time_share_of_movers"].any()
    assert out["vehicles_within_50m_of_sdc"].tolist() == [1] and out["moving_vehicles_within_50m_of_sdc"].tolist() == [0]


def test_leader_gap_and_time_headway():
    """A 4 m car 20 m (centres) behind a 5 m car at 10 m/s: a 15.5 m gap, 1.55 s headway; a car in the
    next lane (3.5 m to the side) and one behind are nobody's leader."""
    s = make_scene([straight(0, 0, 10.0), straight(20, 0, 10.0), straight(10, 3.5, 10.0), straight(-30, 0, 10.0)],
                   lengths=[4.0, 5.0, 4.0, 4.0])
    xy, h = s.tracks.position[:, 10, :2], s.tracks.heading[:, 10]
    gap = leader_gaps(xy, h, np.array([4.0, 5.0, 4.0, 4.0]), np.ones(4, bool))
    assert gap[0] == pytest.approx(15.5) and np.isinf(gap[1]) and np.isinf(gap[2])
    assert gap[3] == pytest.approx(30.0 - 4.0)  # behind the first car
    out = scene_samples(s)
    assert np.allclose(np.sort(np.unique(np.round(out["time_headway_s"], 6))), [1.55, 2.6])
    assert out["has_leader_share"].mean() == pytest.approx(0.5)


def test_an_oncoming_car_is_not_a_leader():
    gap = leader_gaps(np.array([[0.0, 0.0], [20.0, 0.0]]), np.array([0.0, np.pi]), np.array([4.0, 4.0]), np.ones(2, bool))
    assert np.isinf(gap).all()


def _two_lanes():
    x = np.linspace(-50, 200, 251)
    return [np.stack([x, np.zeros_like(x)], -1), np.stack([x, np.full_like(x, 3.5)], -1)]


def test_a_lane_change_between_parallel_lanes_is_counted_once():
    lanes = _two_lanes()
    xy = straight(0, 0, 10.0)
    s_frac = np.clip((t_s - 3.0) / 3.0, 0, 1)  # from y=0 to y=3.5 between 3 s and 6 s
    xy[:, 1] = 3.5 * (3 * s_frac ** 2 - 2 * s_frac ** 3)
    h = np.arctan2(np.gradient(xy[:, 1]), np.gradient(xy[:, 0]))
    matched = match_lanes(xy, h, lanes)
    assert matched[0] == 0 and matched[-1] == 1
    assert count_lane_changes(matched, xy, lanes) == 1
    out = scene_samples(make_scene([xy], lanes=lanes))
    (count, minutes), = out["lane_changes_per_vehicle_minute"]
    assert count == 1 and minutes == pytest.approx(9.1 / 60)


def test_a_lane_change_across_lanes_cut_into_pieces_is_counted_once():
    """WOMD cuts lanes into short pieces: the same lane change where both lanes change piece."""
    lanes = []
    for y in (0.0, 3.5):
        for x0 in range(-50, 200, 25):
            x = np.linspace(x0, x0 + 25, 26)
            lanes.append(np.stack([x, np.full_like(x, y)], -1))
    xy = straight(0, 0, 10.0)
    s_frac = np.clip((t_s - 3.0) / 3.0, 0, 1)
    xy[:, 1] = 3.5 * (3 * s_frac ** 2 - 2 * s_frac ** 3)  # crosses y = 1.75 at 4.5 s, x = 45, mid-piece
    h = np.arctan2(np.gradient(xy[:, 1]), np.gradient(xy[:, 0]))
    matched = match_lanes(xy, h, lanes)
    assert len(set(matched.tolist())) > 4  # many pieces driven
    assert count_lane_changes(matched, xy, lanes) == 1
    shifted = xy + np.array([5.0, 0.0])  # the switch (x = 50) now falls on a piece boundary of both lanes
    assert count_lane_changes(match_lanes(shifted, h, lanes), shifted, lanes) == 1


def test_keeping_the_lane_or_following_a_successor_is_no_lane_change():
    a = np.stack([np.linspace(-50, 40, 91), np.zeros(91)], -1)
    b = np.stack([np.linspace(40, 200, 161), np.zeros(161)], -1)  # a's successor
    lanes = [a, b, *_two_lanes()[1:]]
    xy = straight(0, 0, 10.0)
    matched = match_lanes(xy, np.zeros(T), lanes)
    assert set(matched.tolist()) == {0, 1}
    assert count_lane_changes(matched, xy, lanes) == 0
    # the same vehicle swerving briefly (0.5 s) across the line counts nothing either
    wobble = matched.copy()
    wobble[40:45] = 2
    assert count_lane_changes(wobble, xy, lanes) == 0


def test_lane_width_of_parallel_lanes():
    lanes = _two_lanes()
    widths = lane_widths_m(lanes)
    assert len(widths) > 200 and np.allclose(widths, 3.5)
    # opposite directions are not a lane beside
    assert len(lane_widths_m([lanes[0], lanes[1][::-1]])) == 0


def test_curvature_of_a_circular_lane():
    a = np.linspace(0, np.pi, 400)
    circle = 25.0 * np.stack([np.cos(a), np.sin(a)], -1)
    k = lane_curvatures_per_m(circle)
    assert np.allclose(k, 1 / 25.0, rtol=0.02)
    assert np.allclose(lane_curvatures_per_m(_two_lanes()[0]), 0.0)


def test_yaw_rate_on_a_circle():
    """10 m/s around a 50 m circle: 0.2 rad/s."""
    a = 0.2 * t_s
    xy = 50.0 * np.stack([np.cos(a), np.sin(a)], -1)
    heading = a + np.pi / 2
    yaw, ok = yaw_rate_radps(heading[None], np.ones((1, T), bool))
    assert np.allclose(yaw[ok], 0.2)
    out = scene_samples(make_scene([xy], heading=heading[None]))
    assert np.allclose(out["vehicle_abs_yaw_rate_radps"], 0.2) and out["vehicle_turning_share"].all()
    assert np.allclose(out["vehicle_speed_mps"], 10.0, rtol=1e-3)


def test_pedestrians_cyclists_and_density_per_type():
    xy = [straight(0, 0, 10.0), straight(10, 8, 1.2), straight(-20, -6, 4.0), straight(200, 0, 10.0)]
    s = make_scene(xy, types=[AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST, AgentType.VEHICLE])
    out = scene_samples(s)
    assert np.allclose(out["pedestrian_speed_mps"], 1.2) and np.allclose(out["cyclist_speed_mps"], 4.0)
    assert out["vehicles_per_scene"].tolist() == [2] and out["pedestrians_per_scene"].tolist() == [1]
    assert out["vehicles_within_50m_of_sdc"].tolist() == [0]  # the other car is 200 m away
    assert out["pedestrians_within_50m_of_sdc"].tolist() == [1] and out["cyclists_within_50m_of_sdc"].tolist() == [1]


def test_invalid_frames_are_left_out_and_no_sdc_means_no_density():
    valid = np.ones((1, T), bool)
    valid[0, 40:50] = False
    xy = straight(0, 0, 10.0)
    xy[40:50] = 1e4  # garbage where invalid
    out = scene_samples(make_scene([xy], valid=valid, sdc_index=-1))
    assert np.allclose(out["vehicle_speed_mps"], 10.0)
    assert len(out["vehicle_speed_mps"]) == T - 10
    assert "vehicles_within_50m_of_sdc" not in out and "sdc_speed_mps" not in out


def test_summary_reduces_each_kind():
    acc = StatisticsAccumulator()
    acc.add(make_scene([straight(0, 0, 10.0), straight(20, 0, 10.0)], lanes=_two_lanes()))
    summary = acc.summary()
    assert set(summary) <= set(STATISTICS)
    assert summary["vehicle_speed_mps"]["p50"] == pytest.approx(10.0) and summary["vehicle_speed_mps"]["n"] == 2 * T
    assert summary["vehicle_stopped_time_share"]["share"] == 0.0
    assert summary["lane_changes_per_vehicle_minute"]["rate"] == 0.0
    assert summary["lane_changes_per_vehicle_minute"]["exposure"] == pytest.approx(2 * 9.1 / 60)


def test_bootstrap_interval_brackets_the_share_and_collapses_when_scenes_agree():
    acc = StatisticsAccumulator()
    for speed in (10.0, 10.0, 10.0):
        acc.add(make_scene([straight(0, 0, speed)]))
    share = acc.summary(bootstrap=200)["vehicle_stopped_time_share"]
    assert share["share"] == share["lo"] == share["hi"] == 0.0
    acc.add(make_scene([straight(0, 0, 0.0)], heading=np.zeros((1, T))))  # a fourth scene, all stopped
    share = acc.summary(bootstrap=500)["vehicle_stopped_time_share"]
    assert share["share"] == pytest.approx(0.25) and share["lo"] <= 0.25 <= share["hi"] and share["hi"] - share["lo"] > 0.2
