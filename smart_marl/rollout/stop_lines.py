"""Rollout stage, traffic control: the tokens a vehicle may not draw because of a stop line, and the ones a
standing vehicle may not draw once nothing holds it any more.

What comes in: each scene's stop lines (a signal's stop point, or the start of a lane a stop sign controls, with
the lane's direction there) and their light states on every token step the scene has logged, every slot's pose,
previous pose and box, and each type's token poses. What goes out: ``bool [M, V]`` per sampling row, true on the
tokens to exclude, and after each step the stop signs each vehicle has served.

**Stop.** Per sampling vehicle (not pedestrians or cyclists): the nearest *active* line ahead of it, 0-40 m along
its heading, within 2 m to either side, its lane running within 45 degrees of the vehicle's heading, holds it. The
lanes that leave one stop line (their starts within a metre of each other, running within 45 degrees of each other)
form one line (an *approach*): a signal's line is active while every light of it is red (STOP, ARROW_STOP,
FLASHING_STOP; a through lane's green beside a turn lane's red arrow lets the vehicle go); a stop sign's line until
the vehicle has stood (under 1 m/s) with its front within 8 m of it, after which that approach no longer holds
that vehicle (served per vehicle and per approach: serving one sign does not serve the next, and one vehicle's
stop serves no other). With the front bumper ``d`` metres before the line, a token whose end lies ``x`` metres
ahead and whose end speed is ``v`` needs ``v^2 / (2 (d - x))`` of deceleration after it; tokens needing more than
:data:`STOP_DECEL_MPS2`, or than the row's least demanding token plus 1 m/s2 where none is that gentle, are
excluded, and a token that puts the bumper more than half a metre past the line needs an infinite one.

**Right on red.** A signal's line whose lanes all turn right (:func:`right_turn_lanes`: a dedicated right-turn
lane) and are all at a plain red (STOP or FLASHING_STOP; a red arrow forbids it) is served like a stop sign, as US
law has it: the vehicle stops at it, then turns when the crossing is clear (below).

**Go.** A vehicle that stands (under 1 m/s over its last token), is not held, and has room ahead (no agent within
:data:`CLEAR_GAP_M` of its front in its path, 1.75 m to either side of its heading) is *released* when the reason
it stands has gone: the nearest line ahead of it (in the window above) is a green light (GO, ARROW_GO), or a stop
sign (or right turn on red) it has served and stood at for :data:`SIGN_WAIT_STEPS` (6 s) with the crossing clear
(:func:`crossing_clear`: no other agent within :data:`CROSSING_NEAR_M` of its line coming at it on another heading),
or, queued before a line that does not hold it, the vehicle ahead of it in its path (within 30 m, heading within 30
degrees) drives off (faster than 2 m/s). A released vehicle does not draw the tokens that leave it standing (ending
less than :data:`MIN_ADVANCE_M` ahead). Parked cars stand beside the lanes, away from stop lines and out of
the moving traffic's path, and are not released.

**Pull up.** A held vehicle that stands more than :data:`CREEP_FRONT_M` before its line with room ahead, and has
moved since its log began, does not draw the tokens that leave it standing either: it pulls up to the line, as
queued drivers do (and a stop sign is served only near its line). One that has stood all along stays (a car parked
in a lane 22 m before a red light was pulled into the lane ahead of it and hit: a real WOMD scene).

A row whose every token is excluded keeps them all, as in collision-aware sampling. Light states: the current
frame's, held (``lights="current"``, the sim-agents challenge's rule) or the log's at every step, held after the
scene's last logged frame (``lights="log"``: each scene of a batch on its own clock).

Why: the prior does not start a slowing for a light or sign it has not reached (on 320 generated held-out scenes
the vehicles whose log slows for a red light keep 2.1x its speed at 7-8 s; docs/experiments/2026-11-27-why-traffic-
slows.md), and it rarely starts a standing vehicle again by itself (departures started in 6-13% of rollouts:
docs/experiments/2026-11-29-traffic-control.md). Like collision-aware sampling it changes what is drawn, not the
model: logits, log-probabilities and the KL reference stay the model's. On by default (``stop_lines=True``).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from ..model.batch import stop_sign_lanes
from ..scenario import Scenario, SignalState
from .persistence import mean_speed

STOP_DECEL_MPS2 = 3.0
"""The deceleration a vehicle may need after a token to stop before an active line (m/s2)."""
LINE_AHEAD_M, LINE_SIDE_M = 40.0, 2.0
"""A line holds a vehicle when it lies this far ahead at most, and this far to either side of its heading at most."""
ALIGNED_COS = math.cos(math.radians(45.0))
"""... and its lane runs within 45 degrees of the vehicle's heading."""
STOPPED_MPS, SERVED_WITHIN_M = 1.0, 8.0
"""A vehicle slower than this stands; one slower than :data:`SERVED_BELOW_MPS` with its front this near a stop sign's
line has served it."""
SERVED_BELOW_MPS = 1.0
"""A stop sign is served below this speed (m/s, over the last token) near its line: a full stop."""
RED = (int(SignalState.STOP), int(SignalState.ARROW_STOP), int(SignalState.FLASHING_STOP))
GREEN = (int(SignalState.GO), int(SignalState.ARROW_GO))
TURN_ON_RED = (int(SignalState.STOP), int(SignalState.FLASHING_STOP))
"""The reds a right turn may be made on after a stop (a red arrow, ARROW_STOP, forbids it)."""
RIGHT_TURN_RAD = math.radians(45.0)
"""A signal's lane whose direction turns this far clockwise from its start to its end is a right turn."""
SAME_LINE_M = 1.0
"""Lanes whose stop points lie this near each other, running within 45 degrees of each other, leave one stop line."""
OVERRUN_M = 0.5
"""A token that puts the front bumper further past an active line than this is excluded whatever its speed."""
CLEAR_GAP_M = 4.0
"""A standing vehicle is released only with no agent this near its front bumper in its path."""
PATH_SIDE_M = 1.75
"""An agent whose centre lies this near a vehicle's heading line, ahead of it, is in its path."""
LEADER_AHEAD_M, LEADER_MOVING_MPS = 30.0, 2.0
"""The vehicle ahead in the path, this near (centre to centre), going this fast, releases the one behind it."""
LEADER_ALIGNED_COS = math.cos(math.radians(30.0))
CREEP_FRONT_M = 4.0
"""A held vehicle standing with its front further than this before its line, with room ahead, pulls up to it."""
SIGN_WAIT_STEPS = 12
"""A standing vehicle is released at a stop sign it has served after standing this many token steps (6 s) at least.
The vehicles whose log stops at a sign move on within 8 s in 46% of the 22 shared real scenes' logs (11 vehicles) and
34% of 80 generated intersections' (68). With the gap a driver waits for (:func:`crossing_clear`) and speed
persistence, the rollouts that stop there move on in 62% / 51% released after 4 s, 60% / 50% after 5 s, 45% / 42%
after 6 s (seed 0, 8 / 2 rollouts, lights "log"; docs/experiments/2026-11-29-speed-persistence.md). 4 s until
2026-11-29, chosen before the gap was waited for."""
CROSSING_NEAR_M, CROSSING_MOVING_MPS = 25.0, 1.0
"""A vehicle that has served a stop sign waits while another agent within this distance of its line (m) comes at it
faster than this (m/s) on another heading."""
MIN_ADVANCE_M = 0.25
"""A released vehicle's token must take it at least this far forward (0.5 m/s over the token's 0.5 s)."""


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


def right_turn_lanes(scenario: Scenario, light: np.ndarray) -> np.ndarray:
    """[L] the lanes of light lane indices ``light`` [L] (-1: a stop sign's, never) that turn right: their direction
    at the end lies more than :data:`RIGHT_TURN_RAD` clockwise of the one at the start."""
    rm, tl = scenario.road_map, scenario.traffic_lights
    out = np.zeros(len(light), bool)
    for k in np.flatnonzero(light >= 0):
        found = np.flatnonzero(rm.ids == tl.lane_ids[light[k]])
        p = rm.feature_points(int(found[0]))[:, :2].astype(np.float64) if len(found) else np.zeros((0, 2))
        if len(p) >= 3:
            first, last = p[1] - p[0], p[-1] - p[-2]
            turn = math.atan2(first[0] * last[1] - first[1] * last[0], float(first @ last))
            out[k] = turn < -RIGHT_TURN_RAD
    return out


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


def logged_light_steps(scenario: Scenario, frames_per_step: int = 5) -> int:
    """How many token steps from the current frame on (the current one included) the scene's light states are
    logged for: at least 1 (a scene without later states holds its last one)."""
    frames = scenario.traffic_lights.states.shape[0]
    return max(1, (frames - 1 - scenario.current_frame) // frames_per_step + 1)


def stop_line_tensors(scenes: Sequence[Scenario], device, steps: int = 1) -> dict[str, torch.Tensor]:
    """Every scene's lanes' stop points padded to the most [B, L]: ``stop_xy`` [B, L, 2], ``stop_dir`` [B, L, 2],
    ``stop_group`` [B, L] (:func:`line_groups`), ``stop_sign`` [B, L] (a stop sign's), ``stop_valid`` [B, L], and the
    signals' states on token steps ``0 .. steps - 1`` (frame ``current + 5 k``, the last logged frame's held beyond
    it): ``stop_red_steps`` / ``stop_go_steps`` [B, steps, L], the lanes whose light is red / green then, and
    ``stop_turn_red_steps``, the right turns whose red lets them turn after a stop (:func:`line_lights`)."""
    lines = [scene_stop_lines(sc) for sc in scenes]
    size = max([len(li[2]) for li in lines] + [1])
    b_, s_ = len(scenes), int(steps)
    out = {"stop_xy": torch.zeros(b_, size, 2), "stop_dir": torch.full((b_, size, 2), float("nan")),
           "stop_group": torch.zeros(b_, size, dtype=torch.long), "stop_sign": torch.zeros(b_, size, dtype=torch.bool),
           "stop_valid": torch.zeros(b_, size, dtype=torch.bool),
           "stop_red_steps": torch.zeros(b_, s_, size, dtype=torch.bool), "stop_go_steps": torch.zeros(b_, s_, size, dtype=torch.bool),
           "stop_turn_red_steps": torch.zeros(b_, s_, size, dtype=torch.bool)}
    for b, ((xy, d, light), sc) in enumerate(zip(lines, scenes)):
        k = len(light)
        out["stop_xy"][b, :k], out["stop_dir"][b, :k] = torch.from_numpy(xy), torch.from_numpy(d)
        out["stop_group"][b, :k] = torch.from_numpy(line_groups(xy.astype(np.float64), d.astype(np.float64)))
        out["stop_sign"][b, :k] = torch.from_numpy(light < 0)
        out["stop_valid"][b, :k] = True
        right = right_turn_lanes(sc, light)
        for step in range(s_):
            for name, lanes in zip(("stop_red_steps", "stop_go_steps", "stop_turn_red_steps"), line_lights(sc, light, 5 * step, right)):
                out[name][b, step, :k] = torch.from_numpy(lanes)
    return {name: t.to(device) for name, t in out.items()}


def line_lights(scenario: Scenario, light: np.ndarray, frame_offset: int,
                right: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """([L] red, [L] green, [L] turn on red): the lines of light lane indices ``light`` [L] (-1: a stop sign) whose
    signal is red / green at ``current frame + frame_offset`` (held at the scene's last frame beyond it; neither where
    unknown), and among the ``right`` [L] turns (:func:`right_turn_lanes`; none when not given) those whose red
    (:data:`TURN_ON_RED`) lets a vehicle turn after a stop."""
    tl = scenario.traffic_lights
    red, go, turn = np.zeros(len(light), bool), np.zeros(len(light), bool), np.zeros(len(light), bool)
    has = light >= 0
    if has.any() and tl.states.shape[0]:
        f = min(scenario.current_frame + int(frame_offset), tl.states.shape[0] - 1)
        state, present = tl.states[f, light[has]], tl.present[f, light[has]]
        red[has] = np.isin(state, RED) & present
        go[has] = np.isin(state, GREEN) & present
        turn[has] = np.isin(state, TURN_ON_RED) & present
    return red, go, turn & right if right is not None else np.zeros(len(light), bool)


def lines_ahead(state, g: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(how far ahead of slots ``(g, s)``'s centres each line of their scene lies along their heading [M, L], whether
    it lies where a line can hold them [M, L]: 0-40 m ahead, 2 m to either side, its lane within 45 degrees)."""
    b = state.scene_of_group[g]
    pose = state.pose[g, s]  # [M, 3]
    c, sn = pose[:, 2].cos()[:, None], pose[:, 2].sin()[:, None]
    rel = state.stop_xy[b] - pose[:, None, :2]  # [M, L, 2]
    ahead = rel[..., 0] * c + rel[..., 1] * sn
    side = rel[..., 1] * c - rel[..., 0] * sn
    d = state.stop_dir[b]
    aligned = torch.where(torch.isnan(d[..., 0]), torch.ones_like(ahead, dtype=torch.bool), d[..., 0] * c + d[..., 1] * sn > ALIGNED_COS)
    in_view = state.stop_valid[b] & aligned & (ahead > 0) & (ahead <= LINE_AHEAD_M) & (side.abs() <= LINE_SIDE_M)
    return ahead, in_view


def nearest_line(state, g: torch.Tensor, s: torch.Tensor, view=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(distance [M] from slots ``(g, s)``'s centres to their nearest active line ahead, inf where none; that line's
    index [M], -1 where none), for a :class:`~smart_marl.rollout.RolloutState` with stop lines. ``view``: their
    :func:`lines_ahead`, where the caller has it."""
    b = state.scene_of_group[g]
    ahead, in_view = lines_ahead(state, g, s) if view is None else view
    holds = red_line_holds(state)
    active = (holds | state.stop_sign)[b] & ~(servable(state, holds)[b] & state.stop_served[g, s])
    dist, line = ahead.masked_fill(~(in_view & active), float("inf")).min(-1)
    return dist, torch.where(torch.isfinite(dist), line, torch.full_like(line, -1))


def _per_line(state, lanes: torch.Tensor) -> torch.Tensor:
    """[B, L] whether any lane of each lane's stop line (:func:`line_groups`) is among ``lanes`` [B, L]."""
    count = torch.zeros(lanes.shape, dtype=torch.long, device=lanes.device).scatter_add_(1, state.stop_group, lanes.long())
    return count.gather(1, state.stop_group) > 0  # per line, by its first lane's index


def red_line_holds(state) -> torch.Tensor:
    """[B, L] the signals' lanes whose whole stop line is red (no lane leaving it has a light that is not)."""
    return state.stop_red & ~_per_line(state, state.stop_valid & ~state.stop_sign & ~state.stop_red)


def servable(state, holds: torch.Tensor | None = None) -> torch.Tensor:
    """[B, L] the lines a vehicle serves by standing at them: stop signs, and right turns on red (a signal's line that
    is red as a whole, ``holds`` (:func:`red_line_holds`, computed when not given), and all right turns that may turn
    on that red after a stop, ``stop_turn_red``: a dedicated right-turn lane at a plain red)."""
    holds = red_line_holds(state) if holds is None else holds
    return state.stop_sign | (holds & ~_per_line(state, state.stop_valid & ~state.stop_sign & ~state.stop_turn_red))


def green_line_goes(state) -> torch.Tensor:
    """[B, L] the signals' lanes whose stop line has a green light (one of its lanes may go)."""
    return state.stop_valid & ~state.stop_sign & _per_line(state, state.stop_go & state.stop_valid)


def _speed_mps(pose: torch.Tensor, previous_pose: torch.Tensor) -> torch.Tensor:
    """[...] the speed over the last token (0.5 s) from the poses [..., 3]; 0 where there is no previous pose."""
    return torch.nan_to_num(mean_speed(pose, previous_pose), nan=0.0)


def _standing(state, g: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """[M] the slots ``(g, s)`` that moved less than :data:`STOPPED_MPS` over their last token (not a slot just placed)."""
    before = state.previous_pose[g, s]
    return (_speed_mps(state.pose[g, s], before) < STOPPED_MPS) & ~torch.isnan(before[:, 0])


def _others(state, g: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(poses [M, N, 3], previous poses [M, N, 3], simulated [M, N] except each row's own slot) of the agents of the
    groups of slots ``(g, s)``: the others each vehicle looks at."""
    there = state.simulated.index_select(0, g).clone()
    there[torch.arange(len(g), device=g.device), s] = False
    return state.pose.index_select(0, g), state.previous_pose.index_select(0, g), there


def _path_ahead(state, g: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """([M] no agent within :data:`CLEAR_GAP_M` of the front bumper in the path, [M] the nearest agent in the path lies
    within :data:`LEADER_AHEAD_M` going the same way faster than :data:`LEADER_MOVING_MPS`): the path is the slot's
    heading line, 1.75 m to either side, ahead of its centre."""
    pose, m = state.pose[g, s], torch.arange(len(g), device=g.device)
    others, before, there = _others(state, g, s)
    c, sn = pose[:, 2].cos()[:, None], pose[:, 2].sin()[:, None]
    rel = others[..., :2] - pose[:, None, :2]
    fwd = rel[..., 0] * c + rel[..., 1] * sn
    side = rel[..., 1] * c - rel[..., 0] * sn
    in_path = there & (fwd > 0) & (side.abs() < PATH_SIDE_M)
    length = state.agent_shape.index_select(0, g)[..., 0].to(fwd.dtype)  # [M, N]
    gap = fwd - state.agent_shape[g, s, 0].to(fwd.dtype)[:, None] / 2 - length / 2
    room = ~(in_path & (gap < CLEAR_GAP_M)).any(-1)
    lead_d, lead = fwd.masked_fill(~in_path, float("inf")).min(-1)
    lead_pose = others[m, lead]
    leaves = (torch.isfinite(lead_d) & (lead_d < LEADER_AHEAD_M) & (_speed_mps(lead_pose, before[m, lead]) > LEADER_MOVING_MPS)
              & ((lead_pose[:, 2] - pose[:, 2]).cos() > LEADER_ALIGNED_COS))
    return room, leaves


def released(state, g: torch.Tensor, s: torch.Tensor, held: torch.Tensor, view=None) -> torch.Tensor:
    """[M] the vehicles of slots ``(g, s)`` that stand, are not ``held`` [M], have room ahead and whose reason to
    stand has gone: a green line nearest ahead, or a served stop sign (stood at for :data:`SIGN_WAIT_STEPS`, the
    crossing clear: :func:`crossing_clear`), or, with a line ahead that does not hold it, the vehicle ahead in the path
    driving off. ``view``: as :func:`nearest_line`'s."""
    out = _standing(state, g, s) & ~held
    if not bool(out.any()):
        return out
    b = state.scene_of_group[g]
    ahead, in_view = lines_ahead(state, g, s) if view is None else view
    dist, line = ahead.masked_fill(~in_view, float("inf")).min(-1)  # the nearest line ahead, whatever its light
    lc = line.clamp(min=0)
    waited = state.stop_stood[g, s] >= SIGN_WAIT_STEPS
    at_sign = servable(state)[b, lc] & state.stop_served[g, s].gather(1, lc[:, None]).squeeze(1) & waited
    if bool(at_sign.any()):
        at_sign = at_sign & crossing_clear(state, g, s, dist)
    lets_go = at_sign | green_line_goes(state)[b, lc]
    room, leaves = _path_ahead(state, g, s)
    return out & room & torch.isfinite(dist) & (lets_go | leaves)


def crossing_clear(state, g: torch.Tensor, s: torch.Tensor, line_m: torch.Tensor) -> torch.Tensor:
    """[M] no other agent comes at the stop line of slots ``(g, s)`` (their nearest line ahead, ``line_m`` [M] metres
    ahead of their centres): none within :data:`CROSSING_NEAR_M` of that point moving faster than
    :data:`CROSSING_MOVING_MPS` towards it on another heading (more than 30 degrees off theirs: across their way, or
    head on, since at a stop sign whoever came first goes first), the gap a driver at a sign waits for."""
    pose = state.pose[g, s]
    at = pose[:, :2] + torch.nan_to_num(line_m, posinf=0.0)[:, None] * torch.stack([pose[:, 2].cos(), pose[:, 2].sin()], -1)
    others, before, there = _others(state, g, s)
    velocity = torch.nan_to_num((others[..., :2] - before[..., :2]) / 0.5)  # [M, N, 2]
    to_line = at[:, None] - others[..., :2]
    near = to_line.norm(dim=-1) < CROSSING_NEAR_M
    coming = (velocity * to_line).sum(-1) > CROSSING_MOVING_MPS * to_line.norm(dim=-1)  # closing faster than that
    crossing = (others[..., 2] - pose[:, None, 2]).cos() < LEADER_ALIGNED_COS  # not going its way
    return ~(there & near & coming & crossing).any(-1)


def creeping(state, g: torch.Tensor, s: torch.Tensor, front_m: torch.Tensor) -> torch.Tensor:
    """[M] the held vehicles of slots ``(g, s)``, their front bumpers ``front_m`` [M] before the line that holds them,
    that stand further back than :data:`CREEP_FRONT_M` with room ahead and have moved since the log began: they pull
    up to the line (a sign's is served only within :data:`SERVED_WITHIN_M` of it). One that has stood all along is
    left where it stands: a car parked in a lane, or waiting for what no rule sees."""
    out = _standing(state, g, s) & (front_m > CREEP_FRONT_M) & state.stop_moved[g, s]
    return out & _path_ahead(state, g, s)[0] if bool(out.any()) else out


def token_ends(token_poses: torch.Tensor, interpolation: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(how far ahead each token ends [types, V], its speed there [types, V]) in its start frame: the spline's end
    tangent is the token's chord over its 0.5 s (:mod:`~smart_marl.rollout.frames`), the contour's its last 0.1 s."""
    end = token_poses[..., -1, :2]
    speed = end.norm(dim=-1) / 0.5 if interpolation == "spline" else (end - token_poses[..., -2, :2]).norm(dim=-1) / 0.1
    return end[..., 0], speed


def stop_line_test(state, rows: torch.Tensor):
    """``also`` of :func:`~smart_marl.rollout.avoidance.excluded_tokens` for sampling rows ``rows`` [M] (flat slot
    indices) of ``state``: the held vehicles' tokens after which they could not stop, the released vehicles' tokens
    that leave them standing (module docstring); None when no vehicle among them is held or released."""
    n = state.num_slots
    g, s = rows // n, rows % n
    vehicle = (state.agent_type[g, s] == 0).nonzero().squeeze(1)  # lines hold vehicles only: the others are not measured
    view = lines_ahead(state, g[vehicle], s[vehicle])  # one look at the lines for both rules
    dist, _ = nearest_line(state, g[vehicle], s[vehicle], view)
    ahead = torch.isfinite(dist)
    go = vehicle[released(state, g[vehicle], s[vehicle], ahead, view)]
    held, dist = vehicle[ahead], dist[ahead]
    if not len(held) and not len(go):
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
    stays = end_x < MIN_ADVANCE_M  # [types, V] the tokens that leave a vehicle standing
    creep = creeping(state, g[held], s[held], front)  # [H] held far back: they pull up, as far as they can stop
    bad = torch.cat([(need > limit[:, None]) | (creep[:, None] & stays[kind]), stays[state.agent_type[g[go], s[go]]]])  # [H + Q, V]
    where = torch.full((len(rows),), -1, dtype=torch.long, device=rows.device)
    where[held] = torch.arange(len(held), device=rows.device)
    where[go] = len(held) + torch.arange(len(go), device=rows.device)

    def test(r: torch.Tensor, tok: torch.Tensor) -> torch.Tensor:
        w = where[r]
        out = torch.zeros(tok.shape, dtype=torch.bool, device=tok.device)
        on = (w >= 0).nonzero().squeeze(1)
        if len(on):
            out[on] = bad[w[on][:, None], tok[on].clamp(max=bad.shape[1] - 1)]
        return out
    return test


def served_after_step(state) -> torch.Tensor:
    """[G, N, L] the stop signs' lanes each slot has now served: every lane of the line (:func:`line_groups`) it has
    stood at (:data:`SERVED_BELOW_MPS` within :data:`SERVED_WITHIN_M` of its nearest unserved sign), and what it had
    served before."""
    speed = _speed_mps(state.pose, state.previous_pose)
    g, s = (state.simulated & (state.agent_type == 0) & (speed < SERVED_BELOW_MPS)).nonzero(as_tuple=True)
    served = state.stop_served.clone()
    if len(g):
        dist, line = nearest_line(state, g, s)
        front = dist - state.agent_shape[g, s, 0].to(dist.dtype) / 2
        b, line, serve = state.scene_of_group[g], line.clamp(min=0), servable(state)
        at = (torch.isfinite(dist) & serve[b, line] & (front < SERVED_WITHIN_M)).nonzero().squeeze(1)
        if len(at):
            ga, sa, ba = g[at], s[at], b[at]
            approach = serve[ba] & (state.stop_group[ba] == state.stop_group[ba, line[at]][:, None])  # [K, L]
            served[ga, sa] |= approach
    return served


def stood_after_step(state) -> tuple[torch.Tensor, torch.Tensor]:
    """([G, N] how many token steps in a row each slot has now stood (under :data:`STOPPED_MPS`), [G, N] whether it
    has moved on any step so far)."""
    standing = _speed_mps(state.pose, state.previous_pose) < STOPPED_MPS
    return torch.where(standing, state.stop_stood + 1, torch.zeros_like(state.stop_stood)), state.stop_moved | ~standing


def stood_in_history(valid: torch.Tensor, start: torch.Tensor, end: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """([G, N] how many of the history's last token steps in a row each slot stood (an agent may have waited at a sign
    before the current frame already), [G, N] whether it moved on a logged step), from its steps' ``valid``
    [G, N, S] and start / end poses [G, N, S, 3]."""
    stood = torch.zeros(valid.shape[:2], dtype=torch.long, device=valid.device)
    moved = torch.zeros(valid.shape[:2], dtype=torch.bool, device=valid.device)
    for k in range(valid.shape[2]):
        speed = _speed_mps(end[:, :, k], start[:, :, k])
        standing = valid[:, :, k] & (speed < STOPPED_MPS)
        stood = torch.where(standing, stood + 1, torch.zeros_like(stood))
        moved |= valid[:, :, k] & (speed >= STOPPED_MPS)
    return stood, moved


def lights_at(steps: torch.Tensor, clock: torch.Tensor) -> torch.Tensor:
    """[B, ...] each scene's entry of ``steps`` [B, S, ...] at its own token step ``clock`` [B] (the last held beyond S)."""
    k = clock.clamp(max=steps.shape[1] - 1)
    return steps[torch.arange(steps.shape[0], device=steps.device), k]


__all__ = ["GREEN", "TURN_ON_RED", "STOP_DECEL_MPS2", "creeping", "green_line_goes", "lights_at", "line_lights", "logged_light_steps",
           "nearest_line", "released", "right_turn_lanes", "scene_stop_lines", "servable", "served_after_step", "stood_after_step", "stood_in_history",
           "stop_line_test", "stop_line_tensors", "token_ends"]
