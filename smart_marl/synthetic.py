"""Small synthetic scenes built from nothing: for tests and for commands that must run without any
data on disk. A straight multi-lane road with a crosswalk, a signalised lane and cars that follow
their lanes at constant speed, some appearing late. Not realistic traffic; the real scenes are the
readers' job."""

from __future__ import annotations

import numpy as np

from .scenario import (
    CURRENT_FRAME, DT_S, AgentType, LaneType, LinkType, MapFeatureType, RoadEdgeType, RoadMap, SceneFrame, Scenario, SignalState,
    TrafficLights, Tracks,
)


def synthetic_scenario(seed: int = 0, num_frames: int = 91, num_vehicles: int = 6, num_pedestrians: int = 2,
                       lane_count: int = 3, lane_width_m: float = 3.5, source_origin=(1000.0, -2000.0, 10.0)) -> Scenario:
    """A reproducible synthetic scene (``seed`` picks speeds and placements)."""
    rng = np.random.default_rng(seed)
    length_m = 200.0
    xs = np.linspace(-length_m / 2, length_m / 2, 41)
    features, links = [], []
    for k in range(lane_count):
        y = (k - (lane_count - 1) / 2) * lane_width_m
        # each lane in two halves so that lanes have successors and predecessors
        a, b = 100 + 2 * k, 101 + 2 * k
        features.append(dict(id=a, type=MapFeatureType.LANE, subtype=LaneType.SURFACE_STREET, speed_limit_mph=30.0,
                             points=np.stack([xs[:21], np.full(21, y), np.zeros(21)], 1)))
        features.append(dict(id=b, type=MapFeatureType.LANE, subtype=LaneType.SURFACE_STREET, speed_limit_mph=30.0,
                             points=np.stack([xs[20:], np.full(21, y), np.zeros(21)], 1)))
    for k in range(lane_count):  # links grouped per lane in WOMD's order, so a WOMD round trip is exact
        a, b = 100 + 2 * k, 101 + 2 * k
        links += [(a, b, LinkType.SUCCESSOR)]
        links += [(a, a + 2, LinkType.LEFT_NEIGHBOR)] if k < lane_count - 1 else []
        links += [(a, a - 2, LinkType.RIGHT_NEIGHBOR)] if k > 0 else []
        links += [(b, a, LinkType.PREDECESSOR)]
    half = lane_count * lane_width_m / 2
    for i, y in enumerate((-half, half)):
        features.append(dict(id=200 + i, type=MapFeatureType.ROAD_EDGE, subtype=RoadEdgeType.BOUNDARY,
                             points=np.stack([xs[::-1] if i else xs, np.full(41, y), np.zeros(41)], 1)))  # drivable area on the left (CCW)
    features.append(dict(id=300, type=MapFeatureType.CROSSWALK,
                         points=[[20, -half, 0], [24, -half, 0], [24, half, 0], [20, half, 0]]))
    road_map = RoadMap.from_features(features, links)

    n = num_vehicles + num_pedestrians
    t = np.arange(num_frames) * DT_S
    pos = np.zeros((n, num_frames, 3))
    heading = np.zeros((n, num_frames))
    vel = np.zeros((n, num_frames, 2))
    size = np.zeros((n, num_frames, 3))
    valid = np.ones((n, num_frames), bool)
    types = np.zeros(n, np.int8)
    for i in range(num_vehicles):
        lane = i % lane_count
        speed = rng.uniform(3.0, 12.0)
        x0 = rng.uniform(-90, -10)
        pos[i, :, 0] = x0 + speed * t
        pos[i, :, 1] = (lane - (lane_count - 1) / 2) * lane_width_m
        vel[i, :, 0] = speed
        size[i] = (4.6, 1.9, 1.6)
        if i == num_vehicles - 1:  # appears late
            valid[i, :15] = False
    for j in range(num_pedestrians):
        i = num_vehicles + j
        types[i] = AgentType.PEDESTRIAN
        speed = rng.uniform(0.8, 1.6)
        pos[i, :, 0] = 22.0 + j
        pos[i, :, 1] = -half + speed * t
        heading[i] = np.pi / 2
        vel[i, :, 1] = speed
        size[i] = (0.8, 0.8, 1.8)
    pos[..., 2] = 0.8
    # Like the readers: the local frame's origin is the self-driving car at the current frame.
    current = min(CURRENT_FRAME, num_frames - 1)
    offset = pos[0, current].copy()
    pos -= offset
    road_map = road_map._transform(lambda p: (p - offset).astype(np.float32))
    ox, oy, oz = np.asarray(source_origin) + offset
    tl_states = np.where((np.arange(num_frames) // 40) % 2 == 0, SignalState.GO, SignalState.STOP)
    return Scenario(
        scenario_id=f"synthetic-{seed:04d}",
        source="synthetic",
        timestamps_s=t,
        current_frame=current,
        tracks=Tracks(ids=np.arange(n) + 1, types=types, position=pos, heading=heading, velocity=vel, size=size,
                      valid=valid),
        road_map=road_map,
        traffic_lights=TrafficLights(lane_ids=[101], states=tl_states[:, None], present=np.ones((num_frames, 1), bool),
                                     stop_points=[[0.0, -(lane_count - 1) / 2 * lane_width_m, 0.0] - offset]),
        sdc_index=0,
        predict_indices=[1, 2],
        frame=SceneFrame(ox, oy, oz, 0.0),
    )
