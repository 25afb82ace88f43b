"""Wire schemas the project defines itself (protobuf messages built at import time, no protoc).

``smart_marl.proto.womd``: the Waymo Open Motion Dataset ``Scenario`` and the sim-agents
submission (``SimAgentsChallengeSubmission``...), used by the WOMD reader/writer and the
submission helpers.
"""

from .womd import (  # noqa: F401
    BoundarySegment, Crosswalk, Driveway, DynamicMapState, JointScene, LaneCenter, LaneNeighbor, MapFeature,
    MapPoint, ObjectState, RequiredPrediction, RoadEdge, RoadLine, Scenario, ScenarioRollouts,
    SimAgentsChallengeSubmission, SimulatedTrajectory, SpeedBump, StopSign, Track, TrafficSignalLaneState,
)
