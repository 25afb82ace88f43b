"""Waymo Open Motion Dataset scenario files (TFRecord of ``Scenario`` protobufs) <-> Scenarios.

Stage: a reader, the first stage of the data flow (driving logs -> :class:`~smart_marl.Scenario`),
plus the writer that turns any Scenario back into a WOMD record (for tools that expect WOMD, and
for round-trip tests).

Reading needs neither TensorFlow nor ``waymo-open-dataset``: records come from
:mod:`smart_marl.readers.tfrecord` (plain or GZIP, CRC-checked) and are decoded with the project's
own schema (:mod:`smart_marl.proto.womd`). What a record becomes:

* tracks: ids, types (WOMD 1 vehicle / 2 pedestrian / 3 cyclist; 0 unset and 4 other -> OTHER),
  centre x/y/z, heading, velocity, length/width/height, valid, on every timestamp;
* ``current_time_index``, ``sdc_track_index``, ``tracks_to_predict`` (indices and difficulty),
  ``objects_of_interest``;
* every map feature: lanes (type, ``speed_limit_mph``, ``interpolating``, centre polyline), road
  lines and road edges (type, polyline), stop signs (one point, with a STOP_SIGN_LANE link to each
  lane it controls), crosswalk / speed bump / driveway polygons;
* lane topology as ``RoadMap.links``, per lane in source order: exit lanes -> SUCCESSOR, entry lanes
  -> PREDECESSOR, left / right neighbours -> LEFT_NEIGHBOR / RIGHT_NEIGHBOR;
* traffic lights: ``lane_ids`` = sorted unique lanes over all frames, ``states`` / ``present``
  [T, L], each lane's stop point from its first report.

Coordinates are shifted to the self-driving car's position at the current frame
(:func:`~smart_marl.readers.common.choose_frame`): positions are ``float32(source - origin)``, the origin
is kept in ``Scenario.frame`` (float64).

Not kept (so not written back either): lane boundary segments (``left_boundaries`` /
``right_boundaries``) and the index ranges of lane neighbours (only the neighbour ids are links);
a traffic-light lane that is never reported on any frame cannot be written. Map features without
points (no polyline, or a stop sign without a position) cannot be a RoadMap feature: they are left
out and their ids listed in ``metadata["map_features_without_points"]``.

Decoding is vectorised per scene. A record is parsed with the raw-points view of the schema
(:data:`smart_marl.proto.womd.RAW_POINTS`), which leaves every ``ObjectState`` and ``MapPoint`` as
its serialized bytes; the bytes of all states (all map points) of the scene are joined and decoded
at once by :func:`scan_fixed_width_messages`, a numpy scanner for messages made only of
fixed-width fields. A record it cannot decode that way (a field it does not know inside a state or
point, a multi-byte varint) falls back to the plain schema and one attribute access per value,
with the same result.
"""

from __future__ import annotations

import os
import warnings
import zlib
from itertools import chain
from typing import Iterable, Iterator

import numpy as np
from google.protobuf.message import DecodeError

from ..errors import ScenarioReadError
from ..proto import womd as pb
from ..scenario import (
    AgentType, LinkType, MapFeatureType, RoadMap, Scenario, TrafficLights, Tracks,
)
from . import tfrecord
from .common import choose_frame, read_errors

NAME = "womd"
MULTI_SCENE = True  # records are scenes: errors name the record
SOURCE = "womd"

# WOMD Track.ObjectType -> AgentType (0 unset and 4 other -> OTHER)
_AGENT_TYPE_OF_WOMD = np.array([AgentType.OTHER, AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST,
                                AgentType.OTHER], dtype=np.int8)
_WOMD_TYPE_OF_AGENT = {AgentType.VEHICLE: 1, AgentType.PEDESTRIAN: 2, AgentType.CYCLIST: 3, AgentType.OTHER: 4}

# oneof name -> (MapFeatureType, name of the points field)
_FEATURE_KINDS = {
    "lane": (MapFeatureType.LANE, "polyline"),
    "road_line": (MapFeatureType.ROAD_LINE, "polyline"),
    "road_edge": (MapFeatureType.ROAD_EDGE, "polyline"),
    "stop_sign": (MapFeatureType.STOP_SIGN, None),
    "crosswalk": (MapFeatureType.CROSSWALK, "polygon"),
    "speed_bump": (MapFeatureType.SPEED_BUMP, "polygon"),
    "driveway": (MapFeatureType.DRIVEWAY, "polygon"),
}
_ONEOF_OF_TYPE = {kind: name for name, (kind, _) in _FEATURE_KINDS.items()}
_INT32 = (-(2**31), 2**31 - 1)


# ------------------------------------------------------------------------------------- sniffing
def sniff(path: str, head: bytes) -> bool:
    """A TFRecord whose first length CRC checks, plain or inside GZIP."""
    if tfrecord.is_gzip(head):
        try:
            inner = zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(head, 64)
        except zlib.error:
            return False
        return tfrecord.header_looks_like_tfrecord(inner)
    return tfrecord.header_looks_like_tfrecord(head)


def read(path: str | os.PathLike) -> Iterator[Scenario]:
    """Yield the Scenario of every record of a WOMD scenario file (plain or GZIP), one at a time."""
    path = os.fspath(path)
    for index, payload in enumerate(tfrecord.iter_records(path)):
        yield decode_scenario(payload, path=path, record=index)


# -------------------------------------------------------------------------------------- decoding
# (tag byte, column, width in bytes, numpy dtype); tag = field number << 3 | wire type.
_OBJECT_STATE_FIELDS = (
    (0x11, "center_x", 8, "<f8"), (0x19, "center_y", 8, "<f8"), (0x21, "center_z", 8, "<f8"),
    (0x2D, "length", 4, "<f4"), (0x35, "width", 4, "<f4"), (0x3D, "height", 4, "<f4"), (0x45, "heading", 4, "<f4"),
    (0x4D, "velocity_x", 4, "<f4"), (0x55, "velocity_y", 4, "<f4"), (0x58, "valid", 1, "u1"),  # valid: a 1-byte varint
)
_MAP_POINT_FIELDS = ((0x09, "x", 8, "<f8"), (0x11, "y", 8, "<f8"), (0x19, "z", 8, "<f8"))


def scan_fixed_width_messages(chunks: list[bytes], fields) -> dict[str, np.ndarray] | None:
    """Decode many small serialized messages at once: ``chunks[i]`` is message ``i``; every field
    is one of ``fields`` (single-byte tag, fixed width). Returns one array per field (the proto
    default 0 where a message lacks the field; the last value where it repeats one), or None when
    a message holds anything else (the caller then decodes it with protobuf).

    Messages of one length almost always share one layout (the serializer writes fields in number
    order): each such group is checked and sliced as a 2-D byte array; the rest go through a
    scanner that advances every message by one field per numpy step.
    """
    count = len(chunks)
    lengths = np.fromiter(map(len, chunks), dtype=np.int64, count=count)
    buf = np.frombuffer(b"".join(chunks), dtype=np.uint8)
    ends = np.cumsum(lengths)
    starts = ends - lengths
    out = {name: np.zeros(count, dtype=dtype) for _, name, _, dtype in fields}
    spec = {tag: (name, width, dtype) for tag, name, width, dtype in fields}
    width_of_tag = np.zeros(256, np.int64)
    for tag, _, width, _ in fields:
        width_of_tag[tag] = width
    leftover = []
    for length in np.unique(lengths).tolist():
        rows = np.flatnonzero(lengths == length)
        if length == 0:
            continue
        block = buf.reshape(count, length) if len(rows) == count else buf[starts[rows, None] + np.arange(length)]
        layout, offset, first = [], 0, block[0].tolist()
        while offset < length:
            tag = first[offset]
            width = int(width_of_tag[tag])
            if not width or offset + 1 + width > length:
                return None  # an unknown field, or a truncated one
            layout.append((offset, tag))
            offset += 1 + width
        same = (block[:, [o for o, _ in layout]] == np.array([t for _, t in layout], np.uint8)).all(axis=1)
        for offset, tag in layout:
            name, width, dtype = spec[tag]
            raw = np.ascontiguousarray(block[same, offset + 1 : offset + 1 + width])
            if width == 1 and np.any(raw >= 0x80):
                return None  # a varint longer than one byte
            out[name][rows[same]] = raw.view(dtype).reshape(-1)
        if not same.all():
            leftover.append(rows[~same])
    if leftover:
        rows = np.concatenate(leftover)
        pos = starts.copy()
        while len(rows):
            p = pos[rows]
            tags = buf[p]
            width = width_of_tag[tags]
            if not width.all() or np.any(p + 1 + width > ends[rows]):
                return None
            for tag, name, w, dtype in fields:
                hit = tags == tag
                if hit.any():
                    raw = buf[(p[hit] + 1)[:, None] + np.arange(w)]
                    if w == 1 and np.any(raw >= 0x80):
                        return None
                    out[name][rows[hit]] = raw.view(dtype).reshape(-1)
            pos[rows] = p + 1 + width
            rows = rows[pos[rows] < ends[rows]]
    return out


def _check_state_counts(message, num_frames: int, path: str, record: int) -> None:
    tracks = message.tracks
    counts = [len(t.states) for t in tracks]
    bad = [i for i, c in enumerate(counts) if c != num_frames]
    if bad:
        i = bad[0]
        raise ScenarioReadError(
            path, f"scenario {message.scenario_id}: track {i} (id {tracks[i].id}) has {counts[i]} states but there are "
            f"{num_frames} timestamps", record,
        )


def _track_arrays_raw(view, num_frames: int, path: str, record: int):
    """Like :func:`_track_arrays` from a raw-points view; None when the states need protobuf."""
    _check_state_counts(view, num_frames, path, record)
    tracks = view.tracks
    n = len(tracks)
    cols = scan_fixed_width_messages(list(chain.from_iterable(t.states for t in tracks)), _OBJECT_STATE_FIELDS)
    if cols is None:
        return None
    ids = np.array([t.id for t in tracks], dtype=np.int64)
    types = np.array([t.object_type for t in tracks], dtype=np.int64)
    shape = (n, num_frames)
    xyz = np.stack([cols["center_x"], cols["center_y"], cols["center_z"]], axis=-1).reshape(*shape, 3)
    floats = np.stack([cols[k] for k in ("length", "width", "height", "heading", "velocity_x", "velocity_y")],
                      axis=-1).reshape(*shape, 6)
    return ids, types, xyz, floats, cols["valid"].astype(bool).reshape(shape)


def _raw_points(polylines: list) -> np.ndarray | None:
    """[P, 3] float64 source points from lists of serialized MapPoints; None when they need protobuf."""
    cols = scan_fixed_width_messages(list(chain.from_iterable(polylines)), _MAP_POINT_FIELDS)
    if cols is None:
        return None
    return np.stack([cols["x"], cols["y"], cols["z"]], axis=-1)


def parse_scenario_proto(payload: bytes, path: str = "<bytes>", record: int = 0):
    """The ``waymo.open_dataset.Scenario`` message of one record (ScenarioReadError if it is not one)."""
    try:
        message = pb.Scenario.FromString(bytes(payload))
    except (DecodeError, RuntimeError, ValueError) as exc:
        raise ScenarioReadError(path, f"the record is not a WOMD Scenario protobuf (cannot parse it: {exc})", record) from exc
    if not message.scenario_id:
        raise ScenarioReadError(path, "the record is not a WOMD Scenario protobuf (it has no scenario_id)", record)
    if not len(message.timestamps_seconds):
        raise ScenarioReadError(path, f"scenario {message.scenario_id} has no timestamps_seconds", record)
    return message


def decode_scenario(payload: bytes, path: str = "<bytes>", record: int = 0) -> Scenario:
    """Decode one serialized WOMD ``Scenario`` into a :class:`Scenario` (local frame, see module doc)."""
    payload = bytes(payload)
    try:
        view = pb.RAW_POINTS["Scenario"].FromString(payload)
    except (DecodeError, RuntimeError, ValueError):
        view = None  # the plain parse below says what is wrong
    message = view if view is not None and view.scenario_id and len(view.timestamps_seconds) else None
    if message is not None:
        with read_errors(path, record, f"scenario {message.scenario_id}: "):
            try:
                return scenario_from_proto(message, path=path, record=record)
            except _NeedsProtobuf:
                pass
    message = parse_scenario_proto(payload, path, record)
    with read_errors(path, record, f"scenario {message.scenario_id}: "):
        return scenario_from_proto(message, path=path, record=record)


class _NeedsProtobuf(Exception):
    """The raw-points view met states or points the numpy scanner does not decode."""


def _track_arrays(message, num_frames: int, path: str, record: int):
    """All tracks at once: ids [N], WOMD types [N], doubles [N, T, 3], floats [N, T, 6], valid [N, T]."""
    _check_state_counts(message, num_frames, path, record)
    tracks = message.tracks
    n = len(tracks)
    ids = np.array([t.id for t in tracks], dtype=np.int64)
    types = np.array([t.object_type for t in tracks], dtype=np.int64)
    states = [s for t in tracks for s in t.states]
    xyz = np.array([(s.center_x, s.center_y, s.center_z) for s in states], dtype=np.float64).reshape(n, num_frames, 3)
    floats = np.array([(s.length, s.width, s.height, s.heading, s.velocity_x, s.velocity_y) for s in states],
                      dtype=np.float32).reshape(n, num_frames, 6)
    valid = np.array([s.valid for s in states], dtype=bool).reshape(n, num_frames)
    return ids, types, xyz, floats, valid


def _map_arrays(message, raw: bool = False):
    """Map features: ids, types, subtypes, speed limits, interpolating, source points [P, 3], lengths,
    links [(from, to, LinkType)], ids of features without points. ``raw``: ``message`` is a
    raw-points view (points are serialized MapPoints); the points are then None when they need
    protobuf to decode."""
    ids, types, subtypes, speeds, interp, lengths, polylines = [], [], [], [], [], [], []
    links: list[tuple[int, int, int]] = []
    without_points: list[int] = []
    for feature in message.map_features:
        oneof = feature.WhichOneof("feature_data")
        if oneof is None:
            without_points.append(int(feature.id))
            continue
        kind, points_field = _FEATURE_KINDS[oneof]
        data = getattr(feature, oneof)
        if points_field is None:  # stop sign: one point
            if not data.HasField("position"):
                points = []
            else:
                points = [data.position.SerializeToString()] if raw else [data.position]
        else:
            points = getattr(data, points_field)
        if not len(points):
            without_points.append(int(feature.id))
            continue
        fid = feature.id
        ids.append(fid)
        types.append(kind)
        lengths.append(len(points))
        polylines.append(points)
        if kind == MapFeatureType.LANE:
            subtypes.append(data.type)
            speeds.append(data.speed_limit_mph)
            interp.append(data.interpolating)
            links.extend((fid, to, LinkType.SUCCESSOR) for to in data.exit_lanes)
            links.extend((fid, to, LinkType.PREDECESSOR) for to in data.entry_lanes)
            links.extend((fid, nb.feature_id, LinkType.LEFT_NEIGHBOR) for nb in data.left_neighbors)
            links.extend((fid, nb.feature_id, LinkType.RIGHT_NEIGHBOR) for nb in data.right_neighbors)
        else:
            subtypes.append(data.type if kind in (MapFeatureType.ROAD_LINE, MapFeatureType.ROAD_EDGE) else 0)
            speeds.append(0.0)
            interp.append(False)
            if kind == MapFeatureType.STOP_SIGN:
                links.extend((fid, to, LinkType.STOP_SIGN_LANE) for to in data.lane)
    if raw:
        points = _raw_points(polylines)
    else:
        points = np.array([(p.x, p.y, p.z) for pl in polylines for p in pl], dtype=np.float64).reshape(-1, 3)
    return ids, types, subtypes, speeds, interp, points, lengths, links, without_points


def _traffic_light_arrays(message, num_frames: int, path: str, record: int):
    """(lane_ids [L], states [T, L], present [T, L], source stop points [L, 3])."""
    dynamic = message.dynamic_map_states
    if len(dynamic) > num_frames:
        raise ScenarioReadError(
            path, f"scenario {message.scenario_id}: {len(dynamic)} dynamic_map_states for {num_frames} timestamps", record
        )
    rows = [(f, ls.lane, ls.state) for f, d in enumerate(dynamic) for ls in d.lane_states]
    if not rows:
        return np.zeros(0, np.int64), np.zeros((num_frames, 0), np.int8), np.zeros((num_frames, 0), bool), np.zeros((0, 3))
    stops = np.array([(ls.stop_point.x, ls.stop_point.y, ls.stop_point.z) for d in dynamic for ls in d.lane_states],
                     dtype=np.float64)
    table = np.array(rows, dtype=np.int64)
    lane_ids, first, column = np.unique(table[:, 1], return_index=True, return_inverse=True)
    column = column.reshape(-1)
    states = np.zeros((num_frames, len(lane_ids)), np.int8)
    present = np.zeros((num_frames, len(lane_ids)), bool)
    states[table[:, 0], column] = table[:, 2]
    present[table[:, 0], column] = True
    return lane_ids, states, present, stops[first]


def scenario_from_proto(message, path: str = "<bytes>", record: int = 0) -> Scenario:
    """A :class:`Scenario` from a parsed ``waymo.open_dataset.Scenario`` message (of
    :mod:`smart_marl.proto.womd`, or of its raw-points view)."""
    raw = isinstance(message, pb.RAW_POINTS["Scenario"])
    timestamps = np.array(message.timestamps_seconds, dtype=np.float64)
    num_frames = len(timestamps)
    current = int(message.current_time_index)
    if not 0 <= current < num_frames:
        raise ScenarioReadError(
            path, f"scenario {message.scenario_id}: current_time_index {current} outside [0, {num_frames})", record
        )
    arrays = (_track_arrays_raw if raw else _track_arrays)(message, num_frames, path, record)
    if arrays is None:
        raise _NeedsProtobuf()
    ids, womd_types, xyz_source, floats, valid = arrays
    num_tracks = len(ids)
    sdc = int(message.sdc_track_index) if message.HasField("sdc_track_index") else -1
    if not -1 <= sdc < num_tracks:
        raise ScenarioReadError(path, f"scenario {message.scenario_id}: sdc_track_index {sdc} outside [-1, {num_tracks})", record)

    (map_ids, map_types, subtypes, speeds, interp, map_points_source, lengths, links,
     without_points) = _map_arrays(message, raw=raw)
    if map_points_source is None:
        raise _NeedsProtobuf()
    frame = choose_frame(xyz_source, valid, sdc, current, fallback=map_points_source)
    origin = np.array([frame.x, frame.y, frame.z])

    tracks = Tracks(
        ids=ids,
        types=_AGENT_TYPE_OF_WOMD[np.clip(womd_types, 0, 4)],
        position=(xyz_source - origin).astype(np.float32),
        heading=floats[..., 3],
        velocity=floats[..., 4:6],
        size=floats[..., 0:3],
        valid=valid,
    )
    road_map = RoadMap(
        ids=np.array(map_ids, dtype=np.int64),
        types=np.array(map_types, dtype=np.int8),
        subtypes=np.array(subtypes, dtype=np.int8),
        speed_limit_mph=np.array(speeds, dtype=np.float32),
        interpolating=np.array(interp, dtype=bool),
        points=(map_points_source - origin).astype(np.float32),
        point_offsets=np.concatenate([[0], np.cumsum(lengths, dtype=np.int64)]),
        links=np.array([(a, b) for a, b, _ in links], dtype=np.int64).reshape(-1, 2),
        link_types=np.array([t for _, _, t in links], dtype=np.int8),
    )
    lane_ids, states, present, stops_source = _traffic_light_arrays(message, num_frames, path, record)
    traffic_lights = TrafficLights(
        lane_ids=lane_ids, states=states, present=present, stop_points=(stops_source - origin).astype(np.float32)
    )
    metadata = {"path": path, "record": record}
    if without_points:
        metadata["map_features_without_points"] = without_points
    predict = message.tracks_to_predict
    return Scenario(
        scenario_id=message.scenario_id,
        source=SOURCE,
        timestamps_s=timestamps,
        current_frame=current,
        tracks=tracks,
        road_map=road_map,
        traffic_lights=traffic_lights,
        sdc_index=sdc,
        predict_indices=np.array([r.track_index for r in predict], dtype=np.int64),
        predict_difficulty=np.array([r.difficulty for r in predict], dtype=np.int64),  # int8 range checked by Scenario
        objects_of_interest=np.array(message.objects_of_interest, dtype=np.int64),
        frame=frame,
        metadata=metadata,
    )


# -------------------------------------------------------------------------------------- writing
def _check_int32(values: np.ndarray, what: str, scenario_id: str) -> None:
    if len(values) and (values.min() < _INT32[0] or values.max() > _INT32[1]):
        raise ValueError(f"scenario {scenario_id}: {what} do not fit WOMD's int32")


# The canonical encodings of an ObjectState with every field set and of a MapPoint with x, y, z: what
# protobuf writes (fields in number order), built for a whole scene at once with numpy.
_STATE_RECORD = np.dtype([(f"tag_{name}", "u1") if i % 2 == 0 else (name, dtype)
                          for _, name, _, dtype in _OBJECT_STATE_FIELDS for i in (0, 1)])
_POINT_RECORD = np.dtype([(f"tag_{name}", "u1") if i % 2 == 0 else (name, dtype)
                          for _, name, _, dtype in _MAP_POINT_FIELDS for i in (0, 1)])


def _encode_fixed(fields, dtype: np.dtype, columns: dict[str, np.ndarray]) -> list[bytes]:
    """One serialized message per row of ``columns``, every field of ``fields`` set."""
    count = len(next(iter(columns.values())))
    records = np.zeros(count, dtype=dtype)
    for tag, name, _, _ in fields:
        records[f"tag_{name}"] = tag
        records[name] = columns[name]
    blob, width = records.tobytes(), dtype.itemsize
    return [blob[k : k + width] for k in range(0, count * width, width)]


def encode_scenario(scenario: Scenario) -> bytes:
    """The serialized WOMD ``Scenario`` record of ``scenario``, in its source frame.

    Positions are written as ``frame.to_source(local)`` (float64), headings and velocities are
    rotated back when the frame is rotated. Only what a Scenario holds is written (see the module
    docstring); links WOMD cannot express (from a feature that is neither a lane nor a stop sign, of
    a type its source feature cannot hold, or from an id not in the map) are left out with a warning.
    States and map points are encoded for the whole scene at once (numpy) into the raw-points view.
    """
    raw = pb.RAW_POINTS
    sid = scenario.scenario_id
    frame = scenario.frame
    message = raw["Scenario"](scenario_id=sid, current_time_index=scenario.current_frame)
    message.timestamps_seconds.extend(scenario.timestamps_s.tolist())
    if scenario.sdc_index >= 0:
        message.sdc_track_index = scenario.sdc_index

    # ---- tracks
    tr = scenario.tracks
    _check_int32(tr.ids, "track ids", sid)
    _check_int32(scenario.objects_of_interest, "objects_of_interest", sid)
    xyz = frame.to_source(tr.position)
    if frame.heading == 0.0:  # keep the float32 values bit for bit
        heading, velocity = tr.heading, tr.velocity
    else:
        c, s = np.cos(frame.heading), np.sin(frame.heading)
        v = tr.velocity.astype(np.float64)
        heading = frame.heading_to_source(tr.heading)
        velocity = np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)
    states = _encode_fixed(_OBJECT_STATE_FIELDS, _STATE_RECORD, {
        "center_x": xyz[..., 0].ravel(), "center_y": xyz[..., 1].ravel(), "center_z": xyz[..., 2].ravel(),
        "length": tr.size[..., 0].ravel(), "width": tr.size[..., 1].ravel(), "height": tr.size[..., 2].ravel(),
        "heading": np.asarray(heading).ravel(), "velocity_x": np.asarray(velocity)[..., 0].ravel(),
        "velocity_y": np.asarray(velocity)[..., 1].ravel(), "valid": tr.valid.ravel(),
    }) if tr.num_tracks else []
    num_frames = tr.num_frames
    for i, (track_id, agent_type) in enumerate(zip(tr.ids.tolist(), tr.types.tolist())):
        track = message.tracks.add(id=track_id, object_type=_WOMD_TYPE_OF_AGENT[AgentType(agent_type)])
        track.states.extend(states[i * num_frames : (i + 1) * num_frames])
    message.objects_of_interest.extend(scenario.objects_of_interest.tolist())
    for index, difficulty in zip(scenario.predict_indices.tolist(), scenario.predict_difficulty.tolist()):
        message.tracks_to_predict.add(track_index=index, difficulty=difficulty)

    # ---- map
    rm = scenario.road_map
    src = frame.to_source(rm.points)
    points = _encode_fixed(_MAP_POINT_FIELDS, _POINT_RECORD, {"x": src[:, 0], "y": src[:, 1], "z": src[:, 2]}) if len(src) else []
    offsets = rm.point_offsets.tolist()
    links_from: dict[int, list[tuple[int, int]]] = {}
    for (a, b), t in zip(rm.links.tolist(), rm.link_types.tolist()):
        links_from.setdefault(a, []).append((b, t))
    written_links = 0
    speeds, subtypes, interpolating = rm.speed_limit_mph.tolist(), rm.subtypes.tolist(), rm.interpolating.tolist()
    for i, (fid, ftype) in enumerate(zip(rm.ids.tolist(), rm.types.tolist())):
        kind = MapFeatureType(ftype)
        feature = message.map_features.add(id=fid)
        data = getattr(feature, _ONEOF_OF_TYPE[kind])
        pts = points[offsets[i] : offsets[i + 1]]
        out_links = links_from.get(fid, [])
        if kind == MapFeatureType.LANE:
            data.speed_limit_mph = speeds[i]
            data.type = subtypes[i]
            data.interpolating = interpolating[i]
            data.polyline.extend(pts)
            data.exit_lanes.extend([b for b, t in out_links if t == LinkType.SUCCESSOR])
            data.entry_lanes.extend([b for b, t in out_links if t == LinkType.PREDECESSOR])
            for b, t in out_links:
                if t == LinkType.LEFT_NEIGHBOR:
                    data.left_neighbors.add(feature_id=b)
                elif t == LinkType.RIGHT_NEIGHBOR:
                    data.right_neighbors.add(feature_id=b)
            written_links += sum(t != LinkType.STOP_SIGN_LANE for _, t in out_links)
        elif kind == MapFeatureType.STOP_SIGN:
            if len(pts) != 1:
                warnings.warn(f"scenario {sid}: stop sign {fid} has {len(pts)} points; WOMD keeps the first", stacklevel=2)
            data.position.MergeFromString(pts[0])
            data.lane.extend([b for b, t in out_links if t == LinkType.STOP_SIGN_LANE])
            written_links += sum(t == LinkType.STOP_SIGN_LANE for _, t in out_links)
        elif kind in (MapFeatureType.ROAD_LINE, MapFeatureType.ROAD_EDGE):
            data.type = subtypes[i]
            data.polyline.extend(pts)
        else:
            data.polygon.extend(pts)
    if written_links != len(rm.links):
        warnings.warn(
            f"scenario {sid}: {len(rm.links) - written_links} of {len(rm.links)} map links cannot be expressed in WOMD "
            "and were not written", stacklevel=2,
        )

    # ---- traffic lights
    tl = scenario.traffic_lights
    MapPoint = raw["MapPoint"]
    stops = [MapPoint(x=x, y=y, z=z) for x, y, z in frame.to_source(tl.stop_points).tolist()]
    lane_ids, states_tl = tl.lane_ids.tolist(), tl.states.tolist()
    for f, present in enumerate(tl.present.tolist()):
        dynamic = message.dynamic_map_states.add()
        for j, is_present in enumerate(present):
            if is_present:
                dynamic.lane_states.add(lane=lane_ids[j], state=states_tl[f][j], stop_point=stops[j])
    return message.SerializeToString()


def scenario_to_proto(scenario: Scenario):
    """A ``waymo.open_dataset.Scenario`` message (:mod:`smart_marl.proto.womd`) holding ``scenario``
    in its source frame: the parse of :func:`encode_scenario`."""
    return pb.Scenario.FromString(encode_scenario(scenario))


def write_womd_tfrecord(scenarios: Iterable[Scenario] | Scenario, path: str | os.PathLike, compress: bool = False) -> int:
    """Write Scenarios (from any source) as a WOMD scenario TFRecord file, GZIP-compressed when
    ``compress``; returns the number of records written."""
    if isinstance(scenarios, Scenario):
        scenarios = [scenarios]
    return tfrecord.write_records((encode_scenario(s) for s in scenarios), path, compress=compress)


__all__ = [
    "NAME", "sniff", "read", "decode_scenario", "parse_scenario_proto", "scenario_from_proto", "scenario_to_proto",
    "encode_scenario", "write_womd_tfrecord",
]
