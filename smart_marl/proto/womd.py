"""The Waymo Open Motion Dataset wire schema, defined by this project (no protoc, no TensorFlow).

Stage: below the readers. ``smart_marl.readers.womd`` decodes WOMD ``Scenario`` records with these
classes and writes them back; ``smart_marl.readers.submission`` parses and writes sim-agents
submissions (``SimAgentsChallengeSubmission``).

The schema is a ``FileDescriptorProto`` built here at import time (proto2, package
``waymo.open_dataset``, the field numbers of Waymo's ``scenario.proto``, ``map.proto`` and
``sim_agents_submission.proto``; see docs/womd_wire_format.md) and turned into message classes with
``message_factory.GetMessageClass``, which works across protobuf 4.x-6.x and every backend (upb,
C++, pure Python). Only the fields the project uses are declared; anything else in a record (e.g.
the field 3 of older ``Scenario`` records) is skipped on parsing as an unknown field and kept
verbatim on re-serialising.

Enum names follow Waymo's (``Track.TYPE_VEHICLE``, ``TrafficSignalLaneState.LANE_STATE_GO``...).
"""

from __future__ import annotations

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

PACKAGE = "waymo.open_dataset"
FILE_NAME = "smart_marl/proto/womd_scenario_and_submission.proto"

_F = descriptor_pb2.FieldDescriptorProto
_OPTIONAL, _REPEATED = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED
_SCALAR = {
    "double": _F.TYPE_DOUBLE, "float": _F.TYPE_FLOAT, "int32": _F.TYPE_INT32, "int64": _F.TYPE_INT64,
    "bool": _F.TYPE_BOOL, "string": _F.TYPE_STRING,
}

# message name -> [(field name, number, label, type, packed)]; a type that is not a scalar name is a
# message (".Name") or an enum ("enum:.Name"), fully qualified inside the package.
_MESSAGES: dict[str, list[tuple]] = {
    # ---------------------------------------------------------------------------- map.proto
    "MapPoint": [("x", 1, "", "double"), ("y", 2, "", "double"), ("z", 3, "", "double")],
    "BoundarySegment": [
        ("lane_start_index", 1, "", "int32"), ("lane_end_index", 2, "", "int32"),
        ("boundary_feature_id", 3, "", "int64"), ("boundary_type", 4, "", "enum:RoadLine.RoadLineType"),
    ],
    "LaneNeighbor": [
        ("feature_id", 1, "", "int64"), ("self_start_index", 2, "", "int32"), ("self_end_index", 3, "", "int32"),
        ("neighbor_start_index", 4, "", "int32"), ("neighbor_end_index", 5, "", "int32"),
        ("boundaries", 6, "repeated", "BoundarySegment"),
    ],
    "LaneCenter": [
        ("speed_limit_mph", 1, "", "double"), ("type", 2, "", "enum:LaneCenter.LaneType"),
        ("interpolating", 3, "", "bool"), ("polyline", 8, "repeated", "MapPoint"),
        ("entry_lanes", 9, "packed", "int64"), ("exit_lanes", 10, "packed", "int64"),
        ("left_neighbors", 11, "repeated", "LaneNeighbor"), ("right_neighbors", 12, "repeated", "LaneNeighbor"),
        ("left_boundaries", 13, "repeated", "BoundarySegment"), ("right_boundaries", 14, "repeated", "BoundarySegment"),
    ],
    "RoadLine": [("type", 1, "", "enum:RoadLine.RoadLineType"), ("polyline", 2, "repeated", "MapPoint")],
    "RoadEdge": [("type", 1, "", "enum:RoadEdge.RoadEdgeType"), ("polyline", 2, "repeated", "MapPoint")],
    "StopSign": [("lane", 1, "repeated", "int64"), ("position", 2, "", "MapPoint")],
    "Crosswalk": [("polygon", 1, "repeated", "MapPoint")],
    "SpeedBump": [("polygon", 1, "repeated", "MapPoint")],
    "Driveway": [("polygon", 1, "repeated", "MapPoint")],
    "MapFeature": [
        ("id", 1, "", "int64"),
        ("lane", 3, "oneof", "LaneCenter"), ("road_line", 4, "oneof", "RoadLine"), ("road_edge", 5, "oneof", "RoadEdge"),
        ("stop_sign", 7, "oneof", "StopSign"), ("crosswalk", 8, "oneof", "Crosswalk"),
        ("speed_bump", 9, "oneof", "SpeedBump"), ("driveway", 10, "oneof", "Driveway"),
    ],
    "TrafficSignalLaneState": [
        ("lane", 1, "", "int64"), ("state", 2, "", "enum:TrafficSignalLaneState.State"),
        ("stop_point", 3, "", "MapPoint"),
    ],
    "DynamicMapState": [("lane_states", 1, "repeated", "TrafficSignalLaneState")],
    # ----------------------------------------------------------------------- scenario.proto
    "ObjectState": [
        ("center_x", 2, "", "double"), ("center_y", 3, "", "double"), ("center_z", 4, "", "double"),
        ("length", 5, "", "float"), ("width", 6, "", "float"), ("height", 7, "", "float"),
        ("heading", 8, "", "float"), ("velocity_x", 9, "", "float"), ("velocity_y", 10, "", "float"),
        ("valid", 11, "", "bool"),
    ],
    "Track": [("id", 1, "", "int32"), ("object_type", 2, "", "enum:Track.ObjectType"), ("states", 3, "repeated", "ObjectState")],
    "RequiredPrediction": [("track_index", 1, "", "int32"), ("difficulty", 2, "", "enum:RequiredPrediction.DifficultyLevel")],
    "Scenario": [
        ("timestamps_seconds", 1, "repeated", "double"), ("tracks", 2, "repeated", "Track"),
        ("objects_of_interest", 4, "repeated", "int32"), ("scenario_id", 5, "", "string"),
        ("sdc_track_index", 6, "", "int32"), ("dynamic_map_states", 7, "repeated", "DynamicMapState"),
        ("map_features", 8, "repeated", "MapFeature"), ("current_time_index", 10, "", "int32"),
        ("tracks_to_predict", 11, "repeated", "RequiredPrediction"),
    ],
    # ---------------------------------------------------------- sim_agents_submission.proto
    "SimulatedTrajectory": [
        ("center_x", 2, "packed", "float"), ("center_y", 3, "packed", "float"), ("center_z", 4, "packed", "float"),
        ("heading", 5, "packed", "float"), ("object_id", 6, "", "int32"), ("width", 7, "packed", "float"),
        ("length", 8, "packed", "float"), ("height", 9, "packed", "float"),
        ("object_type", 10, "", "enum:Track.ObjectType"), ("valid", 11, "packed", "bool"),
    ],
    "JointScene": [("simulated_trajectories", 1, "repeated", "SimulatedTrajectory")],
    "ScenarioRollouts": [("scenario_id", 1, "", "string"), ("joint_scenes", 2, "repeated", "JointScene")],
    "SimAgentsChallengeSubmission": [
        ("scenario_rollouts", 1, "repeated", "ScenarioRollouts"),
        ("submission_type", 2, "", "enum:SimAgentsChallengeSubmission.SubmissionType"),
        ("account_name", 3, "", "string"), ("unique_method_name", 4, "", "string"),
        ("authors", 5, "repeated", "string"), ("affiliation", 6, "", "string"), ("description", 7, "", "string"),
        ("method_link", 8, "", "string"), ("uses_lidar_data", 9, "", "bool"), ("uses_camera_data", 10, "", "bool"),
        ("uses_public_model_pretraining", 11, "", "bool"), ("num_model_parameters", 12, "", "string"),
        ("public_model_names", 13, "repeated", "string"),
        ("acknowledge_complies_with_closed_loop_requirement", 14, "", "bool"),
    ],
}

# (message, enum name) -> [(value name, number)]
_ENUMS: dict[tuple[str, str], list[tuple[str, int]]] = {
    ("LaneCenter", "LaneType"): [("TYPE_UNDEFINED", 0), ("TYPE_FREEWAY", 1), ("TYPE_SURFACE_STREET", 2), ("TYPE_BIKE_LANE", 3)],
    ("RoadLine", "RoadLineType"): [
        ("TYPE_UNKNOWN", 0), ("TYPE_BROKEN_SINGLE_WHITE", 1), ("TYPE_SOLID_SINGLE_WHITE", 2),
        ("TYPE_SOLID_DOUBLE_WHITE", 3), ("TYPE_BROKEN_SINGLE_YELLOW", 4), ("TYPE_BROKEN_DOUBLE_YELLOW", 5),
        ("TYPE_SOLID_SINGLE_YELLOW", 6), ("TYPE_SOLID_DOUBLE_YELLOW", 7), ("TYPE_PASSING_DOUBLE_YELLOW", 8),
    ],
    ("RoadEdge", "RoadEdgeType"): [("TYPE_UNKNOWN", 0), ("TYPE_ROAD_EDGE_BOUNDARY", 1), ("TYPE_ROAD_EDGE_MEDIAN", 2)],
    ("TrafficSignalLaneState", "State"): [
        ("LANE_STATE_UNKNOWN", 0), ("LANE_STATE_ARROW_STOP", 1), ("LANE_STATE_ARROW_CAUTION", 2),
        ("LANE_STATE_ARROW_GO", 3), ("LANE_STATE_STOP", 4), ("LANE_STATE_CAUTION", 5), ("LANE_STATE_GO", 6),
        ("LANE_STATE_FLASHING_STOP", 7), ("LANE_STATE_FLASHING_CAUTION", 8),
    ],
    ("Track", "ObjectType"): [("TYPE_UNSET", 0), ("TYPE_VEHICLE", 1), ("TYPE_PEDESTRIAN", 2), ("TYPE_CYCLIST", 3), ("TYPE_OTHER", 4)],
    ("RequiredPrediction", "DifficultyLevel"): [("NONE", 0), ("LEVEL_1", 1), ("LEVEL_2", 2)],
    ("SimAgentsChallengeSubmission", "SubmissionType"): [("UNKNOWN", 0), ("SIM_AGENTS_SUBMISSION", 1)],
}


def build_file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    """The schema as a FileDescriptorProto (proto2, package ``waymo.open_dataset``)."""
    fdp = descriptor_pb2.FileDescriptorProto(name=FILE_NAME, package=PACKAGE, syntax="proto2")
    for msg_name, fields in _MESSAGES.items():
        msg = fdp.message_type.add(name=msg_name)
        for (owner, enum_name), values in _ENUMS.items():
            if owner == msg_name:
                enum = msg.enum_type.add(name=enum_name)
                for value_name, number in values:
                    enum.value.add(name=value_name, number=number)
        if any(kind == "oneof" for _, _, kind, _ in fields):
            msg.oneof_decl.add(name="feature_data")
        for name, number, kind, type_name in fields:
            field = msg.field.add(name=name, number=number, label=_REPEATED if kind in ("repeated", "packed") else _OPTIONAL)
            if type_name in _SCALAR:
                field.type = _SCALAR[type_name]
            elif type_name.startswith("enum:"):
                field.type = _F.TYPE_ENUM
                field.type_name = f".{PACKAGE}.{type_name[5:]}"
            else:
                field.type = _F.TYPE_MESSAGE
                field.type_name = f".{PACKAGE}.{type_name}"
            if kind == "packed":
                field.options.packed = True
            if kind == "oneof":
                field.oneof_index = 0
    return fdp


# The fields that the raw-points view reads as undecoded bytes (one element per sub-message).
RAW_POINT_FIELDS = {
    ("Track", "states"), ("LaneCenter", "polyline"), ("RoadLine", "polyline"), ("RoadEdge", "polyline"),
    ("Crosswalk", "polygon"), ("SpeedBump", "polygon"), ("Driveway", "polygon"),
}


def build_raw_points_descriptor() -> descriptor_pb2.FileDescriptorProto:
    """The same schema in which the repeated ``ObjectState`` and ``MapPoint`` fields of
    :data:`RAW_POINT_FIELDS` are ``repeated bytes`` (the same wire type): parsing a record with it
    leaves every state and map point as its serialized bytes, which the WOMD reader decodes for a
    whole scene at once with numpy instead of one Python attribute access per value."""
    fdp = build_file_descriptor()
    fdp.name = FILE_NAME.replace(".proto", "_raw_points.proto")
    for msg in fdp.message_type:
        for field in msg.field:
            if (msg.name, field.name) in RAW_POINT_FIELDS:
                field.type = _F.TYPE_BYTES
                field.ClearField("type_name")
    return fdp


def _build_classes(fdp: descriptor_pb2.FileDescriptorProto) -> dict[str, type]:
    # A private pool: never clashes with a real waymo_open_dataset installed in the same process.
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    return {name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{PACKAGE}.{name}")) for name in _MESSAGES}


_CLASSES = _build_classes(build_file_descriptor())
RAW_POINTS = _build_classes(build_raw_points_descriptor())
"""Message classes of the raw-points view (see :func:`build_raw_points_descriptor`), by name."""

MapPoint = _CLASSES["MapPoint"]
BoundarySegment = _CLASSES["BoundarySegment"]
LaneNeighbor = _CLASSES["LaneNeighbor"]
LaneCenter = _CLASSES["LaneCenter"]
RoadLine = _CLASSES["RoadLine"]
RoadEdge = _CLASSES["RoadEdge"]
StopSign = _CLASSES["StopSign"]
Crosswalk = _CLASSES["Crosswalk"]
SpeedBump = _CLASSES["SpeedBump"]
Driveway = _CLASSES["Driveway"]
MapFeature = _CLASSES["MapFeature"]
TrafficSignalLaneState = _CLASSES["TrafficSignalLaneState"]
DynamicMapState = _CLASSES["DynamicMapState"]
ObjectState = _CLASSES["ObjectState"]
Track = _CLASSES["Track"]
RequiredPrediction = _CLASSES["RequiredPrediction"]
Scenario = _CLASSES["Scenario"]
SimulatedTrajectory = _CLASSES["SimulatedTrajectory"]
JointScene = _CLASSES["JointScene"]
ScenarioRollouts = _CLASSES["ScenarioRollouts"]
SimAgentsChallengeSubmission = _CLASSES["SimAgentsChallengeSubmission"]

__all__ = ["build_file_descriptor", "build_raw_points_descriptor", "RAW_POINTS", *_MESSAGES]
