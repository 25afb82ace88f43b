"""benchmarks/traffic_control.py: which cause a vehicle's log gives it, when a path runs a red line, when it stops at
a stop sign and moves on, which scenes it rolls out, and that rollouts replaying the log score as the log."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
from types import SimpleNamespace

import numpy as np
import pytest

from smart_marl.rollout import RolloutState
from smart_marl.rollout.stop_lines import line_groups
from smart_marl.scenario import SignalState

from helpers import load_benchmark

F = 81  # frames cf .. cf + 80
STOP, GO, UNKNOWN = int(SignalState.STOP), int(SignalState.GO), int(SignalState.UNKNOWN)


@pytest.fixture(scope="module")
def tc():
    return load_benchmark("traffic_control")


def _lines(tc, xy, direction, sign, red):
    """SceneLines of hand-placed lines; ``red`` [T, L]: each lane's own light red."""
    xy, d = np.asarray(xy, float), np.asarray(direction, float)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    sign = np.asarray(sign, bool)
    group = line_groups(xy, d)
    return tc.SceneLines(xy, d, sign, group, tc.whole_line_red(np.asarray(red, bool), sign, group))


def _straight(x: np.ndarray, y: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A path along +x (positions [F, 2], headings [F] of its direction of travel)."""
    return np.stack([x, np.full_like(x, y)], -1), np.zeros(len(x))


def _signal_cause(tc, x: np.ndarray, red: np.ndarray, lines_x=(30.0,)):
    """signal_cause of a 4.6 m vehicle along +x through lines at ``lines_x`` (lane +x), lights ``red`` [F, L]."""
    lines = _lines(tc, [[lx, 0.0] for lx in lines_x], [[1.0, 0.0]] * len(lines_x), [False] * len(lines_x), red)
    xy, heading = _straight(x)
    along, lateral = tc.lane_coordinates(xy, lines)
    reach = tc.reaching(along, lateral, tc.aligned(heading, lines), 4.6)
    return tc.signal_cause(reach, along, lines.red, np.ones(len(x), bool))


def _red(first_red: int | None = None, until: int | None = None) -> np.ndarray:
    """[F, 1] red from frame ``first_red`` (None: never) up to (not including) frame ``until`` (None: the end)."""
    red = np.zeros((F, 1), bool)
    if first_red is not None:
        red[first_red: until, 0] = True
    return red


# ------------------------------------------------------------------------------------------------ causes

def test_one_cause_per_vehicle_signals_first_then_sign_departure_queue(tc):
    assert tc.first_cause("turns_green", True, True, True) == "turns_green"
    assert tc.first_cause(None, True, True, True) == "stop_sign"
    assert tc.first_cause(None, False, True, True) == "departure"
    assert tc.first_cause(None, False, False, True) == "queue"
    assert tc.first_cause(None, False, False, False) == "none"
    assert tc.CAUSES == ("red_now", "turns_red", "turns_green", "stop_sign", "departure", "queue", "none")


def test_signal_cause_follows_the_line_light_until_the_vehicle_passes(tc):
    """A vehicle at 7.5 m/s from x = 0 passes the line at x = 30 on frame 40; one that stops 2 m before it stays."""
    passing = 0.75 * np.arange(F)
    waiting = np.minimum(0.75 * np.arange(F), 25.4)  # front (centre + 2.3 m) 2.3 m before the line, never past it
    assert _signal_cause(tc, passing, _red(0)) == "red_now"  # it runs it
    assert _signal_cause(tc, waiting, _red(0)) == "red_now"
    assert _signal_cause(tc, passing, _red(0, until=30)) == "turns_green"
    assert _signal_cause(tc, waiting, _red(0, until=70)) == "turns_green"
    assert _signal_cause(tc, passing, _red(20)) == "turns_red"
    assert _signal_cause(tc, passing, _red(50)) is None  # red only after it passed
    assert _signal_cause(tc, passing, _red(None)) is None
    assert _signal_cause(tc, 0.1 * np.arange(F), _red(0)) is None  # 8 s at 1 m/s: never within 8 m of it
    two = np.concatenate([_red(0, until=30), _red(0)], 1)  # a line that turns green at 30 m, one red all along at 55 m
    assert _signal_cause(tc, passing, two, lines_x=(30.0, 55.0)) == "red_now"


def test_a_line_is_red_only_while_every_lane_of_it_is_and_unknown_frames_keep_the_last_state(tc):
    lane_red = np.array([[True, False, True], [True, True, True]])  # lanes 0, 1 leave one line; lane 2 another
    group = np.array([0, 0, 2])
    out = tc.whole_line_red(lane_red, np.zeros(3, bool), group)
    assert out.tolist() == [[False, False, True], [True, True, True]]  # a green through lane beside a red arrow
    assert tc.whole_line_red(lane_red, np.array([False, True, False]), group)[0].tolist() == [True, False, True]
    states = np.array([[UNKNOWN, STOP, UNKNOWN], [STOP, UNKNOWN, UNKNOWN], [UNKNOWN, GO, UNKNOWN], [GO, UNKNOWN, UNKNOWN]], np.int8)
    present = np.ones_like(states, bool)
    present[1, 1] = False
    assert tc.known_states(states, present).T.tolist() == [[UNKNOWN, STOP, STOP, GO], [STOP, STOP, GO, GO], [UNKNOWN] * 4]


def test_causes_on_a_real_intersection_with_edited_lights(tc, womd_scenes):
    """637f20cafde22ff8 with every light red on every frame: each vehicle whose log reaches a signal's line is
    ``red_now``; green on every frame: none is a signal cause; red for 3 s, then green: each of those is ``red_now``
    (it ran the red) or ``turns_green``; green for 3 s, then red: ``turns_red`` or no signal cause (passed before)."""
    scene = womd_scenes[0]
    tl, cf = scene.traffic_lights, scene.current_frame

    def causes(states: np.ndarray) -> dict[int, str]:
        edited = dataclasses.replace(scene, traffic_lights=dataclasses.replace(tl, states=states.astype(np.int8),
                                                                                present=np.ones_like(tl.present)))
        lines = tc.scene_lines(edited)
        vehicles = np.flatnonzero(scene.tracks.valid[:, cf] & (scene.tracks.types == 0))
        return {int(i): tc.vehicle_cause(edited, lines, i, False) for i in vehicles}

    red, green = np.full(tl.states.shape, STOP), np.full(tl.states.shape, GO)
    switch = cf + 30
    to_green, to_red = np.concatenate([red[:switch], green[switch:]]), np.concatenate([green[:switch], red[switch:]])
    all_red, all_green, later_green, later_red = causes(red), causes(green), causes(to_green), causes(to_red)
    signalled = {i for i, c in all_red.items() if c == "red_now"}
    assert len(signalled) >= 5
    assert not {c for c in all_red.values()} & {"turns_red", "turns_green"}
    assert not {c for c in all_green.values()} & {"red_now", "turns_red", "turns_green"}
    assert {i for i, c in later_green.items() if c in ("red_now", "turns_green")} == signalled
    assert sum(c == "turns_green" for c in later_green.values()) >= 3  # the ones waiting at the line
    assert {i for i, c in later_red.items() if c == "turns_red"} <= signalled
    assert {c for c in later_red.values()} & {"red_now", "turns_green"} == set()
    assert all(all_green[i] == later_red[i] for i in all_green if later_red[i] != "turns_red")


# ------------------------------------------------------------------------------------------------ red crossings

def test_red_crossing_counts_a_path_across_a_red_line_in_its_lane_direction(tc):
    lines = _lines(tc, [[20.0, 0.0]], [[1.0, 0.0]], [False], np.ones((F, 1), bool))
    x = np.arange(F, dtype=float) * 0.5  # 5 m/s: across x = 20 on the step to frame 40
    valid = np.ones(F, bool)

    def crosses(xy, red=None, ok=valid):
        red_after = (lines.red if red is None else red)[1:]
        return bool(tc.red_crossing(xy, ok, lines, red_after))

    assert crosses(_straight(x)[0])
    assert not crosses(_straight(np.minimum(x, 18.0))[0])  # stops before it
    assert not crosses(_straight(x)[0], red=np.zeros((F, 1), bool))  # green
    assert not crosses(_straight(x[::-1])[0])  # against the lane's direction
    assert not crosses(_straight(x, y=2.5)[0]) and crosses(_straight(x, y=1.5)[0])  # beside the stop point / within 2 m
    assert not crosses(_straight(x)[0], red=_red(41)) and crosses(_straight(x)[0], red=_red(40))  # red on the frame after the step
    gap = valid.copy()
    gap[40] = False
    assert not crosses(_straight(x)[0], ok=gap)  # the crossing step not logged
    sign = _lines(tc, [[20.0, 0.0]], [[1.0, 0.0]], [True], np.ones((F, 1), bool))
    assert not tc.red_crossing(_straight(x)[0], valid, sign, sign.red[1:])  # a stop sign's line is no red light
    batch = np.stack([_straight(x)[0], _straight(np.minimum(x, 18.0))[0]])
    assert tc.red_crossing(batch, np.ones((2, F), bool), lines, lines.red[1:]).tolist() == [True, False]


# ------------------------------------------------------------------------------------------------ stop signs

def _sign_path(stand_m: float, stand_frames: int, leave_mps: float) -> tuple[np.ndarray, np.ndarray]:
    """Half a second at 8 m/s, then braking at 4 m/s2 (8.4 m) to stand at ``stand_m`` for ``stand_frames`` frames,
    then on at ``leave_mps``."""
    brake = 8.0 - 0.4 * np.arange(20)
    profile = np.concatenate([np.full(5, 8.0), brake, np.zeros(stand_frames), np.full(F, leave_mps)])[: F - 1]
    x = stand_m - 0.1 * (np.full(5, 8.0).sum() + brake.sum()) + np.concatenate([[0.0], np.cumsum(profile * 0.1)])
    return _straight(x)


def test_a_stop_at_a_sign_and_moving_on_after_it(tc):
    lines = _lines(tc, [[40.0, 0.0], [40.3, 0.2], [80.0, 0.0]], [[1.0, 0.0], [0.9, 0.4], [1.0, 0.0]], [True, True, True],
                   np.zeros((F, 3), bool))
    assert lines.group.tolist() == [0, 0, 2]
    valid = np.ones(F, bool)
    xy, heading = _sign_path(36.0, 20, 5.0)  # front 1.7 m before the line, stands 2 s, leaves at 5 m/s
    stop = tc.sign_stop(xy, heading, valid, 4.6, lines)
    assert stop.group == 0 and stop.moves_on and 20 <= stop.frame <= 30
    assert abs(xy[stop.frame, 0] - 36.0) < 1.0  # where it stands
    stays = tc.sign_stop(*_sign_path(36.0, F, 0.0), valid, 4.6, lines)
    assert stays.group == 0 and not stays.moves_on
    assert tc.sign_stop(*_straight(3.0 * 0.1 * np.arange(F) + 20.0), valid, 4.6, lines).group == -1  # rolls through at 3 m/s
    assert tc.sign_stop(*_sign_path(20.0, F, 0.0), valid, 4.6, lines).group == -1  # stands 17.7 m before it: not at it
    assert tc.sign_stop(xy, heading, valid, 4.6, lines, group=2).group == -1  # not the line asked about
    assert tc.sign_stop(xy, heading, valid, 4.6, lines, group=0).moves_on
    creep = tc.sign_stop(*_sign_path(36.0, 20, 1.5), valid, 4.6, lines)  # leaves at 1.5 m/s: moves on by passing the line
    assert creep.group == 0 and creep.moves_on
    signal = _lines(tc, [[40.0, 0.0]], [[1.0, 0.0]], [False], np.ones((F, 1), bool))
    assert tc.sign_stop(xy, heading, valid, 4.6, signal).group == -1  # a red light's line is no stop sign


# ------------------------------------------------------------------------------------------------ rows, scenes, flags

def test_departure_row_adds_false_departures_against_the_log(tc):
    records = [{"drives_off": True, "log": 6.0, "rollout": 3.0, "moving": 0.5, "log_start_s": 2.0, "rollout_start_s": 4.0},
               {"drives_off": False, "log": 0.0, "rollout": 0.5, "moving": 0.25, "log_start_s": 8.0, "rollout_start_s": 8.0},
               {"drives_off": False, "log": 2.0, "rollout": 0.1, "moving": 0.0, "log_start_s": 5.0, "rollout_start_s": 8.0}]
    row = tc.departure_row(records, {"set": "x"})
    assert row["standing"] == 3 and row["drive_off_in_log"] == 1 and row["rollouts_moving"] == 0.5 and row["ratio"] == 0.5
    assert row["keep_standing"] == 2 and row["false_departures"] == 0.125 and row["keep_standing_log_moving"] == 0.5
    assert row["set"] == "x"


def test_scenes_need_8_s_of_log_at_10_hz_and_a_moving_vehicle(tc, shared_data, tmp_path):
    """The AV2 scene (current frame 49 of 110) is too short; the 20 s ScenarioNet scene (current frame 0) gets frame 10
    as its current frame; the nuScenes scenes are in; the big WOMD record without a moving vehicle is out; a file no
    reader reads is counted."""
    garbage = tmp_path / "garbage.json"
    garbage.write_text("{not json")
    scenes, skipped = tc.traffic_scenes([str(shared_data / p) for p in ("av2", "scenarionet/waymo/sd_waymo*.pkl",
                                                                        "scenarionet/nuscenes/*.pkl", "womd_tfrecord/womd_scenario_input.tfrecord")]
                                        + [str(garbage)])
    assert skipped == {"short_log": 1, "no_moving_vehicle": 1, "unreadable": 1}
    assert sorted(sc.source for sc in scenes) == ["scenarionet/nuscenes"] * 3 + ["scenarionet/waymo"]
    twenty = next(sc for sc in scenes if sc.source == "scenarionet/waymo")
    assert twenty.current_frame == 10 and twenty.num_frames == 199
    assert all(tc.scene_problem(sc) is None for sc in scenes)


def test_stop_lines_default_is_the_engines_and_both_switches_work(tc):
    ap = argparse.ArgumentParser()
    tc.drift.vehicle_rollout_arguments(ap, rollouts=8)
    engine = inspect.signature(RolloutState.start).parameters["stop_lines"].default
    assert ap.parse_args([]).stop_lines is engine is True
    assert ap.parse_args(["--no-stop-lines"]).stop_lines is False
    assert ap.parse_args(["--stop-lines"]).stop_lines is True


def test_rollouts_that_replay_the_log_score_as_the_log(tc, shared_data):
    """The 20 s ScenarioNet scene (signals; a right turn on red at 3.4 m/s) and two GPUDrive scenes with stop signs,
    their fully logged agents "rolled out" twice as their log: every speed ratio is 1, the rollouts cross red lines
    exactly as often as the log, stop where it stops and move on as it does."""
    scenes, _ = tc.traffic_scenes([str(shared_data / "scenarionet/waymo/sd_waymo_v1.2_eb4b91b10ca94ff2.pkl"),
                                   str(shared_data / "gpudrive_json/tfrecord-00000-of-01000_4.json"),
                                   str(shared_data / "gpudrive_json/tfrecord-ab2a72c63f8fd589.json")])
    records = {"vehicles": [], "crossings": [], "signs": [], "departures": [], "speed": []}
    for scene in scenes:
        tr, cf = scene.tracks, scene.current_frame
        f = slice(cf + 1, cf + 1 + tc.FRAMES)
        traj = np.concatenate([scene.frame.to_source(tr.position[:, f].astype(np.float64)),
                               scene.frame.heading_to_source(tr.heading[:, f])[..., None]], -1)
        simulated = tr.valid[:, cf - 10: cf + 1 + tc.FRAMES].all(1) & (tr.types <= 2)
        res = SimpleNamespace(trajectory=np.stack([traj, traj]), simulated=np.stack([simulated, simulated]),
                              agent_types=np.stack([tr.types, tr.types]))
        for key, value in tc.scene_records(res, scene).items():
            records[key] += value if isinstance(value, list) else [value]
    rows = {(r["kind"], r.get("cause")): r for r in tc.summarise(records, {"set": "replay"})}
    causes = {c for kind, c in rows if kind == "cause"}
    assert {"red_now", "stop_sign", "queue", "none"} <= causes
    for (kind, _), r in rows.items():
        assert r["set"] == "replay"
        for key, value in r.items():
            if key.startswith("ratio") or key.endswith("_ratio"):
                assert value in (1.0, None), (kind, key, value)
    crossing = rows[("red_crossings", None)]
    assert crossing["log_crossings"] >= 1 and crossing["rollout_crossings"] == 2 * crossing["log_crossings"]
    assert crossing["rollout_rate"] == crossing["log_rate"] and crossing["vehicles_with_signal_ahead"] >= 1
    signs = rows[("stop_signs", None)]
    assert signs["vehicles"] == 4 and signs["rollouts_stop"] == 1.0 and signs["move_on_after_stop"] == signs["log_moves_on"] == 0.5
    assert signs.get("rolling_rollouts_stop", 0.0) == 0.0
    dep = rows[("departures", None)]
    assert dep["false_departures"] == dep["keep_standing_log_moving"]
    assert rows[("speed", None)]["vehicles"] == sum(s.agents for s in records["speed"] if s is not None) > 0
