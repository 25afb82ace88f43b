"""smart_marl.geometry: box corners, (rounded) box signed distance, road-edge signed distance and
time to collision, checked against independent computations (shapely, brute force, closed forms)."""

from __future__ import annotations

import numpy as np
import pytest

from smart_marl import geometry as g

shapely = pytest.importorskip("shapely")
from shapely.geometry import LineString, Point, Polygon  # noqa: E402


def test_box_corners_are_counter_clockwise_front_left_first():
    c = g.box_corners(1.0, 2.0, 4.0, 2.0, np.pi / 2)
    np.testing.assert_allclose(c, [[0.0, 4.0], [0.0, 0.0], [2.0, 0.0], [2.0, 4.0]], atol=1e-12)
    x, y = c[:, 0], c[:, 1]
    assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) == pytest.approx(8.0)  # positive area: CCW


def test_float32_corners_equal_float64_corners_to_float32_precision():
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-9000, 9000, 100), rng.uniform(-9000, 9000, 100)
    l, w, h = rng.uniform(1, 6, 100), rng.uniform(0.5, 3, 100), rng.uniform(-4, 4, 100)
    c32 = g.box_corners_float32(x.astype(np.float32), y.astype(np.float32), l, w, h)
    c64 = g.box_corners(x.astype(np.float32), y.astype(np.float32), l, w, h)
    assert np.abs(c32 - c64).max() < 2e-3
    assert np.all(c32 == c32.astype(np.float32))  # values are float32 numbers


def test_box_signed_distance_equals_shapely_distance_when_apart_and_is_negative_when_overlapping():
    rng = np.random.default_rng(1)
    n = 300
    a = [rng.uniform(-10, 10, n), rng.uniform(-10, 10, n), rng.uniform(1, 5, n), rng.uniform(0.5, 2.5, n), rng.uniform(-4, 4, n)]
    b = [rng.uniform(-10, 10, n), rng.uniform(-10, 10, n), rng.uniform(1, 5, n), rng.uniform(0.5, 2.5, n), rng.uniform(-4, 4, n)]
    ca, cb = g.box_corners(*a), g.box_corners(*b)
    sd = g.box_signed_distance(ca, cb)
    for i in range(n):
        pa, pb = Polygon(ca[i]), Polygon(cb[i])
        if pa.intersects(pb):
            assert sd[i] <= 1e-9
        else:
            assert sd[i] == pytest.approx(pa.distance(pb), abs=1e-9)


def test_box_signed_distance_is_minus_the_penetration_depth_for_aligned_boxes():
    ca = g.box_corners(0.0, 0.0, 4.0, 2.0, 0.0)
    cb = g.box_corners(3.0, 0.5, 4.0, 2.0, 0.0)  # overlaps 1 m along x, 1.5 m along y
    assert g.box_signed_distance(ca, cb) == pytest.approx(-1.0)


def test_rounded_box_distance_between_boxes_side_by_side_is_the_gap():
    # straight sides are unchanged by corner rounding: the gap between parallel sides stays exact
    d = g.rounded_box_signed_distance(0.0, 0.0, 4.0, 2.0, 0.0, 0.0, 5.0, 4.0, 2.0, 0.0)
    assert d == pytest.approx(3.0)
    # corner to corner the rounded boxes are further apart than the sharp ones
    sharp = g.box_signed_distance(g.box_corners(0, 0, 4, 2, 0), g.box_corners(6, 4, 4, 2, 0))
    rounded = g.rounded_box_signed_distance(0, 0, 4, 2, 0, 6, 4, 4, 2, 0)
    s = 2 * 0.7 / 2  # shrink of a 2 m wide box
    expected = np.hypot(6 - 2 * (2 - s), 4 - 2 * (1 - s)) - 2 * s  # distance between the rounded corners
    assert sharp == pytest.approx(np.hypot(2, 2))
    assert rounded == pytest.approx(expected)
    assert bool(g.boxes_overlap(0, 0, 4, 2, 0, 3.5, 0, 4, 2, 0)) and not bool(g.boxes_overlap(0, 0, 4, 2, 0, 4.5, 0, 4, 2, 0))


def test_road_edge_signed_distance_of_a_closed_counter_clockwise_square_matches_shapely():
    square = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [0, 0, 0]], float)
    seg = g.RoadEdgeSegments.from_polylines([square])
    rng = np.random.default_rng(2)
    pts = np.concatenate([rng.uniform(-5, 15, (400, 2)), np.zeros((400, 1))], axis=1)
    sd = g.signed_distance_to_road_edges(pts, seg)
    ring = LineString(square[:, :2])
    poly = Polygon(square[:-1, :2])
    for p, d in zip(pts, sd):
        expected = ring.distance(Point(p[:2]))
        assert abs(d) == pytest.approx(expected, abs=1e-9)
        if expected > 1e-6:
            assert (d < 0) == poly.contains(Point(p[:2]))  # inside the counter-clockwise edge = on road


def test_nearest_segment_search_with_pruning_equals_brute_force():
    rng = np.random.default_rng(3)
    polylines = [np.cumsum(rng.normal(0, 1.0, (60, 3)) * [1, 1, 0.05], axis=0) + rng.uniform(-40, 40, 3) for _ in range(12)]
    seg = g.RoadEdgeSegments.from_polylines(polylines)
    q = np.concatenate([rng.uniform(-60, 60, (3000, 2)), rng.uniform(-2, 2, (3000, 1))], axis=1)
    fast = g.nearest_segment_indices(q, seg.start, seg.end, 3.0)
    d3, _, _, _ = g._segment_terms(q[:, None, :], seg.start[None], seg.end[None], 3.0)
    np.testing.assert_array_equal(fast, np.argmin(d3, axis=1))


def test_z_stretch_prefers_the_edge_at_the_same_level():
    low = np.array([[0, 0, 0], [10, 0, 0]], float)  # 1 m away, 0 m below
    high = np.array([[10, 0.5, 6], [0, 0.5, 6]], float)  # 0.5 m away in 2D but 6 m above
    seg = g.RoadEdgeSegments.from_polylines([low, high])
    d = g.signed_distance_to_road_edges(np.array([[5.0, 1.0, 0.0]]), seg)
    assert d[0] == pytest.approx(-1.0)  # left of the low edge: on road, 1 m


def test_time_to_collision_with_a_slower_leader_and_the_caps():
    # ego 4 m long at x=0 doing 10 m/s; leader 4 m long at x=20 doing 5 m/s: gap 16 m, closing 5 m/s
    args = dict(ego_x=[0.0], ego_y=[0.0], ego_length=[4.0], ego_width=[2.0], ego_heading=[0.0])
    other = dict(other_x=[0.0, 20.0], other_y=[0.0, 0.0], other_length=[4.0, 4.0], other_width=[2.0, 2.0],
                 other_heading=[0.0, 0.0], other_valid=[True, True])
    ttc = g.time_to_collision(**args, ego_speed=[10.0], other_speed=[10.0, 5.0], **other)
    assert ttc[0] == pytest.approx(16.0 / 5.0)
    ttc = g.time_to_collision(**args, ego_speed=[6.0], other_speed=[10.0, 5.0], **other)
    assert ttc[0] == 5.0  # 16 / 1 = 16 s, capped at 5 s
    ttc = g.time_to_collision(**args, ego_speed=[15.0], other_speed=[10.0, 5.0], **other)
    assert ttc[0] == pytest.approx(16.0 / 10.0)
    assert g.time_to_collision(**args, ego_speed=[4.0], other_speed=[10.0, 5.0], **other)[0] == 5.0  # opening gap
    assert g.time_to_collision(**args, ego_speed=[np.nan], other_speed=[10.0, 5.0], **other)[0] == 5.0
    other["other_heading"] = [0.0, np.radians(80)]  # not aligned: not followed
    assert g.time_to_collision(**args, ego_speed=[15.0], other_speed=[10.0, 5.0], **other)[0] == 5.0


def test_box_is_offroad_when_one_corner_crosses_the_edge():
    edge = g.RoadEdgeSegments.from_polylines([np.array([[-50.0, 0.0, 0.0], [50.0, 0.0, 0.0]])])  # road: y > 0
    # a 4 x 2 box at y = 1.5 heading along x: nearest corner 0.5 m inside the road
    assert g.box_distance_to_road_edge(0.0, 1.5, 0.75, 4.0, 2.0, 1.5, 0.0, edge) == pytest.approx(-0.5, abs=1e-6)
    assert not g.is_offroad(0.0, 1.5, 0.75, 4.0, 2.0, 1.5, 0.0, edge)
    # turned 90 degrees the box reaches 0.5 m past the edge
    assert g.box_distance_to_road_edge(0.0, 1.5, 0.75, 4.0, 2.0, 1.5, np.pi / 2, edge) == pytest.approx(0.5, abs=1e-6)
    assert g.is_offroad(0.0, 1.5, 0.75, 4.0, 2.0, 1.5, np.pi / 2, edge)


def test_overlapping_pairs_name_who_overlaps_whom_on_which_frame_and_colliding_agrees():
    # three 4 x 2 m cars on the x axis over 3 frames: 0 and 1 touch on frame 2 only, 2 stays far away;
    # a second scene (leading axis) where nobody overlaps
    poses = np.zeros((2, 3, 3, 3))
    poses[:, 0, :, 0] = [0.0, 0.0, 0.0]
    poses[0, 1, :, 0] = [10.0, 6.0, 3.0]
    poses[1, 1, :, 0] = [10.0, 9.0, 8.0]
    poses[:, 2, :, 0] = 50.0
    present = np.ones((2, 3, 3), bool)
    length, width = np.full(3, 4.0), np.full(3, 2.0)
    s, q, a, f = g.overlapping_pairs(poses, present, length, width)
    assert sorted(zip(s.tolist(), q.tolist(), a.tolist(), f.tolist())) == [(0, 0, 1, 2), (0, 1, 0, 2)]
    np.testing.assert_array_equal(g.colliding(poses, present, length, width), [[True, True, False], [False, False, False]])
    present[0, 1, 2] = False  # absent on the frame of the touch: no pair
    assert len(g.overlapping_pairs(poses, present, length, width)[0]) == 0
    q, a, f = g.overlapping_pairs(poses[0], np.ones((3, 3), bool), length, width, query=np.array([1]))
    assert (q.tolist(), a.tolist(), f.tolist()) == ([0], [0], [2])  # q indexes the query


def test_first_overlaps_give_each_agents_first_collision_frame_and_who_it_touched_then():
    poses = np.zeros((4, 4, 3))
    poses[0, :, 0] = 0.0
    poses[1, :, 0] = [10.0, 10.0, 3.0, 3.0]  # touches 0 from frame 2
    poses[2, :, 0] = [20.0, -3.0, -3.0, -3.0]  # touches 0 from frame 1
    poses[3, :, 0] = 50.0
    present, length, width = np.ones((4, 4), bool), np.full(4, 4.0), np.full(4, 2.0)
    first, partners = g.first_overlaps(poses, present, length, width)
    assert first.tolist() == [1, 2, 1, -1]
    assert [p.tolist() for p in partners] == [[2], [0], [0], []]
    poses[1, 1, 0] = 3.0  # now 1 touches 0 on frame 1 as well: both are 0's partners then
    first, partners = g.first_overlaps(poses, present, length, width, query=np.array([0, 3]))
    assert first.tolist() == [1, -1] and [p.tolist() for p in partners] == [[1, 2], []]
