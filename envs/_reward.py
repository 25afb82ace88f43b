"""Environment stage, events and rewards: one token step's 10 Hz poses -> per controlled agent the
events (collision, offroad, goal reached) and a reward made of weighted terms, for ``B`` scenes at
once.

Events use the sim-agents metrics' geometry (:mod:`smart_marl.geometry`, on tensors through
:mod:`smart_marl.geometry_torch`, checked equal to it):

* collision: the agent's rounded box overlaps another present agent's box at any of the step's
  5 frames (:func:`~smart_marl.geometry_torch.rounded_boxes_overlap`);
* offroad: a vehicle's box has a corner beyond the road edge at the step's last frame (token
  boundaries, every 0.5 s; pedestrians and cyclists are never offroad; nor is anyone in a scene
  without road edges) (:func:`~smart_marl.geometry_torch.signed_distance_to_road_edges`);
* goal reached: the agent ends the step within ``goal_radius_m`` of its logged goal (its last
  logged position), for tracks whose logged route is longer than ``goal_radius_m`` (a parked car
  has no goal to reach).

Reward terms (``REWARD_TERMS`` order, also ``infos[agent]["reward_terms"]``): ``progress``
(metres gained along the logged route this step), ``goal_reached`` (1 the step the goal is
reached), ``collision`` (1), ``offroad`` (1), ``comfort`` (mean jerk magnitude over the step's
frames, m/s^3: give it a negative weight), ``prior_log_likelihood`` (log-probability of the
chosen token under the prior, 0 without a prior), ``headway`` and ``ttc`` (the gaps kept to the
car ahead, below). The reward is the dot product with :class:`RewardConfig`'s weights.

The gap terms (off by default: weight 0; give them a negative weight), from where every track is at the
step's last frame and its velocity over the step's last frame (as the env's state keeps it):

* the **leader** of a controlled agent is the nearest other present track in its path: centre ahead
  along its heading, and close enough sideways that the two boxes would touch if the agent drove
  straight on (its half width plus the other's half extent across its heading; a straight corridor,
  no lanes: on a bend a leader far ahead falls out of it, and a car crossing the path counts while
  it is in it). The **gap** is bumper to bumper along the heading (centre distance ahead less the
  agent's half length and the other's half extent along the heading; 0 when they overlap);
* ``headway``: the time headway ``gap / speed`` (the agent's speed along its heading) below
  ``headway_s``, as the fraction below: ``max(0, 1 - headway / headway_s)`` (0 at ``headway_s`` or
  more, 1 at no gap); 0 without a leader or when the agent does not move forward;
* ``ttc``: the time to collision ``gap / closing speed`` (the agent's speed along its heading less the
  leader's velocity along it) below ``ttc_s``, as ``max(0, 1 - ttc / ttc_s)``; 0 without a leader or
  when the gap opens or holds (closing speed <= 0).

So a follower with a 10 m gap at 20 m/s has a headway of 0.5 s (``headway`` 0.5 at ``headway_s`` 1), and
closing at 5 m/s a time to collision of 2 s (``ttc`` 1/3 at ``ttc_s`` 3). :func:`time_gaps` gives the
seconds themselves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Mapping

import torch

from smart_marl.geometry_torch import bound_length, box_corners_bottom, loose, rounded_boxes_overlap, signed_distance_to_road_edges
from smart_marl.scenario import DT_S, AgentType
from smart_marl.tokens import FRAMES_PER_TOKEN

from ._scene_batch import SceneBatch, gather_tracks
from .errors import EnvConfigError, EnvConfigTypeError

REWARD_TERMS = ("progress", "goal_reached", "collision", "offroad", "comfort", "prior_log_likelihood", "headway", "ttc")
TERMINATION_EVENTS = ("collision", "offroad", "goal")


@dataclass(frozen=True)
class RewardConfig:
    """Weights of the reward terms (see the module docstring), the goal radius and the gap terms' thresholds
    (seconds: a time headway below ``headway_s``, a time to collision below ``ttc_s`` is penalised)."""

    progress: float = 0.1
    goal_reached: float = 1.0
    collision: float = -1.0
    offroad: float = -1.0
    comfort: float = 0.0
    prior_log_likelihood: float = 0.0
    headway: float = 0.0
    ttc: float = 0.0
    goal_radius_m: float = 2.0
    headway_s: float = 1.0
    ttc_s: float = 3.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                raise EnvConfigError(f"reward[{f.name!r}] must be a finite number, got {v!r}")

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

    def weights(self) -> torch.Tensor:
        return torch.tensor([float(getattr(self, t)) for t in REWARD_TERMS], dtype=torch.float64)


def collisions(ctrl_track: torch.Tensor, live: torch.Tensor, frames: torch.Tensor, present: torch.Tensor,
               box_size: torch.Tensor) -> torch.Tensor:
    """[B, C] bool: a live controlled track overlaps another present track at any frame (rounded boxes).
    ctrl_track [B, C], live [B, C], frames [B, N, F, 3] every track's poses over the step, present
    [B, N] bool, box_size [B, N, 2+] length, width. Only pairs whose centres are close enough for
    their boxes to touch are tested box against box, and the centres' distance is measured on every
    frame only for the (agent, other) pairs that can come that close: their distance on the first
    frame less how far each gets from its first frame is a lower bound on every frame (most pairs
    are far apart: the same candidates as measuring every pair)."""
    b, c = ctrl_track.shape
    n = frames.shape[1]
    mine = gather_tracks(frames, ctrl_track)  # [B, C, F, 3]
    my_size = gather_tracks(box_size[..., :2], ctrl_track)  # [B, C, 2]
    reach = bound_length(box_size[..., :2]) / 2  # [B, N] circumscribed radius (bounds below: bound_length and loose)
    my_reach = gather_tracks(reach, ctrl_track)  # [B, C]
    extent = bound_length(frames[..., :2] - frames[:, :, :1, :2]).amax(-1)  # [B, N] farthest from the first frame
    apart = bound_length(mine[:, :, None, 0, :2] - frames[:, None, :, 0, :2])  # [B, C, N] on the first frame
    lower = apart - gather_tracks(extent, ctrl_track)[..., None] - extent[:, None]
    limit = my_reach[..., None] + reach[:, None]
    other = torch.arange(n, device=frames.device)[None, None] != ctrl_track[..., None]  # [B, C, N]
    # NaN (no bound) keeps the pair; the margin covers rounding: only more pairs
    near = other & present[:, None] & live[..., None] & ~(lower >= limit + 1e-3 + 1e-5 * (apart + limit))
    qb, qc, qn = near.nonzero(as_tuple=True)
    f = frames.shape[2]  # the pairs' frames as whole rows of flat views (one index each: a fast gather)
    mine_q = mine.reshape(b * c, f, 3).index_select(0, qb * c + qc)
    other_q = frames.reshape(b * n, f, 3).index_select(0, qb * n + qn)
    dist = bound_length(mine_q[..., :2] - other_q[..., :2])  # [P, F]
    p, fi = (dist < loose(my_reach[qb, qc] + reach[qb, qn])[:, None]).nonzero(as_tuple=True)
    bi, ci, ni = qb[p], qc[p], qn[p]
    out = torch.zeros(b, c, dtype=torch.bool, device=frames.device)
    if len(bi):
        pa, pb = mine_q[p, fi], other_q[p, fi]
        hit = rounded_boxes_overlap(pa[:, :2], pa[:, 2], my_size[bi, ci], pb[:, :2], pb[:, 2], box_size[bi, ni, :2])
        out[bi[hit], ci[hit]] = True
    return out


def offroad(scenes: SceneBatch, ctrl_track: torch.Tensor, live: torch.Tensor, last_pose: torch.Tensor) -> torch.Tensor:
    """[B, C] bool: a live controlled vehicle's box is off the road at ``last_pose`` [B, C, 3]."""
    veh = live & (gather_tracks(scenes.types, ctrl_track) == int(AgentType.VEHICLE))
    if not bool(veh.any()):
        return torch.zeros_like(veh)
    corners = box_corners_bottom(last_pose[..., :2], last_pose[..., 2], gather_tracks(scenes.box_size, ctrl_track),
                                 gather_tracks(scenes.z, ctrl_track))  # [B, C, 4, 3]
    b, c = ctrl_track.shape
    # a box's corners searched together (group=4)
    dist = signed_distance_to_road_edges(corners.reshape(b, c * 4, 3), scenes.edges, group=4).view(b, c, 4)
    return veh & (dist.amax(-1) > 0)


def route_progress_m(scenes: SceneBatch, ctrl_track: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Arc length [B, C] along each controlled track's logged route at its valid route point nearest
    to ``xy`` [B, C, 2] (0 for a track without a route)."""
    route = gather_tracks(scenes.route_xy, ctrl_track)  # [B, C, R, 2]
    valid = gather_tracks(scenes.route_valid, ctrl_track)
    d = (route - xy[:, :, None]).norm(dim=-1).masked_fill(~valid, float("inf"))
    k = d.argmin(-1, keepdim=True)
    return gather_tracks(scenes.route_arc_m, ctrl_track).gather(2, k)[..., 0] * valid.any(-1)


def goal_reached(scenes: SceneBatch, ctrl_track: torch.Tensor, xy: torch.Tensor, radius_m: float) -> torch.Tensor:
    """[B, C] bool: within ``radius_m`` of the logged goal (tracks with a route longer than the radius)."""
    has_goal = gather_tracks(scenes.route_length_m, ctrl_track) > radius_m
    return has_goal & ((xy - gather_tracks(scenes.goal_xy, ctrl_track)).norm(dim=-1) <= radius_m)


def mean_jerk(positions: torch.Tensor, valid: torch.Tensor, new_frames: int) -> torch.Tensor:
    """[...] mean jerk magnitude (m/s^3) at the last ``new_frames`` frames of positions [..., H, 2]
    (third differences at 10 Hz; frames whose 4 support points are not all valid are skipped)."""
    p = positions
    j = (p[..., 3:, :] - 3 * p[..., 2:-1, :] + 3 * p[..., 1:-2, :] - p[..., :-3, :]) / DT_S ** 3
    ok = valid[..., 3:] & valid[..., 2:-1] & valid[..., 1:-2] & valid[..., :-3]
    mag, ok = j.norm(dim=-1)[..., -new_frames:], ok[..., -new_frames:]
    return torch.where(ok.any(-1), (mag * ok).sum(-1) / ok.sum(-1).clamp(min=1), torch.zeros_like(mag[..., 0]))


def half_extents(half: torch.Tensor, turn: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The half extents (along, across) [...] of boxes with half sizes ``half`` [..., 2] (length, width) turned by
    ``turn`` [...] radians against a heading: how far each reaches along that heading and across it."""
    c, s = torch.cos(turn).abs(), torch.sin(turn).abs()
    return half[..., 0] * c + half[..., 1] * s, half[..., 0] * s + half[..., 1] * c


def time_gaps(ctrl_track: torch.Tensor, live: torch.Tensor, frames: torch.Tensor, present: torch.Tensor,
              box_size: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """([B, C] time headway, [B, C] time to collision), in seconds, of each live controlled track to its
    leader at the step's last frame (the module docstring's definitions); ``inf`` where there is none:
    no leader, not moving forward (headway), a gap that opens or holds (time to collision), a slot that
    is not live. ctrl_track [B, C], live [B, C], frames [B, N, F, 3] every track's poses over the step
    (F >= 2), present [B, N] bool, box_size [B, N, 2+] length, width. Every pair at once, no loop."""
    n = frames.shape[1]
    last = frames[:, :, -1]  # [B, N, 3]
    velocity = (frames[:, :, -1, :2] - frames[:, :, -2, :2]) / DT_S  # [B, N, 2], as the env's state keeps it
    mine = gather_tracks(last, ctrl_track)  # [B, C, 3]
    cos, sin = torch.cos(mine[..., 2]), torch.sin(mine[..., 2])
    forward, left = torch.stack([cos, sin], -1), torch.stack([-sin, cos], -1)  # [B, C, 2]
    rel = last[:, None, :, :2] - mine[:, :, None, :2]  # [B, C, N, 2] the others seen from each agent
    ahead, side = (rel * forward[:, :, None]).sum(-1), (rel * left[:, :, None]).sum(-1)  # [B, C, N]
    turn = last[:, None, :, 2] - mine[..., None, 2]  # [B, C, N] the others' headings in the agent's frame
    half = box_size[..., :2].to(last.dtype) / 2  # [B, N, 2]
    along, across = half_extents(half[:, None], turn)  # the others' half extents along the heading and across it
    my_half = gather_tracks(half, ctrl_track)  # [B, C, 2]
    other = torch.arange(n, device=frames.device)[None, None] != ctrl_track[..., None]
    in_path = other & present[:, None] & live[..., None] & (ahead > 0) & (side.abs() < my_half[..., 1:2] + across)
    inf = float("inf")
    gap, leader = (ahead - my_half[..., :1] - along).clamp(min=0.0).masked_fill(~in_path, inf).min(-1)  # [B, C]
    has = torch.isfinite(gap)
    speed = (gather_tracks(velocity, ctrl_track) * forward).sum(-1)  # [B, C] along the heading
    closing = speed - (velocity.gather(1, leader[..., None].expand(-1, -1, 2)) * forward).sum(-1)
    tiny = torch.finfo(last.dtype).tiny
    headway = (gap / speed.clamp(min=tiny)).masked_fill(~(has & (speed > 0)), inf)
    ttc = (gap / closing.clamp(min=tiny)).masked_fill(~(has & (closing > 0)), inf)
    return headway, ttc


def gap_terms(ctrl_track: torch.Tensor, live: torch.Tensor, frames: torch.Tensor, present: torch.Tensor, box_size: torch.Tensor,
              headway_s: float, ttc_s: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``headway`` and ``ttc`` terms [B, C] in [0, 1] (module docstring) of :func:`time_gaps`'
    seconds against the thresholds ``headway_s`` and ``ttc_s`` (> 0): ``max(0, 1 - t / threshold)``,
    0 where :func:`time_gaps` is ``inf``."""
    headway, ttc = time_gaps(ctrl_track, live, frames, present, box_size)
    return (1 - headway / float(headway_s)).clamp(min=0.0), (1 - ttc / float(ttc_s)).clamp(min=0.0)


@dataclass
class StepReward:
    """One step's outcome for the controlled agents [B, C] (zeros / False for those not live)."""

    collision: torch.Tensor  # [B, C] bool
    offroad: torch.Tensor  # [B, C] bool
    goal_reached: torch.Tensor  # [B, C] bool, reached this step (the first time)
    progress_m: torch.Tensor  # [B, C] route progress after the step
    terms: torch.Tensor  # [B, C, 8] the reward terms, REWARD_TERMS order
    reward: torch.Tensor  # [B, C] terms . weights
    terminated: torch.Tensor  # [B, C] bool, an event of ``terminate_on`` happened


def step_reward(scenes: SceneBatch, config: RewardConfig, terminate_on, ctrl_track: torch.Tensor, live: torch.Tensor,
                frames: torch.Tensor, present: torch.Tensor, hist_pose: torch.Tensor, hist_valid: torch.Tensor,
                progress_m: torch.Tensor, goal_done: torch.Tensor, action_log_prob: torch.Tensor) -> StepReward:
    """Events, reward terms, reward and termination of the live controlled agents (``ctrl_track``
    [B, C], ``live`` [B, C]) after a step: frames [B, N, 5, 3] and present [B, N] of every track (the
    step's motion), hist_pose [B, C, H, 3] and hist_valid [B, C, H] the controlled agents' pose history
    *including* the step, progress_m [B, C] their route progress before it, goal_done [B, C] whether
    they reached their goal before, and action_log_prob [B, C] the prior's log-probability of their
    tokens (0 without a prior)."""
    last = gather_tracks(frames[:, :, -1], ctrl_track)  # [B, C, 3]
    coll = collisions(ctrl_track, live, frames, present, scenes.box_size)
    off = offroad(scenes, ctrl_track, live, last)
    progress = torch.where(live, route_progress_m(scenes, ctrl_track, last[..., :2]), progress_m)
    goal = live & goal_reached(scenes, ctrl_track, last[..., :2], config.goal_radius_m) & ~goal_done
    jerk = mean_jerk(hist_pose[..., :2], hist_valid, FRAMES_PER_TOKEN)
    headway, ttc = gap_terms(ctrl_track, live, frames, present, scenes.box_size, config.headway_s, config.ttc_s)
    dtype = torch.float64
    terms = torch.stack([(progress - progress_m).to(dtype), goal.to(dtype), coll.to(dtype), off.to(dtype), jerk.to(dtype),
                         action_log_prob.to(dtype), headway.to(dtype), ttc.to(dtype)], -1) * live[..., None]
    term = torch.zeros_like(live)
    for event, happened in (("collision", coll), ("offroad", off), ("goal", goal)):
        if event in terminate_on:
            term = term | happened
    return StepReward(collision=coll, offroad=off, goal_reached=goal, progress_m=progress, terms=terms,
                      reward=terms @ config.weights().to(terms.device), terminated=term)


__all__ = ["REWARD_TERMS", "RewardConfig", "StepReward", "TERMINATION_EVENTS", "collisions", "gap_terms", "goal_reached",
           "mean_jerk", "offroad", "route_progress_m", "step_reward", "time_gaps"]
