"""Environment stage, events and rewards: one token step's 10 Hz poses -> per controlled agent the
events (collision, offroad, goal reached) and a reward made of weighted terms.

Events use the project's one geometry module (:mod:`smart_marl.geometry`, the sim-agents
metrics' rounded boxes and road-edge signed distance):

* collision: the agent's rounded box overlaps another present agent's box at any of the step's
  5 frames (``boxes_overlap``);
* offroad: a vehicle's box has a corner beyond the road edge at the step's last frame (token
  boundaries, every 0.5 s; pedestrians and cyclists are never offroad; nor is anyone in a scene
  without road edges). ``is_offroad`` runs on the road-edge segments that can be nearest to the
  boxes' corners (:func:`crop_road_edges`, exact), which takes its per-call cost on a WOMD scene
  from ~14 ms to ~2 ms;
* goal reached: the agent ends the step within ``goal_radius_m`` of its logged goal (its last
  logged position), for tracks whose logged route is longer than ``goal_radius_m`` (a parked car
  has no goal to reach).

Reward terms (``REWARD_TERMS`` order, also ``infos[agent]["reward_terms"]``): ``progress``
(metres gained along the logged route this step), ``goal_reached`` (1 the step the goal is
reached), ``collision`` (1), ``offroad`` (1), ``comfort`` (mean jerk magnitude over the step's
frames, m/s^3: give it a negative weight), ``prior_log_likelihood`` (log-probability of the
chosen token under the prior, 0 without a prior). The reward is the dot product with
:class:`RewardConfig`'s weights.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Mapping

import numpy as np

from smart_marl.geometry import Z_STRETCH, RoadEdgeSegments, box_corners_float32, colliding, is_offroad, pairwise_distance
from smart_marl.scenario import DT_S, AgentType
from smart_marl.tokens import FRAMES_PER_TOKEN

from ._scene import SceneStatic
from .errors import EnvConfigError, EnvConfigTypeError

REWARD_TERMS = ("progress", "goal_reached", "collision", "offroad", "comfort", "prior_log_likelihood")
TERMINATION_EVENTS = ("collision", "offroad", "goal")


@dataclass(frozen=True)
class RewardConfig:
    """Weights of the reward terms (see the module docstring) and the goal radius."""

    progress: float = 0.1
    goal_reached: float = 1.0
    collision: float = -1.0
    offroad: float = -1.0
    comfort: float = 0.0
    prior_log_likelihood: float = 0.0
    goal_radius_m: float = 2.0

    @classmethod
    def from_any(cls, value) -> "RewardConfig":
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, Mapping):
            known = {f.name for f in fields(cls)}
            unknown = sorted(set(value) - known)
            if unknown:
                raise EnvConfigError(f"unknown reward term(s) {unknown}; known: {sorted(known)}")
            return cls(**value)
        raise EnvConfigTypeError(f"reward must be a RewardConfig, a dict of weights or None, got {type(value).__name__}")

    def weights(self) -> np.ndarray:
        return np.array([getattr(self, t) for t in REWARD_TERMS], np.float64)


def collisions(ctrl: np.ndarray, frames: np.ndarray, present: np.ndarray, box_size: np.ndarray) -> np.ndarray:
    """[C] bool: controlled track ``ctrl[i]`` overlaps another present track at any frame
    (:func:`smart_marl.geometry.colliding`). frames [N, F, 3] poses of every track over the step,
    present [N] bool, box_size [N, 2+] length, width."""
    on = np.broadcast_to(present[:, None], frames.shape[:2])
    return colliding(frames, on, box_size[:, 0], box_size[:, 1], ctrl)


def crop_road_edges(segments: RoadEdgeSegments, points_xyz: np.ndarray) -> RoadEdgeSegments:
    """The segments that can be the nearest (3D, z stretched, as ``signed_distance_to_road_edges``
    picks it) to any of ``points_xyz`` [Q, 3], plus their prior/next neighbours (the sign rule reads
    them), re-indexed. Exact: a segment is dropped only when its 2D lower bound (distance to its
    midpoint minus half its length) exceeds some point's distance to a segment start point."""
    stretch = np.array([1.0, 1.0, Z_STRETCH])
    ub = pairwise_distance(points_xyz * stretch, segments.start * stretch).min(1)  # [Q] >= the nearest segment's distance
    mid = 0.5 * (segments.start[:, :2] + segments.end[:, :2])
    half = 0.5 * np.linalg.norm(segments.end[:, :2] - segments.start[:, :2], axis=1)
    lb = pairwise_distance(points_xyz[:, :2], mid) - half[None]  # [Q, S] <= the 3D distance
    cand = (lb <= ub[:, None] + 1e-6).any(0)
    keep = cand.copy()
    keep[segments.prior[cand]] = True
    keep[segments.next_[cand]] = True
    idx = np.flatnonzero(keep)
    new_of_old = np.full(segments.num_segments, -1, np.int64)
    new_of_old[idx] = np.arange(len(idx))
    # neighbours outside the crop (only of neighbour-only segments, never consulted) point at themselves
    pr, nx = new_of_old[segments.prior[idx]], new_of_old[segments.next_[idx]]
    own = np.arange(len(idx))
    return RoadEdgeSegments(segments.start[idx], segments.end[idx], np.where(pr >= 0, pr, own), np.where(nx >= 0, nx, own),
                            segments.has_prior[idx], segments.has_next[idx], segments.convex_prior[idx], segments.convex_next[idx])


def offroad(static, ctrl: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """[C] bool: a controlled vehicle's box is off the road at the last of the frames [N, F, 3]."""
    out = np.zeros(len(ctrl), bool)
    veh = static.types[ctrl] == int(AgentType.VEHICLE)
    if static.road_edges is None or not veh.any():
        return out
    t = ctrl[veh]
    f = frames[t][:, -1:]  # [V, 1, 3]
    size = np.broadcast_to(static.box_size[t][:, None], (*f.shape[:2], 3))
    z = np.broadcast_to(static.z[t][:, None], f.shape[:2])
    args = (f[..., 0], f[..., 1], z, size[..., 0], size[..., 1], size[..., 2], f[..., 2])
    corners = box_corners_float32(args[0], args[1], args[3], args[4], args[6], z=args[2], height=args[5]).reshape(-1, 3)
    out[veh] = is_offroad(*args, crop_road_edges(static.road_edges, corners.astype(np.float64))).any(-1)
    return out


def route_progress_m(static: SceneStatic, tracks: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Arc length [C] along each track's logged route at its valid route point nearest to ``xy`` [C, 2]."""
    if static.route_xy.shape[1] == 0 or len(tracks) == 0:
        return np.zeros(len(tracks))
    d = np.linalg.norm(static.route_xy[tracks] - xy[:, None], axis=-1)  # [C, R]
    d = np.where(static.route_valid[tracks], d, np.inf)
    k = d.argmin(1)
    return static.route_arc_m[tracks, k]


def goal_reached(static, ctrl: np.ndarray, xy: np.ndarray, radius_m: float) -> np.ndarray:
    """[C] bool: within ``radius_m`` of the logged goal (tracks with a route longer than the radius)."""
    has_goal = static.route_length_m[ctrl] > radius_m
    return has_goal & (np.linalg.norm(xy - static.goal_xy[ctrl], axis=1) <= radius_m)


def mean_jerk(positions: np.ndarray, valid: np.ndarray, new_frames: int) -> np.ndarray:
    """[C] mean jerk magnitude (m/s^3) at the last ``new_frames`` frames of positions [C, H, 2]
    (third differences at 10 Hz; frames whose 4 support points are not all valid are skipped)."""
    j = (positions[:, 3:] - 3 * positions[:, 2:-1] + 3 * positions[:, 1:-2] - positions[:, :-3]) / DT_S ** 3  # [C, H-3, 2]
    ok = valid[:, 3:] & valid[:, 2:-1] & valid[:, 1:-2] & valid[:, :-3]
    mag = np.linalg.norm(j, axis=-1)[:, -new_frames:]
    ok = ok[:, -new_frames:]
    return np.where(ok.any(1), (mag * ok).sum(1) / np.maximum(ok.sum(1), 1), 0.0)


@dataclass
class StepReward:
    """One step's outcome for the live controlled agents ``ctrl`` [C]."""

    collision: np.ndarray  # [C] bool
    offroad: np.ndarray  # [C] bool
    goal_reached: np.ndarray  # [C] bool, reached this step (the first time)
    progress_m: np.ndarray  # [C] route progress after the step
    terms: np.ndarray  # [C, 6] the reward terms, REWARD_TERMS order
    reward: np.ndarray  # [C] terms . weights
    terminated: np.ndarray  # [C] bool, an event of ``terminate_on`` happened


def step_reward(static: SceneStatic, config: RewardConfig, terminate_on, ctrl: np.ndarray, frames: np.ndarray,
                present: np.ndarray, hist_pose: np.ndarray, hist_valid: np.ndarray, progress_m: np.ndarray,
                goal_done: np.ndarray, action_log_prob: np.ndarray) -> StepReward:
    """Events, reward terms, reward and termination of the controlled tracks ``ctrl`` [C] after a
    step: frames [N, 5, 3] and present [N] of every track (the step's motion), hist_pose [C, H, 3]
    and hist_valid [C, H] the controlled agents' pose history *including* the step, progress_m [C]
    their route progress before it, goal_done [C] whether they reached their goal before, and
    action_log_prob [C] the prior's log-probability of their tokens (0 without a prior)."""
    coll = collisions(ctrl, frames, present, static.box_size)
    off = offroad(static, ctrl, frames)
    progress = route_progress_m(static, ctrl, frames[ctrl, -1, :2])
    goal = goal_reached(static, ctrl, frames[ctrl, -1, :2], config.goal_radius_m) & ~goal_done
    jerk = mean_jerk(hist_pose[:, :, :2], hist_valid, FRAMES_PER_TOKEN)
    terms = np.stack([progress - progress_m, goal.astype(float), coll.astype(float), off.astype(float), jerk, action_log_prob], -1)
    term = np.zeros(len(ctrl), bool)
    for event, happened in (("collision", coll), ("offroad", off), ("goal", goal)):
        if event in terminate_on:
            term |= happened
    return StepReward(collision=coll, offroad=off, goal_reached=goal, progress_m=progress, terms=terms,
                      reward=terms @ config.weights(), terminated=term)
