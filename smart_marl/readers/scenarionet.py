"""ScenarioNet / MetaDrive scenario-description pickles -> :class:`smart_marl.Scenario` (reader stage).

One file holds one scene: a dict with ``id``, ``version``, ``length``, ``metadata``, ``tracks``
(``{id: {type, state: {position, heading, velocity, length, width, height, valid}, metadata}}``),
``map_features`` (``{id: {type, polyline | polygon | position, entry_lanes, exit_lanes,
left_neighbor, right_neighbor, lane, speed_limit_mph | speed_limit_kmh, ...}}``) and
``dynamic_map_states`` (``{id: {state: {object_state: [T]}, lane, stop_point}}``). Formats 0.3
(``MetaDrive v0.3.x``) and 1.2 as well as ScenarioNet's nuScenes conversions (float validity masks,
``[T, 1]`` sizes, 2-D road lines, string ids) are read. Files are unpickled with the restricted
unpickler (:mod:`.safe_pickle`): only numpy arrays and plain containers.

Mapping onto the Scenario:

* agent types ``VEHICLE`` / ``PEDESTRIAN`` / ``CYCLIST`` (a ``TYPE_`` prefix is accepted); everything
  else (traffic cones, barriers, ``OTHER``, ``UNSET``...) is ``AgentType.OTHER``.
* ids: a track or map feature id that is a decimal number becomes that int; any other id (nuScenes
  tokens, ``"ego"``, ``"boundary_3"``) gets a stable int above the largest numeric id, in file order,
  and ``metadata["track_id_map"]`` / ``metadata["map_feature_id_map"]`` keep ``{str(int): original}``.
* map types: ``LANE_*`` -> LANE with :class:`LaneType` (``LANE_SURFACE_UNSTRUCTURE`` and other lanes
  -> UNDEFINED), ``ROAD_LINE_*`` -> ROAD_LINE with :class:`RoadLineType`, ``ROAD_EDGE_*`` -> ROAD_EDGE
  with :class:`RoadEdgeType` (``SIDEWALK`` -> UNKNOWN), ``CROSSWALK`` / ``SPEED_BUMP`` / ``DRIVEWAY``
  polygons, ``STOP_SIGN`` points linked to their lanes. Features of any other type are not kept; their
  counts are reported in ``metadata["skipped_map_features"]``. Lane speed limits are in mph
  (``speed_limit_kmh`` is converted).
* topology: ``exit_lanes`` -> SUCCESSOR, ``entry_lanes`` -> PREDECESSOR, ``left_neighbor`` /
  ``right_neighbor`` -> LEFT_NEIGHBOR / RIGHT_NEIGHBOR, stop sign ``lane`` -> STOP_SIGN_LANE.
* traffic lights: ``LANE_STATE_*`` strings map onto :class:`SignalState` by name, MetaDrive's
  ``TRAFFIC_LIGHT_RED / YELLOW / GREEN / UNKNOWN`` onto STOP / CAUTION / GO / UNKNOWN; a ``None``
  state means the light was not reported on that frame (``present`` False).
* time: ``metadata["ts"]`` when it has one entry per frame, else ``0.1 * arange``; the current frame
  is ``metadata["current_time_index"]`` when present, else :data:`~smart_marl.scenario.CURRENT_FRAME` (the WOMD /
  SMART convention of 11 history frames; nuScenes conversions carry no current frame). Every frame of
  the file is kept (20 s nuScenes and Waymo 1.2 scenes included).
* space: positions are shifted into the local frame of :func:`smart_marl.readers.common.choose_frame`
  (the self-driving car at the current frame), headings and velocities are unchanged.
"""

from __future__ import annotations

import os
import re
from collections import Counter
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
)
from ..values import as_floats, as_int, as_mask
from .common import choose_frame, read_errors
from .safe_pickle import SCENARIONET_GLOBALS, load_restricted, looks_like_pickle

NAME = "scenarionet"

_KMH_PER_MPH = 1.609344

_AGENT_TYPES = {"VEHICLE": AgentType.VEHICLE, "PEDESTRIAN": AgentType.PEDESTRIAN, "CYCLIST": AgentType.CYCLIST}
_LANE_TYPES = {"LANE_FREEWAY": LaneType.FREEWAY, "LANE_SURFACE_STREET": LaneType.SURFACE_STREET,
               "LANE_BIKE_LANE": LaneType.BIKE_LANE}
_POLYGON_TYPES = {"CROSSWALK": MapFeatureType.CROSSWALK, "SPEED_BUMP": MapFeatureType.SPEED_BUMP,
                  "DRIVEWAY": MapFeatureType.DRIVEWAY}
_SIGNAL_ALIASES = {"RED": SignalState.STOP, "YELLOW": SignalState.CAUTION, "GREEN": SignalState.GO}

# Markers of the top-level dict keys: ScenarioNet writes id, version, length and then tracks or
# metadata, so one of those names falls in the first few hundred bytes.
_HEAD_KEYS = (b"tracks", b"metadata", b"map_features", b"dynamic_map_states")


def sniff(path: str, head: bytes) -> bool:
    """A pickle (protocol >= 2) whose first bytes name ScenarioNet's top-level keys and no torch class."""
    return (looks_like_pickle(head) and b"version" in head and any(k in head for k in _HEAD_KEYS)
            and b"torch" not in head)


def read(path: str | os.PathLike) -> Iterator[Scenario]:
    """Yield the one Scenario of a ScenarioNet pickle."""
    path = os.fspath(path)
    data = load_restricted(path, SCENARIONET_GLOBALS)
    yield scenario_from_dict(data, path)


# ------------------------------------------------------------------------------------- helpers
class _IdMap:
    """Source ids (str or int) -> unique int64 ids: decimal ids keep their value, others get new ints."""

    _NUMERIC = re.compile(r"-?\d{1,18}")

    def __init__(self, keys) -> None:
        self._ids: dict[str, int] = {}
        self.assigned: dict[str, str] = {}  # str(new int) -> original id
        numeric = [k for k in map(str, keys) if self._NUMERIC.fullmatch(k)]
        used: set[int] = set()
        for k in numeric:
            value = int(k)
            if value not in used:
                self._ids[k] = value
                used.add(value)
        self._next = max(used) + 1 if used else 0
        self._used = used
        for k in map(str, keys):
            self.get(k)

    def get(self, key: Any) -> int:
        k = str(key)
        value = self._ids.get(k)
        if value is None:
            if self._NUMERIC.fullmatch(k) and int(k) not in self._used:
                value = int(k)
            else:
                while self._next in self._used:
                    self._next += 1
                value = self._next
                self.assigned[str(value)] = k
            self._ids[k] = value
            self._used.add(value)
        return value


def _need(mapping: Any, key: str, path: str, record: str) -> Any:
    if not isinstance(mapping, Mapping):
        raise ScenarioReadError(path, f"expected a dict, found {type(mapping).__name__}", record)
    if key not in mapping:
        raise ScenarioReadError(path, f"missing field '{key}'", record)
    return mapping[key]


def _as_float(value: Any, path: str, record: str) -> np.ndarray:
    with read_errors(path, record):
        return as_floats(value, np.float64, "not numeric")


def _number(value: Any, path: str, record: str, what: str) -> float:
    a = _as_float(value, path, record)
    if a.shape != () or not np.isfinite(a):
        raise ScenarioReadError(path, f"{what} is {value!r}, expected one finite number", record)
    return float(a)


def _per_frame(value: Any, num_frames: int, path: str, record: str, width: int | None = None) -> np.ndarray:
    """A per-frame array [T] (width None) or [T, width]; [T, 1] and scalars broadcast, missing columns
    of [T, 2] positions become 0 (z)."""
    a = _as_float(value, path, record)
    if width is None:
        if a.ndim == 2 and a.shape[1] == 1:
            a = a[:, 0]
        if a.ndim == 0:
            a = np.full(num_frames, float(a))
        if a.shape != (num_frames,):
            raise ScenarioReadError(path, f"has shape {a.shape}, expected ({num_frames},)", record)
        return a
    if width == 3 and a.ndim == 2 and a.shape[0] == num_frames and a.shape[1] == 2:
        a = np.concatenate([a, np.zeros((num_frames, 1))], axis=1)
    if a.ndim != 2 or a.shape[0] != num_frames or a.shape[1] < width:
        raise ScenarioReadError(path, f"has shape {a.shape}, expected ({num_frames}, {width})", record)
    return a[:, :width]


def _points(value: Any, path: str, record: str) -> np.ndarray:
    a = _as_float(value, path, record)
    if a.ndim == 1 and a.shape[0] in (2, 3):
        a = a[None]
    if a.ndim != 2 or a.shape[1] < 2:
        raise ScenarioReadError(path, f"points have shape {a.shape}, expected [n, 2 or 3]", record)
    if a.shape[1] == 2:
        a = np.concatenate([a, np.zeros((len(a), 1))], axis=1)
    a = a[:, :3]
    if not np.isfinite(a).all():
        raise ScenarioReadError(path, "points are not all finite", record)
    return a


def _subtype(enum, name: str, default) -> int:
    return int(enum[name]) if name in enum.__members__ else int(default)


def _signal_code(state: Any) -> int:
    """SignalState code of a MetaDrive light state, -1 for 'not reported', -2 for unrecognised."""
    if state is None or state == "None":
        return -1
    if isinstance(state, (int, np.integer)) and 0 <= int(state) <= SignalState.FLASHING_CAUTION:
        return int(state)
    name = str(state)
    for prefix in ("LANE_STATE_", "TRAFFIC_LIGHT_"):
        if name.startswith(prefix):
            name = name[len(prefix):]
            break
    if name in SignalState.__members__:
        return int(SignalState[name])
    return int(_SIGNAL_ALIASES[name]) if name in _SIGNAL_ALIASES else -2


# ------------------------------------------------------------------------------------- the scene
def _frames(meta: Mapping, tracks_in: Mapping, track_keys: list, path: str) -> tuple[int, np.ndarray, int]:
    """(frame count, [T] timestamps, current frame) of a scene: the frames of its first track's positions,
    ``metadata/ts`` when it fits, ``current_time_index`` or the WOMD default."""
    first_state = _need(tracks_in[track_keys[0]], "state", path, f"tracks/{track_keys[0]}")
    first_position = _as_float(_need(first_state, "position", path, f"tracks/{track_keys[0]}/state"), path,
                               f"tracks/{track_keys[0]}/state/position")
    if first_position.ndim == 0:
        raise ScenarioReadError(path, "position is a single number, expected one row per frame", f"tracks/{track_keys[0]}/state")
    num_frames = int(first_position.shape[0])
    ts = meta.get("ts")
    ts = None if ts is None else _as_float(ts, path, "metadata/ts").reshape(-1)
    timestamps = ts if ts is not None and ts.shape == (num_frames,) and np.isfinite(ts).all() else DT_S * np.arange(num_frames)
    current = meta.get("current_time_index")
    if current is None:
        current = CURRENT_FRAME if num_frames > CURRENT_FRAME else 0
    with read_errors(path, "metadata"):
        current = as_int(current, "current_time_index")
    if not 0 <= current < num_frames:
        raise ScenarioReadError(path, f"current_time_index {current} outside [0, {num_frames})", "metadata")
    return num_frames, timestamps, current


def _tracks(tracks_in: Mapping, track_keys: list, num_frames: int, path: str):
    """(position, heading, velocity, size, valid, types) of every track, dense [N, T, ...] in source coordinates;
    a read error where a valid frame holds a NaN or infinite value."""
    # one small array per track and field, stacked once
    n = len(track_keys)
    position = np.empty((n, num_frames, 3))
    heading = np.empty((n, num_frames))
    velocity = np.empty((n, num_frames, 2))
    size = np.empty((n, num_frames, 3))
    valid = np.empty((n, num_frames), bool)
    types = np.empty(n, np.int8)
    for i, key in enumerate(track_keys):
        record = f"tracks/{key}"
        track = tracks_in[key]
        state = _need(track, "state", path, record)
        srec = record + "/state"
        with read_errors(path, srec):
            valid_raw = as_mask(_need(state, "valid", path, srec), "valid")
        if valid_raw.shape not in ((num_frames,), (num_frames, 1)):
            raise ScenarioReadError(path, f"valid has shape {valid_raw.shape}, expected ({num_frames},)", srec)
        valid[i] = valid_raw.reshape(num_frames)
        position[i] = _per_frame(_need(state, "position", path, srec), num_frames, path, srec + "/position", 3)
        heading[i] = _per_frame(_need(state, "heading", path, srec), num_frames, path, srec + "/heading")
        if "velocity" in state:
            velocity[i] = _per_frame(state["velocity"], num_frames, path, srec + "/velocity", 2)
        else:  # finite differences of the positions (the first frame repeats the second)
            v = np.gradient(position[i, :, :2], axis=0) / DT_S if num_frames > 1 else np.zeros((num_frames, 2))
            velocity[i] = v
        size[i, :, 0] = _per_frame(_need(state, "length", path, srec), num_frames, path, srec + "/length")
        size[i, :, 1] = _per_frame(_need(state, "width", path, srec), num_frames, path, srec + "/width")
        size[i, :, 2] = (_per_frame(state["height"], num_frames, path, srec + "/height")
                         if "height" in state else 0.0)
        type_name = str(track.get("type", "")) if isinstance(track, Mapping) else ""
        type_name = type_name[5:] if type_name.startswith("TYPE_") else type_name
        types[i] = _AGENT_TYPES.get(type_name, AgentType.OTHER)

    for name, values in (("position", position), ("heading", heading), ("velocity", velocity), ("size", size)):
        finite = np.isfinite(values) if values.ndim == 2 else np.isfinite(values).all(axis=-1)
        bad = valid & ~finite
        if bad.any():
            i, f = np.argwhere(bad)[0]
            raise ScenarioReadError(
                path, f"track {track_keys[i]!s}: {name} is NaN or infinite on {int(bad[i].sum())} valid frame(s), "
                f"first on frame {int(f)}", f"tracks/{track_keys[i]}")
    return position, heading, velocity, size, valid, types


def _roles(meta: Mapping, track_keys: list, track_ids: "_IdMap", path: str):
    """(track ids, self-driving car index, tracks to predict, their difficulties, objects of interest) from the metadata."""
    ids = np.array([track_ids.get(k) for k in track_keys], np.int64)
    index_of_key = {str(k): i for i, k in enumerate(track_keys)}
    sdc_key = meta.get("sdc_id")
    sdc_index = index_of_key.get(str(sdc_key), -1) if sdc_key is not None else -1
    if sdc_key is not None and sdc_index < 0:  # a named self-driving car that is not there is a broken file, not "none"
        raise ScenarioReadError(path, f"sdc_id {sdc_key!r} names no track (tracks: {list(index_of_key)[:5]}...)", "metadata")

    predict, difficulty = [], []
    to_predict = meta.get("tracks_to_predict") or {}
    if not isinstance(to_predict, Mapping):
        raise ScenarioReadError(path, f"tracks_to_predict is a {type(to_predict).__name__}, expected a dict", "metadata")
    for key, info in to_predict.items():
        tid = str(info.get("track_id", key)) if isinstance(info, Mapping) else str(key)
        if tid not in index_of_key:
            raise ScenarioReadError(path, f"track to predict {tid} is not among the tracks", "metadata/tracks_to_predict")
        predict.append(index_of_key[tid])
        with read_errors(path, f"metadata/tracks_to_predict/{key}"):
            difficulty.append(as_int(info.get("difficulty", 0), "difficulty") if isinstance(info, Mapping) else 0)
    interest_in = meta.get("objects_of_interest") or []
    if not isinstance(interest_in, (list, tuple, np.ndarray)):
        raise ScenarioReadError(path, f"objects_of_interest is a {type(interest_in).__name__}, expected a list", "metadata")
    interest = np.array([track_ids.get(k) for k in interest_in], np.int64)
    return ids, sdc_index, predict, difficulty, interest


def _road_map(features_in: Mapping, feature_ids: "_IdMap", path: str):
    """The map features kept (ids, types, subtypes, speed limits, interpolating flags, point lists), their links and
    the feature types skipped, counted."""
    feature_keys = list(features_in.keys())
    f_ids, f_types, f_sub, f_speed, f_interp, f_points = [], [], [], [], [], []
    links: list[tuple[int, int, int]] = []
    skipped: Counter = Counter()
    for key in feature_keys:
        record = f"map_features/{key}"
        feat = features_in[key]
        type_name = str(_need(feat, "type", path, record))
        fid = feature_ids.get(key)
        subtype, speed_mph, interpolating = 0, 0.0, False
        if type_name.startswith("LANE"):
            ftype = MapFeatureType.LANE
            subtype = int(_LANE_TYPES.get(type_name, LaneType.UNDEFINED))
            pts = _need(feat, "polyline", path, record)
            if feat.get("speed_limit_mph") is not None:
                speed_mph = _number(feat["speed_limit_mph"], path, record, "speed_limit_mph")
            elif feat.get("speed_limit_kmh") is not None:
                speed_mph = _number(feat["speed_limit_kmh"], path, record, "speed_limit_kmh") / _KMH_PER_MPH
            interpolating = bool(feat.get("interpolating", False))
            for field, link in (("exit_lanes", LinkType.SUCCESSOR), ("entry_lanes", LinkType.PREDECESSOR)):
                links.extend((fid, feature_ids.get(other), int(link)) for other in feat.get(field) or ())
            for field, link in (("left_neighbor", LinkType.LEFT_NEIGHBOR), ("right_neighbor", LinkType.RIGHT_NEIGHBOR)):
                for other in feat.get(field) or ():
                    other = other.get("feature_id") if isinstance(other, Mapping) else other
                    if other is None:
                        raise ScenarioReadError(path, f"{field} entry without a feature_id", record)
                    links.append((fid, feature_ids.get(other), int(link)))
        elif type_name.startswith("ROAD_LINE"):
            ftype = MapFeatureType.ROAD_LINE
            subtype = _subtype(RoadLineType, type_name[len("ROAD_LINE_"):], RoadLineType.UNKNOWN)
            pts = _need(feat, "polyline", path, record)
        elif type_name.startswith("ROAD_EDGE"):
            ftype = MapFeatureType.ROAD_EDGE
            subtype = _subtype(RoadEdgeType, type_name[len("ROAD_EDGE_"):], RoadEdgeType.UNKNOWN)
            pts = _need(feat, "polyline", path, record)
        elif type_name in _POLYGON_TYPES:
            ftype = _POLYGON_TYPES[type_name]
            pts = feat["polygon"] if "polygon" in feat else _need(feat, "polyline", path, record)
        elif type_name == "STOP_SIGN":
            ftype = MapFeatureType.STOP_SIGN
            pts = _need(feat, "position", path, record)
            links.extend((fid, feature_ids.get(lane), int(LinkType.STOP_SIGN_LANE)) for lane in feat.get("lane") or ())
        else:
            skipped[type_name] += 1
            continue
        points = _points(pts, path, record)
        if len(points) == 0:
            skipped[f"{type_name} without points"] += 1
            continue
        f_ids.append(fid)
        f_types.append(int(ftype))
        f_sub.append(subtype)
        f_speed.append(speed_mph)
        f_interp.append(interpolating)
        f_points.append(points)
    return (f_ids, f_types, f_sub, f_speed, f_interp, f_points), links, skipped


def _lights(lights_in: Mapping, feature_ids: "_IdMap", num_frames: int, path: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Lane id -> ([T] signal codes, -1 where unreported; stop point [3]) of every traffic light entry."""
    light_rows: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # lane id -> (codes [T], stop point [3])
    for key, light in lights_in.items():
        record = f"dynamic_map_states/{key}"
        lane = light.get("lane", key) if isinstance(light, Mapping) else key
        states = _need(_need(light, "state", path, record), "object_state", path, record + "/state")
        states = list(states)[:num_frames]
        states += [None] * (num_frames - len(states))
        labels, inverse = np.unique(np.array([str(s) for s in states], dtype=object), return_inverse=True)
        codes = np.array([_signal_code(None if s == "None" else s) for s in labels], np.int64)
        if (codes == -2).any():
            raise ScenarioReadError(path, f"unknown traffic light state {labels[codes == -2][0]!r}", record)
        per_frame = codes[inverse]
        stop_point = _points(_need(light, "stop_point", path, record), path, record + "/stop_point")[0]
        lane_id = feature_ids.get(lane)
        if lane_id in light_rows:  # a second entry for one lane: fill the frames it reports
            old_codes = light_rows[lane_id][0]
            per_frame = np.where(per_frame >= 0, per_frame, old_codes)
        light_rows[lane_id] = (per_frame, stop_point)
    return light_rows


def _metadata(data: Mapping, meta: Mapping, path: str, track_ids: "_IdMap", feature_ids: "_IdMap", skipped: Counter) -> dict[str, Any]:
    """The Scenario's metadata: version, dataset, path, the source's descriptive keys, the id maps and skipped features."""
    metadata: dict[str, Any] = {
        "version": str(data.get("version", "")),
        "dataset": str(meta.get("dataset", "")),
        "path": os.path.abspath(path),
    }
    for key in ("source_file", "map", "coordinate", "date"):
        if isinstance(meta.get(key), (str, int, float)):
            metadata[key] = meta[key]
    if track_ids.assigned:
        metadata["track_id_map"] = dict(track_ids.assigned)
    if feature_ids.assigned:
        metadata["map_feature_id_map"] = dict(feature_ids.assigned)
    if skipped:
        metadata["skipped_map_features"] = dict(skipped)
    return metadata


def scenario_from_dict(data: Any, path: str) -> Scenario:
    """Build the Scenario of an already unpickled ScenarioNet scene dict (``path`` names it in errors)."""
    if not isinstance(data, Mapping):
        raise ScenarioReadError(path, f"the pickle holds a {type(data).__name__}, not a ScenarioNet scene dict")
    meta = _need(data, "metadata", path, "scene")
    tracks_in = _need(data, "tracks", path, "scene")
    features_in = _need(data, "map_features", path, "scene")
    lights_in = data.get("dynamic_map_states") or {}
    if not isinstance(meta, Mapping) or not isinstance(tracks_in, Mapping) or not isinstance(features_in, Mapping) \
            or not isinstance(lights_in, Mapping):
        raise ScenarioReadError(path, "metadata, tracks, map_features and dynamic_map_states must be dicts", "scene")

    track_keys = list(tracks_in.keys())
    if not track_keys:
        raise ScenarioReadError(path, "the scene has no tracks", "tracks")
    track_ids = _IdMap(track_keys)

    num_frames, timestamps, current = _frames(meta, tracks_in, track_keys, path)
    position, heading, velocity, size, valid, types = _tracks(tracks_in, track_keys, num_frames, path)
    ids, sdc_index, predict, difficulty, interest = _roles(meta, track_keys, track_ids, path)
    feature_ids = _IdMap(list(features_in.keys()))
    (f_ids, f_types, f_sub, f_speed, f_interp, f_points), links, skipped = _road_map(features_in, feature_ids, path)
    map_points = np.concatenate(f_points) if f_points else np.zeros((0, 3))
    lengths = np.array([len(p) for p in f_points], np.int64)
    light_rows = _lights(lights_in, feature_ids, num_frames, path)

    # ---- local frame and assembly
    frame = choose_frame(position, valid, sdc_index, current, fallback=map_points if len(map_points) else None)
    origin = np.array([frame.x, frame.y, frame.z])
    lane_ids = np.array(list(light_rows.keys()), np.int64)
    codes = np.stack([row[0] for row in light_rows.values()], axis=1) if light_rows else np.zeros((num_frames, 0), np.int64)
    stops = np.stack([row[1] for row in light_rows.values()]) if light_rows else np.zeros((0, 3))

    metadata = _metadata(data, meta, path, track_ids, feature_ids, skipped)
    dataset = str(meta.get("dataset") or "").lower()
    scenario_id = meta.get("scenario_id") or data.get("id") or meta.get("id") or os.path.basename(path)
    with read_errors(path, "scene"):
        return Scenario(
            scenario_id=str(scenario_id),
            source=f"scenarionet/{dataset}" if dataset else "scenarionet",
            timestamps_s=timestamps,
            current_frame=current,
            tracks=Tracks(
                ids=ids, types=types, position=(position - origin).astype(np.float32),
                heading=heading.astype(np.float32), velocity=velocity.astype(np.float32),
                size=size.astype(np.float32), valid=valid,
            ),
            road_map=RoadMap(
                ids=np.array(f_ids, np.int64), types=np.array(f_types, np.int8), subtypes=np.array(f_sub, np.int8),
                speed_limit_mph=np.array(f_speed, np.float32), interpolating=np.array(f_interp, bool),
                points=(map_points - origin).astype(np.float32),
                point_offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
                links=np.array([(a, b) for a, b, _ in links], np.int64).reshape(-1, 2),
                link_types=np.array([t for _, _, t in links], np.int8),
            ),
            traffic_lights=TrafficLights(
                lane_ids=lane_ids, states=np.maximum(codes, 0).astype(np.int8), present=codes >= 0,
                stop_points=(stops - origin).astype(np.float32).reshape(-1, 3),
            ),
            sdc_index=sdc_index,
            predict_indices=np.array(predict, np.int64),
            predict_difficulty=np.array(difficulty, np.int64),
            objects_of_interest=interest,
            frame=frame,
            metadata=metadata,
        )


__all__ = ["NAME", "sniff", "read", "scenario_from_dict"]
