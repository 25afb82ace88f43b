"""Benchmark of traffic control in closed loop: does the prior's traffic stop, wait and go at real signals and stop
signs as the log does, without running red lights?

What comes in: scene sets (``--set NAME=PATH[,PATH...]``, repeatable: generated scenes with signals, stop signs,
queues and departures go in this way, e.g. ``--set sumo=smart_marl/samples``); by default every shared real scene
the readers read (``../shared/data``: the 91-frame WOMD-derived scenes of ``prior_speed_drift.REAL_91_FRAMES`` and
:data:`LONGER_REAL`, the AV2, nuScenes and 20 s ScenarioNet scenes). A scene is rolled out when its log is at 10 Hz,
covers the current frame + 80 frames (8 s), and has a vehicle moving faster than 5 m/s at the current frame that is
logged at the frame before, the current frame and 8 s later; a scene whose current frame is before frame 10 (the 20 s
ScenarioNet scene: frame 0) gets frame 10 as its current frame (1 s of history, as WOMD's). The others are skipped and
counted in every row (``scenes_skipped``: ``unreadable`` files, ``not_10hz``, ``short_log``, ``no_moving_vehicle``;
``scenes`` counts the scenes rolled out, at most ``--max-scenes``). Each scene is rolled
out ``--rollouts`` times for 8 s with ``prior_speed_drift.rollout_from_log`` (its arguments:
``prior_speed_drift.vehicle_rollout_arguments``; ``--no-stop-lines`` turns the engine's traffic control off, on by
default as the engine's, and the rows report it as ``stop_lines``; ``--persistence B`` the vehicles' speed persistence,
:mod:`smart_marl.rollout.persistence`, reported as ``persistence``).

What goes out (stdout, one JSON object per line, flushed), per set, every row with ``benchmark``, ``set``,
``scenes``, ``scenes_skipped``, ``seed``, ``rollouts``, ``prior``, ``top_k``, ``sampling``, ``lights``,
``stop_lines``, ``persistence`` and its counts:

* ``kind: "cause"``, one row per cause (:data:`CAUSES`) of the simulated vehicles (parked ones too, mostly
  ``none``): ``vehicles``; ``log_mps_4s``, ``rollout_mps_4s``,
  ``ratio_4s`` over the vehicles logged on at least half of the frames 3.5-4.5 s (``vehicles_4s``), and the same at
  7-8 s (``_7_8s``, the last second, ``prior_speed_drift.LATE_FRAMES``). A vehicle's speed in a window is its mean
  10 Hz position-difference speed over the frames it is logged on (at the frame and the one before), the rollout's
  the mean over rollouts on the same frames; a ratio is the sum of rollout speeds over the sum of logged ones.
* ``kind: "speed"``: the vehicles moving faster than 5 m/s at the current frame, exactly as
  ``prior_speed_drift.speed_sums`` counts them: rollout / log mean speed at 4 s and 8 s (one frame) and at 7-8 s,
  and at 7-8 s for the ``late_by_log_trend`` groups (``slows_``, ``keeps_``, ``speeds_up_``: the log's 7-8 s speed
  more than 20% below, within 20% of, more than 20% above the speed now).
* ``kind: "red_crossings"``: per simulated vehicle, whether its path crosses a red line (below) in the log and in
  each rollout; ``log_rate`` (share of the vehicles whose log crosses) and ``rollout_rate`` (share of vehicle
  rollouts that cross), over all simulated vehicles and over those with a signal's line ahead at the current frame
  (``vehicles_with_signal_ahead``: 0-40 m ahead of its centre along the lane, within 2 m of it laterally, heading
  within 45 degrees of the lane).
* ``kind: "stop_signs"``: the vehicles whose log stops at a stop sign's line (below): ``rollouts_stop`` (share of
  their rollouts that stop at that line too), ``rollouts_stop_then_move_on`` (share that stop and then move on),
  ``move_on_after_stop`` (of the rollouts that stop, the share that move on) against ``log_moves_on`` (share of
  the vehicles whose log moves on after its stop); and the vehicles whose log reaches a stop sign's line without
  stopping there (``rolling_vehicles``): ``rolling_rollouts_stop``, the share of their rollouts that stop at a sign.
* ``kind: "departures"``: ``departures.summarise``'s row (standing vehicles whose log drives off: the share of
  rollouts moving at 7-8 s, median start times) plus ``keep_standing`` (standing vehicles whose log does not drive
  off) and ``false_departures``, the share of their rollouts moving at 7-8 s (faster than 1 m/s), against
  ``keep_standing_log_moving``, the share of them whose log moves that fast (1-3 m/s: creeping up, not driving off).

Definitions (every distance in the scene's local frame, metres; frames from the current frame ``cf`` to ``cf + 80``):

* A *stop line* is a lane's stop point with the lane's direction there (``stop_lines.scene_stop_lines``: signals'
  lanes, and the lanes leaving a stop sign); lines whose lane direction is unknown are left out. A vehicle's
  *along* coordinate is its centre's distance past the point along the lane direction (negative before it), its
  *lateral* one the distance across. Lanes leaving one stop line (``stop_lines.line_groups``) form one line, and a
  signal's line is *red* on a frame when every light of it is STOP, ARROW_STOP or FLASHING_STOP on that frame in the
  log (a green through lane beside a red turn arrow: not red), as the engine's rule holds it. A lane's state on a
  frame where the log has it UNKNOWN or does not report it is its last known one (WOMD drops a light for a second
  now and then); before its first known state it is unknown. Everything else (GO, CAUTION, unknown) is *not red*.
* A vehicle *reaches* a line on a frame when its centre is before it (along < 0) with its front bumper within 8 m
  of it (``-along - length / 2 <= 8``), within 2 m laterally (the engine's reach, ``stop_lines.LINE_SIDE_M``: with
  3.5 m a car reaches the next lane's line too, e.g. a red turn arrow beside its green through lane), heading within
  45 degrees of the lane; it *passes* the line on the first later frame whose along >= 0.
* Causes, from each simulated vehicle's LOG, the first that holds (:func:`first_cause`):

  1. ``red_now``: it reaches a signal's line that is red at ``cf`` and stays red on every frame up to the one it
     passes it on (or its last logged frame if it never does): it waits, or runs the light;
  2. ``turns_red``: it reaches a signal's line that is not red at ``cf`` and is red on some frame before it passes;
  3. ``turns_green``: it reaches a signal's line that is red at ``cf`` and not red on some frame before it passes
     (or before its log ends);
  4. ``stop_sign``: it reaches a stop sign's line;
  5. ``departure``: it stands at ``cf`` (under 0.5 m/s over the last 0.5 s) and its log drives off (mean speed at
     7-8 s above 3 m/s; ``departures.standing_vehicles``);
  6. ``queue``: in the last second of its log a vehicle or cyclist lies 0-30 m ahead of it within 1.75 m sideways,
     heading within 30 degrees (``slowing_causes.what_it_meets``);
  7. ``none``.

  Signals come first (a queue at a red light is there for the light; a standing car that leaves on green leaves for
  the light), a sign before a departure (leaving a stop sign is what the sign asks), a departure before a queue (the
  standing-start is what the rollout must produce; who is ahead afterwards matters less). A vehicle queued more than
  8 m back from a red line does not reach it and counts as ``queue``.
* *Red crossing*: a step between consecutive frames (both logged) on which the centre goes from before a signal's
  line to on or past it (along from < 0 to >= 0), crossing within 2 m of the stop point laterally (``CROSS_HALF_M``),
  the step running within 45 degrees of the lane direction, the line red in the log on the frame after the step. A
  rollout's path starts at the logged position at ``cf``.
* *Stop at a sign*: a frame from ``cf + 5`` on at which the vehicle reaches a stop sign's line and its speed over the
  last 0.5 s is under 1 m/s (``stop_lines.STOPPED_MPS``); in the rollouts, at a lane of the same line (group) as
  the log's first stop. It *moves on* when, on a later frame, its speed over 0.5 s exceeds 2 m/s or its centre is on
  or past that line (within 2 m laterally).

    .venv/bin/python benchmarks/traffic_control.py [--prior PATH] [--set NAME=PATH ...] [--rollouts 8] [--seed 0]
        [--sampling default|plain] [--top-k K] [--lights current|log] [--no-stop-lines] [--persistence B] [--max-scenes N] [--threads 2]
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import departures  # noqa: E402  (benchmarks/ is not a package)
import prior_speed_drift as drift  # noqa: E402
import slowing_causes as slowing  # noqa: E402

from smart_marl.readers import read_scenarios  # noqa: E402
from smart_marl.rollout.stop_lines import ALIGNED_COS, RED, STOPPED_MPS, line_groups, scene_stop_lines  # noqa: E402
from smart_marl.scenario import DT_S, AgentType, SignalState, wrap_angle  # noqa: E402

CAUSES = ("red_now", "turns_red", "turns_green", "stop_sign", "departure", "queue", "none")
LONGER_REAL = ["scenarionet/waymo/sd_waymo*.pkl", "scenarionet/nuscenes/*.pkl", "av2"]
"""The shared real scenes beyond the 91-frame ones: the 20 s ScenarioNet WOMD scene, nuScenes-mini, Argoverse 2."""
FRAMES, LATE = drift.NUM_FRAMES, drift.LATE_FRAMES  # 8 s at 10 Hz; the last second
HISTORY_FRAMES = 10  # a scene whose current frame is earlier gets this one (1 s of history)
MID_S = (3.5, 4.5)  # "at 4 s": the frames of this window
MOVING_MPS = drift.MOVING_MPS[AgentType.VEHICLE]  # 5 m/s: a scene needs one vehicle this fast; the speed row's vehicles
LINE_AHEAD_M = 40.0  # a signal's line this far ahead of a vehicle's centre at cf: it has a signal ahead
LINE_SIDE_M = 2.0  # lateral reach of a line for reaching / stopping / ahead (stop_lines.LINE_SIDE_M; module docstring)
REACH_FRONT_M = 8.0  # front bumper this near a line: reaches it (stop_lines.SERVED_WITHIN_M)
CROSS_HALF_M = 2.0  # a red line crossed this near its stop point laterally counts (stop_lines.LINE_SIDE_M)
HALF_SECOND_FRAMES = 5  # speeds over 0.5 s for stops at signs
MOVE_ON_MPS = 2.0  # after a stop at a sign, faster than this: moved on
SPEED_ROW_TRENDS = drift.TRENDS  # ("speeds_up", "keeps", "slows")


# ------------------------------------------------------------------------------------------------ scenes

def scene_problem(scene) -> str | None:
    """Why a scene is not rolled out (``not_10hz``, ``short_log``, ``no_moving_vehicle``), or None."""
    if scene.num_frames > 1 and not np.allclose(np.diff(scene.timestamps_s), DT_S, atol=1e-3):
        return "not_10hz"
    cf = scene.current_frame
    if scene.num_frames < cf + 1 + FRAMES:
        return "short_log"
    tr = scene.tracks
    if cf < 1:  # no speed at the current frame
        return "no_moving_vehicle"
    v_now = np.linalg.norm(tr.position[:, cf, :2] - tr.position[:, cf - 1, :2], axis=-1) / DT_S
    logged = (tr.types == int(AgentType.VEHICLE)) & tr.valid[:, cf - 1] & tr.valid[:, cf] & tr.valid[:, cf + FRAMES]
    return None if (logged & (v_now > MOVING_MPS)).any() else "no_moving_vehicle"


def with_history(scene):
    """``scene`` with frame :data:`HISTORY_FRAMES` as its current frame where its own is earlier (frame 0 of a 20 s
    ScenarioNet scene), else itself."""
    if scene.current_frame >= HISTORY_FRAMES or scene.num_frames <= HISTORY_FRAMES:
        return scene
    return scene.window(0, scene.num_frames, current_frame=HISTORY_FRAMES)


def traffic_scenes(paths: list[str]) -> tuple[list, dict[str, int]]:
    """The scenes of files / folders / globs ``paths`` that are rolled out (:func:`scene_problem`), and how many were
    skipped per reason."""
    scenes, skipped = [], {}
    for path in [f for p in paths for f in (sorted(glob.glob(p)) or [p])]:
        try:
            found = [with_history(scene) for scene in read_scenarios(path)]
        except Exception as error:  # noqa: BLE001  (a file no reader reads: counted, and named on stderr)
            print(f"traffic_control: {path} skipped: {type(error).__name__}: {error}", file=sys.stderr)
            found, skipped["unreadable"] = [], skipped.get("unreadable", 0) + 1
        for scene in found:
            problem = scene_problem(scene)
            if problem:
                skipped[problem] = skipped.get(problem, 0) + 1
            else:
                scenes.append(scene)
    return scenes, skipped


def default_paths() -> list[str]:
    """The default set's files, folders and globs: every shared real scene (module docstring)."""
    return [str(drift.SHARED / p) for p in drift.REAL_91_FRAMES + LONGER_REAL]


# ------------------------------------------------------------------------------------------------ stop lines

class SceneLines(NamedTuple):
    """A scene's stop lines with a known lane direction, and their lights on every frame of its log."""

    xy: np.ndarray  # [L, 2] stop points (m)
    direction: np.ndarray  # [L, 2] unit lane directions
    sign: np.ndarray  # [L] bool: a stop sign's line (else a signal's)
    group: np.ndarray  # [L] the line each lane belongs to (stop_lines.line_groups)
    red: np.ndarray  # [T, L] bool: the whole line red on the frame (signals only)


def whole_line_red(lane_red: np.ndarray, sign: np.ndarray, group: np.ndarray) -> np.ndarray:
    """[T, L] lanes whose whole line is red: ``lane_red`` [T, L] and no signal lane of the same ``group`` not red."""
    same = group[:, None] == group[None, :]  # [L, L]
    not_red = ~sign[None] & ~lane_red  # [T, L]
    return lane_red & ~(not_red[:, None, :] & same[None]).any(-1)


def known_states(states: np.ndarray, present: np.ndarray) -> np.ndarray:
    """[T, L] light states with each lane's gaps (UNKNOWN or not reported) filled with its last known state; UNKNOWN
    before a lane's first known state (the log's dropouts of a frame or a second do not turn a red light green)."""
    known = present & (states != int(SignalState.UNKNOWN))
    frames = np.arange(len(states))[:, None]
    last = np.maximum.accumulate(np.where(known, frames, -1), axis=0)  # [T, L] last known frame, -1 before the first
    filled = np.take_along_axis(states, np.maximum(last, 0), axis=0)
    return np.where(last >= 0, filled, int(SignalState.UNKNOWN)).astype(states.dtype)


def scene_lines(scene) -> SceneLines:
    """The :class:`SceneLines` of a scene (lines whose lane direction is unknown are left out)."""
    xy, direction, light = scene_stop_lines(scene)
    keep = np.isfinite(direction).all(1)
    xy, direction, light = xy[keep].astype(np.float64), direction[keep].astype(np.float64), light[keep]
    tl, sign = scene.traffic_lights, light < 0
    lane_red = np.zeros((scene.num_frames, len(light)), bool)
    lane_red[:, ~sign] = np.isin(known_states(tl.states[:, light[~sign]], tl.present[:, light[~sign]]), RED)
    group = line_groups(xy, direction)
    return SceneLines(xy, direction, sign, group, whole_line_red(lane_red, sign, group))


def lane_coordinates(xy: np.ndarray, lines: SceneLines) -> tuple[np.ndarray, np.ndarray]:
    """(along [..., F, L], lateral [..., F, L]) of positions ``xy`` [..., F, 2] relative to each stop line: metres past
    the stop point along the lane direction (negative before it), and to its left."""
    d = xy[..., None, :] - lines.xy  # [..., F, L, 2]
    along = (d * lines.direction).sum(-1)
    lateral = lines.direction[:, 0] * d[..., 1] - lines.direction[:, 1] * d[..., 0]
    return along, lateral


def aligned(heading: np.ndarray, lines: SceneLines) -> np.ndarray:
    """[..., F, L] headings [..., F] within 45 degrees of each line's lane direction."""
    return np.cos(heading)[..., None] * lines.direction[:, 0] + np.sin(heading)[..., None] * lines.direction[:, 1] > ALIGNED_COS


def reaching(along: np.ndarray, lateral: np.ndarray, heading_aligned: np.ndarray, length_m: float) -> np.ndarray:
    """[..., F, L] the vehicle reaches the line (module docstring): centre before it, front within 8 m, 2 m laterally."""
    return (along < 0) & (-along - length_m / 2 <= REACH_FRONT_M) & (np.abs(lateral) <= LINE_SIDE_M) & heading_aligned


def line_ahead(along: np.ndarray, lateral: np.ndarray, heading_aligned: np.ndarray) -> np.ndarray:
    """[..., L] a line 0-40 m ahead of the centre along its lane, within 2 m laterally, the heading aligned."""
    return (along < 0) & (along >= -LINE_AHEAD_M) & (np.abs(lateral) <= LINE_SIDE_M) & heading_aligned


# ------------------------------------------------------------------------------------------------ causes

def signal_cause(reach: np.ndarray, along: np.ndarray, red: np.ndarray, valid: np.ndarray) -> str | None:
    """``red_now``, ``turns_red``, ``turns_green`` or None: the first (that order) that one of the signal lines a path
    reaches gives. ``reach``, ``along``, ``red`` [F, L] from frame ``cf`` on (signal lines only), ``valid`` [F]."""
    found = set()
    frames = np.arange(len(valid))
    for line in np.flatnonzero((reach & valid[:, None]).any(0)):
        first = int(np.argmax(reach[:, line] & valid))
        passed = np.flatnonzero(valid & (along[:, line] >= 0) & (frames > first))
        end = int(passed[0]) if len(passed) else int(np.flatnonzero(valid)[-1])
        window = red[: end + 1, line]
        if window[0]:
            found.add("red_now" if window.all() else "turns_green")
        elif window.any():
            found.add("turns_red")
    return next((c for c in CAUSES[:3] if c in found), None)


def first_cause(signal: str | None, stop_sign: bool, departure: bool, queue: bool) -> str:
    """The one cause of a vehicle (:data:`CAUSES` order): its signal cause (:func:`signal_cause`), else the first of
    a stop sign reached, a departure, a queue that holds, else ``none``."""
    if signal is not None:
        return signal
    return next((name for name, met in (("stop_sign", stop_sign), ("departure", departure), ("queue", queue)) if met), "none")


class LogPath(NamedTuple):
    """A track's logged path from the current frame to 8 s (:data:`FRAMES` + 1 frames)."""

    xy: np.ndarray  # [F, 2] float64
    heading: np.ndarray  # [F]
    valid: np.ndarray  # [F] bool
    length_m: float


def log_path(scene, i: int) -> LogPath:
    """Track ``i``'s :class:`LogPath` (its length: the median over its logged frames)."""
    tr, cf = scene.tracks, scene.current_frame
    f = slice(cf, cf + FRAMES + 1)
    return LogPath(tr.position[i, f, :2].astype(np.float64), tr.heading[i, f].astype(np.float64), tr.valid[i, f].copy(),
                   float(tr.box_size()[i, 0]))


def vehicle_cause(scene, lines: SceneLines, i: int, departs: bool) -> str:
    """Track ``i``'s cause from its log (:func:`first_cause`); ``departs``: it stands at cf and its log drives off."""
    path = log_path(scene, i)
    along, lateral = lane_coordinates(path.xy, lines)
    reach = reaching(along, lateral, aligned(path.heading, lines), path.length_m) & path.valid[:, None]
    sig = ~lines.sign
    cf = scene.current_frame
    signal = signal_cause(reach[:, sig], along[:, sig], lines.red[cf: cf + FRAMES + 1][:, sig], path.valid)
    at_sign = bool(reach[:, lines.sign].any())
    queue = False if (signal or at_sign or departs) else "queue" in slowing.what_it_meets(scene, i)[0]
    return first_cause(signal, at_sign, departs, queue)


# ------------------------------------------------------------------------------------------------ red crossings

def red_crossing(xy: np.ndarray, valid: np.ndarray, lines: SceneLines, red_after: np.ndarray) -> np.ndarray:
    """[...] whether paths ``xy`` [..., F, 2] (``valid`` [..., F]) cross a red signal line (module docstring);
    ``red_after`` [F - 1, L]: the line red on the frame after each step."""
    sig = ~lines.sign
    if not sig.any():
        return np.zeros(xy.shape[:-2], bool)
    along, lateral = lane_coordinates(xy, lines)
    along, lateral, red_after = along[..., sig], lateral[..., sig], red_after[:, sig]
    a, b = along[..., :-1, :], along[..., 1:, :]  # [..., F - 1, L]
    crosses = (a < 0) & (b >= 0)
    frac = np.where(crosses, -a / np.where(crosses, b - a, 1.0), 0.0)
    across = lateral[..., :-1, :] + frac * (lateral[..., 1:, :] - lateral[..., :-1, :])
    step = np.diff(xy, axis=-2)  # [..., F - 1, 2]
    forward = (step[..., None, :] * lines.direction[sig]).sum(-1) > ALIGNED_COS * np.linalg.norm(step, axis=-1)[..., None]
    both = (valid[..., :-1] & valid[..., 1:])[..., None]
    return (crosses & (np.abs(across) <= CROSS_HALF_M) & forward & red_after & both).any((-2, -1))


# ------------------------------------------------------------------------------------------------ stop signs

def half_second_speeds(xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """[..., F] speed over the last 0.5 s at each frame of paths ``xy`` [..., F, 2]; NaN on the first 5 frames and
    where either end is not logged."""
    k = HALF_SECOND_FRAMES
    out = np.full(xy.shape[:-1], np.nan)
    out[..., k:] = np.where(valid[..., k:] & valid[..., :-k], np.linalg.norm(xy[..., k:, :] - xy[..., :-k, :], axis=-1) / (k * DT_S), np.nan)
    return out


class SignStop(NamedTuple):
    """A path's first stop at a stop sign's line: the line (group, -1: none), the frame index, whether it moves on."""

    group: int
    frame: int
    moves_on: bool


def sign_stop(xy: np.ndarray, heading: np.ndarray, valid: np.ndarray, length_m: float, lines: SceneLines,
              group: int | None = None) -> SignStop:
    """The first stop of one path (``xy`` [F, 2], ``heading`` [F], ``valid`` [F]) at a stop sign's line (of line
    ``group`` alone if given), and whether it moves on after it (module docstring)."""
    on = lines.sign if group is None else lines.sign & (lines.group == group)
    if not on.any():
        return SignStop(-1, -1, False)
    along, lateral = lane_coordinates(xy, lines)
    along, lateral = along[:, on], lateral[:, on]
    speed = half_second_speeds(xy, valid)
    at = reaching(along, lateral, aligned(heading, lines)[:, on], length_m) & valid[:, None]
    stopped = at & (speed < STOPPED_MPS)[:, None]  # NaN speeds compare False
    if not stopped.any():
        return SignStop(-1, -1, False)
    frame = int(np.flatnonzero(stopped.any(1))[0])
    line = int(np.flatnonzero(stopped[frame])[0])
    later = np.arange(len(valid)) > frame
    same = lines.group[on] == lines.group[on][line]
    past = ((along[:, same] >= 0) & (np.abs(lateral[:, same]) <= LINE_SIDE_M)).any(1)
    moves = later & valid & ((speed > MOVE_ON_MPS) | past)
    return SignStop(int(lines.group[on][line]), frame, bool(moves.any()))


def reaches_a_sign(path: LogPath, lines: SceneLines) -> bool:
    """Whether a logged path reaches a stop sign's line (:func:`reaching`)."""
    along, lateral = lane_coordinates(path.xy, lines)
    reach = reaching(along, lateral, aligned(path.heading, lines), path.length_m) & path.valid[:, None]
    return bool(reach[:, lines.sign].any())


# ------------------------------------------------------------------------------------------------ per scene

def window_speed(log_speed: np.ndarray, ok: np.ndarray, sim_speed: np.ndarray, frames: np.ndarray) -> tuple[float, float] | None:
    """(log, rollout) mean speed of one vehicle over the frame indices ``frames`` it is logged on (``ok`` [T]), the
    rollouts' [R, T] averaged over rollouts; None where it is logged on fewer than half of them."""
    on = frames[ok[frames]]
    if len(on) * 2 < len(frames):
        return None
    return float(log_speed[on].mean()), float(sim_speed[:, on].mean())


MID_INDICES = np.arange(int(round(MID_S[0] * 10)) - 1, int(round(MID_S[1] * 10)))  # index k: frame cf + k + 1
LATE_INDICES = np.arange(FRAMES - LATE, FRAMES)


def scene_records(res, scene) -> dict[str, list]:
    """Per-vehicle records of one scene and its rollouts ``res`` (a one-scene RolloutResult of 8 s): ``vehicles``
    (cause and window speeds), ``crossings``, ``signs``, ``departures`` (``departures.scene_records``), and the
    scene's ``speed`` (``prior_speed_drift.speed_sums`` of its vehicles, or None)."""
    tr, cf = scene.tracks, scene.current_frame
    lines = scene_lines(scene)
    frames = np.arange(cf + 1, cf + 1 + FRAMES)
    simulated = res.simulated[0][: tr.num_tracks]
    vehicles = np.flatnonzero(simulated & (tr.types[: len(simulated)] == int(AgentType.VEHICLE)))
    standing, standing_late = departures.standing_vehicles(scene, simulated)
    departs = set(standing[standing_late > departures.DRIVES_OFF_MPS].tolist())
    num_rollouts = res.trajectory.shape[0]
    sim_xy = drift.rollout_xy(res, scene, vehicles)  # [R, V, T, 2]
    sim_heading = wrap_angle(res.trajectory[:, vehicles][..., 3] - scene.frame.heading)  # [R, V, T]
    red_after = lines.red[cf + 1: cf + 1 + FRAMES]
    out = {"vehicles": [], "crossings": [], "signs": []}
    for v, i in enumerate(vehicles):
        path = log_path(scene, i)
        roll_xy = np.concatenate([np.broadcast_to(path.xy[0], (num_rollouts, 1, 2)), sim_xy[:, v]], 1)  # [R, F, 2]
        roll_heading = np.concatenate([np.full((num_rollouts, 1), path.heading[0]), sim_heading[:, v]], 1)
        roll_valid = np.ones(roll_xy.shape[:2], bool)
        # cause and speeds
        ok = tr.valid[i, frames] & tr.valid[i, frames - 1]
        log_speed = drift._speeds_from_positions(tr.position[i, frames, :2], tr.position[i, cf, :2])
        sim_speed = drift._speeds_from_positions(sim_xy[:, v], np.broadcast_to(tr.position[i, cf, :2], (num_rollouts, 2)))
        out["vehicles"].append({"cause": vehicle_cause(scene, lines, i, i in departs),
                                "mid": window_speed(log_speed, ok, sim_speed, MID_INDICES),
                                "late": window_speed(log_speed, ok, sim_speed, LATE_INDICES)})
        # red crossings
        along, lateral = lane_coordinates(path.xy[0], lines)
        ahead = line_ahead(along, lateral, aligned(path.heading[:1], lines)[0])
        out["crossings"].append({"signal_ahead": bool(ahead[~lines.sign].any()),
                                 "log": bool(red_crossing(path.xy, path.valid, lines, red_after)),
                                 "rollouts": red_crossing(roll_xy, roll_valid, lines, red_after)})
        # stop signs
        logged = sign_stop(path.xy, path.heading, path.valid, path.length_m, lines)
        if logged.group >= 0:
            stops = [sign_stop(x, h, ok_r, path.length_m, lines, logged.group) for x, h, ok_r in zip(roll_xy, roll_heading, roll_valid)]
            out["signs"].append({"log_stops": True, "log_moves_on": logged.moves_on, "stop": [s.group >= 0 for s in stops],
                                 "moves_on": [s.moves_on for s in stops]})
        elif reaches_a_sign(path, lines):
            stops = [sign_stop(x, h, ok_r, path.length_m, lines) for x, h, ok_r in zip(roll_xy, roll_heading, roll_valid)]
            out["signs"].append({"log_stops": False, "stop": [s.group >= 0 for s in stops]})
    out["departures"] = departures.scene_records(res, scene)
    out["speed"] = drift.speed_sums(res, scene).get(AgentType.VEHICLE)
    return out


# ------------------------------------------------------------------------------------------------ rows

def _ratio(sim: float, log: float) -> float:
    return round(sim / max(log, 1e-9), 3)


def cause_rows(vehicles: list[dict]) -> list[dict]:
    """``kind: "cause"`` rows of the vehicle records (:func:`scene_records`), one per cause with vehicles."""
    rows = []
    for cause in CAUSES:
        recs = [r for r in vehicles if r["cause"] == cause]
        if not recs:
            continue
        row = {"kind": "cause", "cause": cause, "vehicles": len(recs)}
        for key, name in (("mid", "4s"), ("late", "7_8s")):
            pairs = np.array([r[key] for r in recs if r[key] is not None]).reshape(-1, 2)
            row[f"vehicles_{name}"] = len(pairs)
            if len(pairs):
                log, sim = pairs.sum(0)
                row.update({f"log_mps_{name}": round(log / len(pairs), 3), f"rollout_mps_{name}": round(sim / len(pairs), 3),
                            f"ratio_{name}": _ratio(sim, log)})
        rows.append(row)
    return rows


def speed_row(sums) -> dict:
    """``kind: "speed"`` of the summed vehicle :class:`prior_speed_drift.SpeedSums` (None: no moving vehicle)."""
    row = {"kind": "speed", "vehicles": int(sums.agents) if sums is not None else 0}
    if sums is None:
        return row
    for t_s in (4.0, 8.0):
        k = int(round(t_s * 10)) - 1
        row.update({f"log_mps_{t_s:g}s": round(sums.log[k] / max(sums.count[k], 1), 3),
                    f"rollout_mps_{t_s:g}s": round(sums.sim[k] / max(sums.count[k], 1), 3),
                    f"ratio_{t_s:g}s": _ratio(sums.sim[k], sums.log[k]), f"logged_at_{t_s:g}s": int(sums.count[k])})
    _, log, sim, n = sums.by_trend.sum(0)
    row.update(vehicles_7_8s=int(n), ratio_7_8s=_ratio(sim, log))
    for name, (_, log, sim, n) in zip(SPEED_ROW_TRENDS, sums.by_trend):
        row.update({f"{name}_vehicles": int(n), f"{name}_log_mps": round(log / n, 3) if n else None,
                    f"{name}_rollout_mps": round(sim / n, 3) if n else None, f"{name}_ratio": _ratio(sim, log) if n else None})
    return row


def crossing_row(crossings: list[dict]) -> dict:
    """``kind: "red_crossings"`` of the crossing records."""
    row = {"kind": "red_crossings", "vehicles": len(crossings), "vehicles_with_signal_ahead": sum(r["signal_ahead"] for r in crossings)}
    for suffix, recs in (("", crossings), ("_with_signal_ahead", [r for r in crossings if r["signal_ahead"]])):
        if recs:
            row.update({f"log_crossings{suffix}": int(sum(r["log"] for r in recs)),
                        f"rollout_crossings{suffix}": int(sum(r["rollouts"].sum() for r in recs)),
                        f"log_rate{suffix}": round(float(np.mean([r["log"] for r in recs])), 4),
                        f"rollout_rate{suffix}": round(float(np.mean([r["rollouts"].mean() for r in recs])), 4)})
    return row


def sign_row(signs: list[dict]) -> dict:
    """``kind: "stop_signs"`` of the stop-sign records."""
    stop = [r for r in signs if r["log_stops"]]
    rolling = [r for r in signs if not r["log_stops"]]
    row = {"kind": "stop_signs", "vehicles": len(stop), "rolling_vehicles": len(rolling)}
    if stop:
        stops, moves = np.array([r["stop"] for r in stop], bool), np.array([r["moves_on"] for r in stop], bool)  # [V, R]
        row.update(log_moves_on=round(float(np.mean([r["log_moves_on"] for r in stop])), 3),
                   rollouts_stop=round(float(stops.mean()), 3), rollouts_stop_then_move_on=round(float((stops & moves).mean()), 3),
                   move_on_after_stop=round(float((stops & moves).sum() / stops.sum()), 3) if stops.any() else None)
    if rolling:
        row["rolling_rollouts_stop"] = round(float(np.mean([r["stop"] for r in rolling])), 3)
    return row


def departure_row(records: list[dict], common: dict) -> dict:
    """``departures.summarise``'s row with the vehicles that keep standing in the log and their false departures."""
    row = departures.summarise(records, common)
    stay = [r for r in records if not r["drives_off"]]
    row["keep_standing"] = len(stay)
    if stay:  # the log's own share moving at 7-8 s (above 1 m/s, not driving off above 3 m/s) is the baseline
        row["false_departures"] = round(float(np.mean([r["moving"] for r in stay])), 3)
        row["keep_standing_log_moving"] = round(float(np.mean([r["log"] > departures.MOVING_MPS for r in stay])), 3)
    return row


def summarise(records: dict[str, list], common: dict) -> list[dict]:
    """Every row of a set from its scenes' records merged (lists added, speed sums summed)."""
    speeds = [s for s in records["speed"] if s is not None]
    sums = None
    for s in speeds:
        sums = s if sums is None else sums.plus(s)
    rows = cause_rows(records["vehicles"]) + [speed_row(sums), crossing_row(records["crossings"]), sign_row(records["signs"])]
    return [{**row, **common} for row in rows] + [departure_row(records["departures"], common)]


# ------------------------------------------------------------------------------------------------ command line

def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    drift.vehicle_rollout_arguments(ap, rollouts=8)
    next(a for a in ap._actions if a.dest == "sets").help = ("a named set of scenes; repeatable (default: every shared real scene "
                                                             "that qualifies, module docstring)")
    args = ap.parse_args(argv)
    model, _, rollout_kwargs, fields = drift.vehicle_rollout_sets(args)  # its own sets (read again below) are not used
    specs = args.sets or [f"real={','.join(default_paths())}"]
    for spec in specs:
        name, _, paths = spec.partition("=")
        scenes, skipped = traffic_scenes(paths.split(","))
        if args.max_scenes:
            scenes = scenes[: args.max_scenes]
        records = {"vehicles": [], "crossings": [], "signs": [], "departures": [], "speed": []}
        for scene in scenes:
            for key, value in scene_records(drift.rollout_from_log(model, scene, **rollout_kwargs), scene).items():
                records[key] += value if isinstance(value, list) else [value]
        common = {"benchmark": "traffic_control", "set": name, "scenes": len(scenes), "scenes_skipped": skipped, **fields}
        for row in summarise(records, common):
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
