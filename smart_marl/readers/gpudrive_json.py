"""Reader: GPUDrive / Nocturne JSON scenes -> :class:`smart_marl.Scenario` (first stage of the flow).

One JSON file holds one WOMD-derived scene: ``objects`` (per-agent lists of ``position`` {x, y[, z]},
``heading``, ``velocity`` {x, y}, ``valid``, plus scalar ``width``/``length``[/``height``] and a
``type`` string), ``roads`` (typed polylines/polygons under ``geometry``), ``tl_states`` and, in
newer GPUDrive files, ``scenario_id`` and ``metadata``. What this reader decides, and why:

* **Flavour / ``source``.** Nocturne wrote ``name``, ``objects``, ``roads``, ``tl_states`` with 2-D
  points and headings in degrees; early GPUDrive wrote the same layout (so such files read as
  ``"nocturne"`` wherever they come from). Later GPUDrive converters added ``scenario_id``,
  ``metadata``, ``z`` coordinates, object ``id``/``height``/``mark_as_expert`` and road
  ``id``/``map_element_id``. A file carrying any of these reads as ``source="gpudrive"``.
* **Heading unit.** Converters that write object ``id`` also switched to radians wrapped to
  [-pi, pi]; the older ones wrote ``math.degrees(heading)`` unwrapped (values like 543.8). So:
  radians when the objects carry ``id`` and every valid heading lies within [-2 pi, 2 pi], degrees
  otherwise (``metadata["heading_unit_in_source"]`` says which). On the shared files this agrees
  with the direction of motion of moving agents to within 0.02 rad (median).
* **Ids.** Track ids are the objects' ``id`` when given, else their index; map feature ids are the
  roads' ``id`` when given, else their index.
* **Types.** ``vehicle``/``pedestrian``/``cyclist``; anything else (``other``, ``unset``) is OTHER.
* **Sizes.** ``length``, ``width`` (and ``height``) are one box per object (the converter takes the
  last valid state), repeated on every frame. Without ``height``, its type's
  :data:`~smart_marl.scenario.TYPICAL_BOX_M` height.
  A length or width of 0 on an object with a valid frame is missing (Nocturne files carry
  zero boxes: 23 of the 80 objects of one shared file, 14 vehicles and 9 pedestrians): the object gets
  the typical box of its type (:data:`~smart_marl.scenario.TYPICAL_BOX_M`), and ``metadata["default_box_ids"]``
  lists their track ids.
  Without ``z``, z = 0 (tracks and map alike).
* **Map subtypes.** From ``map_element_id`` when present (GPUDrive's Waymax-style codes: lanes 0-3,
  road lines 5-13, road edges 14-16, i.e. the WOMD codes shifted); otherwise UNDEFINED / UNKNOWN.
  The JSON has **no lane topology** (no entry/exit lanes, neighbours or stop-sign lanes): the
  RoadMap has no links.
* **Traffic lights.** ``tl_states`` maps a WOMD lane id to ``{"state": [names], "x": [...],
  "y": [...], "z": [...], "time_index": [...]}`` (frame indices); state names (``"stop"``,
  ``"arrow_go"``...) map onto :class:`SignalState`; the stop point is the lane's first reported one.
  Lane ids refer to road ids, so in files without road ids they may not resolve to a feature.
* **Roles.** ``metadata.sdc_track_index`` is the self-driving car (else -1),
  ``metadata.tracks_to_predict`` (track_index, difficulty) the tracks to predict,
  ``metadata.objects_of_interest`` (track ids) the objects of interest.
* **Time.** 10 Hz. The current frame is index 10 (WOMD's 1.1 s of history) for the 91-frame scenes
  these converters produce, ``min(10, T - 1)`` for any other length.
* **Scenario id.** ``scenario_id`` when given, else ``name`` without ``.json`` (Nocturne's ``name`` is
  the WOMD shard and index, e.g. ``tfrecord-00358-of-01000_65``), else the file stem.

Values on invalid frames (the converters write -1e4 or 1e-4 there) are replaced by zeros.
"""

from __future__ import annotations

import math
import os
from itertools import chain
from operator import itemgetter
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import ScenarioReadError
from ..scenario import (
    CURRENT_FRAME, DT_S, TYPICAL_BOX_M, AgentType, MapFeatureType, RoadMap, Scenario, SignalState, TrafficLights, Tracks,
    wrap_angle,
)
from ..values import as_int, as_integers
from .common import choose_frame, is_json_number, json_point, load_json_object, read_errors

NAME = "gpudrive_json"

_AGENT_TYPES = {"vehicle": AgentType.VEHICLE, "pedestrian": AgentType.PEDESTRIAN, "cyclist": AgentType.CYCLIST}

_ROAD_TYPES = {
    "lane": MapFeatureType.LANE,
    "road_line": MapFeatureType.ROAD_LINE,
    "road_edge": MapFeatureType.ROAD_EDGE,
    "stop_sign": MapFeatureType.STOP_SIGN,
    "crosswalk": MapFeatureType.CROSSWALK,
    "speed_bump": MapFeatureType.SPEED_BUMP,
    "driveway": MapFeatureType.DRIVEWAY,
}

# map_element_id (GPUDrive / Waymax codes) -> (first code, number of subtypes) per feature type
_SUBTYPE_CODES = {
    MapFeatureType.LANE: (0, 4),
    MapFeatureType.ROAD_LINE: (5, 9),
    MapFeatureType.ROAD_EDGE: (14, 3),
}

_OBJECT_FIELDS = ("position", "heading", "velocity", "valid", "width", "length", "type")
_GPUDRIVE_TOP_KEYS = ("scenario_id", "metadata")
_GPUDRIVE_OBJECT_KEYS = ("id", "height", "mark_as_expert")
_GPUDRIVE_ROAD_KEYS = ("id", "map_element_id")

_XY = itemgetter("x", "y")
_XYZ = itemgetter("x", "y", "z")

_SCAN_CHUNK_BYTES = 1 << 20
_SCAN_LIMIT_BYTES = 64 << 20


# ----------------------------------------------------------------------------------------- sniff
def sniff(path: str, head: bytes) -> bool:
    """A JSON object (``{`` after whitespace) with ``"objects"`` near its start; when the head does
    not show it, the file (``.json`` only) is scanned in chunks for both ``"objects"`` and
    ``"roads"`` (the roads come after megabytes of objects, so they are rarely in the head)."""
    text = head.lstrip()
    if not text.startswith(b"{"):
        return False
    if b'"objects"' in head[:1024] and (b'"roads"' in head or b'"position"' in head):
        return True
    if not str(path).lower().endswith(".json"):
        return False
    return _file_mentions(path, (b'"objects"', b'"roads"'))


def _file_mentions(path: str, needles: tuple[bytes, ...]) -> bool:
    found = set()
    tail = b""
    try:
        with open(path, "rb") as f:
            read = 0
            while read < _SCAN_LIMIT_BYTES:
                chunk = f.read(_SCAN_CHUNK_BYTES)
                if not chunk:
                    break
                read += len(chunk)
                window = tail + chunk
                found.update(n for n in needles if n in window)
                if len(found) == len(needles):
                    return True
                tail = window[-32:]
    except OSError:
        return False
    return False


# ------------------------------------------------------------------------------------------ read
def read(path: str | os.PathLike) -> Iterator[Scenario]:
    """Yield the one Scenario of a GPUDrive / Nocturne JSON file."""
    path = os.fspath(path)
    yield scenario_from_json(load_json_object(path), path)


def scenario_from_json(data: dict[str, Any], path: str = "<memory>") -> Scenario:
    """Build a Scenario from an already parsed GPUDrive / Nocturne JSON dict (see the module doc)."""
    for key in ("objects", "roads"):
        if key not in data:
            raise ScenarioReadError(path, f"missing top-level field '{key}'")
        if not isinstance(data[key], list):
            raise ScenarioReadError(path, f"'{key}' is a {type(data[key]).__name__}, expected a list", record=key)
    objects, roads = data["objects"], data["roads"]
    metadata_in = data.get("metadata") or {}
    if not isinstance(metadata_in, dict):
        raise ScenarioReadError(path, "'metadata' is not an object", record="metadata")

    track = _read_objects(objects, path)
    num_frames = track["valid"].shape[1]
    road = _read_roads(roads, path)
    flavour = _flavour(data, objects, roads, track["has_z"] or road["has_z"])

    current_frame = CURRENT_FRAME if num_frames > CURRENT_FRAME else num_frames - 1
    with read_errors(path, "metadata"):
        sdc_index = as_int(metadata_in.get("sdc_track_index", -1), "sdc_track_index")
    if not -1 <= sdc_index < len(objects):
        raise ScenarioReadError(path, f"sdc_track_index {sdc_index} outside [0, {len(objects)})", record="metadata")
    predict, difficulty = [], []
    to_predict = metadata_in.get("tracks_to_predict", []) or []
    if not isinstance(to_predict, list):
        raise ScenarioReadError(path, f"tracks_to_predict is a {type(to_predict).__name__}, expected a list", record="metadata")
    for k, entry in enumerate(to_predict):
        record = f"metadata.tracks_to_predict[{k}]"
        if isinstance(entry, dict) and "track_index" not in entry:
            raise ScenarioReadError(path, f"bad entry {entry!r}: no track_index", record=record)
        with read_errors(path, record):
            index = as_int(entry["track_index"] if isinstance(entry, dict) else entry, "track_index")
            difficulty.append(as_int(entry.get("difficulty", 0), "difficulty") if isinstance(entry, dict) else 0)
        if not 0 <= index < len(objects):
            raise ScenarioReadError(path, f"track_index {index} outside [0, {len(objects)})", record=record)
        predict.append(index)
    with read_errors(path, "metadata.objects_of_interest"):
        interest = as_integers(metadata_in.get("objects_of_interest", []) or [], np.int64, "objects_of_interest").reshape(-1)

    frame = choose_frame(track["position"], track["valid"], sdc_index, current_frame,
                         fallback=road["points"] if len(road["points"]) else None)
    origin = np.array([frame.x, frame.y, frame.z])
    position = np.where(track["valid"][..., None], track["position"] - origin, 0.0)

    lights = _read_traffic_lights(data.get("tl_states"), num_frames, origin, path)
    if data.get("scenario_id") is not None and not isinstance(data["scenario_id"], (str, int)):
        raise ScenarioReadError(path, f"scenario_id is a {type(data['scenario_id']).__name__}, expected a string",
                                record="scenario_id")
    scenario_id = data.get("scenario_id") or _strip_json(data.get("name")) or Path(path).stem
    meta: dict[str, Any] = {
        "source_path": os.path.abspath(path) if path != "<memory>" else path,
        "file_name": data.get("name") if isinstance(data.get("name"), str) else Path(path).name,
        "heading_unit_in_source": track["heading_unit"],
    }
    if track["experts"] is not None:
        meta["mark_as_expert_ids"] = track["experts"]
    if track["default_box"]:
        meta["default_box_ids"] = track["default_box"]

    with read_errors(path):
        return Scenario(
            scenario_id=str(scenario_id),
            source=flavour,
            timestamps_s=np.arange(num_frames) * DT_S,
            current_frame=current_frame,
            tracks=Tracks(ids=track["ids"], types=track["types"], position=position, heading=track["heading"],
                          velocity=track["velocity"], size=track["size"], valid=track["valid"]),
            road_map=RoadMap(
                ids=road["ids"], types=road["types"], subtypes=road["subtypes"],
                speed_limit_mph=np.zeros(len(road["ids"]), np.float32), interpolating=np.zeros(len(road["ids"]), bool),
                points=road["points"] - origin if len(road["points"]) else road["points"],
                point_offsets=road["offsets"], links=np.zeros((0, 2), np.int64), link_types=np.zeros(0, np.int8),
            ),
            traffic_lights=lights,
            sdc_index=sdc_index,
            predict_indices=np.asarray(predict, np.int64),
            predict_difficulty=np.asarray(difficulty, np.int64),
            objects_of_interest=interest,
            frame=frame,
            metadata=meta,
        )


def _strip_json(name: Any) -> str | None:
    if not isinstance(name, str) or not name:
        return None
    return name[:-5] if name.lower().endswith(".json") else name


def _flavour(data: dict, objects: list, roads: list, has_z: bool) -> str:
    if has_z or any(k in data for k in _GPUDRIVE_TOP_KEYS):
        return "gpudrive"
    if objects and any(k in objects[0] for k in _GPUDRIVE_OBJECT_KEYS):
        return "gpudrive"
    if roads and any(k in roads[0] for k in _GPUDRIVE_ROAD_KEYS):
        return "gpudrive"
    return "nocturne"


# --------------------------------------------------------------------------------------- objects
def _read_objects(objects: list, path: str) -> dict[str, Any]:
    n = len(objects)
    for i, obj in enumerate(objects):
        if not isinstance(obj, dict):
            raise ScenarioReadError(path, f"is a {type(obj).__name__}, expected an object", record=f"objects[{i}]")
        for key in _OBJECT_FIELDS:
            if key not in obj:
                raise ScenarioReadError(path, f"missing field '{key}'", record=f"objects[{i}]")
    if n == 0:
        num_frames = 0
    else:
        num_frames = len(objects[0]["valid"])
    for i, obj in enumerate(objects):
        for key in ("position", "heading", "velocity", "valid"):
            seq = obj[key]
            if not isinstance(seq, list) or len(seq) != num_frames:
                got = len(seq) if isinstance(seq, list) else type(seq).__name__
                raise ScenarioReadError(path, f"'{key}' has {got} entries, expected {num_frames} (as objects[0].valid)",
                                        record=f"objects[{i}]")
    if n and num_frames == 0:
        raise ScenarioReadError(path, "objects have no frames", record="objects[0]")

    all_pos = list(chain.from_iterable(o["position"] for o in objects))
    has_z = bool(all_pos) and all(isinstance(p, dict) and "z" in p for p in (all_pos[0], all_pos[-1]))
    position = np.zeros((n, num_frames, 3), np.float64)
    try:
        if has_z:
            position[:] = _numbers(list(map(_XYZ, all_pos))).reshape(n, num_frames, 3)
        else:
            position[..., :2] = _numbers(list(map(_XY, all_pos))).reshape(n, num_frames, 2)
    except (KeyError, TypeError, ValueError):
        position, has_z = _points_slow(objects, "position", num_frames, path)
    try:
        velocity = _numbers(list(map(_XY, chain.from_iterable(o["velocity"] for o in objects)))).reshape(n, num_frames, 2)
    except (KeyError, TypeError, ValueError):
        velocity = _points_slow(objects, "velocity", num_frames, path, dims=2)[0][..., :2]
    try:
        heading = _numbers([o["heading"] for o in objects]).reshape(n, num_frames)
    except (TypeError, ValueError) as exc:
        raise ScenarioReadError(path, f"'heading' holds a non-number: {exc}", record=_first_bad(objects, "heading")) from exc
    valid = np.array([o["valid"] for o in objects], dtype=None if n else bool).reshape(n, num_frames)
    if valid.dtype != np.bool_:  # JSON true/false give a boolean array; anything else is named
        for i, obj in enumerate(objects):
            for f, v in enumerate(obj["valid"]):
                if not isinstance(v, bool):
                    raise ScenarioReadError(path, f"valid[{f}] is {v!r}, expected true/false", record=f"objects[{i}]")
    for i, obj in enumerate(objects):
        if not isinstance(obj["type"], str):
            raise ScenarioReadError(path, f"'type' is {obj['type']!r}, expected a string", record=f"objects[{i}]")
    types = np.array([_AGENT_TYPES.get(o["type"], AgentType.OTHER) for o in objects], np.int8)
    try:
        length = _numbers([o["length"] for o in objects])
        width = _numbers([o["width"] for o in objects])
        height = _numbers([o.get("height", TYPICAL_BOX_M[AgentType(int(t))][2]) for o, t in zip(objects, types)])
        if length.shape != (n,) or width.shape != (n,) or height.shape != (n,):
            raise ValueError("one number per object expected")
    except (TypeError, ValueError) as exc:
        raise ScenarioReadError(path, f"a box size (length, width, height) is not a number: {exc}",
                                record=_first_bad(objects, "length", "width", "height")) from exc

    has_ids = n > 0 and all("id" in o for o in objects)
    ids = _unique_ids(objects, path, "objects", "object", "track id")

    # NaN / inf on valid frames: name the object, the field and the frame
    for name, values in (("position", position), ("velocity", velocity), ("heading", heading)):
        finite = np.isfinite(values) if values.ndim == 2 else np.isfinite(values).all(axis=-1)
        bad = valid & ~finite
        if bad.any():
            i, f = np.argwhere(bad)[0]
            raise ScenarioReadError(path, f"'{name}' is not finite on valid frame {int(f)}", record=f"objects[{int(i)}]")
    for name, values in (("length", length), ("width", width), ("height", height)):
        bad = ~np.isfinite(values) & valid.any(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ScenarioReadError(path, f"'{name}' is not finite", record=f"objects[{i}]")

    valid_heading = heading[valid]
    radians = has_ids and (valid_heading.size == 0 or float(np.abs(valid_heading).max()) <= 2 * math.pi + 1e-3)
    heading_rad = heading if radians else np.radians(heading)
    with np.errstate(invalid="ignore"):  # invalid frames may hold anything (checked finite on valid ones above)
        heading_rad = np.where(valid, wrap_angle(heading_rad), 0.0)
    empty = ((length == 0) | (width == 0)) & valid.any(axis=1)  # negative ones are refused (Tracks)
    default = np.array([TYPICAL_BOX_M[AgentType(int(t))][:2] for t in types], np.float64).reshape(n, 2)
    length, width = np.where(empty, default[:, 0], length), np.where(empty, default[:, 1], width)
    size = np.repeat(np.stack([length, width, height], axis=-1)[:, None, :], num_frames, axis=1)
    experts = [int(i) for i, o in zip(ids, objects) if o.get("mark_as_expert")] if any(
        "mark_as_expert" in o for o in objects) else None
    return {
        "ids": ids, "types": types, "position": position, "has_z": has_z, "valid": valid,
        "heading": heading_rad, "heading_unit": "radians" if radians else "degrees",
        "velocity": np.where(valid[..., None], velocity, 0.0), "size": size, "experts": experts,
        "default_box": [int(i) for i in ids[empty]],
    }


def _numbers(values: list) -> np.ndarray:
    """Numbers (nested lists of them) as float64; ValueError for strings, None or anything else."""
    a = np.array(values)
    if a.dtype.kind not in "iuf" and not (a.size == 0 and a.dtype.kind in "fO"):
        raise ValueError(f"expected numbers, found values of type {a.dtype}")
    return a.astype(np.float64)


def _unique_ids(items: list, path: str, key: str, noun: str, id_name: str) -> np.ndarray:
    """The ``id`` of every item of ``items`` (the JSON list ``key``) as int64, or 0..n-1 when no item
    has one; a read error naming the item when only some have one, one is not an integer, or two share one."""
    n = len(items)
    has_ids = n > 0 and all("id" in o for o in items)
    if n and not has_ids and any("id" in o for o in items):
        i = next(i for i, o in enumerate(items) if "id" not in o)
        raise ScenarioReadError(path, f"missing field 'id' (other {noun}s have one)", record=f"{key}[{i}]")
    with read_errors(path, key):
        ids = as_integers([o["id"] for o in items], np.int64, f"{noun} id") if has_ids else np.arange(n, dtype=np.int64)
    if ids.shape != (n,):
        raise ScenarioReadError(path, f"a {noun} id is not one integer", record=key)
    if len(np.unique(ids)) != n:
        uniq, counts = np.unique(ids, return_counts=True)
        dup = int(uniq[counts > 1][0])
        raise ScenarioReadError(path, f"{id_name} {dup} is used by more than one {noun}",
                                record=f"{key}[{int(np.flatnonzero(ids == dup)[1])}]")
    return ids


def _points_slow(objects: list, key: str, num_frames: int, path: str, dims: int = 3) -> tuple[np.ndarray, bool]:
    """Per-point reading, only to find and name a malformed point (the fast path failed)."""
    out = np.zeros((len(objects), num_frames, 3), np.float64)
    has_z = False
    for i, obj in enumerate(objects):
        for f, p in enumerate(obj[key]):
            x, y, z = json_point(p, path, f"objects[{i}].{key}[{f}]", with_z=dims == 3)
            out[i, f, 0], out[i, f, 1] = x, y
            if z is not None:
                out[i, f, 2] = z
                has_z = True
    return out, has_z


def _first_bad(objects: list, *keys: str) -> str:
    for i, obj in enumerate(objects):
        for key in keys:
            if key not in obj:
                continue
            try:
                _numbers(obj[key])
            except (TypeError, ValueError):
                return f"objects[{i}].{key}"
    return "objects"


# ----------------------------------------------------------------------------------------- roads
def _read_roads(roads: list, path: str) -> dict[str, Any]:
    f = len(roads)
    types = np.zeros(f, np.int8)
    subtypes = np.zeros(f, np.int8)
    lengths = np.zeros(f, np.int64)
    for i, road in enumerate(roads):
        record = f"roads[{i}]"
        if not isinstance(road, dict):
            raise ScenarioReadError(path, f"is a {type(road).__name__}, expected an object", record=record)
        for key in ("type", "geometry"):
            if key not in road:
                raise ScenarioReadError(path, f"missing field '{key}'", record=record)
        kind = _ROAD_TYPES.get(road["type"]) if isinstance(road["type"], str) else None
        if kind is None:
            raise ScenarioReadError(path, f"unknown road type {road['type']!r} (known: {', '.join(_ROAD_TYPES)})",
                                    record=record)
        types[i] = kind
        geometry = road["geometry"]
        if not isinstance(geometry, list) or not geometry:
            raise ScenarioReadError(path, "'geometry' has no points", record=record)
        lengths[i] = len(geometry)
        code = road.get("map_element_id")
        if kind in _SUBTYPE_CODES and isinstance(code, int):
            first, count = _SUBTYPE_CODES[kind]
            if first <= code < first + count:
                subtypes[i] = code - first

    ids = _unique_ids(roads, path, "roads", "road", "road id")

    all_points = list(chain.from_iterable(r["geometry"] for r in roads))
    has_z = bool(all_points) and isinstance(all_points[0], dict) and "z" in all_points[0]
    try:
        if has_z:
            points = _numbers(list(map(_XYZ, all_points))).reshape(-1, 3)
        else:
            xy = _numbers(list(map(_XY, all_points))).reshape(-1, 2)
            points = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
    except (KeyError, TypeError, ValueError):
        points, has_z = _road_points_slow(roads, path)
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        k = int(np.flatnonzero(~finite)[0])
        i = int(np.searchsorted(offsets, k, side="right") - 1)
        raise ScenarioReadError(path, f"geometry point {k - offsets[i]} is not finite", record=f"roads[{i}]")
    return {"ids": ids, "types": types, "subtypes": subtypes, "points": points, "offsets": offsets, "has_z": has_z}


def _road_points_slow(roads: list, path: str) -> tuple[np.ndarray, bool]:
    rows = []
    has_z = False
    for i, road in enumerate(roads):
        for k, p in enumerate(road["geometry"]):
            x, y, z = json_point(p, path, f"roads[{i}].geometry[{k}]")
            rows.append((x, y, 0.0 if z is None else z))
            has_z = has_z or z is not None
    return np.array(rows, np.float64).reshape(-1, 3), has_z


# -------------------------------------------------------------------------------- traffic lights
def _signal_state(name: Any) -> SignalState | None:
    if isinstance(name, int) and 0 <= name <= SignalState.FLASHING_CAUTION:
        return SignalState(name)
    if not isinstance(name, str):
        return None
    key = name.strip().upper()
    key = key[len("LANE_STATE_"):] if key.startswith("LANE_STATE_") else key
    return SignalState.__members__.get(key)


def _read_traffic_lights(tl_states: Any, num_frames: int, origin: np.ndarray, path: str) -> TrafficLights:
    if not tl_states:
        return TrafficLights.empty(num_frames)
    if not isinstance(tl_states, dict):
        raise ScenarioReadError(path, f"'tl_states' is a {type(tl_states).__name__}, expected an object keyed by lane id",
                                record="tl_states")
    lane_ids, stop_points = [], []
    states = np.zeros((num_frames, len(tl_states)), np.int8)
    present = np.zeros((num_frames, len(tl_states)), bool)
    for col, (lane_key, entry) in enumerate(tl_states.items()):
        record = f"tl_states[{lane_key}]"
        try:
            lane_ids.append(int(lane_key))
        except ValueError as exc:
            raise ScenarioReadError(path, f"lane id {lane_key!r} is not an integer", record=record) from exc
        if not isinstance(entry, dict):
            raise ScenarioReadError(path, f"is a {type(entry).__name__}, expected an object", record=record)
        for key in ("state", "time_index", "x", "y"):
            if key not in entry:
                raise ScenarioReadError(path, f"missing field '{key}'", record=record)
        names, frames = entry["state"], entry["time_index"]
        if not all(isinstance(entry[k], list) for k in ("state", "time_index", "x", "y")):
            raise ScenarioReadError(path, "state, time_index, x and y must be lists", record=record)
        if len(names) != len(frames):
            raise ScenarioReadError(path, f"{len(names)} states but {len(frames)} time indices", record=record)
        codes = [_signal_state(s) for s in names]
        if any(c is None for c in codes):
            bad = names[[c is None for c in codes].index(True)]
            raise ScenarioReadError(path, f"unknown signal state {bad!r}", record=record)
        with read_errors(path, record):
            frames = as_integers(frames, np.int64, "time_index").reshape(-1)
        if frames.size and (frames.min() < 0 or frames.max() >= num_frames):
            raise ScenarioReadError(path, f"time_index outside [0, {num_frames})", record=record)
        states[frames, col] = np.asarray(codes, np.int8)
        present[frames, col] = True
        if not entry["x"]:
            raise ScenarioReadError(path, "no stop point", record=record)
        z = entry.get("z") or [0.0]
        point = (entry["x"][0], entry["y"][0], z[0] if isinstance(z, list) else z)
        if not all(is_json_number(v) for v in point):
            raise ScenarioReadError(path, f"stop point {point!r} is not three numbers", record=record)
        stop_points.append(tuple(float(v) for v in point))
    if len(set(lane_ids)) != len(lane_ids):
        raise ScenarioReadError(path, "a lane appears twice", record="tl_states")
    with read_errors(path, "tl_states"):
        return TrafficLights(lane_ids=np.asarray(lane_ids, np.int64), states=states, present=present,
                             stop_points=np.asarray(stop_points, np.float64).reshape(-1, 3) - origin)
