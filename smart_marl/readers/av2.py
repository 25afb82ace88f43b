"""Reader: Argoverse 2 motion-forecasting scenarios -> :class:`smart_marl.Scenario` (first stage).

An AV2 scenario is two files in one directory: ``scenario_<id>.parquet`` (one row per track and
observed timestep) and ``log_map_archive_<id>.json`` (the local vector map). Needs ``pyarrow``
(``pip install 'smart-marl[av2]'``), imported only when a file is read. What this reader decides:

* **Time.** ``timestep`` is the frame index (110 frames at 10 Hz, 11 s); the current frame is 49,
  the last of AV2's 5 s of history (``min(49, T - 1)`` for other lengths). A frame is valid where
  the track has a row. (AV2's ``observed`` column marks the history part, not validity.)
* **Tracks.** ``track_id`` strings become int64 ids: decimal ids keep their value; the others
  (``"AV"``) get ``max(decimal ids) + 1 + rank`` in sorted order. ``metadata["track_id_map"]``
  maps every source string to its int. Tracks keep the order of their first row.
  ``object_type``: vehicle, bus -> VEHICLE; pedestrian -> PEDESTRIAN; cyclist, motorcyclist ->
  CYCLIST; static, background, construction, riderless_bicycle, unknown... -> OTHER.
* **Positions.** AV2 tracks are 2-D: z = 0 (the map keeps its own z, metres above the city's
  datum, so map and tracks differ in height; everything downstream is planar).
* **Sizes.** AV2 has no boxes: :data:`DEFAULT_SIZE_M` per AV2 object type (length, width, height),
  on every frame.
* **Roles.** The ``"AV"`` track is the self-driving car. Tracks to predict: the focal track first
  (``object_category`` 3, or ``focal_track_id``), then the scored tracks (category 2), in track
  order. ``objects_of_interest`` holds the focal track's id.
* **Map.** Lane segments -> LANE features (id = the segment id) whose centerline is the average of
  the left and right boundaries resampled by arc length to the same number of points, spaced about
  :data:`CENTERLINE_SPACING_M` apart (the map file's own ``centerline``, when present, is not used:
  in these archives it has z = 0). ``lane_type`` BIKE -> BIKE_LANE, VEHICLE/BUS -> SURFACE_STREET;
  ``is_intersection`` -> ``interpolating`` (the closest WOMD notion: lanes drawn across an
  intersection). Successors, predecessors and left/right neighbours -> links (they may name
  segments outside this local map). Painted lane boundaries (mark type not ``NONE``) -> ROAD_LINE
  features with :data:`ROAD_LINE_TYPES` subtypes, one per distinct geometry (a boundary shared by two
  lanes, in either direction, appears once); their ids continue after the largest source id.
  Drivable areas -> ROAD_EDGE (BOUNDARY) polylines along their closed outline (id = the area's).
  Pedestrian crossings -> CROSSWALK polygons ``edge1[0], edge1[-1], edge2[-1], edge2[0]``.
* **Traffic lights.** AV2 has none: an empty :class:`TrafficLights`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import ScenarioReadError, check_regular_file
from ..scenario import (
    DT_S, TYPICAL_BOX_M, AgentType, LaneType, LinkType, MapFeatureType, RoadEdgeType, RoadLineType, RoadMap, Scenario,
    TrafficLights, Tracks, wrap_angle,
)
from ..values import as_floats, as_int, as_integers
from .common import choose_frame, load_json_object, read_errors

NAME = "av2"

AV2_CURRENT_FRAME = 49
"""Last frame of AV2's 5 s observed history."""

CENTERLINE_SPACING_M = 0.5
"""Target spacing of the lane centerlines built from the boundaries (WOMD's spacing)."""

AGENT_TYPES = {
    "vehicle": AgentType.VEHICLE, "bus": AgentType.VEHICLE,
    "pedestrian": AgentType.PEDESTRIAN,
    "cyclist": AgentType.CYCLIST, "motorcyclist": AgentType.CYCLIST,
}
"""AV2 object types with an agent type of their own; every other type is OTHER."""

DEFAULT_SIZE_M = {
    "vehicle": TYPICAL_BOX_M[AgentType.VEHICLE],
    "bus": (12.0, 2.6, 3.2),
    "pedestrian": TYPICAL_BOX_M[AgentType.PEDESTRIAN],
    "cyclist": TYPICAL_BOX_M[AgentType.CYCLIST],
    "motorcyclist": (2.2, 0.8, 1.6),
    "riderless_bicycle": (1.8, 0.6, 1.1),
}
"""(length, width, height) per AV2 object type; AV2 gives no boxes. The types that are agent types of their own
take :data:`~smart_marl.scenario.TYPICAL_BOX_M`'s; others: :data:`OTHER_SIZE_M`."""

OTHER_SIZE_M = TYPICAL_BOX_M[AgentType.OTHER]

ROAD_LINE_TYPES = {
    "DASHED_WHITE": RoadLineType.BROKEN_SINGLE_WHITE,
    "DASHED_YELLOW": RoadLineType.BROKEN_SINGLE_YELLOW,
    "SOLID_WHITE": RoadLineType.SOLID_SINGLE_WHITE,
    "SOLID_YELLOW": RoadLineType.SOLID_SINGLE_YELLOW,
    "DOUBLE_SOLID_WHITE": RoadLineType.SOLID_DOUBLE_WHITE,
    "DOUBLE_SOLID_YELLOW": RoadLineType.SOLID_DOUBLE_YELLOW,
    "DOUBLE_DASH_YELLOW": RoadLineType.BROKEN_DOUBLE_YELLOW,
    "DOUBLE_DASH_WHITE": RoadLineType.BROKEN_SINGLE_WHITE,  # WOMD has no broken double white
    "DASH_SOLID_YELLOW": RoadLineType.PASSING_DOUBLE_YELLOW,
    "SOLID_DASH_YELLOW": RoadLineType.PASSING_DOUBLE_YELLOW,
    "DASH_SOLID_WHITE": RoadLineType.SOLID_SINGLE_WHITE,  # WOMD has no mixed white: the solid side rules
    "SOLID_DASH_WHITE": RoadLineType.SOLID_SINGLE_WHITE,
    "SOLID_BLUE": RoadLineType.UNKNOWN,
    "UNKNOWN": RoadLineType.UNKNOWN,
}
"""AV2 lane mark types -> WOMD road-line types (``NONE``: no painted line, no feature)."""

_LANE_TYPES = {"VEHICLE": LaneType.SURFACE_STREET, "BUS": LaneType.SURFACE_STREET, "BIKE": LaneType.BIKE_LANE}

_REQUIRED_COLUMNS = ("track_id", "object_type", "timestep", "position_x", "position_y", "heading",
                     "velocity_x", "velocity_y")
_OPTIONAL_COLUMNS = ("scenario_id", "object_category", "track_category", "focal_track_id", "city", "map_id",
                     "slice_id", "num_timestamps")
_FOCAL, _SCORED = 3, 2

MAX_FRAMES = 2000
"""Most frames a scenario may declare (200 s; AV2 scenarios have 110). A larger ``timestep`` or
``num_timestamps`` is refused before anything of that size is allocated."""

MAX_FRAMES_PER_ROW = 64
"""The track x frame grid may be at most this many times the number of rows the file holds (AV2
files: about 2), so a few rows cannot declare a grid the memory cannot hold."""


def sniff(path: str, head: bytes) -> bool:
    """A parquet file (magic ``PAR1``)."""
    return head[:4] == b"PAR1"


def _parquet():
    try:
        import pyarrow.parquet as pq
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "reading Argoverse 2 scenarios needs pyarrow: pip install 'smart-marl[av2]'"
        ) from exc
    return pq


def map_path_for(path: str | os.PathLike) -> Path:
    """The map archive that goes with ``scenario_<id>.parquet``: ``log_map_archive_<id>.json`` beside it."""
    path = Path(path)
    stem = path.stem[len("scenario_"):] if path.stem.startswith("scenario_") else path.stem
    return path.with_name(f"log_map_archive_{stem}.json")


def read(path: str | os.PathLike) -> Iterator[Scenario]:
    """Yield the one Scenario of an AV2 scenario parquet (its map file must sit beside it)."""
    path = os.fspath(path)
    yield read_av2(path)


def read_av2(path: str, map_path: str | os.PathLike | None = None) -> Scenario:
    pq = _parquet()
    map_path = Path(map_path) if map_path is not None else map_path_for(path)
    if not map_path.exists():
        raise ScenarioReadError(path, f"the map file is missing: expected {map_path}")
    check_regular_file(map_path)
    try:
        parquet = pq.ParquetFile(path)
        names = set(parquet.schema_arrow.names)
        missing = [c for c in _REQUIRED_COLUMNS if c not in names]
        if missing:
            raise ScenarioReadError(path, f"missing column(s) {', '.join(missing)}: not an AV2 scenario parquet")
        table = parquet.read(columns=[c for c in _REQUIRED_COLUMNS + _OPTIONAL_COLUMNS if c in names])
    except ScenarioReadError:
        raise
    except Exception as exc:  # pyarrow raises ArrowInvalid, OSError...
        raise ScenarioReadError(path, f"cannot read parquet: {exc}") from exc
    columns = {name: table.column(name).to_numpy(zero_copy_only=False) for name in table.column_names}
    tracks, roles = _read_tracks(columns, path)
    road_map_source = _read_map(map_path)

    num_frames = tracks["valid"].shape[1]
    current_frame = min(AV2_CURRENT_FRAME, num_frames - 1)
    frame = choose_frame(tracks["position"], tracks["valid"], roles["sdc_index"], current_frame,
                         fallback=road_map_source["points"] if len(road_map_source["points"]) else None)
    origin = np.array([frame.x, frame.y, frame.z])
    position = np.where(tracks["valid"][..., None], tracks["position"] - origin, 0.0)
    rm = road_map_source

    scenario_id = _single(columns, "scenario_id", path) or Path(path).stem.removeprefix("scenario_")
    metadata: dict[str, Any] = {
        "source_path": os.path.abspath(path),
        "map_path": os.path.abspath(map_path),
        "track_id_map": tracks["id_map"],
        "focal_track_id": roles["focal_id"],
    }
    for key in ("city", "map_id", "slice_id"):
        value = _single(columns, key, path)
        if value is not None:
            metadata[key] = value.item() if isinstance(value, np.generic) else value
    with read_errors(path):
        return Scenario(
            scenario_id=str(scenario_id),
            source="av2",
            timestamps_s=np.arange(num_frames) * DT_S,
            current_frame=current_frame,
            tracks=Tracks(ids=tracks["ids"], types=tracks["types"], position=position, heading=tracks["heading"],
                          velocity=tracks["velocity"], size=tracks["size"], valid=tracks["valid"]),
            road_map=RoadMap(
                ids=rm["ids"], types=rm["types"], subtypes=rm["subtypes"],
                speed_limit_mph=np.zeros(len(rm["ids"]), np.float32), interpolating=rm["interpolating"],
                points=rm["points"] - origin, point_offsets=rm["offsets"], links=rm["links"],
                link_types=rm["link_types"],
            ),
            traffic_lights=TrafficLights.empty(num_frames),
            sdc_index=roles["sdc_index"],
            predict_indices=roles["predict"],
            objects_of_interest=np.asarray([] if roles["focal_id"] is None else [roles["focal_id"]], np.int64),
            frame=frame,
            metadata=metadata,
        )


def _single(columns: dict[str, np.ndarray], name: str, path: str):
    """The one value of a per-scenario column (None when absent)."""
    if name not in columns or len(columns[name]) == 0:
        return None
    values = columns[name]
    first = values[0]
    if not (values == first).all():
        raise ScenarioReadError(path, f"column {name} holds more than one value", record=f"column {name}")
    return first


# ---------------------------------------------------------------------------------------- tracks
def _track_ids(id_strings: np.ndarray, path: str) -> np.ndarray:
    """[N] int64 track ids: decimal id strings as their numbers, the others numbered after the largest, in sorted order."""
    n = len(id_strings)
    numeric = np.array([s.isdecimal() for s in id_strings], bool)
    ids = np.zeros(n, np.int64)
    ids[numeric] = [int(s) for s in id_strings[numeric]]
    base = int(ids[numeric].max()) + 1 if numeric.any() else 0
    others = np.flatnonzero(~numeric)
    for k, i in enumerate(others[np.argsort(id_strings[others], kind="stable")]):
        ids[i] = base + k
    if len(np.unique(ids)) != n:
        raise ScenarioReadError(path, "two track ids map to the same integer", record="column track_id")
    return ids


def _timesteps(columns: dict[str, np.ndarray], path: str) -> tuple[np.ndarray, int]:
    """Every row's timestep and the scenario's frame count (``num_timestamps`` when given), each checked against the limits."""
    with read_errors(path, "column timestep"):
        timestep = as_integers(columns["timestep"], np.int64, "timestep")
    if len(timestep) and timestep.min() < 0:
        row = int(np.argmin(timestep))
        raise ScenarioReadError(path, f"negative timestep {int(timestep[row])}", record=f"row {row}")
    if len(timestep) and timestep.max() >= MAX_FRAMES:
        row = int(np.argmax(timestep))
        raise ScenarioReadError(path, f"timestep {int(timestep[row])} is beyond the {MAX_FRAMES} frames a scenario may have",
                                record=f"row {row}")
    num_frames = int(timestep.max()) + 1 if len(timestep) else 0
    declared = _single(columns, "num_timestamps", path)
    if declared is not None:
        with read_errors(path, "column num_timestamps"):
            declared = as_int(declared, "num_timestamps")
        if declared < num_frames:
            row = int(np.argmax(timestep))
            raise ScenarioReadError(path, f"timestep {num_frames - 1} beyond num_timestamps {declared}", record=f"row {row}")
        if declared > MAX_FRAMES:
            raise ScenarioReadError(path, f"num_timestamps {declared} is more than the {MAX_FRAMES} frames a scenario may have",
                                    record="column num_timestamps")
        num_frames = declared
    if num_frames == 0:
        raise ScenarioReadError(path, "no rows")
    return timestep, num_frames


def _read_tracks(columns: dict[str, np.ndarray], path: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The Tracks fields and the roles (self-driving car, tracks to predict, focal track) of a scenario's track columns."""
    for name in ("track_id", "object_type"):
        if columns[name].dtype.kind not in "OUS" or not all(isinstance(v, str) for v in columns[name][:1]):
            raise ScenarioReadError(path, f"column {name} holds {columns[name].dtype} values, expected strings",
                                    record=f"column {name}")
    raw_ids = columns["track_id"].astype(str)
    unique, first_row, inverse = np.unique(raw_ids, return_index=True, return_inverse=True)
    order = np.argsort(first_row, kind="stable")  # tracks in the order of their first row
    rank = np.empty(len(unique), np.int64)
    rank[order] = np.arange(len(unique))
    track_of_row = rank[inverse.reshape(-1)]
    id_strings = unique[order]
    n = len(id_strings)

    ids = _track_ids(id_strings, path)

    timestep, num_frames = _timesteps(columns, path)
    if n * num_frames > max(MAX_FRAMES_PER_ROW * len(timestep), 1 << 16):
        raise ScenarioReadError(path, f"{len(timestep)} rows cannot fill {n} tracks x {num_frames} frames (declared sizes "
                                      f"larger than the data)", record="column num_timestamps")

    valid = np.zeros((n, num_frames), bool)
    valid[track_of_row, timestep] = True
    if valid.sum() != len(timestep):
        flat = track_of_row * num_frames + timestep
        _, first, counts = np.unique(flat, return_index=True, return_counts=True)
        row = int(np.flatnonzero(flat == flat[first[counts > 1][0]])[1])
        raise ScenarioReadError(path, f"track {raw_ids[row]} has two rows for timestep {int(timestep[row])}",
                                record=f"row {row}")
    position = np.zeros((n, num_frames, 3))
    velocity = np.zeros((n, num_frames, 2))
    heading = np.zeros((n, num_frames))
    for name, target, index in (("position_x", position, 0), ("position_y", position, 1),
                                ("velocity_x", velocity, 0), ("velocity_y", velocity, 1), ("heading", heading, None)):
        with read_errors(path, f"column {name}"):
            values = as_floats(columns[name], np.float64, name)
        bad = ~np.isfinite(values)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise ScenarioReadError(path, f"{name} is {values[row]} (track {raw_ids[row]}, timestep {int(timestep[row])})",
                                    record=f"row {row}")
        if index is None:
            target[track_of_row, timestep] = values
        else:
            target[track_of_row, timestep, index] = values

    type_names = columns["object_type"].astype(str)[first_row[order]]
    types = np.array([AGENT_TYPES.get(t, AgentType.OTHER) for t in type_names], np.int8)
    box = np.array([DEFAULT_SIZE_M.get(t, OTHER_SIZE_M) for t in type_names], np.float64).reshape(n, 3)
    size = np.repeat(box[:, None, :], num_frames, axis=1)

    category_col = "object_category" if "object_category" in columns else "track_category" if "track_category" in columns else None
    with read_errors(path, f"column {category_col}"):
        category = (as_integers(columns[category_col], np.int64, category_col)[first_row[order]] if category_col
                    else np.zeros(n, np.int64))
    focal_str = _single(columns, "focal_track_id", path)
    focal = np.flatnonzero(category == _FOCAL)
    if focal_str is not None and str(focal_str) in set(id_strings):
        focal = np.flatnonzero(id_strings == str(focal_str))
    scored = np.flatnonzero(category == _SCORED)
    predict = np.concatenate([focal, scored[~np.isin(scored, focal)]]).astype(np.int64)
    sdc = np.flatnonzero(id_strings == "AV")

    tracks = {
        "ids": ids, "types": types, "position": position, "heading": wrap_angle(heading),
        "velocity": velocity, "size": size, "valid": valid,
        "id_map": {str(s): int(i) for s, i in zip(id_strings, ids)},
    }
    roles = {
        "sdc_index": int(sdc[0]) if len(sdc) else -1,
        "predict": predict,
        "focal_id": int(ids[focal[0]]) if len(focal) else None,
    }
    return tracks, roles


# ------------------------------------------------------------------------------------------- map
def _xyz(points: Any, map_path: Path, record: str) -> np.ndarray:
    try:
        out = as_floats([(p["x"], p["y"], p.get("z", 0.0)) for p in points], np.float64, "points").reshape(-1, 3)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:  # ScenarioValidationError is a ValueError
        raise ScenarioReadError(map_path, f"malformed points: {exc}", record=record) from exc
    if len(out) == 0:
        raise ScenarioReadError(map_path, "no points", record=record)
    if not np.isfinite(out).all():
        raise ScenarioReadError(map_path, "a point is not finite", record=record)
    return out


def resample_polyline(points: np.ndarray, num_points: int) -> np.ndarray:
    """``num_points`` points evenly spaced by arc length along a polyline [n, D] (n >= 1)."""
    if len(points) == 1:
        return np.repeat(points, num_points, axis=0)
    seg = np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return np.repeat(points[:1], num_points, axis=0)
    t = np.linspace(0.0, s[-1], num_points)
    return np.stack([np.interp(t, s, points[:, d]) for d in range(points.shape[1])], axis=1)


def lane_centerline(left: np.ndarray, right: np.ndarray, spacing_m: float = CENTERLINE_SPACING_M) -> np.ndarray:
    """The average of the two boundaries, each resampled to the same number of points."""
    length = 0.5 * sum(float(np.linalg.norm(np.diff(b[:, :2], axis=0), axis=1).sum()) for b in (left, right))
    num_points = max(2, int(np.ceil(length / spacing_m)) + 1)
    return 0.5 * (resample_polyline(left, num_points) + resample_polyline(right, num_points))


def _map_id(value: Any, map_path: Path, record: str) -> int:
    """A map id: an integer (or the decimal string of a JSON object key), never a truncated float."""
    if isinstance(value, str) and value.lstrip("-").isdecimal():
        value = int(value)
    with read_errors(map_path, record):
        return as_int(value, "id")


def _text(value: Any, map_path: Path, record: str, field: str) -> str | None:
    if value is not None and not isinstance(value, str):
        raise ScenarioReadError(map_path, f"'{field}' is {value!r}, expected a string", record=record)
    return value


def _read_map(map_path: Path) -> dict[str, Any]:
    data = load_json_object(map_path)
    for key in ("lane_segments", "drivable_areas", "pedestrian_crossings"):
        if not isinstance(data.get(key, {}), dict):
            raise ScenarioReadError(map_path, f"'{key}' is not an object keyed by id", record=key)
    if "lane_segments" not in data:
        raise ScenarioReadError(map_path, "missing field 'lane_segments': not an AV2 map archive")

    ids, types, subtypes, interp, pts = [], [], [], [], []
    links: list[tuple[int, int, int]] = []
    road_lines: list[tuple[np.ndarray, int]] = []
    seen_lines: set[bytes] = set()
    for key, lane in data["lane_segments"].items():
        record = f"lane_segments[{key}]"
        if not isinstance(lane, dict):
            raise ScenarioReadError(map_path, f"is a {type(lane).__name__}, expected an object", record=record)
        for field in ("id", "left_lane_boundary", "right_lane_boundary"):
            if field not in lane:
                raise ScenarioReadError(map_path, f"missing field '{field}'", record=record)
        lane_id = _map_id(lane["id"], map_path, record)
        left = _xyz(lane["left_lane_boundary"], map_path, record + ".left_lane_boundary")
        right = _xyz(lane["right_lane_boundary"], map_path, record + ".right_lane_boundary")
        ids.append(lane_id)
        types.append(MapFeatureType.LANE)
        subtypes.append(_LANE_TYPES.get(_text(lane.get("lane_type"), map_path, record, "lane_type"), LaneType.UNDEFINED))
        interp.append(bool(lane.get("is_intersection", False)))
        pts.append(lane_centerline(left, right))
        for field, link in (("successors", LinkType.SUCCESSOR), ("predecessors", LinkType.PREDECESSOR)):
            others = lane.get(field) or []
            if not isinstance(others, list):
                raise ScenarioReadError(map_path, f"'{field}' is a {type(others).__name__}, expected a list", record=record)
            links += [(lane_id, _map_id(other, map_path, f"{record}.{field}"), link) for other in others]
        for side, link in (("left", LinkType.LEFT_NEIGHBOR), ("right", LinkType.RIGHT_NEIGHBOR)):
            neighbour = lane.get(f"{side}_neighbor_id")
            if neighbour is not None:
                links.append((lane_id, _map_id(neighbour, map_path, f"{record}.{side}_neighbor_id"), link))
            mark = _text(lane.get(f"{side}_lane_mark_type", "NONE"), map_path, record, f"{side}_lane_mark_type")
            if mark == "NONE":
                continue
            boundary = left if side == "left" else right
            key_fwd = np.round(boundary[:, :2], 2).tobytes()
            key_rev = np.round(boundary[::-1, :2], 2).tobytes()
            if key_fwd in seen_lines or key_rev in seen_lines:
                continue
            seen_lines.add(key_fwd)
            road_lines.append((boundary, ROAD_LINE_TYPES.get(mark, RoadLineType.UNKNOWN)))

    for key, area in (data.get("drivable_areas") or {}).items():
        record = f"drivable_areas[{key}]"
        if not isinstance(area, dict) or "area_boundary" not in area:
            raise ScenarioReadError(map_path, "missing field 'area_boundary'", record=record)
        outline = _xyz(area["area_boundary"], map_path, record + ".area_boundary")
        if len(outline) > 1 and not np.array_equal(outline[0], outline[-1]):
            outline = np.concatenate([outline, outline[:1]])
        ids.append(_map_id(area.get("id", key), map_path, record))
        types.append(MapFeatureType.ROAD_EDGE)
        subtypes.append(RoadEdgeType.BOUNDARY)
        interp.append(False)
        pts.append(outline)

    for key, crossing in (data.get("pedestrian_crossings") or {}).items():
        record = f"pedestrian_crossings[{key}]"
        for field in ("edge1", "edge2"):
            if not isinstance(crossing, dict) or field not in crossing:
                raise ScenarioReadError(map_path, f"missing field '{field}'", record=record)
        e1 = _xyz(crossing["edge1"], map_path, record + ".edge1")
        e2 = _xyz(crossing["edge2"], map_path, record + ".edge2")
        ids.append(_map_id(crossing.get("id", key), map_path, record))
        types.append(MapFeatureType.CROSSWALK)
        subtypes.append(0)
        interp.append(False)
        pts.append(np.stack([e1[0], e1[-1], e2[-1], e2[0]]))

    next_id = max(ids) + 1 if ids else 0
    for k, (boundary, line_type) in enumerate(road_lines):
        ids.append(next_id + k)
        types.append(MapFeatureType.ROAD_LINE)
        subtypes.append(line_type)
        interp.append(False)
        pts.append(boundary)

    id_array = np.asarray(ids, np.int64)
    if len(np.unique(id_array)) != len(id_array):
        uniq, counts = np.unique(id_array, return_counts=True)
        raise ScenarioReadError(map_path, f"feature id {int(uniq[counts > 1][0])} is used twice")
    lengths = np.array([len(p) for p in pts], np.int64)
    return {
        "ids": id_array,
        "types": np.asarray(types, np.int8),
        "subtypes": np.asarray(subtypes, np.int8),
        "interpolating": np.asarray(interp, bool),
        "points": np.concatenate(pts) if pts else np.zeros((0, 3)),
        "offsets": np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        "links": np.asarray([(a, b) for a, b, _ in links], np.int64).reshape(-1, 2),
        "link_types": np.asarray([t for _, _, t in links], np.int8),
    }
