"""Environment stage, dynamics: every agent's motion over one token step (Waymax's "dynamics").

What comes in: the scene's constants (:class:`~envs._scene.SceneStatic`), the episode's state at
the start of the step (every track's pose, who is present, the frame), the controlled agents'
tokens, the background mode and the prior (a :class:`smart_marl.rollout.RolloutState` with one
group, or None). What goes out: a :class:`Motion`, every track's 5 new 10 Hz poses, who is present
after the step and the prior's log-probability of each track's token.

Who moves how (see :mod:`envs.smart_traffic_v0`):

* controlled agents: their tokens, placed at their poses (by the prior's step when there is one,
  which is given the tokens as forced tokens, so it conditions everyone else on them);
* background ``"prior"``: the prior's step samples every other vehicle, pedestrian and cyclist;
  agents of type OTHER move at constant velocity;
* background ``"log"`` / ``"constant_velocity"``: the logged poses (present on the frames the log
  is valid; a missing frame keeps the last pose) / the logged velocity at the current frame,
  heading held. With a prior, the prior still steps (for its logits): the agents it simulates that
  move by the log or constant velocity are given the token nearest their move
  (:func:`smart_marl.tokens.motion.match_token_ends`) and re-anchored at their true poses.

:func:`release` takes agents out of the prior's scene after the step (done controlled agents,
log agents that left), so nobody's neighbourhood sees them again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from smart_marl.rollout import RolloutState
from smart_marl.scenario import DT_S
from smart_marl.tokens import FRAMES_PER_TOKEN, MotionVocabulary, compose_poses, relative_poses
from smart_marl.tokens.motion import match_token_ends

from ._scene import SceneStatic

BACKGROUNDS = ("prior", "log", "constant_velocity")


@dataclass
class Motion:
    """One token step of every track of the scene (``N`` tracks)."""

    frames: np.ndarray  # [N, 5, 3] float64 x, y, heading on the step's 5 frames (local frame)
    present: np.ndarray  # [N] bool, present after the step
    action_log_prob: np.ndarray  # [N] float64, the prior's log-probability of the track's token (0 without one)


def background_frames(static: SceneStatic, tracks: np.ndarray, mode: str, frame: int, pose: np.ndarray,
                      cv_velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(poses [B, 5, 3], present after the step [B]) of ``tracks`` [B] moved by ``mode`` ("log" or
    "constant_velocity") over the 5 frames after ``frame``; ``pose`` [N, 3] is every track's pose now
    and ``cv_velocity`` [N, 2] its velocity at the current frame."""
    k = np.arange(1, FRAMES_PER_TOKEN + 1)
    tr = static.scenario.tracks
    if mode == "log":
        frames = frame + k
        inside = frames < tr.num_frames
        fi = np.minimum(frames, tr.num_frames - 1)
        valid = tr.valid[tracks][:, fi] & inside[None]  # [B, 5]
        pos = np.concatenate([tr.position[tracks][:, fi, :2], tr.heading[tracks][:, fi, None]], -1).astype(np.float64)
        # frames the log misses keep the last pose
        out = np.empty_like(pos)
        last = pose[tracks]
        for j in range(FRAMES_PER_TOKEN):
            last = np.where(valid[:, j, None], pos[:, j], last)
            out[:, j] = last
        return out, valid[:, -1]
    # constant velocity (also OTHER agents under the prior)
    cf = static.scenario.current_frame
    t = (frame - cf + k) * DT_S
    start = np.concatenate([tr.position[tracks, cf, :2], tr.heading[tracks, cf, None]], -1).astype(np.float64)
    out = np.repeat(start[:, None], FRAMES_PER_TOKEN, 1)
    out[..., :2] += cv_velocity[tracks][:, None] * t[None, :, None]
    return out, np.ones(len(tracks), bool)


def nearest_tokens(static: SceneStatic, motion_vocab: MotionVocabulary, tracks: np.ndarray, start_pose: np.ndarray,
                   end_pose: np.ndarray) -> np.ndarray:
    """The token of each track's type whose end best matches its move from ``start_pose`` to
    ``end_pose`` [B, 3] (position and heading)."""
    out = np.zeros(len(tracks), np.int64)
    rel = relative_poses(end_pose, start_pose)  # [B, 3] the move in the track's frame
    types = static.types[tracks]
    for t in np.unique(types):
        sel = types == t
        out[sel] = match_token_ends(motion_vocab[int(t)].poses[:, -1], rel[sel])
    return out


def place_tokens(static: SceneStatic, motion_vocab: MotionVocabulary, tracks: np.ndarray, tokens: np.ndarray,
                 pose: np.ndarray) -> np.ndarray:
    """The 5 poses [C, 5, 3] of each track's token placed at its pose (``pose`` [N, 3], every track)."""
    out = np.zeros((len(tracks), FRAMES_PER_TOKEN, 3))
    types = static.types[tracks]
    for t in np.unique(types):
        sel = types == t
        local = motion_vocab[int(t)].poses[tokens[sel], 1:].astype(np.float64)  # [c, 5, 3]
        out[sel] = compose_poses(pose[tracks[sel]][:, None], local)
    return out


def move(static: SceneStatic, background: str, motion_vocab: MotionVocabulary, prior: RolloutState | None,
         slot_of_track: np.ndarray, pose: np.ndarray, present: np.ndarray, in_sim: np.ndarray, done: np.ndarray, frame: int,
         cv_velocity: np.ndarray, ctrl: np.ndarray, ctrl_tokens: np.ndarray) -> Motion:
    """One token step of every track (see the module docstring).

    pose [N, 3] every track's pose now, present / in_sim / done [N] bool (present now, one of the
    episode's agents, a controlled agent that is done), frame the current 10 Hz frame; ctrl [C] the
    live controlled tracks and ctrl_tokens [C] their tokens; slot_of_track [N] each track's slot in
    ``prior`` (-1: none). ``prior`` is stepped (and the agents that follow the log or constant
    velocity are re-anchored in it).
    """
    n = static.num_tracks
    is_ctrl = np.zeros(n, bool)
    is_ctrl[ctrl] = True
    moving = present & ~done
    frames = np.repeat(pose[:, None], FRAMES_PER_TOKEN, 1)  # [N, 5, 3]
    present_after = moving.copy()
    action_logp = np.zeros(n)

    # background agents outside the prior's control: log or constant velocity
    if background == "prior":
        outside = np.flatnonzero(moving & ~is_ctrl & ~static.is_motion)  # OTHER agents: constant velocity
    elif background == "log":  # present when the log is valid: an agent may come back after a gap
        outside = np.flatnonzero(in_sim & ~done & ~is_ctrl)
    else:
        outside = np.flatnonzero(moving & ~is_ctrl)
    if len(outside):
        mode = "log" if background == "log" else "constant_velocity"
        frames[outside], present_after[outside] = background_frames(static, outside, mode, frame, pose, cv_velocity)

    if prior is None:
        frames[ctrl] = place_tokens(static, motion_vocab, ctrl, ctrl_tokens, pose)
        return Motion(frames, present_after, action_logp)

    # the prior: controlled agents' tokens forced, log / cv agents it simulates follow their moves
    forced = np.full(prior.num_slots, -1, np.int64)
    forced[slot_of_track[ctrl]] = ctrl_tokens
    follow = outside[slot_of_track[outside] >= 0] if len(outside) else outside
    follow = follow[prior.valid[0].numpy()[slot_of_track[follow]]]
    if len(follow):
        forced[slot_of_track[follow]] = nearest_tokens(static, motion_vocab, follow, pose[follow], frames[follow, -1])
    out = prior.step(torch.from_numpy(forced)[None])
    slot_tracks = prior.track_index[0].numpy()
    by_prior = np.flatnonzero(out.simulated[0].numpy() & (slot_tracks >= 0))
    prior_tracks = slot_tracks[by_prior]
    keep = ~np.isin(prior_tracks, outside)  # log / cv agents keep their own poses
    frames[prior_tracks[keep]] = out.poses[0, by_prior[keep]].numpy().astype(np.float64)
    action_logp[prior_tracks] = out.log_probs[0, by_prior].numpy()
    if len(follow):  # re-anchor log / cv agents at their true poses
        pose_t = prior.current_pose.clone()
        mask = torch.zeros_like(prior.valid)
        pose_t[0, slot_of_track[follow]] = torch.from_numpy(frames[follow, -1]).float()
        mask[0, slot_of_track[follow]] = True
        prior.set_agent_pose(pose_t, mask)
    return Motion(frames, present_after, action_logp)


def release(prior: RolloutState, slot_of_track: np.ndarray, gone: np.ndarray) -> None:
    """Take the tracks ``gone`` (bool [N]) out of the prior's scene from its next step on."""
    keep_slot = torch.ones_like(prior.valid)
    keep_slot[0, slot_of_track[np.flatnonzero(gone & (slot_of_track >= 0))]] = False
    prior.set_agent_valid(keep_slot)
