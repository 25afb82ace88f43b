"""Scenes edited so that a leader brakes in front of its follower: the pairs, and the edited log.

Training stage (closed-loop fine-tuning that keeps gaps, :mod:`smart_marl.catk`) and the reactivity
benchmark (``benchmarks/reactivity.py``, part (c)) both need the vehicles that follow another one
in its lane, and training needs the leader's log rewritten as a hard stop: its path is the logged
one, its speed falls at a constant deceleration from an onset frame until it stands. The follower's
log is left as it was, so the log alone would drive it into the leader; that is the point: a
closed-loop target that keeps gaps has to brake where the log does not.

What comes in: a :class:`~smart_marl.scenario.Scenario`. What goes out: ``(leader, follower, gap)``
track indices, or a new Scenario (the input is not modified) whose leaders' positions, headings and
velocities from the onset on follow the stop.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .scenario import DT_S, AgentType, Scenario

FOLLOW_GAP_M = 30.0  # a follower's centre at most this far behind its leader
LANE_HALF_M = 1.75  # "in its lane": lateral offset within this
SAME_DIRECTION_RAD = math.radians(30.0)
LEADER_MIN_MPS = 3.0
FOLLOWER_MIN_MPS = 1.0


def speeds_now(scene: Scenario) -> np.ndarray:
    """[N] every track's speed at the current frame (m/s, from the last 0.1 s of its position; 0 where
    either frame is missing)."""
    tr, cf = scene.tracks, scene.current_frame
    ok = tr.valid[:, cf] & tr.valid[:, cf - 1]
    return np.where(ok, np.linalg.norm(tr.position[:, cf, :2] - tr.position[:, cf - 1, :2], axis=-1) / DT_S, 0.0)


def poses_relative_to(scene: Scenario, i: int) -> np.ndarray:
    """[N, 3] every track's current pose in track ``i``'s frame (x forward, y left, heading)."""
    tr, cf = scene.tracks, scene.current_frame
    d = tr.position[:, cf, :2].astype(np.float64) - tr.position[i, cf, :2]
    h = float(tr.heading[i, cf])
    c, s = math.cos(h), math.sin(h)
    dh = np.angle(np.exp(1j * (tr.heading[:, cf].astype(np.float64) - h)))
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], dh], -1)


def leader_follower_pairs(scene: Scenario, max_gap_m: float = FOLLOW_GAP_M, max_pairs: int | None = None) -> list[tuple[int, int, float]]:
    """(leader, follower, centre gap m) track indices: vehicles valid at the current frame, the leader moving
    faster than :data:`LEADER_MIN_MPS`, the follower (faster than :data:`FOLLOWER_MIN_MPS`) the nearest vehicle
    behind it (centre within ``max_gap_m``) in its lane (lateral offset within :data:`LANE_HALF_M`, heading
    within 30 degrees). Nearest pairs first; at most ``max_pairs``."""
    tr, cf = scene.tracks, scene.current_frame
    v = speeds_now(scene)
    veh = tr.valid[:, cf] & (tr.types == int(AgentType.VEHICLE))
    out = []
    for i in np.flatnonzero(veh & (v > LEADER_MIN_MPS)):
        rel = poses_relative_to(scene, int(i))
        behind = veh & (v > FOLLOWER_MIN_MPS) & _in_lane_behind(rel, max_gap_m)
        behind[i] = False
        if behind.any():
            j = int(np.flatnonzero(behind)[np.argmax(rel[behind, 0])])
            out.append((int(i), j, float(-rel[j, 0])))
    out.sort(key=lambda p: p[2])
    return out[:max_pairs] if max_pairs else out


def _last_if_unbroken(valid: np.ndarray, onset_frame: int) -> int | None:
    """A track's last valid frame when it is valid without a gap from ``onset_frame - 1`` to it and that
    frame is at or after the onset; else None (the track cannot brake from there)."""
    last = int(np.flatnonzero(valid)[-1]) if valid.any() else -1
    return last if last >= onset_frame and valid[onset_frame - 1 : last + 1].all() else None


def brake_along_log(scene: Scenario, track: int, onset_frame: int, decel_mps2: float) -> Scenario:
    """``scene`` with track ``track`` braking at ``decel_mps2`` from ``onset_frame`` on, along its logged path,
    to a standstill where it stays. The track must be valid from ``onset_frame - 1`` to its last valid frame
    without a gap (the frames after its last valid one stay absent). Its speed at the onset is the log's
    (the last 0.1 s); positions are placed on the logged path by distance travelled, headings and heights
    taken from the log at that distance, velocities along the heading."""
    tr = scene.tracks
    if not 1 <= onset_frame < scene.num_frames:
        raise ValueError(f"brake_along_log: onset frame {onset_frame} outside 1..{scene.num_frames - 1}")
    if decel_mps2 <= 0:
        raise ValueError(f"brake_along_log: decel_mps2 must be > 0, got {decel_mps2}")
    last = _last_if_unbroken(tr.valid[track], onset_frame)
    if last is None:
        raise ValueError(f"brake_along_log: track {track} (id {int(tr.ids[track])}) is not valid without a gap "
                         f"from frame {onset_frame - 1} to its end")
    path = tr.position[track, onset_frame - 1 : last + 1].astype(np.float64)  # the logged path from the frame before the onset
    step = np.linalg.norm(np.diff(path[:, :2], axis=0), axis=-1)
    along = np.concatenate([[0.0], np.cumsum(step)])  # distance along the logged path at each logged frame
    v0 = step[0] / DT_S
    t = DT_S * np.arange(1, last - onset_frame + 2)  # seconds from the frame before the onset
    t_stop = v0 / decel_mps2
    travelled = np.where(t < t_stop, v0 * t - 0.5 * decel_mps2 * t**2, 0.5 * v0 * t_stop)
    travelled = np.minimum(travelled, along[-1])
    position = tr.position.copy()
    heading, velocity = tr.heading.copy(), tr.velocity.copy()
    frames = np.arange(onset_frame, last + 1)
    for c in range(3):
        position[track, frames, c] = np.interp(travelled, along, path[:, c])
    h_log = np.unwrap(tr.heading[track, onset_frame - 1 : last + 1].astype(np.float64))
    heading[track, frames] = np.angle(np.exp(1j * np.interp(travelled, along, h_log)))
    speed = np.clip(v0 - decel_mps2 * t, 0.0, None)
    velocity[track, frames] = np.stack([np.cos(heading[track, frames]), np.sin(heading[track, frames])], -1) * speed[:, None]
    tracks = dataclasses.replace(tr, position=position, heading=heading, velocity=velocity)
    return dataclasses.replace(scene, tracks=tracks)


def braking_leaders(scene: Scenario, rng: np.random.Generator, share: float, decel_mps2: tuple[float, float] = (4.0, 9.0),
                    onset_s: tuple[float, float] = (0.0, 3.0)) -> list[tuple[int, int, float]]:
    """Which leaders of ``scene`` brake: (track, onset frame, deceleration) for each of its leader / follower
    pairs' leaders (:func:`leader_follower_pairs`; a leader once) with probability ``share``, at a deceleration
    drawn uniformly from ``decel_mps2`` from an onset drawn from ``onset_s`` after the current frame (on the
    10 Hz grid); leaders whose log has a gap from the onset on are left out. Draws come from ``rng``."""
    out: list[tuple[int, int, float]] = []
    if share <= 0:
        return out
    done = set()
    for leader, _follower, _gap in leader_follower_pairs(scene):
        if leader in done:
            continue
        done.add(leader)
        brakes, decel, onset = rng.random() < share, rng.uniform(*decel_mps2), rng.uniform(*onset_s)
        frame = scene.current_frame + 1 + int(round(onset / DT_S))
        if brakes and _last_if_unbroken(scene.tracks.valid[leader], frame) is not None:
            out.append((leader, frame, float(decel)))
    return out


def _in_lane_behind(rel: np.ndarray, max_gap_m: float) -> np.ndarray:
    """bool [N]: the tracks whose centre is within ``max_gap_m`` behind a track in its lane (lateral offset within
    :data:`LANE_HALF_M`, heading within 30 degrees of its), ``rel`` [N, 3] their poses relative to it
    (:func:`poses_relative_to`)."""
    return (rel[:, 0] < 0) & (-rel[:, 0] <= max_gap_m) & (np.abs(rel[:, 1]) < LANE_HALF_M) & (np.abs(rel[:, 2]) < SAME_DIRECTION_RAD)


def behind_in_lane(scene: Scenario, tracks, max_gap_m: float) -> np.ndarray:
    """bool [N]: the vehicles valid at the current frame within ``max_gap_m`` behind any of ``tracks`` in its
    lane (:func:`_in_lane_behind`): the queue a braking leader holds up, not only its nearest follower."""
    tr, cf = scene.tracks, scene.current_frame
    veh = tr.valid[:, cf] & (tr.types == int(AgentType.VEHICLE))
    out = np.zeros(scene.num_tracks, bool)
    for i in tracks:
        out |= veh & _in_lane_behind(poses_relative_to(scene, int(i)), max_gap_m)
    return out


def with_braking_leaders(scene: Scenario, edits: list[tuple[int, int, float]]) -> Scenario:
    """``scene`` with each (track, onset frame, deceleration) of ``edits`` (:func:`braking_leaders`) braking."""
    for track, frame, decel in edits:
        scene = brake_along_log(scene, track, frame, decel)
    return scene
