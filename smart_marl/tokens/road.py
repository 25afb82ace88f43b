"""Road-vector tokens (tokens stage): a scene's vector map -> road pieces -> road tokens and the
piece sequences the road next-token task trains on.

What comes in: a :class:`~smart_marl.scenario.RoadMap` (and the scene's
:class:`~smart_marl.scenario.TrafficLights`). What goes out: :class:`RoadPieces` (RoadNet's
input), their token ids in a :class:`RoadVocabulary`, and successor pairs / walks.

* Pieces: every polyline feature (lane centrelines, road lines, road edges) and every polygon
  outline (crosswalks, speed bumps, driveways; closed by repeating the first point) with at least
  two points is split by arc length into ``ceil(length / 5 m)`` equal pieces, so every piece is at
  most ``max_length_m`` (5 m) long and no short remainder is left, each resampled to
  ``PIECE_POINTS = 11`` points evenly spaced along the arc (like the reference ``traj_src``
  [1024, 11, 2]). Single-point features (stop signs) have no piece. A zero-length feature (all
  points equal) gives one degenerate piece.
* A piece's frame: origin at its first point, +x from its first to its last point (heading 0
  when they coincide). Its pose (x, y, heading) is kept with the feature index, type, subtype, its
  order along the feature and its traffic-light link (index into ``TrafficLights.lane_ids`` when
  the piece's lane is signalised, else -1).
* The road vocabulary: k-disks (:mod:`.kdisks`) on the pieces' points in their own frames,
  distance = mean point distance; 1024 tokens by default. Matching picks the nearest token, or
  draws uniformly among the ``noise_topk`` nearest. With fewer distinct pieces than the requested
  size, the vocabulary holds every distinct piece (it comes out smaller; ``size`` says so).
* Sequences (:func:`road_successor_pairs`): directed pairs (piece i -> piece j) meaning "j comes
  right after i when driving/following the feature": consecutive pieces of one feature (kind 0),
  and the last piece of a lane -> the first piece of each of its successor lanes from
  ``RoadMap.link_indices(LinkType.SUCCESSOR)`` (kind 1). :func:`sample_road_walks` draws walks of a
  fixed length along those pairs (the road next-token training sequences).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np
import torch

from ..scenario import POLYGON_FEATURES, LinkType, MapFeatureType, RoadMap, TrafficLights
from .kdisks import kdisks, point_distance_matrices
from .motion import VOCABULARY_VERSION, hash_arrays

__all__ = [
    "MAX_PIECE_LENGTH_M", "PIECE_POINTS", "RoadPieces", "RoadVocabulary", "build_road_vocabulary",
    "match_road_pieces", "road_pieces", "road_successor_pairs", "road_vocabulary_hash", "sample_road_walks",
]

PIECE_POINTS = 11
MAX_PIECE_LENGTH_M = 5.0
PIECE_FEATURES = (MapFeatureType.LANE, MapFeatureType.ROAD_LINE, MapFeatureType.ROAD_EDGE, MapFeatureType.CROSSWALK,
                  MapFeatureType.SPEED_BUMP, MapFeatureType.DRIVEWAY)


@dataclass(frozen=True, eq=False)
class RoadPieces:
    """``K`` road pieces of one scene, ordered by feature then along it."""

    points: np.ndarray  # [K, P, 2] float32, scene frame
    local: np.ndarray  # [K, P, 2] float32, the piece's own frame
    pose: np.ndarray  # [K, 3] float32, x, y of the first point, heading first -> last point
    length_m: np.ndarray  # [K] float32, arc length
    feature_index: np.ndarray  # [K] int64, index into the RoadMap
    feature_type: np.ndarray  # [K] int8, MapFeatureType
    feature_subtype: np.ndarray  # [K] int8
    piece_in_feature: np.ndarray  # [K] int64, 0 .. (pieces of its feature) - 1
    traffic_light_index: np.ndarray  # [K] int64, index into TrafficLights.lane_ids, -1 when none

    @property
    def num_pieces(self) -> int:
        return int(self.points.shape[0])


def road_pieces(road_map: RoadMap, traffic_lights: TrafficLights | None = None, max_length_m: float = MAX_PIECE_LENGTH_M,
                num_points: int = PIECE_POINTS) -> RoadPieces:
    """Split every polyline / polygon outline of ``road_map`` into pieces (see the module docstring)."""
    rm = road_map
    counts = np.diff(rm.point_offsets)
    feats = np.flatnonzero(np.isin(rm.types, [int(t) for t in PIECE_FEATURES]) & (counts >= 2))
    closed = np.isin(rm.types[feats], [int(t) for t in POLYGON_FEATURES])
    n_pts = counts[feats] + closed  # points per feature after closing polygons
    starts = rm.point_offsets[feats]
    total = int(n_pts.sum())
    feat_of = np.repeat(np.arange(len(feats)), n_pts)  # [Q] position in feats
    first_q = np.concatenate([[0], np.cumsum(n_pts)[:-1]]).astype(np.int64)
    j = np.arange(total) - first_q[feat_of]
    idx = starts[feat_of] + j % counts[feats][feat_of]  # polygon closure wraps to the first point
    pts = rm.points[idx, :2].astype(np.float64)  # [Q, 2]

    seg = np.zeros(total)
    same = np.ones(total, bool)
    same[first_q] = False
    seg[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=-1)
    seg[~same] = 0.0
    cum = np.cumsum(seg)
    cum_first = cum[first_q]
    arc = cum - cum_first[feat_of]  # arc length within the feature
    length = np.zeros(len(feats))
    np.maximum.at(length, feat_of, arc)
    base = np.concatenate([[0.0], np.cumsum(length + 1.0)[:-1]])  # features 1 m apart on a global arc axis
    g = base[feat_of] + arc

    m = np.maximum(1, np.ceil(length / max_length_m - 1e-9)).astype(np.int64)  # pieces per feature
    piece_feat = np.repeat(np.arange(len(feats)), m)  # [K]
    piece_first = np.concatenate([[0], np.cumsum(m)[:-1]]).astype(np.int64)
    q = np.arange(len(piece_feat)) - piece_first[piece_feat]
    plen = length[piece_feat] / m[piece_feat]
    u = np.arange(num_points) / (num_points - 1)
    s = np.minimum((q[:, None] + u[None, :]) * plen[:, None], length[piece_feat][:, None])  # [K, P]
    gq = base[piece_feat][:, None] + s
    x = np.interp(gq.ravel(), g, pts[:, 0]).reshape(gq.shape)
    y = np.interp(gq.ravel(), g, pts[:, 1]).reshape(gq.shape)
    points = np.stack([x, y], -1)  # [K, P, 2]

    d = points[:, -1] - points[:, 0]
    heading = np.where(np.hypot(d[:, 0], d[:, 1]) > 1e-6, np.arctan2(d[:, 1], d[:, 0]), 0.0)
    c, sn = np.cos(heading)[:, None], np.sin(heading)[:, None]
    rel = points - points[:, :1]
    local = np.stack([c * rel[..., 0] + sn * rel[..., 1], -sn * rel[..., 0] + c * rel[..., 1]], -1)

    fidx = feats[piece_feat]
    tl_index = np.full(len(fidx), -1, np.int64)
    if traffic_lights is not None and len(traffic_lights.lane_ids):
        lane_pos = {int(lid): i for i, lid in enumerate(traffic_lights.lane_ids)}
        ids = rm.ids[fidx]
        is_lane = rm.types[fidx] == MapFeatureType.LANE
        tl_index = np.array([lane_pos.get(int(i), -1) if l else -1 for i, l in zip(ids, is_lane)], np.int64).reshape(-1)
    return RoadPieces(
        points=points.astype(np.float32), local=local.astype(np.float32),
        pose=np.concatenate([points[:, 0], heading[:, None]], -1).astype(np.float32),
        length_m=plen.astype(np.float32), feature_index=fidx.astype(np.int64), feature_type=rm.types[fidx].astype(np.int8),
        feature_subtype=rm.subtypes[fidx].astype(np.int8), piece_in_feature=q.astype(np.int64), traffic_light_index=tl_index,
    )


@dataclass(frozen=True, eq=False)
class RoadVocabulary:
    points: np.ndarray  # [V, P, 2] float32, token points in the piece frame
    tolerance_m: float
    requested_size: int
    max_piece_length_m: float = MAX_PIECE_LENGTH_M
    num_samples: int = 0
    seed: int | None = None
    provenance: Mapping[str, Any] = field(default_factory=dict)

    @property
    def size(self) -> int:
        return int(self.points.shape[0])

    def content_hash(self) -> str:
        return road_vocabulary_hash(self)


def road_vocabulary_hash(vocab: RoadVocabulary) -> str:
    """SHA-256 (hex) of a road vocabulary's token points."""
    return hash_arrays(f"road/v{VOCABULARY_VERSION}/", [("points", vocab.points.astype(np.float32))])


def build_road_vocabulary(local_points: np.ndarray, size: int = 1024, seed: int = 0, provenance: Mapping[str, Any] | None = None,
                          progress: bool = True) -> RoadVocabulary:
    """k-disks road tokens from pieces' points in their own frames [M, P, 2]."""
    local_points = np.asarray(local_points, np.float32)
    res = kdisks(local_points, size, seed=seed, progress=progress, desc=f"k-disks road {size}")
    return RoadVocabulary(points=local_points[res.centre_indices], tolerance_m=res.tolerance_m, requested_size=size,
                          num_samples=len(local_points), seed=seed, provenance=dict(provenance or {}))


def match_road_pieces(local_points: np.ndarray, vocab: RoadVocabulary, noise_topk: int = 0,
                      rng: np.random.Generator | int | None = None, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Token ids [K] of pieces [K, P, 2] (own frame): the nearest by mean point distance, or with
    ``noise_topk > 1`` uniformly among that many nearest. Returns (ids, nearest ids, distance_m [K])."""
    if not isinstance(rng, np.random.Generator):
        rng = np.random.default_rng(rng)
    x = torch.from_numpy(np.asarray(local_points, np.float32))
    v = torch.from_numpy(vocab.points.astype(np.float32))
    k = len(x)
    nearest = np.zeros(k, np.int64)
    dist_best = np.zeros(k, np.float32)
    ids = np.zeros(k, np.int64)
    for c0 in range(0, k, chunk):
        xc = x[c0 : c0 + chunk]
        d = point_distance_matrices(xc, v).mean(0)  # [c, V] mean point distance
        best = d.argmin(-1)
        nearest[c0 : c0 + len(xc)] = best.numpy()
        dist_best[c0 : c0 + len(xc)] = d.gather(1, best[:, None])[:, 0].numpy()
        if noise_topk > 1:
            kk = min(noise_topk, vocab.size)
            top = torch.topk(d, kk, dim=-1, largest=False).indices.numpy()
            ids[c0 : c0 + len(xc)] = top[np.arange(len(xc)), rng.integers(0, kk, len(xc))]
        else:
            ids[c0 : c0 + len(xc)] = best.numpy()
    return ids, nearest, dist_best


def road_successor_pairs(pieces: RoadPieces, road_map: RoadMap) -> tuple[np.ndarray, np.ndarray]:
    """Directed pairs [E, 2] (piece i -> piece j) and their kind [E] (0: next piece of the same
    feature; 1: last piece of a lane -> first piece of a successor lane)."""
    fi = pieces.feature_index
    within = np.flatnonzero(fi[1:] == fi[:-1])
    pairs = [np.stack([within, within + 1], -1)]
    kinds = [np.zeros(len(within), np.int8)]
    links = road_map.link_indices(LinkType.SUCCESSOR)  # [L, 2] feature indices
    if len(links) and len(fi):
        nf = road_map.num_features
        first = np.full(nf, -1, np.int64)
        last = np.full(nf, -1, np.int64)
        order = np.arange(len(fi))
        first[fi[::-1]] = order[::-1]  # first occurrence wins
        last[fi] = order
        a, b = last[links[:, 0]], first[links[:, 1]]
        keep = (a >= 0) & (b >= 0)
        pairs.append(np.stack([a[keep], b[keep]], -1))
        kinds.append(np.ones(int(keep.sum()), np.int8))
    p = np.concatenate(pairs).astype(np.int64).reshape(-1, 2)
    kd = np.concatenate(kinds)
    p, uniq = np.unique(p, axis=0, return_index=True)
    return p, kd[uniq]


def sample_road_walks(pairs: np.ndarray, num_pieces: int, length: int, num_walks: int,
                      rng: np.random.Generator | int | None = None, starts: np.ndarray | None = None) -> np.ndarray:
    """Walks [W, length] of piece indices along ``pairs``, each step to a uniformly chosen successor;
    -1 after a piece with no successor. Starts are drawn uniformly from the pieces unless given."""
    if not isinstance(rng, np.random.Generator):
        rng = np.random.default_rng(rng)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    order = np.argsort(pairs[:, 0], kind="stable")
    src, dst = pairs[order, 0], pairs[order, 1]
    offsets = np.searchsorted(src, np.arange(num_pieces + 1))
    cur = np.asarray(starts, np.int64) if starts is not None else rng.integers(0, num_pieces, num_walks)
    walks = np.full((len(cur), length), -1, np.int64)
    walks[:, 0] = cur
    for step in range(1, length):
        alive = cur >= 0
        deg = np.where(alive, offsets[np.maximum(cur, 0) + 1] - offsets[np.maximum(cur, 0)], 0)
        has = deg > 0
        pick = offsets[np.maximum(cur, 0)] + (rng.random(len(cur)) * np.maximum(deg, 1)).astype(np.int64)
        cur = np.where(has, dst[np.minimum(pick, len(dst) - 1)] if len(dst) else -1, -1)
        walks[:, step] = cur
    return walks
