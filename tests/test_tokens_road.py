"""Road-vector tokens: 5 m pieces that cover every polyline, the road vocabulary, and the piece
sequences along lanes and successor links (checked on a known lane chain of the WOMD test scene).

The general properties run on the package's sample scenes and, where ../shared/data is present, on
the real scenes of every format too."""

from __future__ import annotations

import numpy as np
import pytest

from smart_marl import read_scenarios
from smart_marl.scenario import POLYGON_FEATURES, LinkType, MapFeatureType
from smart_marl.tokens import (
    build_road_vocabulary, load_road_vocabulary, match_road_pieces, road_pieces, road_successor_pairs, sample_road_walks,
    save_road_vocabulary,
)
from smart_marl.tokens.road import PIECE_FEATURES

SCENE_FOLDERS = ("womd_tfrecord", "scenarionet", "gpudrive_json", "nocturne_json", "smart_pkl", "av2")


@pytest.fixture(scope="module")
def real_scenes(shared_data):
    out = []
    for folder in SCENE_FOLDERS:
        out.extend(read_scenarios(shared_data / folder))
    assert len(out) >= 20
    return out


@pytest.fixture(scope="module", params=["sample", "real"])
def scenes(request, sample_scenes):
    """The four sample scenes (SUMO), or the real scenes of every format."""
    return sample_scenes if request.param == "sample" else request.getfixturevalue("real_scenes")


@pytest.fixture(scope="module")
def womd_scene(shared_data):
    return next(read_scenarios(shared_data / "womd_tfrecord" / "motion_data_one_scenario.tfrecord"))


@pytest.fixture(scope="module", params=["sample", "womd"])
def scene(request, sample_scenes):
    """The sample scene sumo-7-000000-02 (155 signalised lanes), or the real WOMD scene."""
    return sample_scenes[2] if request.param == "sample" else request.getfixturevalue("womd_scene")


def _polyline(rm, f) -> np.ndarray:
    p = rm.feature_points(f)[:, :2].astype(np.float64)
    return np.concatenate([p, p[:1]]) if rm.types[f] in POLYGON_FEATURES else p


def test_road_pieces_cover_every_polyline_of_the_scenes_and_are_at_most_5m(scenes):
    for sc in scenes:
        rm = sc.road_map
        pieces = road_pieces(rm, sc.traffic_lights)
        assert (pieces.length_m <= 5.0 + 1e-4).all()
        chord = np.linalg.norm(np.diff(pieces.points, axis=1), axis=-1).sum(1)  # resampled length <= arc
        assert (chord <= pieces.length_m + 1e-3).all()
        expected = [f for f in range(rm.num_features)
                    if rm.types[f] in [int(t) for t in PIECE_FEATURES] and len(rm.feature_points(f)) >= 2]
        assert sorted(set(pieces.feature_index.tolist())) == expected, sc.scenario_id
        # per feature: pieces in order, lengths add up to the polyline's, ends on its ends
        total = np.zeros(rm.num_features)
        np.add.at(total, pieces.feature_index, pieces.length_m.astype(np.float64))
        for f in expected[:: max(1, len(expected) // 25)]:
            line = _polyline(rm, f)
            length = np.linalg.norm(np.diff(line, axis=0), axis=-1).sum()
            assert total[f] == pytest.approx(length, rel=1e-4, abs=1e-3)
            sel = np.flatnonzero(pieces.feature_index == f)
            assert pieces.piece_in_feature[sel].tolist() == list(range(len(sel)))
            np.testing.assert_allclose(pieces.points[sel[0], 0], line[0], atol=1e-3)
            np.testing.assert_allclose(pieces.points[sel[-1], -1], line[-1], atol=1e-3)
            # consecutive pieces share their end points: the pieces chain into the polyline
            np.testing.assert_allclose(pieces.points[sel[1:], 0], pieces.points[sel[:-1], -1], atol=1e-3)


def test_piece_frame_has_origin_at_the_first_point_and_x_towards_the_last(scene):
    p = road_pieces(scene.road_map)
    np.testing.assert_allclose(p.local[:, 0], 0.0, atol=1e-6)
    long_enough = np.linalg.norm(p.points[:, -1] - p.points[:, 0], axis=-1) > 0.1
    np.testing.assert_allclose(p.local[long_enough, -1, 1], 0.0, atol=1e-4)
    assert (p.local[long_enough, -1, 0] > 0).all()
    c, s = np.cos(p.pose[:, 2]), np.sin(p.pose[:, 2])
    world = np.stack([c[:, None] * p.local[..., 0] - s[:, None] * p.local[..., 1],
                      s[:, None] * p.local[..., 0] + c[:, None] * p.local[..., 1]], -1) + p.pose[:, None, :2]
    np.testing.assert_allclose(world, p.points, atol=1e-3)


def test_signalised_lanes_link_their_pieces_to_the_traffic_light(scene):
    sc = scene
    p = road_pieces(sc.road_map, sc.traffic_lights)
    linked = p.traffic_light_index >= 0
    assert linked.any()
    np.testing.assert_array_equal(sc.road_map.ids[p.feature_index[linked]], sc.traffic_lights.lane_ids[p.traffic_light_index[linked]])
    lanes = p.feature_type == MapFeatureType.LANE
    signalised = np.isin(sc.road_map.ids[p.feature_index], sc.traffic_lights.lane_ids) & lanes
    np.testing.assert_array_equal(linked, signalised)


def test_road_sequences_follow_a_known_lane_chain(womd_scene):
    """Lanes 154 -> 158 -> 559 -> 557 are a successor chain of scenario 637f20cafde22ff8."""
    rm = womd_scene.road_map
    p = road_pieces(rm)
    pairs, kind = road_successor_pairs(p, rm)
    index_of = {int(i): f for f, i in enumerate(rm.ids)}
    chain = [index_of[i] for i in (154, 158, 559, 557)]
    # walk from the first piece of lane 154, always taking the successor on the chain
    succ: dict[int, list[int]] = {}
    for a, b in pairs:
        succ.setdefault(int(a), []).append(int(b))
    cur = int(np.flatnonzero(p.feature_index == chain[0])[0])
    visited = [cur]
    while p.feature_index[cur] != chain[-1]:
        nxt = [b for b in succ.get(cur, []) if p.feature_index[b] in chain[chain.index(p.feature_index[cur]):]]
        assert nxt, f"piece {cur} of lane {rm.ids[p.feature_index[cur]]} has no successor on the chain"
        cur = nxt[0]
        visited.append(cur)
    lanes_seen = [int(rm.ids[f]) for f in dict.fromkeys(p.feature_index[visited].tolist())]
    assert lanes_seen == [154, 158, 559, 557]
    # every step moves on along the road: the next piece starts where this one ends
    gaps = np.linalg.norm(p.points[visited[1:], 0] - p.points[visited[:-1], -1], axis=-1)
    assert gaps.max() < 0.5
    # kind 1 pairs are exactly the successor links between lanes that have pieces (lane 529 of this
    # scene is a single point, so it has none), last piece -> first piece
    has = set(p.feature_index.tolist())
    links = {(int(a), int(b)) for a, b in rm.link_indices(LinkType.SUCCESSOR) if a in has and b in has}
    assert len(links) >= 180
    k1 = pairs[kind == 1]
    assert {(int(p.feature_index[a]), int(p.feature_index[b])) for a, b in k1} == links
    assert (p.piece_in_feature[k1[:, 1]] == 0).all()


def test_sampled_walks_only_step_along_pairs(scene):
    rm = scene.road_map
    p = road_pieces(rm)
    pairs, _ = road_successor_pairs(p, rm)
    walks = sample_road_walks(pairs, p.num_pieces, 12, 300, rng=0)
    allowed = {(int(a), int(b)) for a, b in pairs}
    steps = [(int(a), int(b)) for w in walks for a, b in zip(w[:-1], w[1:]) if b >= 0]
    assert len(steps) > 1000 and all(s in allowed for s in steps)
    ended = walks[:, :-1] >= 0
    dead = ended & (walks[:, 1:] < 0)  # a walk stops only at a piece without successor
    assert all(int(a) not in {x for x, _ in allowed} for a in walks[:, :-1][dead])


def test_road_vocabulary_matches_pieces_closely_and_round_trips(scenes, tmp_path):
    train = np.concatenate([road_pieces(sc.road_map).local for sc in scenes[1::2]])
    test = road_pieces(scenes[0].road_map).local
    vocab = build_road_vocabulary(train, 256, seed=0, progress=False)
    assert vocab.size == 256 and vocab.points.shape == (256, 11, 2)
    ids, nearest, dist = match_road_pieces(test, vocab)
    assert np.array_equal(ids, nearest) and np.median(dist) < 0.2
    noisy, nearest2, _ = match_road_pieces(test, vocab, noise_topk=4, rng=0)
    assert np.array_equal(nearest2, nearest) and 0.65 < (noisy != nearest).mean() < 0.85
    save_road_vocabulary(vocab, tmp_path / "road_256")
    back = load_road_vocabulary(tmp_path / "road_256.json", expected_hash=vocab.content_hash())
    np.testing.assert_array_equal(back.points, vocab.points)
