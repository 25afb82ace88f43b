"""The tensor geometry (smart_marl.geometry_torch) against the numpy geometry the metrics use
(smart_marl.geometry): the same collisions and the same signed road-edge distances, batched over
scenes with padded road edges."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from smart_marl import geometry
from smart_marl.embedded import sample_scenarios
from smart_marl.geometry_torch import (RoadEdgeTensors, bound_length, box_corners, box_corners_bottom, loose, rounded_boxes_overlap,
                                       signed_distance_to_road_edges, squared_length)
from smart_marl.scenario import MapFeatureType


def _random_box_pairs(rng, n):
    a = np.stack([rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(0.5, 6, n), rng.uniform(0.4, 2.6, n),
                  rng.uniform(-np.pi, np.pi, n)], -1)
    b = np.stack([rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(0.5, 6, n), rng.uniform(0.4, 2.6, n),
                  rng.uniform(-np.pi, np.pi, n)], -1)
    return a, b


def test_box_corners_equal_the_numpy_corners():
    rng = np.random.default_rng(0)
    a, _ = _random_box_pairs(rng, 100)
    want = geometry.box_corners(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4])
    t = lambda x: torch.as_tensor(x, dtype=torch.float64)  # noqa: E731
    got = box_corners(t(a[:, :2]), t(a[:, 4]), t(a[:, 2]), t(a[:, 3])).numpy()
    np.testing.assert_allclose(got, want, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_rounded_box_overlap_equals_the_metrics_collision_test_on_random_boxes(dtype):
    rng = np.random.default_rng(1)
    a, b = _random_box_pairs(rng, 20000)
    want = geometry.boxes_overlap(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], b[:, 0], b[:, 1], b[:, 2], b[:, 3], b[:, 4])
    t = lambda x: torch.as_tensor(x, dtype=dtype)  # noqa: E731
    got = rounded_boxes_overlap(t(a[:, :2]), t(a[:, 4]), t(a[:, 2:4]), t(b[:, :2]), t(b[:, 4]), t(b[:, 2:4])).numpy()
    assert 0.2 < want.mean() < 0.8  # both outcomes are exercised
    sd = geometry.rounded_box_signed_distance(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], b[:, 0], b[:, 1], b[:, 2], b[:, 3],
                                              b[:, 4])
    boundary = np.abs(sd) < (1e-9 if dtype == torch.float64 else 1e-4)  # within rounding of touching
    np.testing.assert_array_equal(got[~boundary], want[~boundary])
    assert boundary.sum() <= 2


def _edge_segments(scenario):
    rm = scenario.road_map
    return geometry.RoadEdgeSegments.from_polylines([rm.feature_points(i) for i in rm.indices_of(MapFeatureType.ROAD_EDGE)])


def test_signed_road_edge_distance_equals_the_numpy_one_on_padded_scenes():
    scenes = sample_scenarios()[:3]
    segs = [_edge_segments(sc) for sc in scenes]
    assert len({s.num_segments for s in segs}) == 3  # different sizes: the smaller scenes are padded
    edges = RoadEdgeTensors.from_segments(segs + [None], dtype=torch.float64)
    rng = np.random.default_rng(2)
    pts = []
    for sc in scenes:
        tr, cf = sc.tracks, sc.current_frame
        base = tr.position[tr.valid[:, cf], cf]
        p = base[rng.integers(len(base), size=300)] + np.concatenate([rng.normal(0, 6, (300, 2)), rng.normal(0, 0.3, (300, 1))], -1)
        pts.append(p)
    pts.append(pts[0])  # the scene without edges
    got = signed_distance_to_road_edges(torch.as_tensor(np.stack(pts)), edges, max_pairs=1 << 16).numpy()
    for k, seg in enumerate(segs):
        want = geometry.signed_distance_to_road_edges(pts[k], seg)
        np.testing.assert_allclose(got[k], want, atol=1e-9)
        assert (want > 0).sum() > 10 and (want < 0).sum() > 10  # on and off the road
    assert np.isneginf(got[3]).all()


def test_offroad_boxes_equal_the_numpy_offroad_test():
    sc = sample_scenarios()[2]
    seg = _edge_segments(sc)
    rng = np.random.default_rng(3)
    tr, cf = sc.tracks, sc.current_frame
    base = tr.position[tr.valid[:, cf], cf]
    n = 400
    c = base[rng.integers(len(base), size=n)] + np.concatenate([rng.normal(0, 5, (n, 2)), np.zeros((n, 1))], -1)
    h = rng.uniform(-np.pi, np.pi, n)
    size = np.stack([np.full(n, 4.5), np.full(n, 2.0), np.full(n, 1.6)], -1)
    want = geometry.box_distance_to_road_edge(c[:, 0], c[:, 1], c[:, 2], size[:, 0], size[:, 1], size[:, 2], h, seg,
                                              float32_corners=False)
    t = lambda x: torch.as_tensor(x, dtype=torch.float64)  # noqa: E731
    corners = box_corners_bottom(t(c[:, :2]), t(h), t(size), t(c[:, 2]))  # [n, 4, 3]
    edges = RoadEdgeTensors.from_segments([seg], dtype=torch.float64)
    got = signed_distance_to_road_edges(corners.reshape(1, -1, 3), edges).reshape(n, 4).amax(-1).numpy()
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert 10 < (want > 0).sum() < n - 10


def test_pruned_nearest_edge_search_equals_the_exhaustive_one_with_any_number_of_candidates():
    from smart_marl.geometry_torch import nearest_road_edge

    scenes = sample_scenarios()[:2]
    edges = RoadEdgeTensors.from_segments([_edge_segments(sc) for sc in scenes], dtype=torch.float64)
    gen = torch.Generator().manual_seed(4)
    pts = torch.cat([torch.rand(2, 500, 2, generator=gen, dtype=torch.float64) * 300 - 150,
                     torch.rand(2, 500, 1, generator=gen, dtype=torch.float64) * 4 - 2], -1)
    sp = pts[:, :, None] - edges.start[:, None]
    e = (edges.end - edges.start)[:, None]
    t = ((sp[..., :2] * e[..., :2]).sum(-1) / (e[..., :2] ** 2).sum(-1).clamp_min(1e-30)).clamp(0, 1)
    d = sp - e * t[..., None]
    full = (d[..., 0] ** 2 + d[..., 1] ** 2 + (3.0 * d[..., 2]) ** 2).masked_fill(~edges.valid[:, None], float("inf")).argmin(-1)
    for k in (1, 4, 16, 10**6):  # 1 candidate: most points fall back to every segment; 10**6: every segment is a candidate
        assert torch.equal(nearest_road_edge(pts, edges, candidates=k), full)


def test_the_nearest_edge_search_in_small_blocks_of_scenes_equals_one_block():
    """On the CPU the bounds run over blocks of scenes ordered by their segment count, each cut to its
    largest scene (``max_pairs``); any block size gives the same nearest segments, scenes without edges included."""
    from smart_marl.geometry_torch import nearest_road_edge

    scenes = sample_scenarios()
    segs = [_edge_segments(sc) for sc in scenes]
    segs.insert(1, None)  # a scene without road edges
    edges = RoadEdgeTensors.from_segments(segs, dtype=torch.float64)
    gen = torch.Generator().manual_seed(5)
    b = len(segs)
    pts = torch.cat([torch.rand(b, 40, 2, generator=gen, dtype=torch.float64) * 300 - 150,
                     torch.rand(b, 40, 1, generator=gen, dtype=torch.float64) * 4 - 2], -1)
    want = nearest_road_edge(pts, edges, max_pairs=1 << 30)
    assert len(set(edges.valid.sum(1).tolist())) >= 3  # scenes of different sizes
    for pairs in (1, 5000, 40 * int(edges.valid.sum(1).max()) * 2):
        assert torch.equal(nearest_road_edge(pts, edges, max_pairs=pairs), want), pairs


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_fast_length_of_the_bounds_passes_every_pair_the_norm_passes(dtype):
    g = torch.Generator().manual_seed(3)
    v = (torch.rand(200_000, 2, generator=g, dtype=dtype) - 0.5) * torch.logspace(-3, 3, 200_000, dtype=dtype)[:, None]
    exact = v.norm(dim=-1)
    fast = bound_length(v)
    assert torch.allclose(fast, exact, rtol=4 * torch.finfo(dtype).eps, atol=0)
    # a limit at the norm itself and an ulp above it: whatever the norm passes, the loosened bound passes too
    for limit in (exact, torch.nextafter(exact, torch.full_like(exact, math.inf))):
        assert bool((fast < loose(limit))[exact < limit].all())
        assert bool((fast < loose(limit)).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_squared_length_is_the_square_sum_bit_for_bit(dtype):
    g = torch.Generator().manual_seed(4)
    v = torch.randn(100_000, 2, generator=g, dtype=dtype) * torch.logspace(-4, 4, 100_000, dtype=dtype)[:, None]
    assert torch.equal(squared_length(v), v.square().sum(-1))
    assert torch.equal(squared_length(v[:, None].expand(-1, 3, -1)), v[:, None].expand(-1, 3, -1).square().sum(-1))  # strided
