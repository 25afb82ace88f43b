"""Inputs of the realism metrics: the logged scene as plain arrays, and simulated rollouts.

Stage: metrics. :func:`logged_scene` turns a :class:`~smart_marl.scenario.Scenario` into a
:class:`LoggedScene` (the simulated agents' logged boxes, the evaluated agents, road edges, lanes
and signals); :class:`Rollouts` holds simulated trajectories ``[R, A, 80]`` (x, y, z, heading) of
the same agents in the scene's local frame. The features (:mod:`.features`) are pure functions of
these two.

Frames and precision: the official package computes in float32 in the *source* frame (WOMD
coordinates are thousands of metres, so float32 rounds them to ~1e-4 m); a value that sits on a
histogram edge then falls on the side that rounding decides. To give the official numbers, the
metrics see what a submission file carries: the LoggedScene holds float32-exact source-frame
coordinates (float64 arrays of float32 values, from ``scene.frame.to_source``), and rollouts are
mapped to the source frame and rounded to float32 the same way (:func:`metric_frame_rollouts`).
Distances are frame-independent, so nothing else changes.

Who is who (the challenge's rules): simulated agents are every track valid at the current step
(index 10), in scenario order; evaluated agents are the self-driving car plus the tracks to
predict, unique and sorted by id.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import SmartMarlError
from ..geometry import RoadEdgeSegments
from ..scenario import AgentType, LaneType, MapFeatureType, Scenario, SceneFrame
from .config import CURRENT_STEP, NUM_SIMULATION_STEPS, NUM_STEPS


class RolloutError(SmartMarlError, ValueError):
    """Simulated rollouts that do not fit the scene (wrong steps, missing or extra agents)."""


class SceneNotScorableError(RolloutError):
    """A scene the realism metrics cannot score, whatever the rollouts: not 91 frames with the
    current frame at 10 (``smart-marl eval`` first cuts every scene to such a window,
    :mod:`smart_marl.metrics.windows`, and raises this when none fits or the rate cannot be resampled), or no
    evaluated agent (no self-driving car and no track to predict; through a window, none that the windows'
    rule picks either), or an evaluated agent not valid at the current frame. ``smart-marl eval`` skips such a
    scene with a warning naming it."""


@dataclass(frozen=True)
class LaneMap:
    """Surface-street lanes padded as the official traffic-light code pads them.

    ``points`` [NL, P, 2] (padding points sit at the *source* origin, an official quirk: the segment
    from a lane's last point to its first padding point counts), ``point_valid`` [NL, P],
    ``ids`` [NL]."""

    ids: np.ndarray
    points: np.ndarray
    point_valid: np.ndarray


@dataclass(frozen=True)
class Signals:
    """Traffic signals: ``lane_ids`` [L], ``states`` [T, L] (0 where absent), ``stop_points`` [L, 2]."""

    lane_ids: np.ndarray
    states: np.ndarray
    stop_points: np.ndarray


@dataclass(frozen=True)
class LoggedScene:
    """One scenario's logged side of the metrics. ``A`` simulated agents, ``E`` evaluated, 91 steps.

    Arrays (float64 holding float32 values, source frame): ``position`` [A, 91, 3], ``heading`` [A, 91] (raw, not wrapped),
    ``size`` [A, 91, 3] length/width/height per step, ``valid`` [A, 91]; ``object_ids`` [A],
    ``object_types`` [A] (AgentType); ``evaluated`` [E] indices into the A agents (sorted by id).
    """

    scenario_id: str
    object_ids: np.ndarray
    object_types: np.ndarray
    evaluated: np.ndarray
    position: np.ndarray
    heading: np.ndarray
    size: np.ndarray
    valid: np.ndarray
    road_edges: RoadEdgeSegments
    lanes: LaneMap | None = None
    signals: Signals | None = None
    frame: SceneFrame = field(default_factory=SceneFrame)

    @property
    def num_agents(self) -> int:
        return int(self.object_ids.shape[0])

    @property
    def evaluated_ids(self) -> np.ndarray:
        return self.object_ids[self.evaluated]


@dataclass(frozen=True)
class Rollouts:
    """Simulated futures of a scene's simulated agents: ``x``, ``y``, ``z``, ``heading`` [R, A, 80]
    (float64, the scene's local frame), agents in the order of ``object_ids`` [A]."""

    object_ids: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    heading: np.ndarray

    @property
    def num_rollouts(self) -> int:
        return int(self.x.shape[0])

    @classmethod
    def from_array(cls, object_ids, trajectories) -> "Rollouts":
        """From an array [R, A, 80, 4] of x, y, z, heading."""
        t = np.asarray(trajectories, dtype=np.float64)
        return cls(np.asarray(object_ids, np.int64), t[..., 0], t[..., 1], t[..., 2], t[..., 3])

    @classmethod
    def from_source(cls, object_ids, trajectories_source, frame: SceneFrame) -> "Rollouts":
        """From source-frame trajectories [R, A, 80, 4] (e.g. read from a submission file)."""
        t = np.asarray(trajectories_source, dtype=np.float64)
        xyz = frame.from_source(t[..., :3])
        heading = t[..., 3] - frame.heading if frame.heading != 0.0 else t[..., 3]
        return cls(np.asarray(object_ids, np.int64), xyz[..., 0], xyz[..., 1], xyz[..., 2], heading)

    def to_source(self, frame: SceneFrame) -> np.ndarray:
        """Source-frame trajectories [R, A, 80, 4]."""
        xyz = frame.to_source(np.stack([self.x, self.y, self.z], axis=-1))
        heading = self.heading + frame.heading if frame.heading != 0.0 else self.heading
        return np.concatenate([xyz, heading[..., None]], axis=-1)


def simulated_agent_indices(scenario: Scenario) -> np.ndarray:
    """Track indices of the simulated agents: valid at the current step, in scenario order."""
    return np.flatnonzero(scenario.tracks.valid[:, scenario.current_frame])


def evaluated_track_indices(scenario: Scenario) -> np.ndarray:
    """Track indices of the evaluated agents: SDC + tracks to predict, unique, sorted by id."""
    idx = set(int(i) for i in scenario.predict_indices)
    if scenario.sdc_index >= 0:
        idx.add(scenario.sdc_index)
    idx = np.array(sorted(idx), dtype=np.int64)
    return idx[np.argsort(scenario.tracks.ids[idx], kind="stable")]


def _source32(frame: SceneFrame, xyz: np.ndarray) -> np.ndarray:
    """Local points -> float32-rounded source points, as float64."""
    return frame.to_source(np.asarray(xyz, np.float64)).astype(np.float32).astype(np.float64)


def _polylines(scenario: Scenario, feature_type: MapFeatureType, subtype: int | None = None):
    rm = scenario.road_map
    out, ids = [], []
    for i in rm.indices_of(feature_type):
        if subtype is not None and int(rm.subtypes[i]) != subtype:
            continue
        out.append(_source32(scenario.frame, rm.feature_points(int(i))))
        ids.append(int(rm.ids[i]))
    return out, ids


def lane_map(polylines: list[np.ndarray], ids: list[int], pad_point_xy: np.ndarray) -> LaneMap | None:
    """Pad lane polylines [n_i, >=2] to the longest (padding at ``pad_point_xy``); None when none."""
    keep = [(np.asarray(p, np.float64)[:, :2], i) for p, i in zip(polylines, ids) if len(p) >= 2]
    if not keep:
        return None
    max_len = max(len(p) for p, _ in keep)
    pts = np.empty((len(keep), max_len, 2))
    pts[:] = pad_point_xy
    valid = np.zeros((len(keep), max_len), bool)
    for k, (p, _) in enumerate(keep):
        pts[k, : len(p)] = p
        valid[k, : len(p)] = True
    # lane ids are int32 in the official code
    lane_ids = np.array([i for _, i in keep], dtype=np.int64).astype(np.int32).astype(np.int64)
    return LaneMap(lane_ids, pts, valid)


def logged_scene(scenario: Scenario, evaluated_tracks: np.ndarray | None = None) -> LoggedScene:
    """The metrics' logged inputs of a (WOMD-like, 91-step) scenario. ``evaluated_tracks``: track
    indices to evaluate instead of the challenge's (the SDC and the tracks to predict), e.g. the
    agents a policy controls; they must be valid at the current step."""
    if scenario.num_frames != NUM_STEPS or scenario.current_frame != CURRENT_STEP:
        raise SceneNotScorableError(
            f"scenario {scenario.scenario_id}: the sim-agents metrics need {NUM_STEPS} frames with the current frame "
            f"at {CURRENT_STEP} (got {scenario.num_frames} frames, current {scenario.current_frame})"
        )
    sim = simulated_agent_indices(scenario)
    if evaluated_tracks is None:
        ev_tracks = evaluated_track_indices(scenario)
    else:
        ev_tracks = np.unique(np.asarray(evaluated_tracks, np.int64))
        ev_tracks = ev_tracks[np.argsort(scenario.tracks.ids[ev_tracks], kind="stable")]
    if len(ev_tracks) == 0:
        raise SceneNotScorableError(f"scenario {scenario.scenario_id}: no agent to evaluate (the scene has no self-driving car and "
                                    f"no track to predict; the metrics score exactly those)")
    pos_of_track = {int(t): k for k, t in enumerate(sim)}
    missing = [int(scenario.tracks.ids[t]) for t in ev_tracks if int(t) not in pos_of_track]
    if missing:
        raise SceneNotScorableError(f"scenario {scenario.scenario_id}: evaluated agents {missing} are not valid at the current step")
    tr = scenario.tracks
    edges, _ = _polylines(scenario, MapFeatureType.ROAD_EDGE)
    lanes, lane_ids = _polylines(scenario, MapFeatureType.LANE, int(LaneType.SURFACE_STREET))
    pad = np.zeros(2)  # the official padding points sit at the source origin
    tl = scenario.traffic_lights
    signals = None
    if tl.lane_ids.size and tl.present.any():
        states = np.where(tl.present, tl.states, 0).astype(np.int64)
        signals = Signals(tl.lane_ids.astype(np.int32).astype(np.int64), states,
                          _source32(scenario.frame, tl.stop_points)[:, :2])
    heading = tr.heading[sim].astype(np.float64)
    if scenario.frame.heading != 0.0:
        heading = (heading + scenario.frame.heading).astype(np.float32).astype(np.float64)
    return LoggedScene(
        scenario_id=scenario.scenario_id,
        object_ids=tr.ids[sim].astype(np.int64),
        object_types=tr.types[sim].astype(np.int64),
        evaluated=np.array([pos_of_track[int(t)] for t in ev_tracks], dtype=np.int64),
        position=_source32(scenario.frame, tr.position[sim]),
        heading=heading,
        size=tr.size[sim].astype(np.float64),
        valid=tr.valid[sim].copy(),
        road_edges=RoadEdgeSegments.from_polylines(edges),
        lanes=lane_map(lanes, lane_ids, pad),
        signals=signals,
        frame=scenario.frame,
    )


def align_rollouts(scene: LoggedScene, rollouts: Rollouts, where: str = "") -> Rollouts:
    """Rollouts reordered to the scene's simulated agents; RolloutError naming the scenario and the
    object when steps are wrong or agents are missing or extra (``where`` names the file)."""
    prefix = f"{where}: " if where else ""
    sid = scene.scenario_id
    if rollouts.x.ndim != 3 or rollouts.x.shape[-1] != NUM_SIMULATION_STEPS:
        raise RolloutError(f"{prefix}scenario {sid}: rollouts must have {NUM_SIMULATION_STEPS} steps per agent "
                           f"(shape [R, A, {NUM_SIMULATION_STEPS}]), got shape {tuple(rollouts.x.shape)}")
    ids = np.asarray(rollouts.object_ids, np.int64)
    if rollouts.x.shape[1] != len(ids):
        raise RolloutError(f"{prefix}scenario {sid}: {len(ids)} object ids for {rollouts.x.shape[1]} simulated agents")
    uniq, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        raise RolloutError(f"{prefix}scenario {sid}: object {int(uniq[counts > 1][0])} appears more than once")
    extra = np.setdiff1d(ids, scene.object_ids)
    if extra.size:
        raise RolloutError(f"{prefix}scenario {sid}: object {int(extra[0])} is not a simulated agent of the scene "
                           f"({extra.size} extra object(s); simulated agents are the tracks valid at step {CURRENT_STEP})")
    missing = np.setdiff1d(scene.object_ids, ids)
    if missing.size:
        raise RolloutError(f"{prefix}scenario {sid}: simulated agent {int(missing[0])} is missing from the rollouts "
                           f"({missing.size} missing)")
    for name in ("x", "y", "z", "heading"):
        if not np.isfinite(getattr(rollouts, name)).all():
            raise RolloutError(f"{prefix}scenario {sid}: rollouts have non-finite {name} values")
    order = np.argsort(ids)[np.searchsorted(ids[np.argsort(ids)], scene.object_ids)]
    return Rollouts(scene.object_ids, rollouts.x[:, order], rollouts.y[:, order], rollouts.z[:, order],
                    rollouts.heading[:, order])


def is_vehicle(scene: LoggedScene) -> np.ndarray:
    return scene.object_types == int(AgentType.VEHICLE)


def metric_frame_rollouts(scene: LoggedScene, rollouts: Rollouts) -> Rollouts:
    """Local-frame rollouts -> the metrics' frame: source coordinates rounded to float32 (what a
    submission file would carry; see the module docstring)."""
    src = rollouts.to_source(scene.frame).astype(np.float32).astype(np.float64)
    return Rollouts.from_array(rollouts.object_ids, src)
