"""Environment stage, dynamics: every agent's motion over one token step, for ``B`` scenes at once
(Waymax's "dynamics"; tensors with a leading scene dimension, no loop over scenes or agents).

What comes in: the scenes' constants (:class:`~envs._scene_batch.SceneBatch`), the state at the
start of the step (every track's pose, who is present, the frame of each scene), the controlled
agents' tokens, the background mode and the prior (a :class:`smart_marl.rollout.RolloutState` with
one group per scene, or None). What goes out: a :class:`Motion`, every track's 5 new 10 Hz poses,
who is present after the step and the prior's log-probability of each track's token.

Who moves how (see :mod:`envs.smart_traffic_v0`):

* controlled agents: their tokens, placed at their poses (by the prior's step when there is one,
  which is given the tokens as forced tokens, so everyone's next steps are conditioned on them; without a
  prior, the token's own contour poses);
* background ``"prior"``: the prior samples every other vehicle, pedestrian and cyclist, drawn before the
  controlled agents act (:func:`draw_background`, when the step's logits are computed: the same step's
  background tokens do not depend on the controlled agents' tokens, and a shield knows where the background
  goes); agents of type OTHER move at constant velocity;
* background ``"log"`` / ``"constant_velocity"``: the logged poses (present on the frames the log
  is valid; a missing frame keeps the last pose) / the logged velocity at the current frame,
  heading held. With a prior, the prior still steps (for its logits): the agents it simulates that
  move by the log or constant velocity are given the token nearest their move
  (:func:`nearest_tokens`) and re-anchored at their true poses.

:func:`release` takes agents out of the prior's scene after the step (done controlled agents,
log agents that left), so nobody's neighbourhood sees them again.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from smart_marl.geometry_torch import squared_length
from smart_marl.rollout import FORCED_LATER, Draw, RolloutState
from smart_marl.rollout.frames import compose_torch
from smart_marl.scenario import DT_S, wrap_angle
from smart_marl.tokens import FRAMES_PER_TOKEN

from ._scene_batch import SceneBatch

BACKGROUNDS = ("prior", "log", "constant_velocity")
_STEP_FRAMES = torch.arange(1, FRAMES_PER_TOKEN + 1)


@dataclass
class Motion:
    """One token step of every track of ``B`` scenes (``N`` track slots each)."""

    frames: torch.Tensor  # [B, N, 5, 3] x, y, heading on the step's 5 frames (local frame)
    present: torch.Tensor  # [B, N] bool, present after the step
    action_log_prob: torch.Tensor  # [B, N] the prior's log-probability of a forced (controlled) track's token, else 0


def log_frames(scenes: SceneBatch, frame: torch.Tensor, pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(poses [B, N, 5, 3], present after the step [B, N]) of every track replayed from its log over
    the 5 frames after ``frame`` [B]; frames the log misses keep the last pose (``pose`` [B, N, 3] now)."""
    f = frame[:, None] + _STEP_FRAMES.to(frame.device)  # [B, 5]
    inside = f < scenes.num_frames[:, None]
    fi = torch.minimum(f, scenes.num_frames[:, None] - 1)
    b, n = pose.shape[:2]
    idx = fi[:, None, :].expand(b, n, -1)  # [B, N, 5]
    logged = scenes.log_pose.gather(2, idx[..., None].expand(-1, -1, -1, 3))  # [B, N, 5, 3]
    valid = scenes.log_valid.gather(2, idx) & inside[:, None]  # [B, N, 5]
    out = torch.empty_like(logged)
    last = pose
    for j in range(FRAMES_PER_TOKEN):
        last = torch.where(valid[:, :, j, None], logged[:, :, j], last)
        out[:, :, j] = last
    return out, valid[:, :, -1]


def constant_velocity_frames(scenes: SceneBatch, frame: torch.Tensor) -> torch.Tensor:
    """[B, N, 5, 3] every track at its logged current-frame velocity, heading held, over the 5 frames
    after ``frame`` [B] (from its logged pose at the current frame)."""
    b, n = scenes.track_valid.shape
    t = ((frame - scenes.current_frame)[:, None] + _STEP_FRAMES.to(frame.device)).to(scenes.cv_velocity.dtype) * DT_S  # [B, 5]
    cf = scenes.current_frame[:, None, None, None].expand(b, n, 1, 3)
    start = scenes.log_pose.gather(2, cf)  # [B, N, 1, 3]
    out = start.expand(b, n, FRAMES_PER_TOKEN, 3).clone()
    out[..., :2] += scenes.cv_velocity[:, :, None] * t[:, None, :, None]
    return out


def nearest_tokens(token_ends: torch.Tensor, in_vocab: torch.Tensor, agent_type: torch.Tensor, start: torch.Tensor,
                   end: torch.Tensor) -> torch.Tensor:
    """[M] the token of each agent's type whose end best matches its move from ``start`` to ``end``
    [M, 3] (squared position error plus the squared wrapped heading error, radians as metres, as
    :func:`smart_marl.tokens.motion.match_token_ends`); ``token_ends`` [3, Vmax, 3] every type's token
    ends in the token's start frame, ``in_vocab`` [3, Vmax] which of them are the type's tokens."""
    c, s = start[:, 2].cos(), start[:, 2].sin()
    dx, dy = end[:, 0] - start[:, 0], end[:, 1] - start[:, 1]
    rel = torch.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(end[:, 2] - start[:, 2])], -1)  # [M, 3]
    ends = token_ends[agent_type]  # [M, Vmax, 3]
    err = squared_length(rel[:, None, :2] - ends[..., :2]) + wrap_angle(rel[:, None, 2] - ends[..., 2]).square()
    return err.masked_fill(~in_vocab[agent_type], float("inf")).argmin(-1)


def place_tokens(token_poses: torch.Tensor, agent_type: torch.Tensor, tokens: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """[M, 5, 3] the contour poses of each token placed at ``pose`` [M, 3]; ``token_poses`` [3, Vmax, 6, 3]."""
    local = token_poses[agent_type, tokens][:, 1:]  # [M, 5, 3]
    return compose_torch(pose[:, None], local)


def move(scenes: SceneBatch, background: str, token_poses: torch.Tensor, prior: RolloutState | None, slot_of_track: torch.Tensor,
         pose: torch.Tensor, present: torch.Tensor, in_sim: torch.Tensor, done: torch.Tensor, frame: torch.Tensor,
         ctrl_track: torch.Tensor, ctrl_live: torch.Tensor, actions: torch.Tensor) -> Motion:
    """One token step of every track of every scene (module docstring).

    pose [B, N, 3] every track's pose now, present / in_sim / done [B, N] bool (present now, one of the
    episode's agents, a controlled agent that is done), frame [B] each scene's current 10 Hz frame;
    ctrl_track [B, C] the controlled tracks (-1: none), ctrl_live [B, C] those that act this step,
    actions [B, C] their tokens; slot_of_track [B, N] each track's slot in ``prior`` (-1: none);
    token_poses [3, Vmax, 6, 3]. ``prior`` is stepped (and the agents that follow the log or constant
    velocity are re-anchored in it); where its tokens were drawn ahead (:func:`draw_background`), it takes them.
    """
    b, n = pose.shape[:2]
    dev = pose.device
    rows = torch.arange(b, device=dev)[:, None].expand_as(ctrl_track)
    lb, lt, la = rows[ctrl_live], ctrl_track[ctrl_live], actions[ctrl_live]  # the live controlled agents
    outside, frames, present_after = _outside_moves(scenes, background, pose, present, in_sim, done, frame, _controlled(ctrl_track, ctrl_live, n))
    action_logp = torch.zeros(b, n, dtype=pose.dtype, device=dev)
    agent_type = scenes.types.clamp(min=0)
    if prior is None:
        frames[lb, lt] = place_tokens(token_poses, agent_type[lb, lt], la, pose[lb, lt])
        return Motion(frames, present_after, action_logp)

    # the prior: controlled agents' tokens forced, log / cv agents it simulates follow their moves
    forced, follow = _prior_forced(prior, slot_of_track, outside, frames, pose, agent_type, token_poses)
    forced[lb, slot_of_track[lb, lt]] = la
    out = prior.step(forced)
    slot_track = prior.track_index  # [B, Ns] (-1 on padding)
    slot_of = slot_track.clamp(min=0)
    by_prior = out.simulated & (slot_track >= 0)  # [B, Ns]
    pb, ps = by_prior.nonzero(as_tuple=True)
    pt = slot_of[pb, ps]
    keep = ~outside[pb, pt]  # log / cv agents keep their own poses
    frames[pb[keep], pt[keep]] = out.poses[pb[keep], ps[keep]].to(frames.dtype)
    action_logp[pb, pt] = out.log_probs[pb, ps].to(action_logp.dtype)
    fb, fs = follow.nonzero(as_tuple=True)
    if len(fb):  # re-anchor log / cv agents at their true poses
        new_pose = prior.current_pose.clone()
        new_pose[fb, fs] = frames[fb, slot_of[fb, fs], -1].to(new_pose.dtype)
        prior.set_agent_pose(new_pose, follow)
    return Motion(frames, present_after, action_logp)


def draw_background(scenes: SceneBatch, background: str, token_poses: torch.Tensor, prior: RolloutState, slot_of_track: torch.Tensor,
                    pose: torch.Tensor, present: torch.Tensor, in_sim: torch.Tensor, done: torch.Tensor, frame: torch.Tensor,
                    ctrl_track: torch.Tensor, ctrl_live: torch.Tensor) -> Draw:
    """The prior's tokens of the coming step drawn before the controlled agents act
    (:meth:`RolloutState.draw_ahead <smart_marl.rollout.RolloutState.draw_ahead>`; arguments as :func:`move`, which
    then takes them): the live controlled agents' slots are forced later, the agents that follow the log or
    constant velocity get the tokens :func:`move` gives them, everyone else's are drawn."""
    n = pose.shape[1]
    is_ctrl = _controlled(ctrl_track, ctrl_live, n)
    outside, frames, _ = _outside_moves(scenes, background, pose, present, in_sim, done, frame, is_ctrl)
    forced, _ = _prior_forced(prior, slot_of_track, outside, frames, pose, scenes.types.clamp(min=0), token_poses)
    lb, lt = is_ctrl.nonzero(as_tuple=True)
    slot = slot_of_track[lb, lt]
    forced[lb[slot >= 0], slot[slot >= 0]] = FORCED_LATER
    return prior.draw_ahead(forced)


def _controlled(ctrl_track: torch.Tensor, ctrl_live: torch.Tensor, n: int) -> torch.Tensor:
    """[B, N] bool, the tracks of the live controlled agents."""
    rows = torch.arange(ctrl_track.shape[0], device=ctrl_track.device)[:, None].expand_as(ctrl_track)
    is_ctrl = torch.zeros(ctrl_track.shape[0], n, dtype=torch.bool, device=ctrl_track.device)
    is_ctrl[rows[ctrl_live], ctrl_track[ctrl_live]] = True
    return is_ctrl


def _outside_moves(scenes: SceneBatch, background: str, pose: torch.Tensor, present: torch.Tensor, in_sim: torch.Tensor,
                   done: torch.Tensor, frame: torch.Tensor, is_ctrl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(outside [B, N], frames [B, N, 5, 3], present after [B, N]): the background agents that move outside the
    prior (by the log or at constant velocity) and their frames; everyone else held at ``pose`` for now."""
    b, n = pose.shape[:2]
    moving = present & ~done
    frames = pose[:, :, None].expand(b, n, FRAMES_PER_TOKEN, 3).clone()
    present_after = moving.clone()
    if background == "prior":
        outside = moving & ~is_ctrl & ~scenes.is_motion  # OTHER agents: constant velocity
    elif background == "log":  # present when the log is valid: an agent may come back after a gap
        outside = in_sim & ~done & ~is_ctrl
    else:
        outside = moving & ~is_ctrl
    if bool(outside.any()):
        if background == "log":
            moved, logged_present = log_frames(scenes, frame, pose)
            present_after = torch.where(outside, logged_present, present_after)
        else:
            moved = constant_velocity_frames(scenes, frame)
        frames = torch.where(outside[..., None, None], moved, frames)
    return outside, frames, present_after


def _prior_forced(prior: RolloutState, slot_of_track: torch.Tensor, outside: torch.Tensor, frames: torch.Tensor, pose: torch.Tensor,
                  agent_type: torch.Tensor, token_poses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(forced [B, Ns], follow [B, Ns]): the prior's forced tokens for the slots that move outside it (the token
    nearest their move; -1 elsewhere), and those slots."""
    b, ns = prior.track_index.shape
    forced = torch.full((b, ns), -1, dtype=torch.long, device=pose.device)
    slot_track = prior.track_index  # [B, Ns] (-1 on padding)
    slot_valid = prior.valid & (slot_track >= 0)
    slot_of = slot_track.clamp(min=0)
    follow = slot_valid & outside.gather(1, slot_of)  # [B, Ns] slots moved outside the prior
    fb, fs = follow.nonzero(as_tuple=True)
    if len(fb):
        ft = slot_of[fb, fs]
        forced[fb, fs] = nearest_tokens(token_poses[:, :, -1].to(pose.dtype), _in_vocab(token_poses, prior.vocab_sizes),
                                        agent_type[fb, ft], pose[fb, ft], frames[fb, ft, -1])
    return forced, follow


def _in_vocab(token_poses: torch.Tensor, vocab_sizes: torch.Tensor) -> torch.Tensor:
    """[3, Vmax] bool, the token ids of each type's vocabulary."""
    v = token_poses.shape[1]
    return torch.arange(v, device=token_poses.device)[None] < vocab_sizes.to(token_poses.device)[:, None]


def release(prior: RolloutState, slot_of_track: torch.Tensor, gone: torch.Tensor) -> None:
    """Take the tracks ``gone`` (bool [B, N]) out of the prior's scenes from its next step on."""
    keep = torch.ones_like(prior.valid)
    gb, gt = (gone & (slot_of_track >= 0)).nonzero(as_tuple=True)
    keep[gb, slot_of_track[gb, gt]] = False
    prior.set_agent_valid(keep)


__all__ = ["BACKGROUNDS", "Motion", "constant_velocity_frames", "draw_background", "log_frames", "move", "nearest_tokens", "place_tokens", "release"]
