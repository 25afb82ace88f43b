"""The reactivity benchmark's helpers (benchmarks/reactivity.py, issue 33): which leader / follower pairs it
brakes, the scripted cut-in, how a follower's answer is measured, and which crossings of a stop line count as
running a red light (the 2025 rules' traffic-light violation)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from smart_marl.metrics.inputs import logged_scene, simulated_agent_indices
from smart_marl.scenario import AgentType

from helpers import load_benchmark


@pytest.fixture(scope="module")
def reactivity():
    return load_benchmark("reactivity")


def test_leader_follower_pairs_find_the_lane_of_the_whatif_scene(reactivity, womd_scenes):
    """637f20cafde22ff8 (tests/test_whatif.py): 1630 follows 1609 27 m behind in its lane; every pair's follower is
    behind its leader, in its lane, within 30 m, nearest pairs first."""
    scene = womd_scenes[0]
    tr, cf = scene.tracks, scene.current_frame
    pairs = reactivity.leader_follower_pairs(scene)
    ids = [(int(tr.ids[a]), int(tr.ids[b])) for a, b, _ in pairs]
    assert (1609, 1630) in ids
    gap = dict(zip(ids, [g for _, _, g in pairs]))[(1609, 1630)]
    assert abs(gap - 27.0) < 1.0
    assert [g for _, _, g in pairs] == sorted(g for _, _, g in pairs)
    for lead, fol, g in pairs:
        h = tr.heading[lead, cf]
        d = tr.position[fol, cf, :2] - tr.position[lead, cf, :2]
        along, across = d[0] * math.cos(h) + d[1] * math.sin(h), -d[0] * math.sin(h) + d[1] * math.cos(h)
        assert -30.0 <= along < 0 and abs(across) < 1.75 and 0 < g <= 30.0
        assert tr.types[lead] == tr.types[fol] == int(AgentType.VEHICLE)
    assert len(reactivity.leader_follower_pairs(scene, max_pairs=2)) == 2


def test_cut_in_arrives_in_the_lane_the_given_gap_ahead_of_a_follower_at_constant_speed(reactivity):
    v = 12.0
    traj = reactivity.cut_in_trajectory(v, 80, gap_m=10.0, side=-1.0)
    dt = 0.1
    assert traj[0, 1] == pytest.approx(-3.5) and traj[0, 0] > 10.0  # beside the follower's lane, ahead
    k = int(round(2.0 / dt))  # in the lane after the 2 s manoeuvre
    assert abs(traj[k, 1]) < 1e-9 and abs(traj[-1, 1]) < 1e-9
    assert traj[k, 0] - v * k * dt == pytest.approx(10.0)
    speed = np.diff(traj[:, 0]) / dt
    np.testing.assert_allclose(speed, 0.8 * v)
    assert traj[5, 2] > 0  # heading into the follower's lane (toward +y from the right)
    assert traj[-1, 2] == pytest.approx(0.0)


def test_follower_response_measures_overlap_gap_and_deceleration(reactivity):
    """A follower 20 m behind a standing leader, at 10 m/s: stopping at 4 m/s2 (12.5 m) leaves a gap; not braking
    runs into it."""
    t = np.arange(1, 41) * 0.1
    lead = np.zeros((2, 40, 3))
    lead[..., 0] = 20.0
    stop = np.minimum(t, 2.5)
    fol = np.zeros((2, 40, 3))
    fol[0, :, 0] = 10.0 * stop - 2.0 * stop**2  # 4 m/s2 from the first frame
    fol[1, :, 0] = 10.0 * t  # keeps going
    size = np.array([4.5, 2.0])
    out = reactivity.follower_response(fol, lead, size, size, np.zeros(3), 0)
    assert out["hit"].tolist() == [False, True]
    assert out["min_gap_m"][0] == pytest.approx(20.0 - 12.5 - 4.5, abs=0.05)  # bumper to bumper at the stop
    assert out["min_gap_m"][1] < 0
    assert out["max_decel_mps2"][0] == pytest.approx(4.0, abs=0.05)
    assert out["max_decel_mps2"][1] == pytest.approx(0.0, abs=1e-6)
    # only what happens from the onset on counts: the second follower has driven through the leader by frame 25
    late = reactivity.follower_response(fol, lead, size, size, np.zeros(3), 25)
    assert late["hit"].tolist() == [False, False]


def _through_stop_line(scene, lane_id: int, cross_at: int, stop_short_m: float | None = None) -> np.ndarray:
    """Rollout trajectories [1, A, 80, 2] (source frame): every track stands at its logged current position, the
    first simulated vehicle drives at 10 m/s along ``lane_id`` past its stop point between rollout frames
    ``cross_at - 1`` and ``cross_at`` (or stops ``stop_short_m`` before it)."""
    ls = logged_scene(scene)
    j = list(ls.signals.lane_ids).index(lane_id)
    li = int(np.flatnonzero(ls.lanes.ids == lane_id)[0])
    pts = ls.lanes.points[li][ls.lanes.point_valid[li]]
    stop = ls.signals.stop_points[j]
    seg = int(np.argmin(np.linalg.norm(pts[:-1] - stop, axis=1)))
    d = (pts[seg + 1] - pts[seg]) / np.linalg.norm(pts[seg + 1] - pts[seg])
    sim = simulated_agent_indices(scene)
    a = scene.num_tracks
    traj = np.zeros((1, a, 80, 2))
    traj[0, sim] = ls.position[:, 10, None, :2]
    vehicle = int(sim[np.flatnonzero(scene.tracks.types[sim] == int(AgentType.VEHICLE))[0]])
    s = (np.arange(80) - cross_at + 0.5) * 1.0  # metres past the stop point, 1 m a frame
    if stop_short_m is not None:
        s = np.minimum(s, -stop_short_m)
    traj[0, vehicle] = stop + s[:, None] * d
    return traj


def test_a_vehicle_driven_over_a_red_stop_line_counts_and_one_that_stops_short_or_crosses_unsignalled_does_not(reactivity,
                                                                                                          womd_scenes):
    """637f20cafde22ff8: lane 443's signal is STOP from the current frame on except at frame 50, where the scene logs
    no light state; none of its 45 vehicles crosses on red in the log."""
    scene = womd_scenes[0]
    ls = logged_scene(scene)
    j = list(ls.signals.lane_ids).index(443)
    assert ls.signals.states[30, j] == 4 and ls.signals.states[50, j] == 0
    assert reactivity.red_light_shares(scene, None) == (0, 45)
    # crossing between frames 29 and 30 (rollout frames 18 and 19, the window's 19 and 20): on red
    assert reactivity.red_light_shares(scene, _through_stop_line(scene, 443, 19)) == (1, 45)
    assert reactivity.red_light_shares(scene, _through_stop_line(scene, 443, 19, stop_short_m=2.0)) == (0, 45)
    # crossing between frames 49 and 50: no light state at frame 50, so no violation
    assert reactivity.red_light_shares(scene, _through_stop_line(scene, 443, 39)) == (0, 45)


def test_part_e_controls_the_vehicles_whose_logged_route_is_longer_than_10_m(reactivity, womd_scenes):
    scene = womd_scenes[0]
    tr, cf = scene.tracks, scene.current_frame
    mask = reactivity.moving_route_vehicles(scene)
    assert mask.any() and not mask.all()
    for i in np.flatnonzero(mask):
        last = np.flatnonzero(tr.valid[i])[-1]
        assert tr.types[i] == int(AgentType.VEHICLE) and tr.valid[i, cf]
        assert np.linalg.norm(tr.position[i, last, :2] - tr.position[i, cf, :2]) > 10.0


def test_background_collisions_leave_out_the_other_controlled_agents(reactivity):
    """Cars in a row on x (4 m x 2 m): 0 and 1 controlled, 2 background. 1 drives into 0, which stands (both
    controlled); 2 drives into 1 from behind and stops short of 0. Counted against the background, 1 is
    rear-ended by 2 and 0 has no collision."""
    f = 20
    poses = np.zeros((3, f, 3))
    poses[0, :, 0] = 20.0
    poses[1, :, 0] = np.minimum(np.linspace(10.0, 30.0, f), 17.0)  # stops overlapping 0
    poses[2, :, 0] = np.minimum(np.linspace(0.0, 40.0, f), 15.0)  # stops overlapping 1, 5 m short of 0
    present = np.ones((3, f), bool)
    box = np.array([[4.0, 2.0], [4.0, 2.0], [4.0, 2.0]])
    from agents.evaluate import first_collision_kinds

    assert first_collision_kinds(poses, present, box, [0, 1])[0] == "rear_ended"  # 1 ran into 0
    assert reactivity.background_collision_kinds(poses, present, box, [0, 1]) == [None, "rear_ended"]


# ------------------------------------------------------------------------------------ why a log slows
def _straight_road_scene(motions: list, stop_sign_x: float | None = None):
    """A scene on a straight lane along x: one vehicle per entry of ``motions`` ((x0, y, speed at each of
    the 91 frames)), a stop sign at ``stop_sign_x`` if given, no signals."""
    from smart_marl.scenario import (DT_S, LaneType, MapFeatureType, RoadMap, SceneFrame, Scenario, TrafficLights,
                                     Tracks)

    t = 91
    features = [dict(id=1, type=MapFeatureType.LANE, subtype=LaneType.SURFACE_STREET, speed_limit_mph=30.0,
                      points=np.stack([np.linspace(-100, 200, 31), np.zeros(31), np.zeros(31)], 1))]
    if stop_sign_x is not None:
        features.append(dict(id=2, type=MapFeatureType.STOP_SIGN, points=[[stop_sign_x, 2.0, 0.0]]))
    n = len(motions)
    pos, vel = np.zeros((n, t, 3)), np.zeros((n, t, 2))
    for i, (x0, y, speed) in enumerate(motions):
        pos[i, :, 0] = x0 + np.concatenate([[0.0], np.cumsum(speed[1:] * DT_S)])
        pos[i, :, 1] = y
        vel[i, :, 0] = speed
    return Scenario(scenario_id="straight", source="synthetic", timestamps_s=np.arange(t) * DT_S, current_frame=10,
                    tracks=Tracks(ids=np.arange(n) + 1, types=np.zeros(n, np.int8), position=pos, heading=np.zeros((n, t)),
                                  velocity=vel, size=np.tile([4.6, 1.9, 1.6], (n, t, 1)), valid=np.ones((n, t), bool)),
                    road_map=RoadMap.from_features(features),
                    traffic_lights=TrafficLights(lane_ids=np.zeros(0, np.int64), states=np.zeros((t, 0), np.int8),
                                                 present=np.zeros((t, 0), bool), stop_points=np.zeros((0, 3))),
                    sdc_index=0, predict_indices=[], frame=SceneFrame(0.0, 0.0, 0.0, 0.0))


def _braking(v0: float, until: float, start: int = 15, decel: float = 3.0) -> np.ndarray:
    """Speeds over 91 frames: ``v0``, from frame ``start`` down at ``decel`` m/s2 to ``until``."""
    v = v0 - decel * np.clip(np.arange(91) - start, 0, None) * 0.1
    return np.maximum(v, until)


def test_slowing_causes_split_a_stop_at_a_stop_sign_from_a_queue_behind_a_braking_car():
    sc = load_benchmark("slowing_causes")
    # a car that stops at a stop sign 60 m ahead; a car in the next lane that keeps its speed
    scene = _straight_road_scene([(0.0, 0.0, _braking(10.0, 0.0)), (0.0, 3.5, np.full(91, 10.0))], stop_sign_x=62.0)
    slowing = sc.slowing_vehicles(scene, np.ones(2, bool))
    assert [s[0] for s in slowing] == [0]
    assert sc.what_it_meets(scene, 0) == (["stop_sign"], None)
    # no sign: a car brakes for nothing anyone can see; the one 15 m behind it slows in its queue
    scene = _straight_road_scene([(15.0, 0.0, _braking(10.0, 2.0)), (0.0, 0.0, _braking(10.0, 2.0, start=20)),
                                  (0.0, 3.5, np.full(91, 10.0))])
    assert [s[0] for s in sc.slowing_vehicles(scene, np.ones(3, bool))] == [0, 1]
    assert sc.what_it_meets(scene, 0) == ([], None)
    assert sc.what_it_meets(scene, 1) == (["queue"], 0)
    # a light 50 m ahead that turns red after 2 s
    scene = _straight_road_scene([(0.0, 0.0, _braking(10.0, 0.0))])
    states = np.where(np.arange(91) >= 30, 4, 6)[:, None]  # STOP from frame 30, GO before
    lights = dataclasses.replace(scene.traffic_lights, lane_ids=np.array([1]), states=states, present=np.ones((91, 1), bool),
                                 stop_points=np.array([[60.0, 0.0, 0.0]]))
    assert sc.what_it_meets(dataclasses.replace(scene, traffic_lights=lights), 0) == (["red_light_later"], None)
    lights = dataclasses.replace(lights, states=np.full((91, 1), 4))
    assert sc.what_it_meets(dataclasses.replace(scene, traffic_lights=lights), 0) == (["red_light"], None)
    # the sign behind the car (passed before the current frame) is not met
    scene = _straight_road_scene([(0.0, 0.0, _braking(10.0, 0.0))], stop_sign_x=-5.0)
    assert sc.what_it_meets(scene, 0) == ([], None)
