"""Rollout stage, stopping at stop lines: the tokens a vehicle may not draw because after them it could not stop
before a red light's or a stop sign's stop line ahead in its lane.

What comes in: each scene's stop lines (a signal's stop point, or the start of a lane a stop sign controls, with
the lane's direction there), the light states of the current frame, every slot's pose and box, and each type's
token poses. What goes out: ``bool [M, V]`` per sampling row, true on the tokens to exclude, and after each step
the stop signs each vehicle has served.

The rule, per sampling vehicle (not pedestrians or cyclists): the nearest *active* line ahead of it, 0-40 m along
its heading, within 2 m to either side, its lane running within 45 degrees of the vehicle's heading, holds it. The
lanes that leave one stop line (their starts within a metre of each other, running within 45 degrees of each other)
form one line: a signal's line is active while every light of it is red (STOP, ARROW_STOP, FLASHING_STOP; a through
lane's green beside a turn lane's red arrow lets the vehicle go; the states the model sees: the current frame's,
held, or the log's at every step with ``lights="log"``); a stop sign's line until the vehicle has stood (under
1 m/s) with its front within 8 m of it, after which that line no longer holds it (stop, then go). With the
front bumper ``d`` metres before the line, a token whose end lies ``x`` metres ahead and whose end speed is ``v``
needs ``v^2 / (2 (d - x))`` of deceleration after it; tokens needing more than :data:`STOP_DECEL_MPS2`, or than
the row's least demanding token plus 1 m/s2 where none is that gentle, are excluded, and a token that puts the
bumper more than half a metre past the line needs an infinite one. A row whose every token is excluded keeps
them all, as in collision-aware sampling.

Why: the prior does not start a slowing for a light or sign it has not reached (on 320 generated held-out scenes
the vehicles whose log slows for a red light keep 2.1x its speed at 7-8 s; docs/experiments/2026-11-27-why-traffic-
slows.md). Like collision-aware sampling it changes what is drawn, not the model: logits, log-probabilities and
the KL reference stay the model's. Off by default (``stop_lines=False``).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from ..model.batch import stop_sign_lanes
from ..scenario import Scenario, SignalState

STOP_DECEL_MPS2 = 3.0
"""The deceleration a vehicle may need after a token to stop before an active line (m/s2)."""
LINE_AHEAD_M, LINE_SIDE_M = 40.0, 2.0
"""A line holds a vehicle when it lies this far ahead at most, and this far to either side of its heading at most."""
ALIGNED_COS = math.cos(math.radians(45.0))
"""... and its lane runs within 45 degrees of the vehicle's heading."""
STOPPED_MPS, SERVED_WITHIN_M = 1.0, 8.0
"""A vehicle slower than this with its front this near a stop sign's line has stopped there."""
RED = (int(SignalState.STOP), int(SignalState.ARROW_STOP), int(SignalState.FLASHING_STOP))
SAME_LINE_M = 1.0
"""Lanes whose stop points lie this near each other, running within 45 degrees of each other, leave one stop line."""
OVERRUN_M = 0.5
"""A token that puts the front bumper further past an active line than this is excluded whatever its speed."""


def scene_stop_lines(scenario: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A scene's stop lines: (points [L, 2], lane directions there [L, 2] (unit; NaN where the lane is unknown),
    the traffic-light lane index of each [L] (-1: a stop sign's line, :func:`~smart_marl.model.batch.stop_sign_lanes`))."""
    rm, tl = scenario.road_map, scenario.traffic_lights
    xy, direction, light = [], [], []

    def lane_start(index: int):
        p = rm.feature_points(int(index))[:, :2].astype(np.float64)
        step = p[1] - p[0] if len(p) >= 2 else np.zeros(2)
        norm = float(np.linalg.norm(step))
        return p[0], step / norm if norm > 1e-6 else np.full(2, np.nan)

    for lane in range(len(tl.lane_ids)):
        found = np.flatnonzero(rm.ids == tl.lane_ids[lane])
        xy.append(tl.stop_points[lane, :2].astype(np.float64))
        direction.append(lane_start(found[0])[1] if len(found) else np.full(2, np.nan))
        light.append(lane)
    for index in stop_sign_lanes(rm):
        start, d = lane_start(index)
        if np.isfinite(d).all():
            xy.append(start)
            direction.append(d)
            light.append(-1)
    return (np.array(xy, np.float32).reshape(-1, 2), np.array(direction, np.float32).reshape(-1, 2),
            np.array(light, np.int64))


def line_groups(xy: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """[L] the stop line each lane's stop point belongs to (the smallest index of its connected lanes: points within
    :data:`SAME_LINE_M` of each other, directions within 45 degrees or unknown)."""
    near = np.linalg.norm(xy[:, None] - xy[None], axis=-1) < SAME_LINE_M
    cos = np.nan_to_num((direction[:, None] * direction[None]).sum(-1), nan=1.0)
    linked = near & (cos > ALIGNED_COS)
    group = np.arange(len(xy))
    while True:  # each point takes the smallest label among those it is linked to, until none changes
        new = np.where(linked, group[None], len(xy)).min(1, initial=len(xy))
        if np.array_equal(new, group):
            return group
        group = new


def stop_line_tensors(scenes: Sequence[Scenario], frame_offset: int, device) -> dict[str, torch.Tensor]:
    """Every scene's lanes' stop points padded to the most [B, L]: ``stop_xy`` [B, L, 2], ``stop_dir`` [B, L, 2],
    ``stop_group`` [B, L] (:func:`line_groups`), ``stop_sign`` [B, L] (a stop sign's), ``stop_red`` [B, L] (a signal's,
    red at ``current frame + frame_offset``), ``stop_valid`` [B, L]."""
    lines = [scene_stop_lines(sc) for sc in scenes]
    size = max([len(li[2]) for li in lines] + [1])
    out = {"stop_xy": torch.zeros(len(scenes), size, 2), "stop_dir": torch.full((len(scenes), size, 2), float("nan")),
           "stop_group": torch.zeros(len(scenes), size, dtype=torch.long),
           "stop_sign": torch.zeros(len(scenes), size, dtype=torch.bool), "stop_red": torch.zeros(len(scenes), size, dtype=torch.bool),
           "stop_valid": torch.zeros(len(scenes), size, dtype=torch.bool)}
    for b, ((xy, d, light), sc) in enumerate(zip(lines, scenes)):
        k = len(light)
        out["stop_xy"][b, :k], out["stop_dir"][b, :k] = torch.from_numpy(xy), torch.from_numpy(d)
        out["stop_group"][b, :k] = torch.from_numpy(line_groups(xy.astype(np.float64), d.astype(np.float64)))
        out["stop_sign"][b, :k] = torch.from_numpy(light < 0)
        out["stop_red"][b, :k] = torch.from_numpy(red_lines(sc, light, frame_offset))
        out["stop_valid"][b, :k] = True
    return {name: t.to(device) for name, t in out.items()}


def red_lines(scenario: Scenario, light: np.ndarray, frame_offset: int) -> np.ndarray:
    """[L] bool: the lines of light lane indices ``light`` [L] (-1: a stop sign) whose signal is red at
    ``current frame + frame_offset`` (held at the scene's last frame beyond it)."""
    tl = scenario.traffic_lights
    out = np.zeros(len(light), bool)
    has = light >= 0
    if has.any() and tl.states.shape[0]:
        f = min(scenario.current_frame + int(frame_offset), tl.states.shape[0] - 1)
        out[has] = np.isin(tl.states[f, light[has]], RED) & tl.present[f, light[has]]
    return out


def nearest_line(state, g: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(distance [M] from slots ``(g, s)``'s centres to their nearest active line ahead, inf where none; that line's
    index [M], -1 where none), for a :class:`~smart_marl.rollout.RolloutState` with stop lines."""
    b = state.scene_of_group[g]
    pose = state.pose[g, s]  # [M, 3]
    c, sn = pose[:, 2].cos()[:, None], pose[:, 2].sin()[:, None]
    rel = state.stop_xy[b] - pose[:, None, :2]  # [M, L, 2]
    ahead = rel[..., 0] * c + rel[..., 1] * sn
    side = rel[..., 1] * c - rel[..., 0] * sn
    d = state.stop_dir[b]
    aligned = torch.where(torch.isnan(d[..., 0]), torch.ones_like(ahead, dtype=torch.bool), d[..., 0] * c + d[..., 1] * sn > ALIGNED_COS)
    group = state.stop_group[b]  # [M, L]
    served = state.stop_sign[b] & (group == state.stop_served[g, s][:, None])
    active = red_line_holds(state)[b] | (state.stop_sign[b] & ~served)
    holds = state.stop_valid[b] & active & aligned & (ahead > 0) & (ahead <= LINE_AHEAD_M) & (side.abs() <= LINE_SIDE_M)
    dist, line = ahead.masked_fill(~holds, float("inf")).min(-1)
    return dist, torch.where(torch.isfinite(dist), line, torch.full_like(line, -1))


def red_line_holds(state) -> torch.Tensor:
    """[B, L] the signals' lanes whose whole stop line is red (no lane leaving it has a light that is not)."""
    green = (state.stop_valid & ~state.stop_sign & ~state.stop_red).long()
    any_green = torch.zeros_like(green).scatter_add_(1, state.stop_group, green) > 0  # per line, by its first lane's index
    return state.stop_red & ~any_green.gather(1, state.stop_group)


def token_ends(token_poses: torch.Tensor, interpolation: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(how far ahead each token ends [types, V], its speed there [types, V]) in its start frame: the spline's end
    tangent is the token's chord over its 0.5 s (:mod:`~smart_marl.rollout.frames`), the contour's its last 0.1 s."""
    end = token_poses[..., -1, :2]
    speed = end.norm(dim=-1) / 0.5 if interpolation == "spline" else (end - token_poses[..., -2, :2]).norm(dim=-1) / 0.1
    return end[..., 0], speed


def stop_line_test(state, rows: torch.Tensor):
    """``also`` of :func:`~smart_marl.rollout.avoidance.excluded_tokens` for sampling rows ``rows`` [M] (flat slot
    indices) of ``state``, or None when no vehicle among them has an active line ahead."""
    n = state.num_slots
    g, s = rows // n, rows % n
    vehicle = (state.agent_type[g, s] == 0).nonzero().squeeze(1)  # lines hold vehicles only: the others are not measured
    dist, _ = nearest_line(state, g[vehicle], s[vehicle])
    ahead = torch.isfinite(dist)
    held, dist = vehicle[ahead], dist[ahead]
    if not len(held):
        return None
    end_x, end_v = state.stop_token_ends
    kind = state.agent_type[g[held], s[held]]
    front = dist - state.agent_shape[g[held], s[held], 0].to(dist.dtype) / 2  # [H] bumper to line
    room = front[:, None] - end_x[kind]  # [H, V]
    need = end_v[kind] ** 2 / (2 * room.clamp(min=0.05))
    need = need.masked_fill(room < -OVERRUN_M, float("inf"))
    size = state.vocab_sizes.to(need.device)[kind]
    need = need.masked_fill(torch.arange(need.shape[1], device=need.device)[None] >= size[:, None], float("inf"))
    limit = torch.clamp(need.amin(-1) + 1.0, min=STOP_DECEL_MPS2)
    bad = need > limit[:, None]  # [H, V]
    where = torch.full((len(rows),), -1, dtype=torch.long, device=rows.device)
    where[held] = torch.arange(len(held), device=rows.device)

    def test(r: torch.Tensor, tok: torch.Tensor) -> torch.Tensor:
        w = where[r]
        out = torch.zeros(tok.shape, dtype=torch.bool, device=tok.device)
        on = (w >= 0).nonzero().squeeze(1)
        if len(on):
            out[on] = bad[w[on][:, None], tok[on].clamp(max=bad.shape[1] - 1)]
        return out
    return test


def served_after_step(state) -> torch.Tensor:
    """[G, N] the stop sign's line (:func:`line_groups`) each slot has now served (:data:`STOPPED_MPS` within
    :data:`SERVED_WITHIN_M`), else what it had served before."""
    speed = (state.pose[..., :2] - state.previous_pose[..., :2]).norm(dim=-1) / 0.5
    g, s = (state.simulated & (state.agent_type == 0) & (speed < STOPPED_MPS)).nonzero(as_tuple=True)
    served = state.stop_served.clone()
    if len(g):
        dist, line = nearest_line(state, g, s)
        front = dist - state.agent_shape[g, s, 0].to(dist.dtype) / 2
        b, line = state.scene_of_group[g], line.clamp(min=0)
        at_sign = torch.isfinite(dist) & state.stop_sign[b, line] & (front < SERVED_WITHIN_M)
        served[g[at_sign], s[at_sign]] = state.stop_group[b, line][at_sign]
    return served


__all__ = ["STOP_DECEL_MPS2", "nearest_line", "scene_stop_lines", "served_after_step", "stop_line_test", "stop_line_tensors",
           "token_ends"]
