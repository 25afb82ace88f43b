"""Environment stage, per-scene constants: what the environment precomputes once per scene.

What comes in: a :class:`~smart_marl.scenario.Scenario`. What goes out: a :class:`SceneStatic`
with the arrays every step reads (agent names and box sizes, the road points the observation
samples, the road-edge segments the offroad test uses, each track's logged route and goal, the
traffic-light stop points) so that a step does no per-scene Python work.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from smart_marl.geometry import RoadEdgeSegments
from smart_marl.geometry_torch import scene_road_edges
from smart_marl.scenario import Scenario
from smart_marl.tokens import MOTION_TYPES

ROAD_POINT_SPACING_M = 2.0  # road points kept for observations: about one every 2 m along each polyline


@dataclass
class SceneStatic:
    scenario: Scenario
    names: list[str]  # [N] "vehicle_1234"
    name_to_track: dict[str, int]
    types: np.ndarray  # [N] int64 AgentType
    is_motion: np.ndarray  # [N] bool, vehicle / pedestrian / cyclist
    controllable: np.ndarray  # [N] bool, a motion type valid at the current frame
    box_size: np.ndarray  # [N, 3] float64 length, width, height (median over valid frames)
    z: np.ndarray  # [N] float64, z at the last valid frame at or before the current frame
    road_xy: np.ndarray  # [P, 2] float64, road points (subsampled ~2 m)
    road_type: np.ndarray  # [P] int64 MapFeatureType
    road_edges: RoadEdgeSegments | None  # None when the scene has no road edge
    route_xy: np.ndarray  # [N, R, 2] float64, logged positions from the current frame on (padded)
    route_valid: np.ndarray  # [N, R] bool
    route_arc_m: np.ndarray  # [N, R] float64, arc length along the valid route points
    route_length_m: np.ndarray  # [N] float64
    goal_xy: np.ndarray  # [N, 2] float64, last valid logged position
    light_xy: np.ndarray  # [L, 2] float64, stop points of the signalised lanes

    @property
    def num_tracks(self) -> int:
        return len(self.names)


def _road_points(scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    rm = scenario.road_map
    if rm.num_features == 0 or len(rm.points) == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    feat = rm.point_feature_index()  # [P]
    pts = rm.points[:, :2].astype(np.float64)
    # keep a point when it is >= spacing from the last kept one along its feature (approximated by
    # cumulative arc length crossing a multiple of the spacing), plus every feature's first point
    seg = np.zeros(len(pts))
    same = feat[1:] == feat[:-1]
    seg[1:] = np.where(same, np.linalg.norm(pts[1:] - pts[:-1], axis=1), 0.0)
    arc = np.cumsum(seg)
    start_arc = arc[rm.point_offsets[:-1]][np.clip(feat, 0, rm.num_features - 1)]
    bucket = np.floor((arc - start_arc) / ROAD_POINT_SPACING_M).astype(np.int64)
    first = np.ones(len(pts), bool)
    first[1:] = ~same | (bucket[1:] != bucket[:-1])
    return pts[first], rm.types[feat[first]].astype(np.int64)


def scene_static(scenario: Scenario) -> SceneStatic:
    tr = scenario.tracks
    cf = scenario.current_frame
    names = tr.names()
    types = tr.types.astype(np.int64)
    is_motion = np.isin(types, [int(t) for t in MOTION_TYPES])
    z = tr.z_at(cf)
    # logged route: positions from the current frame to the end, valid frames only
    route_xy = tr.position[:, cf:, :2].astype(np.float64)
    route_valid = tr.valid[:, cf:].copy()
    step = np.zeros(route_valid.shape)
    if route_xy.shape[1] > 1:
        # arc length over valid points only: distance from each valid point to the previous valid one
        idx = np.where(route_valid, np.arange(route_valid.shape[1])[None], -1)
        prev = np.maximum.accumulate(idx, axis=1)
        prev_before = np.concatenate([np.full((len(prev), 1), -1), prev[:, :-1]], 1)
        has_prev = route_valid & (prev_before >= 0)
        pb = np.clip(prev_before, 0, None)
        d = np.linalg.norm(route_xy - np.take_along_axis(route_xy, pb[..., None], 1), axis=-1)
        step = np.where(has_prev, d, 0.0)
    arc = np.cumsum(step, axis=1)
    length = arc[:, -1] if arc.shape[1] else np.zeros(tr.num_tracks)
    any_valid = route_valid.any(1)
    last_valid = np.where(any_valid, route_valid.shape[1] - 1 - np.argmax(route_valid[:, ::-1], axis=1), 0)
    goal = route_xy[np.arange(tr.num_tracks), last_valid] if route_xy.shape[1] else np.zeros((tr.num_tracks, 2))
    road_xy, road_type = _road_points(scenario)
    return SceneStatic(
        scenario=scenario, names=names, name_to_track={n: i for i, n in enumerate(names)}, types=types, is_motion=is_motion,
        controllable=is_motion & tr.valid[:, cf], box_size=tr.box_size().astype(np.float64), z=z, road_xy=road_xy,
        road_type=road_type, road_edges=scene_road_edges(scenario.road_map), route_xy=route_xy, route_valid=route_valid, route_arc_m=arc,
        route_length_m=length, goal_xy=goal, light_xy=scenario.traffic_lights.stop_points[:, :2].astype(np.float64),
    )


__all__ = ["SceneStatic", "scene_static"]
