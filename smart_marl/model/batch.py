"""Model stage, input side: tokenized scenes -> padded batch tensors (:class:`SmartBatch`).

Per scene (in DataLoader workers, never in the training step): rolling-matching motion tokens
(:func:`smart_marl.tokens.tokenize_motion`, with top-k token noise for training), road pieces and
their road tokens (:mod:`smart_marl.tokens.road`), the successor pairs along road sequences and the
pieces whose content is hidden for the road next-token task. :func:`collate_scenes` pads those
per-scene arrays into one batch of tensors, so the model sees several scenes without a per-scene
Python loop.

Alignment: the agent input at token step s is token s placed at the pose it reached (the end of
token s); its target is the token of step s + 1, valid when both tokens are valid. The target is
the noise-free (nearest) token from the pose the (possibly noised) sequence reached, so the model
learns to correct drift (``MotionTokens.nearest_ids``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from ..scenario import LaneType, LinkType, MapFeatureType, RoadEdgeType, RoadLineType, Scenario, SignalState
from ..tokens import MotionVocabulary, tokenize_motion
from ..tokens.road import RoadVocabulary, match_road_pieces, road_pieces, road_successor_pairs
from .roadnet import NUM_LIGHT_STATES, NUM_ROAD_TYPES

NO_LIGHT = NUM_LIGHT_STATES - 1
_SUBTYPES = 9  # road type id = feature_type * 9 + subtype (MapFeatureType 0..6, subtypes 0..8)
assert 7 * _SUBTYPES <= NUM_ROAD_TYPES


@dataclass
class SmartBatch:
    """B scenes, N agents (padded), S token steps, R road pieces (padded), E road pairs (padded)."""

    agent_tokens: torch.Tensor  # [B, N, S] long, token id in the agent's type vocabulary (0 where invalid)
    agent_valid: torch.Tensor  # [B, N, S] bool
    agent_type: torch.Tensor  # [B, N] long, 0..2 (padding: 0, never valid)
    agent_shape: torch.Tensor  # [B, N, 3] float, length, width, height (m)
    agent_start_pose: torch.Tensor  # [B, N, S, 3] float, where token s starts
    agent_pose: torch.Tensor  # [B, N, S, 3] float, where token s ends (the pose the sequence reached)
    target_tokens: torch.Tensor  # [B, N, S] long, token of step s + 1
    target_valid: torch.Tensor  # [B, N, S] bool
    road_points: torch.Tensor  # [B, R, P, 2] float, piece points in the piece's frame
    road_pose: torch.Tensor  # [B, R, 3] float
    road_type: torch.Tensor  # [B, R] long
    road_light: torch.Tensor  # [B, R] long, SignalState at the current frame, NO_LIGHT when unsignalised
    road_valid: torch.Tensor  # [B, R] bool
    road_token: torch.Tensor  # [B, R] long, nearest road-vocabulary token
    road_masked: torch.Tensor  # [B, R] bool, content hidden (targets of the road next-token task)
    road_pairs: torch.Tensor  # [B, E, 2] long, (piece i -> next piece j) along road sequences
    road_pair_valid: torch.Tensor  # [B, E] bool

    def to(self, device, non_blocking: bool = False) -> "SmartBatch":
        return SmartBatch(**{f.name: getattr(self, f.name).to(device, non_blocking=non_blocking) for f in fields(self)})

    def pin_memory(self) -> "SmartBatch":
        return SmartBatch(**{f.name: getattr(self, f.name).pin_memory() for f in fields(self)})

    @property
    def num_scenes(self) -> int:
        return int(self.agent_tokens.shape[0])


@dataclass
class RoadArrays:
    """The static road part of one scene (cached per scene by the dataset)."""

    local: np.ndarray  # [R, P, 2]
    pose: np.ndarray  # [R, 3]
    type_id: np.ndarray  # [R]
    light: np.ndarray  # [R]
    token: np.ndarray  # [R]
    pairs: np.ndarray  # [E, 2]
    light_index: np.ndarray  # [R] traffic-light lane index (-1: none; STOP_SIGN_LIGHT): ``light`` at any frame is light_codes of it


ROAD_TYPE_SETS = ("all", "sumo")
"""What the model's road-type embedding distinguishes (``SmartConfig.road_types``): ``all`` every WOMD
feature type and subtype; ``sumo`` the kinds the SUMO source produces, for a model trained on SUMO
scenes and run on real ones. Under ``sumo``, subtypes SUMO never makes take the nearest kind it
makes (a freeway or undefined lane is a street lane, every road edge a boundary, an unknown line a
broken white one, a double white a solid white one, every yellow centre line but a solid single
one a solid double yellow), and speed bumps and driveways are left out of the model's road: their
embeddings would never have been trained."""

_SUMO_SUBTYPE = {  # feature type -> {subtype: the subtype SUMO makes}
    MapFeatureType.LANE: {LaneType.UNDEFINED: LaneType.SURFACE_STREET, LaneType.FREEWAY: LaneType.SURFACE_STREET},
    MapFeatureType.ROAD_LINE: {RoadLineType.UNKNOWN: RoadLineType.BROKEN_SINGLE_WHITE,
                               RoadLineType.SOLID_DOUBLE_WHITE: RoadLineType.SOLID_SINGLE_WHITE,
                               RoadLineType.BROKEN_SINGLE_YELLOW: RoadLineType.SOLID_DOUBLE_YELLOW,
                               RoadLineType.BROKEN_DOUBLE_YELLOW: RoadLineType.SOLID_DOUBLE_YELLOW,
                               RoadLineType.PASSING_DOUBLE_YELLOW: RoadLineType.SOLID_DOUBLE_YELLOW},
    MapFeatureType.ROAD_EDGE: {RoadEdgeType.UNKNOWN: RoadEdgeType.BOUNDARY, RoadEdgeType.MEDIAN: RoadEdgeType.BOUNDARY},
}
_SUMO_LEFT_OUT = (MapFeatureType.SPEED_BUMP, MapFeatureType.DRIVEWAY)


@dataclass(frozen=True)
class RoadSettings:
    """What of a scene's road the model reads, beside the pieces themselves: which road kinds its type
    embedding tells apart (``types``, :data:`ROAD_TYPE_SETS`) and whether the lanes a stop sign controls carry
    FLASHING_STOP (``stop_signs``, :func:`stop_sign_lanes`). A model's are :attr:`SmartConfig.road_settings
    <smart_marl.model.SmartConfig.road_settings>`; road arrays, token caches and rollouts are made with them."""

    types: str = "all"
    stop_signs: bool = False


def road_type_ids(feature_type: np.ndarray, subtype: np.ndarray, road_types: str = "all") -> tuple[np.ndarray, np.ndarray]:
    """The model's road-type ids (feature type * 9 + subtype) of pieces ``feature_type``, ``subtype``
    [R] under ``road_types`` (see :data:`ROAD_TYPE_SETS`), and which pieces the model sees [R] bool."""
    if road_types not in ROAD_TYPE_SETS:
        raise ValueError(f"road_types must be one of {ROAD_TYPE_SETS}, got {road_types!r}")
    ftype = np.asarray(feature_type, np.int64)
    sub = np.clip(np.asarray(subtype, np.int64), 0, _SUBTYPES - 1)
    keep = np.ones(len(ftype), bool)
    if road_types == "sumo":
        sub = sub.copy()
        for f, table in _SUMO_SUBTYPE.items():
            for a, b in table.items():
                sub[(ftype == int(f)) & (sub == int(a))] = int(b)
        keep = ~np.isin(ftype, [int(f) for f in _SUMO_LEFT_OUT])
    return ftype * _SUBTYPES + sub, keep


STOP_SIGN_LIGHT = -2
"""In a light index (:attr:`RoadArrays.light_index`): a lane that a stop sign controls and no signal does; its
pieces carry the light code FLASHING_STOP, the signal that means what a stop sign means."""


def light_codes(traffic_lights, light_index: np.ndarray, frame: int) -> np.ndarray:
    """[R] the light codes of road pieces whose traffic-light lane index is ``light_index`` [R] (-1: none,
    :data:`STOP_SIGN_LIGHT`: a stop sign's lane) at ``frame`` (held at the scene's last frame beyond it): the
    signal's state, UNKNOWN where it is not logged then, FLASHING_STOP on a stop sign's lanes, NO_LIGHT on
    the other pieces without a signal."""
    light = np.full(len(light_index), NO_LIGHT, np.int64)
    light[light_index == STOP_SIGN_LIGHT] = int(SignalState.FLASHING_STOP)
    has = light_index >= 0
    if has.any():
        f = min(int(frame), traffic_lights.states.shape[0] - 1)
        li = light_index[has]
        light[has] = np.where(traffic_lights.present[f, li], traffic_lights.states[f, li], int(SignalState.UNKNOWN))
    return light


STOP_SIGN_REACH_M, STOP_SIGN_APPROACH_M = 5.0, 8.0
"""A stop sign without lane links (formats without lane topology, e.g. GPUDrive JSON) controls the lanes
that start within the first of these of it, and those that start where a lane ends within the second of it,
the sign on their right (see :func:`stop_sign_lanes`)."""


def stop_sign_lanes(road_map) -> np.ndarray:
    """Feature indices of the lanes that leave a stop sign's stop line, the ones its light code goes on (as a
    signal's goes on the lanes that cross the junction):

    * a STOP_SIGN_LANE link to a lane that starts at the sign (WOMD's convention): that lane;
    * a link to a lane that ends at the sign (the SUMO source's: the approach): the lanes that follow it;
    * a sign without links: the lanes that start within 5 m of it and those that start where a lane ends within
      8 m of it (:data:`STOP_SIGN_APPROACH_M`), the sign on their right and not more than 3 m behind. On the 6 real
      scenes whose signs are linked this finds 76% of the linked lanes, and 60% of what it finds is linked."""
    o = road_map.point_offsets
    first = road_map.points[o[:-1].clip(max=len(road_map.points) - 1), :2]  # [F, 2] each feature's first / last point
    last = road_map.points[(o[1:] - 1).clip(min=0), :2]
    links = road_map.link_indices(LinkType.STOP_SIGN_LANE)
    linked_xy = first[links[:, 0]]  # a sign's one point
    approach = np.linalg.norm(last[links[:, 1]] - linked_xy, axis=1) < np.linalg.norm(first[links[:, 1]] - linked_xy, axis=1)
    follow = road_map.link_indices(LinkType.SUCCESSOR)
    lanes = [links[~approach, 1], follow[np.isin(follow[:, 0], links[approach, 1]), 1]]
    signs = road_map.indices_of(MapFeatureType.STOP_SIGN)
    unlinked = signs[~np.isin(signs, links[:, 0])]
    cand = road_map.indices_of(MapFeatureType.LANE)
    cand = cand[np.diff(o)[cand] >= 2]
    if len(unlinked) and len(cand):
        unlinked_xy = first[unlinked]
        starts = _sign_on_right(first[cand], road_map.points[o[cand] + 1, :2] - first[cand], unlinked_xy, STOP_SIGN_REACH_M)
        ends = _sign_on_right(last[cand], last[cand] - road_map.points[o[cand + 1] - 2, :2], unlinked_xy, STOP_SIGN_APPROACH_M)
        joined = np.linalg.norm(first[cand][:, None] - last[cand][ends][None], axis=-1).min(1, initial=np.inf) <= 1.0
        lanes.append(cand[starts | joined])
    return np.unique(np.concatenate(lanes)).astype(np.int64)


def _sign_on_right(xy: np.ndarray, direction: np.ndarray, sign_xy: np.ndarray, reach_m: float) -> np.ndarray:
    """[L] bool: some sign of ``sign_xy`` [S, 2] lies within ``reach_m`` of point ``xy`` [L, 2], on the right of
    ``direction`` [L, 2] (or less than 0.5 m left of it) and not more than 3 m behind."""
    unit = direction / (np.linalg.norm(direction, axis=1, keepdims=True) + 1e-9)
    rel = sign_xy[None] - xy[:, None]  # [L, S, 2]
    ahead = (unit[:, None] * rel).sum(-1)
    left = unit[:, None, 0] * rel[..., 1] - unit[:, None, 1] * rel[..., 0]
    return ((np.linalg.norm(rel, axis=-1) <= reach_m) & (left < 0.5) & (ahead > -3.0)).any(1)


def _piece_light_index(scenario: Scenario, pieces, stop_signs: bool) -> np.ndarray:
    """[K] the pieces' traffic-light lane index; with ``stop_signs``, :data:`STOP_SIGN_LIGHT` on the lanes a stop
    sign controls (:func:`stop_sign_lanes`) where no signal does."""
    index = pieces.traffic_light_index
    if not stop_signs:
        return index
    stopped = stop_sign_lanes(scenario.road_map)
    on_stop_lane = np.isin(pieces.feature_index, stopped) & (pieces.feature_type == MapFeatureType.LANE) & (index < 0)
    return np.where(on_stop_lane, STOP_SIGN_LIGHT, index)


def scene_road(scenario: Scenario, road_vocab: RoadVocabulary, road: RoadSettings = RoadSettings()) -> RoadArrays:
    """Road pieces, their tokens, types (:func:`road_type_ids` of ``road.types``), light states (at the current
    frame; with ``road.stop_signs``, FLASHING_STOP on the lanes a stop sign controls and no signal does) and
    successor pairs."""
    pieces = road_pieces(scenario.road_map, scenario.traffic_lights)
    ids, _, _ = match_road_pieces(pieces.local, road_vocab) if pieces.num_pieces else (np.zeros(0, np.int64),) * 3
    light_index = _piece_light_index(scenario, pieces, road.stop_signs)
    light = light_codes(scenario.traffic_lights, light_index, scenario.current_frame)
    pairs, _ = road_successor_pairs(pieces, scenario.road_map)
    type_id, keep = road_type_ids(pieces.feature_type, pieces.feature_subtype, road.types)
    arrays = RoadArrays(local=pieces.local, pose=pieces.pose, type_id=type_id, light=light, token=ids, pairs=pairs,
                        light_index=light_index)
    return arrays if keep.all() else crop_road(arrays, keep)


def crop_road(road: RoadArrays, keep: np.ndarray) -> RoadArrays:
    """The pieces where ``keep`` [R] is true, successor pairs re-indexed (pairs touching a dropped piece go)."""
    new_index = np.cumsum(keep) - 1
    pk = keep[road.pairs[:, 0]] & keep[road.pairs[:, 1]] if len(road.pairs) else np.zeros(0, bool)
    return RoadArrays(local=road.local[keep], pose=road.pose[keep], type_id=road.type_id[keep], light=road.light[keep],
                      token=road.token[keep], pairs=new_index[road.pairs[pk]].reshape(-1, 2), light_index=road.light_index[keep])


def scene_tensors(scenario: Scenario, motion_vocab: MotionVocabulary, road: RoadArrays, noise_topk: int = 0,
                  road_mask_prob: float = 0.15, rng: np.random.Generator | int | None = None, motion_tokens=None,
                  road_keep_radius_m: float | None = None) -> dict[str, np.ndarray]:
    """One scene's unpadded arrays (see :class:`SmartBatch` for the meaning of each).

    Agents kept: those with at least one valid motion token (type OTHER never has one).
    ``motion_tokens`` may be given (already tokenized without noise) to skip the rolling matching.
    ``road_keep_radius_m``: drop road pieces farther than this from every valid agent pose. With
    ``map_radius_m + road_layers * road_radius_m`` this changes no agent's features (no dropped
    piece is reachable through map-agent and RoadNet attention), only the road task's piece set.
    """
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    mt = motion_tokens if motion_tokens is not None else tokenize_motion(scenario, motion_vocab, noise_topk=noise_topk, rng=rng)
    keep = np.flatnonzero(mt.valid.any(1))
    valid = mt.valid[keep]
    if road_keep_radius_m is not None and len(road.token):
        xy = mt.reached[keep][:, 1:][valid][:, :2]  # valid token end poses [M, 2]
        if len(xy):
            near = torch.cdist(torch.from_numpy(road.pose[:, :2]).float(), torch.from_numpy(xy).float()).amin(1) <= road_keep_radius_m
            road = crop_road(road, near.numpy())
        else:
            road = crop_road(road, np.zeros(len(road.token), bool))
    tr = scenario.tracks
    size = np.where(tr.valid[keep][..., None], tr.size[keep], np.nan)
    shape = np.nan_to_num(np.nanmedian(size, axis=1)) if len(keep) else np.zeros((0, 3))
    target = np.zeros_like(mt.ids[keep])
    target[:, :-1] = mt.nearest_ids[keep][:, 1:]
    target_valid = np.zeros_like(valid)
    target_valid[:, :-1] = valid[:, :-1] & valid[:, 1:]
    masked = rng.random(len(road.token)) < road_mask_prob
    return dict(
        agent_tokens=mt.ids[keep], agent_valid=valid, agent_type=mt.types[keep].astype(np.int64),
        agent_shape=shape.astype(np.float32), agent_start_pose=mt.start_pose[keep], agent_pose=mt.reached[keep][:, 1:],
        target_tokens=target, target_valid=target_valid,
        road_points=road.local, road_pose=road.pose, road_type=road.type_id, road_light=road.light,
        road_valid=np.ones(len(road.token), bool), road_token=road.token, road_masked=masked,
        road_pairs=road.pairs, road_pair_valid=np.ones(len(road.pairs), bool),
    )


_PAD_DIMS = {  # which leading dims are padded: "n" agents, "s" steps, "r" road pieces, "e" pairs
    "agent_tokens": "ns", "agent_valid": "ns", "agent_type": "n", "agent_shape": "n", "agent_start_pose": "ns",
    "agent_pose": "ns", "target_tokens": "ns", "target_valid": "ns", "road_points": "r", "road_pose": "r",
    "road_type": "r", "road_light": "r", "road_valid": "r", "road_token": "r", "road_masked": "r", "road_pairs": "e",
    "road_pair_valid": "e",
}


def collate_scenes(scenes: list[dict[str, np.ndarray]]) -> SmartBatch:
    """Pad per-scene arrays (from :func:`scene_tensors`) to the batch's largest N, S, R, E and stack."""
    if not scenes:
        raise ValueError("cannot collate an empty list of scenes")
    size = {
        "n": max(max(len(s["agent_type"]) for s in scenes), 1),
        "s": max(s["agent_tokens"].shape[1] if s["agent_tokens"].ndim == 2 else 0 for s in scenes) or 1,
        "r": max(max(len(s["road_token"]) for s in scenes), 1),
        "e": max(max(len(s["road_pairs"]) for s in scenes), 1),
    }
    out = {}
    for name, dims in _PAD_DIMS.items():
        first = np.asarray(scenes[0][name])
        trailing = first.shape[len(dims):]
        arr = np.zeros((len(scenes), *[size[d] for d in dims], *trailing), first.dtype)
        for i, s in enumerate(scenes):
            a = np.asarray(s[name])
            arr[(i, *[slice(0, a.shape[k]) for k in range(len(dims))])] = a.reshape(*a.shape[: len(dims)], *trailing)
        out[name] = torch.from_numpy(arr)
    return SmartBatch(**out)
