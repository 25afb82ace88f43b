"""SMART reference preprocessed pickles -> :class:`smart_marl.Scenario` (reader stage).

The SMART reference code (rainmaker22/SMART, ``data_preprocess.py``) turns each WOMD scene into a
pickled dict of torch tensors: ``scenario_id``, ``city``, ``agent``, ``map_polygon``, ``map_point``,
``('map_point', 'to', 'map_polygon')`` and ``('map_polygon', 'to', 'map_polygon')``. Files are read
with the restricted unpickler (:mod:`.safe_pickle`; torch tensors are rebuilt with
``torch.load(weights_only=True)``), so torch is imported when such a file is read, never before.

What the preprocessing did, and how it is undone here:

* agents: only agents valid at the current frame (10) are kept. Their ``valid_mask`` is SMART's
  "vector" validity (frame 0 always False, history frame ``t`` valid only when ``t - 1`` also is);
  the recorded validity is recovered as "the box size was written on this frame" (the script writes
  position, heading, velocity and size exactly on the observed frames and zeros elsewhere), which
  reproduces ``valid_mask`` on frames 11.. and contains it everywhere. ``type`` 0/1/2/3 = vehicle /
  pedestrian / cyclist / background (-> OTHER); ``category == 3`` marks the tracks to predict;
  ``av_index`` is the self-driving car; ids are the WOMD track ids (stored as floats). Headings are
  wrapped to [-pi, pi).
* map: polygons are the WOMD lanes, road edges, road lines and crosswalks, in that order, without
  their WOMD ids (the polygon index is used as feature id). Each polygon's points are its polyline
  without the last point, plus the vector to the next point (``orientation``, ``magnitude``,
  ``height``); the last point is restored from the last vector. Point type 16 (CENTERLINE) -> LANE,
  12 (EDGE) -> ROAD_EDGE (boundary/median lost: UNKNOWN), 15 (CROSSWALK) -> CROSSWALK, the road-line
  point types -> ROAD_LINE with the WOMD line type they came from (SMART files WOMD
  SOLID_DOUBLE_WHITE as ``DOUBLE_DASH_WHITE`` and PASSING_DOUBLE_YELLOW as ``DASH_SOLID_YELLOW``;
  both are mapped back). Lane polygon types: VEHICLE -> SURFACE_STREET (SMART merges freeway and
  surface street), BIKE -> BIKE_LANE, BUS (SMART's name for WOMD's undefined lanes) -> UNDEFINED.
  Stop signs, speed bumps and driveways are not in these files.
* topology: an edge ``(j, i)`` of type PRED / SUCC / LEFT / RIGHT says that ``j`` is an entry lane /
  exit lane / left / right neighbour of lane ``i``: links ``(i, j)`` PREDECESSOR / SUCCESSOR /
  LEFT_NEIGHBOR / RIGHT_NEIGHBOR.
* traffic lights: one state per lane polygon (``light_type`` 0/1/2 = STOP / GO / CAUTION, taken by
  the preprocessing at frame 11, arrows and flashing lights folded in; 3 = unknown or no light). Lanes
  with a known state get a TrafficLights entry whose state is **held constant over all frames**
  (``metadata["traffic_light_state_held_constant"]``); their stop point is the lane's first point.
* time: 91 frames at 0.1 s, current frame 10. Positions are WOMD global coordinates, shifted into the
  local frame of :func:`smart_marl.readers.common.choose_frame`.
"""

from __future__ import annotations

import os
from typing import Any, Iterator, Mapping

import numpy as np

from ..errors import ScenarioReadError
from ..scenario import (
    CURRENT_FRAME,
    DT_S,
    AgentType,
    LaneType,
    LinkType,
    MapFeatureType,
    RoadEdgeType,
    RoadLineType,
    RoadMap,
    Scenario,
    SignalState,
    TrafficLights,
    Tracks,
    wrap_angle,
)
from ..values import as_floats, as_int, as_integers, as_mask
from .common import choose_frame, read_errors
from .safe_pickle import load_restricted, looks_like_pickle, smart_pickle_globals

NAME = "smart_pkl"

LIGHT_SOURCE_FRAME = 11
"""The frame whose light states the SMART preprocessing stored (``time_step == "11"``)."""

# SMART's _agent_types = ['vehicle', 'pedestrian', 'cyclist', 'background']
_AGENT_TYPE = np.array([AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST, AgentType.OTHER], np.int8)

# SMART's _point_types, index -> (MapFeatureType, subtype); -1: not a type these files use.
_POINT_TYPES = [
    ("DASH_SOLID_YELLOW", MapFeatureType.ROAD_LINE, RoadLineType.PASSING_DOUBLE_YELLOW),
    ("DASH_SOLID_WHITE", MapFeatureType.ROAD_LINE, RoadLineType.UNKNOWN),
    ("DASHED_WHITE", MapFeatureType.ROAD_LINE, RoadLineType.BROKEN_SINGLE_WHITE),
    ("DASHED_YELLOW", MapFeatureType.ROAD_LINE, RoadLineType.BROKEN_SINGLE_YELLOW),
    ("DOUBLE_SOLID_YELLOW", MapFeatureType.ROAD_LINE, RoadLineType.SOLID_DOUBLE_YELLOW),
    ("DOUBLE_SOLID_WHITE", MapFeatureType.ROAD_LINE, RoadLineType.SOLID_DOUBLE_WHITE),
    ("DOUBLE_DASH_YELLOW", MapFeatureType.ROAD_LINE, RoadLineType.BROKEN_DOUBLE_YELLOW),
    ("DOUBLE_DASH_WHITE", MapFeatureType.ROAD_LINE, RoadLineType.SOLID_DOUBLE_WHITE),  # SMART's name for it
    ("SOLID_YELLOW", MapFeatureType.ROAD_LINE, RoadLineType.SOLID_SINGLE_YELLOW),
    ("SOLID_WHITE", MapFeatureType.ROAD_LINE, RoadLineType.SOLID_SINGLE_WHITE),
    ("SOLID_DASH_WHITE", MapFeatureType.ROAD_LINE, RoadLineType.UNKNOWN),
    ("SOLID_DASH_YELLOW", MapFeatureType.ROAD_LINE, RoadLineType.UNKNOWN),
    ("EDGE", MapFeatureType.ROAD_EDGE, RoadEdgeType.UNKNOWN),
    ("NONE", MapFeatureType.ROAD_LINE, RoadLineType.UNKNOWN),
    ("UNKNOWN", MapFeatureType.ROAD_LINE, RoadLineType.UNKNOWN),
    ("CROSSWALK", MapFeatureType.CROSSWALK, 0),
    ("CENTERLINE", MapFeatureType.LANE, LaneType.UNDEFINED),
]
_POINT_FEATURE = np.array([t for _, t, _ in _POINT_TYPES], np.int8)
_POINT_SUBTYPE = np.array([int(s) for _, _, s in _POINT_TYPES], np.int8)
# SMART's _polygon_types = ['VEHICLE', 'BIKE', 'BUS', 'PEDESTRIAN'] -> lane subtype
_LANE_SUBTYPE = np.array([LaneType.SURFACE_STREET, LaneType.BIKE_LANE, LaneType.UNDEFINED, LaneType.UNDEFINED], np.int8)
# SMART's _polygon_light_type = ['LANE_STATE_STOP', 'LANE_STATE_GO', 'LANE_STATE_CAUTION', 'LANE_STATE_UNKNOWN']
_LIGHT_STATE = np.array([SignalState.STOP, SignalState.GO, SignalState.CAUTION, SignalState.UNKNOWN], np.int8)
# SMART's _polygon_to_polygon_types = ['NONE', 'PRED', 'SUCC', 'LEFT', 'RIGHT'] -> LinkType (-1: none)
_LINK_TYPE = np.array([-1, LinkType.PREDECESSOR, LinkType.SUCCESSOR, LinkType.LEFT_NEIGHBOR, LinkType.RIGHT_NEIGHBOR], np.int64)


def sniff(path: str, head: bytes) -> bool:
    """A pickle whose first bytes rebuild torch tensors and name SMART's ``agent`` fields."""
    return looks_like_pickle(head) and b"_rebuild_tensor_v2" in head and (b"av_index" in head or b"map_polygon" in head)


def read(path: str | os.PathLike) -> Iterator[Scenario]:
    """Yield the one Scenario of a SMART preprocessed pickle."""
    path = os.fspath(path)
    data = load_restricted(path, smart_pickle_globals())
    yield scenario_from_dict(data, path)


def _field(mapping: Any, key: Any, path: str, record: str) -> Any:
    if not isinstance(mapping, Mapping):
        raise ScenarioReadError(path, f"expected a dict, found {type(mapping).__name__}", record)
    if key not in mapping:
        raise ScenarioReadError(path, f"missing field {key!r}", record)
    return mapping[key]


def _array(mapping: Any, key: Any, path: str, record: str, shape: tuple, dtype=None) -> np.ndarray:
    """A field as numpy (torch tensors converted), checked against ``shape`` (None: any size)."""
    value = _field(mapping, key, path, record)
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    with read_errors(path, record):
        what = f"{key}"
        a = (np.asarray(value) if dtype is None else as_mask(value, what) if dtype is bool
             else as_integers(value, dtype, what) if np.dtype(dtype).kind in "iu" else as_floats(value, dtype, what))
    if a.ndim != len(shape) or any(s is not None and s != g for s, g in zip(shape, a.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ScenarioReadError(path, f"{key} has shape {list(a.shape)}, expected {want}", record)
    return a


def _count(mapping: Any, path: str, record: str) -> int:
    """A ``num_nodes`` field: a non-negative integer (a tensor of one, or a plain number)."""
    value = _field(mapping, "num_nodes", path, record)
    if hasattr(value, "detach") and value.numel() == 1:
        value = value.item()
    with read_errors(path, record):
        n = as_int(value, "num_nodes")
    if n < 0:
        raise ScenarioReadError(path, f"num_nodes is {n}", record)
    return n


def _agents(data: Mapping, path: str):
    """(ids, types, category, position, heading, velocity, shape, valid, self-driving car index) of the scene's
    agents, source coordinates; a read error where a valid frame holds a NaN or infinite value."""
    agent = _field(data, "agent", path, "scene")
    n = _count(agent, path, "agent")
    position = _array(agent, "position", path, "agent", (n, None, 3), np.float64)  # [N, T, 3]
    t = position.shape[1]
    heading = _array(agent, "heading", path, "agent", (n, t), np.float64)
    velocity = _array(agent, "velocity", path, "agent", (n, t, None), np.float64)[..., :2]
    shape = _array(agent, "shape", path, "agent", (n, t, 3), np.float64)
    vector_valid = _array(agent, "valid_mask", path, "agent", (n, t), bool)
    types = _array(agent, "type", path, "agent", (n,), np.int64)
    category = _array(agent, "category", path, "agent", (n,), np.int64)
    ids = _array(agent, "id", path, "agent", (n,), np.int64)  # stored as floats: whole numbers only
    if np.any((types < 0) | (types >= len(_AGENT_TYPE))):
        raise ScenarioReadError(path, f"agent type outside 0..{len(_AGENT_TYPE) - 1}", "agent")
    with read_errors(path, "agent"):
        sdc_index = as_int(_field(agent, "av_index", path, "agent"), "av_index")
    if not -1 <= sdc_index < n:
        raise ScenarioReadError(path, f"av_index {sdc_index} outside [0, {n})", "agent")

    observed = np.any(shape != 0, axis=-1)
    valid = observed | vector_valid
    for name, values in (("position", position), ("heading", heading), ("velocity", velocity), ("shape", shape)):
        finite = np.isfinite(values) if values.ndim == 2 else np.isfinite(values).all(axis=-1)
        bad = valid & ~finite
        if bad.any():
            i, f = np.argwhere(bad)[0]
            raise ScenarioReadError(path, f"agent {int(ids[i])}: {name} is NaN or infinite on "
                                    f"{int(bad[i].sum())} valid frame(s), first on frame {int(f)}", "agent")
    return ids, types, category, position, heading, velocity, shape, valid, sdc_index


def _map_features(data: Mapping, path: str):
    """The map's polygons as features: (kept polygon ids, point offsets, points with each polyline's end point
    restored, feature types, subtypes, lane mask, polygon count, light types of all polygons); points are grouped
    per polygon in their stored order."""
    polygon = _field(data, "map_polygon", path, "scene")
    num_polygons = _count(polygon, path, "map_polygon")
    polygon_type = _array(polygon, "type", path, "map_polygon", (num_polygons,), np.int64)
    light_type = _array(polygon, "light_type", path, "map_polygon", (num_polygons,), np.int64)
    point = _field(data, "map_point", path, "scene")
    p = _count(point, path, "map_point")
    pt_pos = _array(point, "position", path, "map_point", (p, 3), np.float64)
    pt_orient = _array(point, "orientation", path, "map_point", (p,), np.float64)
    pt_mag = _array(point, "magnitude", path, "map_point", (p,), np.float64)
    pt_height = (_array(point, "height", path, "map_point", (p,), np.float64) if "height" in point
                 else np.zeros(p))
    pt_type = _array(point, "type", path, "map_point", (p,), np.int64)
    key = ("map_point", "to", "map_polygon")
    pt_edges = _array(_field(data, key, path, "scene"), "edge_index", path, str(key), (2, p), np.int64)
    if np.any((pt_type < 0) | (pt_type >= len(_POINT_TYPES))):
        raise ScenarioReadError(path, f"map point type outside 0..{len(_POINT_TYPES) - 1}", "map_point")
    point_index, polygon_of_point = pt_edges
    if np.any((polygon_of_point < 0) | (polygon_of_point >= num_polygons)) or np.any((point_index < 0) | (point_index >= p)):
        raise ScenarioReadError(path, "point-to-polygon edge outside the points or polygons", str(key))
    for name, values in (("position", pt_pos), ("orientation", pt_orient), ("magnitude", pt_mag), ("height", pt_height)):
        if not np.isfinite(values).all():
            raise ScenarioReadError(path, f"map point {name} is not all finite", "map_point")
    order = np.lexsort((point_index, polygon_of_point))
    point_index, polygon_of_point = point_index[order], polygon_of_point[order]
    counts = np.bincount(polygon_of_point, minlength=num_polygons)
    kept = counts > 0  # a polygon without points cannot be drawn; none exist in SMART's output
    starts = np.concatenate([[0], np.cumsum(counts)])[:-1]
    last = point_index[starts[kept] + counts[kept] - 1]
    end_points = pt_pos[last] + np.stack([pt_mag[last] * np.cos(pt_orient[last]),
                                          pt_mag[last] * np.sin(pt_orient[last]), pt_height[last]], axis=-1)
    # Interleave: the stored points of polygon k, then its restored end point.
    kept_ids = np.flatnonzero(kept)
    new_counts = counts[kept] + 1
    offsets = np.concatenate([[0], np.cumsum(new_counts)]).astype(np.int64)
    points = np.empty((offsets[-1], 3))
    is_end = np.zeros(offsets[-1], bool)
    is_end[offsets[1:] - 1] = True
    points[~is_end] = pt_pos[point_index]
    points[is_end] = end_points

    first_type = pt_type[point_index[starts[kept]]]
    sorted_types = pt_type[point_index]
    mixed = (sorted_types[1:] != sorted_types[:-1]) & (polygon_of_point[1:] == polygon_of_point[:-1])
    if mixed.any():
        raise ScenarioReadError(path, f"map polygon {int(polygon_of_point[1:][mixed][0])} mixes point types", "map_point")
    feature_types = _POINT_FEATURE[first_type]
    subtypes = _POINT_SUBTYPE[first_type].copy()
    lane = feature_types == MapFeatureType.LANE
    ptype = polygon_type[kept_ids]
    if np.any((ptype < 0) | (ptype >= len(_LANE_SUBTYPE))):
        raise ScenarioReadError(path, f"polygon type outside 0..{len(_LANE_SUBTYPE) - 1}", "map_polygon")
    subtypes[lane] = _LANE_SUBTYPE[ptype[lane]]
    return kept_ids, offsets, points, feature_types, subtypes, lane, num_polygons, light_type


def _topology(data: Mapping, num_polygons: int, path: str) -> tuple[np.ndarray, np.ndarray]:
    """(links [E, 2] as (lane, its neighbour), their LinkType codes) of the polygon-to-polygon edges the map keeps."""
    key = ("map_polygon", "to", "map_polygon")
    topo = data.get(key, {})
    if topo:
        edge_index = _array(topo, "edge_index", path, str(key), (2, None), np.int64)
        edge_type = _array(topo, "type", path, str(key), (edge_index.shape[1],), np.int64)
    else:
        edge_index, edge_type = np.zeros((2, 0), np.int64), np.zeros(0, np.int64)
    if np.any((edge_type < 0) | (edge_type >= len(_LINK_TYPE))) or np.any((edge_index < 0) | (edge_index >= num_polygons)):
        raise ScenarioReadError(path, "polygon-to-polygon edge with an unknown type or polygon", str(key))
    link_type = _LINK_TYPE[edge_type]
    has_link = link_type >= 0
    links = np.stack([edge_index[1], edge_index[0]], axis=1)[has_link]  # (lane, its neighbour)
    return links, link_type[has_link]


def scenario_from_dict(data: Any, path: str) -> Scenario:
    """Build the Scenario of an already unpickled SMART scene dict (``path`` names it in errors)."""
    if not isinstance(data, Mapping):
        raise ScenarioReadError(path, f"the pickle holds a {type(data).__name__}, not a SMART scene dict")
    scenario_id = str(_field(data, "scenario_id", path, "scene"))

    ids, types, category, position, heading, velocity, shape, valid, sdc_index = _agents(data, path)
    t = position.shape[1]
    current = CURRENT_FRAME if t > CURRENT_FRAME else 0
    kept_ids, offsets, points, feature_types, subtypes, lane, num_polygons, light_type = _map_features(data, path)
    links, link_types = _topology(data, num_polygons, path)

    # ---- traffic lights: one state per lane, held over every frame
    if np.any((light_type < 0) | (light_type >= len(_LIGHT_STATE))):
        raise ScenarioReadError(path, f"light type outside 0..{len(_LIGHT_STATE) - 1}", "map_polygon")
    lit_lanes = np.flatnonzero((light_type[kept_ids] != 3) & lane)  # indices into the kept features
    light_polygons = kept_ids[lit_lanes]
    stop_points = points[offsets[lit_lanes]]

    # ---- local frame and assembly
    frame = choose_frame(position, valid, sdc_index, current, fallback=points if len(points) else None)
    origin = np.array([frame.x, frame.y, frame.z])
    category_ids = np.flatnonzero(category == 3)
    city = data.get("city")
    metadata: dict[str, Any] = {
        "path": os.path.abspath(path),
        "traffic_light_state_held_constant": True,
        "traffic_light_source_frame": LIGHT_SOURCE_FRAME,
        "map_feature_ids": "SMART polygon indices (the pickle has no WOMD map ids)",
    }
    if isinstance(city, (str, int, float, np.floating, np.integer)):
        metadata["city"] = city if isinstance(city, str) else float(city)
    with read_errors(path, "scene"):
        return Scenario(
            scenario_id=scenario_id,
            source=NAME,
            timestamps_s=DT_S * np.arange(t),
            current_frame=current,
            tracks=Tracks(
                ids=ids, types=_AGENT_TYPE[types], position=(position - origin).astype(np.float32),
                heading=wrap_angle(heading).astype(np.float32), velocity=velocity.astype(np.float32),
                size=shape.astype(np.float32), valid=valid,
            ),
            road_map=RoadMap(
                ids=kept_ids.astype(np.int64), types=feature_types, subtypes=subtypes,
                speed_limit_mph=np.zeros(len(kept_ids), np.float32), interpolating=np.zeros(len(kept_ids), bool),
                points=(points - origin).astype(np.float32), point_offsets=offsets,
                links=links.astype(np.int64).reshape(-1, 2), link_types=link_types.astype(np.int8),
            ),
            traffic_lights=TrafficLights(
                lane_ids=light_polygons.astype(np.int64),
                states=np.broadcast_to(_LIGHT_STATE[light_type[light_polygons]], (t, len(light_polygons))).copy(),
                present=np.ones((t, len(light_polygons)), bool),
                stop_points=(stop_points - origin).astype(np.float32).reshape(-1, 3),
            ),
            sdc_index=sdc_index,
            predict_indices=category_ids.astype(np.int64),
            frame=frame,
            metadata=metadata,
        )


__all__ = ["NAME", "sniff", "read", "scenario_from_dict"]
