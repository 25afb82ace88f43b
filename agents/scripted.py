"""Agents stage, scripted motion: what-if manoeuvres as 10 Hz target poses -> forced motion tokens.

What comes in: an agent's pose and speed when a manoeuvre starts (one row per rollout), the
manoeuvre's parameters, and the motion vocabulary's token poses. What goes out: target paths
``[G, T, 3]`` (x, y, heading in the scene's local frame, frames 1..T after the onset) and, each
0.5 s token step, the token of the agent's type vocabulary whose 5 placed poses come closest to the
next 5 target poses (:func:`smart_marl.tokens.motion.match_token_path`, also :func:`nearest_tokens`
here). The rollout engine takes those tokens as forced tokens (``RolloutState.step(forced_tokens)``),
so a scripted agent moves only by real vocabulary tokens, as every other agent does.

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

:mod:`agents.whatif` uses these inside the rollout engine (any agent, every rollout at once);
:class:`ScriptedPolicy` uses them as a policy for the controlled agents of the PettingZoo env
``envs.smart_traffic_v0`` (a :class:`Manoeuvre` per agent name); :class:`LogFollowingPolicy` drives
them along their logged paths (the expert of :mod:`agents.evaluate`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from smart_marl.errors import SmartMarlError
from smart_marl.scenario import DT_S, AgentType, wrap_angle
from smart_marl.tokens import FRAMES_PER_TOKEN, TOKEN_S
from smart_marl.tokens.motion import match_token_path, path_heading_weight

from .prior_policy import SampledPolicy

nearest_tokens = match_token_path  # the scripted agents' token choice (smart_marl.tokens.motion.match_token_path)


def _along(pose: np.ndarray, forward_m: np.ndarray, left_m: np.ndarray, heading_rel: np.ndarray) -> np.ndarray:
    """Poses [G, T, 3] at (forward, left) offsets [G, T] in the frame of ``pose`` [G, 3]."""
    c, s = np.cos(pose[:, None, 2]), np.sin(pose[:, None, 2])
    x = pose[:, None, 0] + c * forward_m - s * left_m
    y = pose[:, None, 1] + s * forward_m + c * left_m
    return np.stack([x, y, wrap_angle(pose[:, None, 2] + heading_rel)], -1)


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


# ------------------------------------------------------------------------ as an env policy
MANOEUVRES = ("brake", "stop", "cut_in", "hold", "path", "tokens")


class ManoeuvreError(SmartMarlError, ValueError):
    """A :class:`Manoeuvre` of an unknown kind."""


@dataclass
class Manoeuvre:
    """One controlled agent's scripted manoeuvre from ``at_s`` (seconds after the episode's start)
    on: ``brake``/``stop`` (at ``decel_mps2``; stop defaults to 3), ``cut_in`` (``lateral_m``, left
    positive, over ``duration_s`` at ``speed_mps`` or the current speed), ``hold`` (stand still),
    ``path`` (``waypoints`` [[x, y], ...] in the scene's local frame at ``speed_mps``), ``tokens``
    (given token ids, one per step). After a cut-in, a path or the tokens, the fallback acts again."""

    kind: str
    at_s: float = 0.0
    decel_mps2: float | None = None
    lateral_m: float = 3.5
    duration_s: float = 2.0
    speed_mps: float | None = None
    waypoints: Any = None
    tokens: Sequence[int] | None = None

    def __post_init__(self) -> None:
        if self.kind not in MANOEUVRES:
            raise ManoeuvreError(f"Manoeuvre kind must be one of {MANOEUVRES}, got {self.kind!r}")

    def path(self, pose: np.ndarray, speed_mps: float, num_frames: int) -> np.ndarray:
        """Target poses [num_frames, 3] after the onset, from ``pose`` [3] at ``speed_mps``."""
        p = np.asarray(pose, np.float64)[None]
        v = np.array([speed_mps if self.speed_mps is None else self.speed_mps], np.float64)
        if self.kind in ("brake", "stop"):
            decel = self.decel_mps2 or (8.0 if self.kind == "brake" else 3.0)
            return brake_path(p, v, decel, num_frames)[0]
        if self.kind == "cut_in":
            n = FRAMES_PER_TOKEN * int(np.ceil(self.duration_s / DT_S / FRAMES_PER_TOKEN))
            return cut_in_path(p, v, self.lateral_m, self.duration_s, n)[0]
        if self.kind == "hold":
            return hold_path(p, num_frames)[0]
        return polyline_path(self.waypoints, float(v[0]), num_frames, first_frame=1)


class ScriptedPolicy:
    """Scripted controlled agents for ``envs.smart_traffic_v0``: ``policy(observations, infos)`` ->
    ``{agent: token}``, like :class:`agents.prior_policy.PriorPolicy`. The agents named in
    ``manoeuvres`` take, once their manoeuvre has started, the token closest to its target path
    (:func:`nearest_tokens`, one token of look-ahead, from the pose the env reports); every other
    agent, and those agents before and after their manoeuvre, act by ``fallback`` (any policy with
    that call signature; default: the prior's most likely token from ``infos``).
    """

    def __init__(self, env, manoeuvres: Mapping[str, Manoeuvre], fallback=None) -> None:
        self.env = env.unwrapped if hasattr(env, "unwrapped") else env
        self.manoeuvres = dict(manoeuvres)
        self.fallback = fallback
        self._paths: dict[str, np.ndarray] = {}

    def reset(self, seed: int | None = None) -> None:
        self._paths.clear()
        if self.fallback is not None and hasattr(self.fallback, "reset") and seed is not None:
            self.fallback.reset(seed)

    def __call__(self, observations: Mapping, infos: Mapping, agents: list[str] | None = None) -> dict[str, int]:
        env = self.env
        agents = list(agents if agents is not None else env.agents)
        if self.fallback is not None:
            actions = dict(self.fallback(observations, infos, agents))
        else:
            actions = {a: int(np.argmax(infos[a]["prior_logits"])) for a in agents}
        step = int(env.step_count)
        for name in agents:
            m = self.manoeuvres.get(name)
            if m is None:
                continue
            j = step - int(round(m.at_s / TOKEN_S))
            if j < 0:
                continue
            track = env.static.name_to_track[name]
            atype = int(env.static.types[track])
            if m.kind == "tokens":
                if j < len(m.tokens):
                    actions[name] = int(m.tokens[j])
                continue
            if name not in self._paths:
                horizon = FRAMES_PER_TOKEN * (int(env.horizon_steps) - step) + 2 * FRAMES_PER_TOKEN
                self._paths[name] = m.path(env.pose[track], float(np.linalg.norm(env.velocity[track])), horizon)
            path = self._paths[name]
            lo = FRAMES_PER_TOKEN * j
            if lo >= len(path) and m.kind in ("cut_in", "path"):
                continue  # done: the fallback drives again
            seg = path[lo: lo + 2 * FRAMES_PER_TOKEN]
            if len(seg) < 2 * FRAMES_PER_TOKEN:
                seg = np.concatenate([seg, np.repeat(path[-1:], 2 * FRAMES_PER_TOKEN - len(seg), 0)])
            vocab = env.motion_vocab[atype]
            tok = match_token_path(torch.from_numpy(vocab.poses.astype(np.float64)), vocab.size,
                                   torch.from_numpy(env.pose[track][None]), torch.from_numpy(seg[None]), path_heading_weight(atype))
            actions[name] = int(tok[0])
        return actions


def log_following_tokens(core, allowed: torch.Tensor | None = None) -> torch.Tensor:
    """[B, C] the expert's token of every controlled slot of a :class:`envs._core.TrafficCore`: the token
    of its type whose placed poses come closest to its logged path over the next two token steps
    (:func:`~smart_marl.tokens.motion.match_token_path`, from the pose it has reached, so quantisation
    errors are corrected at the next step). Frames the log misses hold the last logged pose before
    them (the agent stops where its log ends). ``allowed`` [B, C, V] bool: the tokens each slot may
    take (the first of the matched pair), None: all. Padded and done slots get token 0."""
    sb, dev = core.scenes, core.device
    b, c = core.ctrl_track.shape
    track = core.ctrl_track.clamp(min=0)
    f = core.frame[:, None] + torch.arange(1, 2 * FRAMES_PER_TOKEN + 1, device=dev)  # [B, 10]
    fi = torch.minimum(f, sb.num_frames[:, None] - 1)[:, None].expand(b, c, -1)  # [B, C, 10]
    rows = torch.arange(b, device=dev)[:, None, None]
    logged = sb.log_pose[rows, track[..., None], fi].to(torch.float64)  # [B, C, 10, 3]
    valid = sb.log_valid[rows, track[..., None], fi] & (f < sb.num_frames[:, None])[:, None]
    start = core.pose.gather(1, track[..., None].expand(-1, -1, 3)).to(torch.float64)  # [B, C, 3]
    last, seg = start, torch.empty_like(logged)
    for j in range(logged.shape[2]):  # frames the log misses hold the last pose
        last = torch.where(valid[..., j, None], logged[..., j, :], last)
        seg[..., j, :] = last
    types = sb.types.gather(1, track)
    live = core.live
    out = torch.zeros(b, c, dtype=torch.long, device=dev)
    for t in torch.unique(types[live]).tolist():
        sel = live & (types == t)
        vocab = core.motion_vocab[AgentType(t)]
        out[sel] = match_token_path(torch.from_numpy(vocab.poses.astype(np.float64)).to(dev), vocab.size, start[sel], seg[sel],
                                    path_heading_weight(t), None if allowed is None else allowed.to(dev)[sel])
    return out


class LogFollowingPolicy(SampledPolicy):
    """The expert on the PettingZoo env: each controlled agent takes, every step, the token of
    :func:`log_following_tokens` (its logged path over the next two token steps). Deterministic:
    ``log_probs`` is one-hot on the chosen token."""

    name = "expert (log)"
    top_k = 1

    def __init__(self, env, seed: int = 0) -> None:
        super().__init__(seed)
        self.env = env.unwrapped if hasattr(env, "unwrapped") else env

    def tokens(self, agents: list[str]) -> np.ndarray:
        """[A] the nearest token to each agent's logged path."""
        env = self.env
        tokens = log_following_tokens(env.core)[0].cpu().numpy()
        return np.array([tokens[env.possible_agents.index(a)] for a in agents], np.int64)

    def log_probs(self, agents: list[str], observations: Mapping, infos: Mapping) -> torch.Tensor:
        v = max(self.env.action_space(a).n for a in agents)
        out = torch.full((len(agents), v), float("-inf"))
        out[torch.arange(len(agents)), torch.from_numpy(self.tokens(agents))] = 0.0
        return out
