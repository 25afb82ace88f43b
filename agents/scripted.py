"""Agents stage, scripted motion: what-if manoeuvres as 10 Hz target poses -> forced motion tokens.

What comes in: an agent's pose and speed when a manoeuvre starts (one row per rollout), the
manoeuvre's parameters, and the motion vocabulary's token poses. What goes out: target paths
``[G, T, 3]`` (x, y, heading in the scene's local frame, frames 1..T after the onset) and, each
0.5 s token step, the token of the agent's type vocabulary whose 5 placed poses come closest to the
next 5 target poses (:func:`nearest_tokens`). The rollout engine takes those tokens as forced
tokens (``RolloutState.step(forced_tokens)``), so a scripted agent moves only by real vocabulary
tokens, as every other agent does.

Closed loop, no drift: the target path is fixed in space when the manoeuvre starts; each step's
token is chosen from the pose the agent actually reached, so quantisation errors are corrected at
the next step instead of accumulating (the same idea as the tokenizer's rolling matching).

Paths (all vectorised over the ``G`` rows):

* :func:`brake_path`: straight along the heading, speed ``v(t) = max(v0 - a t, 0)``, then held;
* :func:`cut_in_path`: a lateral shift (left positive) with a smooth cosine profile over
  ``duration_s`` at constant forward speed, heading along the path's tangent;
* :func:`hold_path`: stay at the pose (a stalled vehicle, a stopped car);
* :func:`polyline_path`: along waypoints at a constant speed, optionally after standing still
  for a while (an inserted agent, a jaywalking pedestrian).
"""

from __future__ import annotations

import numpy as np
import torch

DT_S = 0.1
FRAMES_PER_TOKEN = 5
HEADING_WEIGHT_M_PER_RAD = 2.0
"""How much a heading error counts against a position error when matching a token (m per rad)."""
PEDESTRIAN_HEADING_WEIGHT_M_PER_RAD = 1.0
"""Pedestrians turn on the spot and their headings are noisy in the data: heading counts half as much."""


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _along(pose: np.ndarray, forward_m: np.ndarray, left_m: np.ndarray, heading_rel: np.ndarray) -> np.ndarray:
    """Poses [G, T, 3] at (forward, left) offsets [G, T] in the frame of ``pose`` [G, 3]."""
    c, s = np.cos(pose[:, None, 2]), np.sin(pose[:, None, 2])
    x = pose[:, None, 0] + c * forward_m - s * left_m
    y = pose[:, None, 1] + s * forward_m + c * left_m
    return np.stack([x, y, _wrap(pose[:, None, 2] + heading_rel)], -1)


def brake_path(pose: np.ndarray, speed_mps: np.ndarray, decel_mps2: float, num_frames: int) -> np.ndarray:
    """Braking at ``decel_mps2`` from ``speed_mps`` [G] at ``pose`` [G, 3], straight ahead, then
    standing still: [G, num_frames, 3] for frames 1..num_frames after the onset."""
    pose = np.asarray(pose, np.float64).reshape(-1, 3)
    v0 = np.maximum(np.asarray(speed_mps, np.float64).reshape(-1), 0.0)
    t = DT_S * np.arange(1, num_frames + 1)[None, :]  # (1, T)
    t_stop = v0[:, None] / max(decel_mps2, 1e-6)  # (G, 1)
    tt = np.minimum(t, t_stop)
    dist = v0[:, None] * tt - 0.5 * decel_mps2 * tt**2  # (G, T)
    return _along(pose, dist, np.zeros_like(dist), np.zeros_like(dist))


def stop_time_s(speed_mps: float, decel_mps2: float) -> float:
    """Seconds to a standstill from ``speed_mps`` at ``decel_mps2``."""
    return max(float(speed_mps), 0.0) / max(float(decel_mps2), 1e-6)


def cut_in_path(pose: np.ndarray, speed_mps: np.ndarray, lateral_m: float, duration_s: float, num_frames: int) -> np.ndarray:
    """A lane change of ``lateral_m`` (left positive) over ``duration_s`` at constant speed
    ``speed_mps`` [G] from ``pose`` [G, 3], then straight on: [G, num_frames, 3]."""
    pose = np.asarray(pose, np.float64).reshape(-1, 3)
    v = np.maximum(np.asarray(speed_mps, np.float64).reshape(-1), 0.0)[:, None]
    t = DT_S * np.arange(1, num_frames + 1)[None, :]
    u = np.clip(t / max(duration_s, 1e-6), 0.0, 1.0)
    left = lateral_m * 0.5 * (1.0 - np.cos(np.pi * u))  # (1, T) smooth 0 -> lateral_m
    dleft_dt = np.where(t < duration_s, lateral_m * 0.5 * np.pi / max(duration_s, 1e-6) * np.sin(np.pi * u), 0.0)
    forward = v * t
    heading = np.arctan2(dleft_dt, np.maximum(v, 0.5))  # tangent of the path (a creeping car still points along it)
    return _along(pose, forward, np.broadcast_to(left, forward.shape), np.broadcast_to(heading, forward.shape))


def hold_path(pose: np.ndarray, num_frames: int) -> np.ndarray:
    """Standing still at ``pose`` [G, 3]: [G, num_frames, 3]."""
    pose = np.asarray(pose, np.float64).reshape(-1, 3)
    return np.repeat(pose[:, None], num_frames, 1)


def polyline_path(waypoints: np.ndarray, speed_mps: float, num_frames: int, wait_s: float = 0.0,
                  first_frame: int = 0) -> np.ndarray:
    """Poses [num_frames, 3] for frames ``first_frame .. first_frame + num_frames - 1`` (frame 0 =
    at the first waypoint) of an agent that stands at ``waypoints[0]`` for ``wait_s``, then walks
    or drives along the polyline ``waypoints`` [K, 2] at ``speed_mps`` and stops at its end.
    Heading follows the segment it is on (the first segment's while waiting)."""
    wp = np.asarray(waypoints, np.float64).reshape(-1, 2)
    if len(wp) < 2:
        wp = np.concatenate([wp, wp], 0)
    seg = np.diff(wp, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    t = DT_S * np.arange(first_frame, first_frame + num_frames)
    s = np.clip((t - wait_s) * max(speed_mps, 0.0), 0.0, cum[-1])
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    frac = np.where(seg_len[i] > 0, (s - cum[i]) / np.where(seg_len[i] > 0, seg_len[i], 1.0), 0.0)
    xy = wp[i] + frac[:, None] * seg[i]
    moving_seg = np.flatnonzero(seg_len > 1e-6)
    first_heading = np.arctan2(*seg[moving_seg[0]][::-1]) if len(moving_seg) else 0.0
    heading = np.where(seg_len[i] > 1e-6, np.arctan2(seg[i, 1], seg[i, 0]), first_heading)
    return np.concatenate([xy, heading[:, None]], 1)


def nearest_tokens(token_poses: torch.Tensor, vocab_size: int, current_pose: torch.Tensor, targets: torch.Tensor,
                   heading_weight: float = HEADING_WEIGHT_M_PER_RAD) -> torch.Tensor:
    """The token closest to a scripted motion, per row.

    token_poses [V, 6, 3] (one type's token poses in the token's start frame; rows beyond
    ``vocab_size`` are ignored), current_pose [M, 3] (where the token starts), targets [M, 5, 3]
    or [M, 10, 3] (the next 5 or 10 target poses, same frame as ``current_pose``) -> token ids [M]
    minimising the mean position error plus ``heading_weight`` x the mean heading error. With 10
    targets it looks one token ahead: the first token of the best *pair* of tokens (V^2 pairs), so
    that a token which is good now but leaves the agent badly oriented for the next one loses.
    """
    poses = token_poses[:vocab_size, 1:].to(torch.float64)  # (V, 5, 3)
    cur = current_pose.to(torch.float64)
    tgt = targets.to(torch.float64)
    c, s = cur[:, 2].cos()[:, None], cur[:, 2].sin()[:, None]
    dx, dy = tgt[..., 0] - cur[:, None, 0], tgt[..., 1] - cur[:, None, 1]
    local = torch.stack([c * dx + s * dy, -s * dx + c * dy, tgt[..., 2] - cur[:, None, 2]], -1)  # (M, F, 3)

    def error(candidate: torch.Tensor, target: torch.Tensor) -> torch.Tensor:  # (..., F, 3) vs (M, 1.., F, 3)
        pos = (candidate[..., :2] - target[..., :2]).norm(dim=-1).mean(-1)
        dh = candidate[..., 2] - target[..., 2]
        return pos + heading_weight * torch.atan2(dh.sin(), dh.cos()).abs().mean(-1)

    if local.shape[1] < 2 * FRAMES_PER_TOKEN:
        return error(poses[None], local[:, None, :FRAMES_PER_TOKEN]).argmin(1)
    # pairs: token b placed at the end of token a -> (V, V, 5, 3)
    end = poses[:, -1]  # (V, 3)
    ce, se = end[:, 2].cos()[:, None, None], end[:, 2].sin()[:, None, None]
    bx, by = poses[None, :, :, 0], poses[None, :, :, 1]
    second = torch.stack([end[:, None, None, 0] + ce * bx - se * by, end[:, None, None, 1] + se * bx + ce * by,
                          end[:, None, None, 2] + poses[None, :, :, 2]], -1)
    pair = torch.cat([poses[:, None].expand(-1, poses.shape[0], -1, -1), second], 2)  # (V, V, 10, 3)
    err = error(pair[None], local[:, None, None, : 2 * FRAMES_PER_TOKEN])  # (M, V, V)
    return err.amin(2).argmin(1)
