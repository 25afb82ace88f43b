"""Traffic control (smart_marl.rollout.stop_lines): which line holds a vehicle, which tokens it may not draw, that
rollouts with the rule do not run the red lines that held them, stop signs served once per vehicle and approach, a
green, a served sign or a leader driving off releasing a standing vehicle, and that batching keeps the lines, the
served signs and each scene's light clock."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from smart_marl.embedded import sample_scenarios
from smart_marl.model.checkpoint import load_prior
from smart_marl.rollout import RolloutState
from smart_marl.rollout.refill import replace_scenes, split_state, stack_states
from smart_marl.rollout.stop_lines import (MIN_ADVANCE_M, SIGN_WAIT_STEPS, STOP_DECEL_MPS2, creeping, line_groups, nearest_line,
                                           released, right_turn_lanes, scene_stop_lines, served_after_step, stop_line_test)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def _lines_state(**extra) -> SimpleNamespace:
    """One scene, two vehicles at the origin heading +x, and six lines: a red one 20 m ahead, a green one 10 m ahead,
    a red one 5 m to the side, a red one behind, a red one whose lane runs the other way, a stop sign 12 m ahead."""
    xy = torch.tensor([[[20.0, 0.0], [10.0, 0.0], [6.0, 5.0], [-5.0, 0.0], [15.0, 0.0], [12.0, 0.5]]])
    direction = torch.tensor([[[1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [1.0, 0.0]]])
    state = SimpleNamespace(
        scene_of_group=torch.tensor([0]), pose=torch.zeros(1, 2, 3), previous_pose=torch.zeros(1, 2, 3),
        stop_xy=xy, stop_dir=direction, stop_valid=torch.ones(1, 6, dtype=torch.bool), stop_group=torch.arange(6)[None],
        stop_red=torch.tensor([[True, False, True, True, True, False]]), stop_go=torch.zeros(1, 6, dtype=torch.bool),
        stop_sign=torch.tensor([[False, False, False, False, False, True]]),
        stop_served=torch.tensor([[[False] * 6, [False] * 5 + [True]]]), stop_stood=torch.zeros(1, 2, dtype=torch.long),
        agent_type=torch.zeros(1, 2, dtype=torch.long),
        agent_shape=torch.tensor([[[4.0, 2.0, 1.5], [4.0, 2.0, 1.5]]]), simulated=torch.ones(1, 2, dtype=torch.bool), num_slots=2)
    for name, value in extra.items():
        setattr(state, name, value)
    if "stop_turn_red" not in extra:
        state.stop_turn_red = torch.zeros_like(state.stop_red)
    if "stop_moved" not in extra:  # every vehicle has moved since the log began (a queue that closed up)
        state.stop_moved = torch.ones_like(state.stop_stood, dtype=torch.bool)
    return state


def test_the_nearest_active_line_ahead_in_the_lane_holds_a_vehicle():
    state = _lines_state()
    dist, line = nearest_line(state, torch.tensor([0, 0]), torch.tensor([0, 1]))
    assert line.tolist() == [5, 0]  # the unserved stop sign, then (sign served) the red light; never green, side, behind, other way
    torch.testing.assert_close(dist, torch.tensor([12.0, 20.0]))
    state.stop_red[:] = False
    dist, line = nearest_line(state, torch.tensor([0]), torch.tensor([1]))
    assert line.tolist() == [-1] and torch.isinf(dist).all()


def test_a_red_arrow_beside_a_green_light_of_the_same_line_lets_a_vehicle_go():
    """Two lanes leave the line 20 m ahead (a through lane and a turn lane, starting at the same point): the vehicle is
    held only while both are red; the lanes of another stop line 3 m on, or running the other way, are another line."""
    xy = torch.tensor([[[20.0, 0.0], [20.3, 0.2], [23.0, 0.0], [20.0, 0.5]]])
    direction = torch.tensor([[[1.0, 0.0], [0.9, 0.44], [1.0, 0.0], [-1.0, 0.0]]])
    groups = line_groups(xy[0].double().numpy(), direction[0].double().numpy())
    assert groups.tolist() == [0, 0, 2, 3]
    assert line_groups(np.zeros((0, 2)), np.zeros((0, 2))).tolist() == []  # a scene without lines
    state = _lines_state(stop_xy=xy, stop_dir=direction, stop_group=torch.from_numpy(groups)[None],
                         stop_valid=torch.ones(1, 4, dtype=torch.bool), stop_sign=torch.zeros(1, 4, dtype=torch.bool),
                         stop_red=torch.tensor([[True, False, True, True]]), stop_served=torch.zeros(1, 2, 4, dtype=torch.bool))
    _, line = nearest_line(state, torch.tensor([0]), torch.tensor([0]))
    assert line.tolist() == [2]  # the through lane is green: the next line, 23 m on, holds it
    state.stop_red[0, 1] = True
    _, line = nearest_line(state, torch.tensor([0]), torch.tensor([0]))
    assert line.tolist() == [0]


def test_a_held_vehicle_may_draw_only_the_tokens_after_which_it_can_stop():
    # five tokens ending 0, 2, 5, 8 and 12 m ahead at 0, 4, 10, 16 and 24 m/s; the sign's line 12 m ahead (front 10 m)
    ends = (torch.tensor([[0.0, 2.0, 5.0, 8.0, 12.0]]), torch.tensor([[0.0, 4.0, 10.0, 16.0, 24.0]]))
    state = _lines_state(stop_token_ends=ends, vocab_sizes=torch.tensor([5]))
    state.previous_pose[0, 0, 0] = -2.0  # slot 0 drives at 4 m/s, held by the sign 12 m ahead
    test = stop_line_test(state, torch.tensor([0]))
    # needs 0, 16 / 16 = 1.0, 100 / 10 = 10, 256 / 4 = 64 m/s2 and an overrun of 2 m
    assert test(torch.tensor([0]), torch.arange(5)[None]).tolist() == [[False, False, True, True, True]]
    state.previous_pose[0, 0, 0] = 0.0  # standing 10 m before the line (more than CREEP_FRONT_M): it pulls up
    test = stop_line_test(state, torch.tensor([0]))
    assert test(torch.tensor([0]), torch.arange(5)[None]).tolist() == [[True, False, True, True, True]]
    state.pose[0, 0, 0] = state.previous_pose[0, 0, 0] = 7.5  # standing 2.5 m before it: it waits there
    test = stop_line_test(state, torch.tensor([0]))
    assert test(torch.tensor([0]), torch.arange(5)[None]).tolist() == [[False, True, True, True, True]]
    state.pose[0, 0, 0] = state.previous_pose[0, 0, 0] = 0.0
    assert STOP_DECEL_MPS2 == 3.0
    state.stop_red[:] = False
    state.stop_served[..., 5] = True
    state.pose[0, :, 0] = torch.tensor([0.0, 30.0])  # slot 0 stands, slot 1 has driven 30 m
    state.previous_pose[0, :, 0] = torch.tensor([float("nan"), 20.0])  # and slot 0 was just placed: no motion to go on from
    assert stop_line_test(state, torch.tensor([0, 1])) is None  # nothing holds or releases either: the plain search


def test_a_vehicle_that_stood_at_a_stop_sign_has_served_it():
    state = _lines_state()
    state.pose = torch.tensor([[[7.5, 0.0, 0.0], [9.0, 0.0, 0.0]]])
    state.previous_pose = torch.tensor([[[7.4, 0.0, 0.0], [4.0, 0.0, 0.0]]])  # slot 0 stands, slot 1 drives on
    assert served_after_step(state)[0, :, 5].tolist() == [True, True]
    state.stop_served = torch.zeros(1, 2, 6, dtype=torch.bool)
    assert served_after_step(state)[0, :, 5].tolist() == [True, False]  # the one that drove on has not


def test_a_stop_sign_is_served_once_per_vehicle_and_approach():
    """Two approaches of one all-way stop (two lanes leaving the line 12 m ahead, one line; another line 30 m on) and
    two vehicles: the first stands at the first line and has served both its lanes, and nothing else; it is then held
    by the next sign, and the second vehicle, behind it, is still held by the first."""
    xy = torch.tensor([[[12.0, 0.0], [12.2, 0.3], [30.0, 0.0]]])
    direction = torch.tensor([[[1.0, 0.0], [0.9, 0.44], [1.0, 0.0]]])
    state = _lines_state(stop_xy=xy, stop_dir=direction, stop_group=torch.from_numpy(line_groups(xy[0].double().numpy(),
                                                                                               direction[0].double().numpy()))[None],
                         stop_valid=torch.ones(1, 3, dtype=torch.bool), stop_sign=torch.ones(1, 3, dtype=torch.bool),
                         stop_red=torch.zeros(1, 3, dtype=torch.bool), stop_go=torch.zeros(1, 3, dtype=torch.bool),
                         stop_served=torch.zeros(1, 2, 3, dtype=torch.bool))
    state.pose = torch.tensor([[[5.0, 0.0, 0.0], [-5.0, 0.0, 0.0]]])  # front 3 m before the line; the second 10 m behind
    state.previous_pose = state.pose.clone()  # both stand
    state.stop_served = served_after_step(state)
    assert state.stop_served[0].tolist() == [[True, True, False], [False, False, False]]
    _, line = nearest_line(state, torch.tensor([0, 0]), torch.tensor([0, 1]))
    assert line.tolist() == [2, 0]  # the first: the next approach holds it; the second: this one still does
    state.stop_served = served_after_step(state)  # standing on does not serve the next line 25 m ahead
    assert state.stop_served[0].tolist() == [[True, True, False], [False, False, False]]


def _released(state, slots) -> list[bool]:
    g, s = torch.zeros(len(slots), dtype=torch.long), torch.tensor(slots)
    dist, _ = nearest_line(state, g, s)
    return released(state, g, s, torch.isfinite(dist)).tolist()


def test_a_green_light_releases_a_held_vehicle_and_a_red_one_does_not():
    """Slot 0 stands 6 m before a signal's line (the only line); slot 1 stands 20 m to the side, out of the way."""
    state = _lines_state(stop_xy=torch.tensor([[[8.0, 0.0]]]), stop_dir=torch.tensor([[[1.0, 0.0]]]),
                         stop_group=torch.zeros(1, 1, dtype=torch.long), stop_valid=torch.ones(1, 1, dtype=torch.bool),
                         stop_sign=torch.zeros(1, 1, dtype=torch.bool), stop_red=torch.ones(1, 1, dtype=torch.bool),
                         stop_go=torch.zeros(1, 1, dtype=torch.bool), stop_served=torch.zeros(1, 2, 1, dtype=torch.bool))
    state.pose[0, 1, 1] = 20.0
    state.previous_pose = state.pose.clone()
    assert _released(state, [0, 1]) == [False, False]  # red: held, not released
    state.stop_red[:], state.stop_go[:] = False, True
    assert _released(state, [0, 1]) == [True, False]  # green: the one at the line goes, the one far aside stays
    state.stop_go[:] = False
    assert _released(state, [0]) == [False]  # a light that is neither (unknown, caution) releases nobody
    state.stop_go[:] = True
    state.previous_pose[0, 0, 0] = -2.0  # moving at 4 m/s: not standing, the prior drives
    assert _released(state, [0]) == [False]
    state.previous_pose[0, 0, 0] = 0.0
    state.pose[0, 1] = torch.tensor([6.0, 0.5, 0.0])  # someone 2 m in front of its bumper: no room to go
    state.previous_pose[0, 1] = state.pose[0, 1]
    assert _released(state, [0]) == [False]
    ends = (torch.tensor([[0.0, 0.1, 0.3, 2.0]]), torch.tensor([[0.0, 0.2, 0.6, 4.0]]))
    state.pose[0, 1] = torch.tensor([0.0, 20.0, 0.0])
    state.previous_pose[0, 1] = state.pose[0, 1]
    state = _lines_state(**{**vars(state), "stop_token_ends": ends, "vocab_sizes": torch.tensor([4])})
    test = stop_line_test(state, torch.tensor([0, 1]))
    assert test(torch.tensor([0, 1]), torch.arange(4).expand(2, 4)).tolist() == [[True, True, False, False], [False] * 4]
    assert MIN_ADVANCE_M == 0.25


def test_a_leader_driving_off_releases_the_vehicle_behind_it():
    """A signal's line 25 m ahead whose light is unknown (it neither holds nor releases): slot 0 stands, slot 1 is 12 m
    ahead in its lane; a parked car (slot 2) stands beside the lane."""
    state = _lines_state(stop_xy=torch.tensor([[[25.0, 0.0]]]), stop_dir=torch.tensor([[[1.0, 0.0]]]),
                         stop_group=torch.zeros(1, 1, dtype=torch.long), stop_valid=torch.ones(1, 1, dtype=torch.bool),
                         stop_sign=torch.zeros(1, 1, dtype=torch.bool), stop_red=torch.zeros(1, 1, dtype=torch.bool),
                         stop_go=torch.zeros(1, 1, dtype=torch.bool), stop_served=torch.zeros(1, 3, 1, dtype=torch.bool),
                         agent_type=torch.zeros(1, 3, dtype=torch.long), agent_shape=torch.tensor([[[4.0, 2.0, 1.5]] * 3]),
                         simulated=torch.ones(1, 3, dtype=torch.bool), num_slots=3, stop_stood=torch.zeros(1, 3, dtype=torch.long))
    state.pose = torch.tensor([[[0.0, 0.0, 0.0], [12.0, 0.2, 0.0], [5.0, -3.5, 0.0]]])
    state.previous_pose = state.pose.clone()
    assert _released(state, [0, 2]) == [False, False]  # the leader stands: so does the queue
    state.previous_pose[0, 1, 0] = 10.5  # the leader drives off at 3 m/s
    assert _released(state, [0, 2]) == [True, False]  # the follower goes, the parked car beside the lane stays
    state.pose[0, 1, 2] = 3.0  # ... one going the other way (turned around) releases nobody
    assert _released(state, [0]) == [False]
    state.pose[0, 1, 2] = 0.0
    state.stop_valid[:] = False  # away from any line (a parked row, a jam): the prior alone decides
    assert _released(state, [0]) == [False]


def _one_line_state(sign: bool, red: bool, **extra) -> SimpleNamespace:
    """One line 8 m ahead of slot 0 (standing at the origin, heading +x, front 6 m before it); slot 1 stands far aside."""
    state = _lines_state(stop_xy=torch.tensor([[[8.0, 0.0]]]), stop_dir=torch.tensor([[[1.0, 0.0]]]),
                         stop_group=torch.zeros(1, 1, dtype=torch.long), stop_valid=torch.ones(1, 1, dtype=torch.bool),
                         stop_sign=torch.tensor([[sign]]), stop_red=torch.tensor([[red]]),
                         stop_served=torch.zeros(1, 2, 1, dtype=torch.bool), **{"stop_go": torch.zeros(1, 1, dtype=torch.bool), **extra})
    state.pose[0, 1, 1] = 60.0
    state.previous_pose = state.pose.clone()
    return state


def test_a_served_stop_sign_releases_a_vehicle_only_when_the_crossing_is_clear():
    state = _one_line_state(sign=True, red=False)
    state.pose[0, 0, 0] = state.previous_pose[0, 0, 0] = 4.0  # front 2 m before the sign, standing
    state.stop_served = served_after_step(state)
    state.stop_stood[0, 0] = SIGN_WAIT_STEPS
    assert _released(state, [0]) == [True]
    state.stop_stood[0, 0] = SIGN_WAIT_STEPS - 1
    assert _released(state, [0]) == [False]  # not stood long enough yet
    state.stop_stood[0, 0] = SIGN_WAIT_STEPS
    state.pose[0, 1] = torch.tensor([8.0, 15.0, -np.pi / 2])  # a car 15 m up the crossing road, coming at 6 m/s
    state.previous_pose[0, 1] = torch.tensor([8.0, 18.0, -np.pi / 2])
    assert _released(state, [0]) == [False]
    state.pose[0, 1, :2] = state.previous_pose[0, 1, :2] = torch.tensor([8.0, 15.0])  # it stands (waits for us)
    assert _released(state, [0]) == [True]
    state.pose[0, 1] = torch.tensor([8.0, -15.0, -np.pi / 2])  # it has crossed and drives away
    state.previous_pose[0, 1] = torch.tensor([8.0, -12.0, -np.pi / 2])
    assert _released(state, [0]) == [True]
    state.pose[0, 1] = torch.tensor([20.0, 0.2, 0.0])  # a car ahead going our way, 12 m past the line: not a crossing
    state.previous_pose[0, 1] = torch.tensor([17.0, 0.2, 0.0])
    assert _released(state, [0]) == [True]
    state.pose[0, 1] = torch.tensor([20.0, 3.5, np.pi])  # an oncoming car: at a stop sign it came first, it goes first
    state.previous_pose[0, 1] = torch.tensor([23.0, 3.5, np.pi])
    assert _released(state, [0]) == [False]
    state.stop_sign[:], state.stop_go[:] = False, True  # a green is not a stop sign: it lets the vehicle go all the same
    assert _released(state, [0]) == [True]


def test_a_dedicated_right_turn_lane_at_a_plain_red_is_served_like_a_stop_sign():
    """A right-turn lane's red (STOP) holds a vehicle until it has stood at the line, then lets it turn as a served
    stop sign does; a red arrow, or a line whose lanes do not all turn right, holds it as any red."""
    state = _one_line_state(sign=False, red=True, stop_turn_red=torch.tensor([[True]]))
    _, line = nearest_line(state, torch.tensor([0]), torch.tensor([0]))
    assert line.tolist() == [0]  # held: it has not stopped at the line yet
    state.pose[0, 0, 0] = state.previous_pose[0, 0, 0] = 4.0  # it stands with its front 2 m before the line
    state.stop_served = served_after_step(state)
    assert state.stop_served[0, :, 0].tolist() == [True, False]
    _, line = nearest_line(state, torch.tensor([0]), torch.tensor([0]))
    assert line.tolist() == [-1]  # served: the line holds it no more
    state.stop_stood[0, 0] = SIGN_WAIT_STEPS
    assert _released(state, [0]) == [True]
    state.stop_turn_red[:] = False  # a red arrow (ARROW_STOP), or a through lane beside the turn: a red like any other
    assert _released(state, [0]) == [False]
    _, line = nearest_line(state, torch.tensor([0]), torch.tensor([0]))
    assert line.tolist() == [0]


def test_right_turn_lanes_are_the_signal_lanes_whose_direction_turns_clockwise():
    scenes = sample_scenarios()
    found = 0
    for sc in scenes:
        xy, direction, light = scene_stop_lines(sc)
        right = right_turn_lanes(sc, light)
        assert not right[light < 0].any()  # a stop sign's lane is never one
        for k in np.flatnonzero(right):
            p = sc.road_map.feature_points(int(np.flatnonzero(sc.road_map.ids == sc.traffic_lights.lane_ids[light[k]])[0]))[:, :2]
            a, b = np.arctan2(*(p[1] - p[0])[::-1]), np.arctan2(*(p[-1] - p[-2])[::-1])
            assert np.angle(np.exp(1j * (b - a))) < -np.pi / 4
            found += 1
    assert found > 0


def test_a_vehicle_that_has_stood_all_along_is_not_pulled_up_to_its_red_line():
    """A car standing 20 m before a red line since its log began (parked in the lane) stays; one that stopped there
    after driving pulls up."""
    state = _one_line_state(sign=False, red=True)
    state.stop_xy[0, 0, 0] = 25.0
    g, s = torch.zeros(1, dtype=torch.long), torch.zeros(1, dtype=torch.long)
    assert creeping(state, g, s, torch.tensor([23.0])).tolist() == [True]
    state.stop_moved[0, 0] = False
    assert creeping(state, g, s, torch.tensor([23.0])).tolist() == [False]


def _red_crossings(state: RolloutState, steps: int = 16) -> int:
    """Vehicle-steps whose front went more than half a metre past the red line that held them when the step began."""
    count = 0
    for _ in range(steps):
        g, s = (state.simulated & (state.agent_type == 0)).nonzero(as_tuple=True)
        _, line = nearest_line(state, g, s)
        b = state.scene_of_group[g]
        red = (line >= 0) & state.stop_red[b, line.clamp(min=0)]
        state.step()
        pose = state.pose[g, s]
        rel = state.stop_xy[b, line.clamp(min=0)] - pose[:, :2]
        front = rel[:, 0] * pose[:, 2].cos() + rel[:, 1] * pose[:, 2].sin() - state.agent_shape[g, s, 0] / 2
        count += int((red & (front < -0.5)).sum())
    return count


def test_rollouts_with_the_rule_do_not_run_the_red_lines_that_held_them():
    scene = sample_scenarios()[0]  # 15 of its vehicles are held by a red line at the current frame
    plain = RolloutState.start("embedded", scene, num_rollouts=4, seed=0, stop_lines=True)
    plain.stop_lines = False  # the lines kept to measure with, the rule off
    assert _red_crossings(plain) >= 5  # the prior alone runs some (15 vehicle-steps at this seed)
    assert _red_crossings(RolloutState.start("embedded", scene, num_rollouts=4, seed=0, stop_lines=True)) == 0


def test_batching_keeps_each_scenes_lines_and_served_signs():
    model, _ = load_prior("embedded", "cpu")
    scenes = sample_scenarios()
    both = RolloutState.start(model, scenes[:2], seed=0, stop_lines=True)
    parts = split_state(both)
    again = stack_states(parts[::-1], seed=0)
    for name in ("stop_xy", "stop_dir", "stop_sign", "stop_red", "stop_valid"):
        for row, part in enumerate(parts[::-1]):
            k = part.stop_xy.shape[1]
            assert torch.equal(torch.nan_to_num(getattr(again, name)[row, :k]), torch.nan_to_num(getattr(part, name)[0]))
    one = RolloutState.start(model, scenes[0], seed=0, stop_lines=True)
    one.stop_served = torch.ones_like(one.stop_served)
    replace_scenes(both, [1], one)
    k = one.stop_xy.shape[1]
    assert both.stop_served[1, : one.num_slots, :k].all() and not both.stop_served[0].any() and not both.stop_served[1, :, k:].any()
    k = one.stop_xy.shape[1]
    assert torch.equal(both.stop_red[1, :k], one.stop_red[0]) and not both.stop_valid[1, k:].any()
    with pytest.raises(ValueError, match="stop lines"):
        replace_scenes(both, [0], RolloutState.start(model, scenes[2], seed=0, stop_lines=False))


def test_both_environments_take_the_rule_and_refill_with_it():
    from envs import smart_traffic_v0
    from envs.errors import EnvConfigError
    from envs.smart_traffic_batched_v0 import SmartTrafficBatchedEnv

    env = smart_traffic_v0.parallel_env(stop_lines=True, horizon_steps=2)
    env.reset(seed=0)
    env.step({a: 0 for a in env.agents})
    assert env.core.prior.stop_lines and env.core.prior.stop_served is not None
    batched = SmartTrafficBatchedEnv(scenarios="embedded", prior="embedded", num_scenes=2, max_agents=2, horizon_steps=2,
                                     stop_lines=True)
    td = batched.reset()
    for _ in range(5):  # episodes of 2 steps: every scene refilled twice
        td["agents", "action"] = td["agents", "observation", "prior_logits"].argmax(-1)
        _, td = batched.step_and_maybe_reset(td)
    assert batched.core.prior.stop_lines and batched.core.prior.stop_xy.shape[0] == 2
    with pytest.raises(EnvConfigError, match="stop_lines"):
        smart_traffic_v0.parallel_env(stop_lines="false")


def _turned_green(scene, frame: int):
    """``scene`` with every light GO from ``frame`` on."""
    import dataclasses

    from smart_marl.scenario import SignalState, TrafficLights

    tl = scene.traffic_lights
    states, present = tl.states.copy(), tl.present.copy()
    states[frame:], present[frame:] = int(SignalState.GO), True
    return dataclasses.replace(scene, traffic_lights=TrafficLights(tl.lane_ids, states, present, tl.stop_points))


def test_a_green_releases_the_vehicles_a_red_held_in_rollouts():
    """A sample scene whose lights all turn green 2 s in: the vehicles standing at a red line at the current frame
    move off with the log's clock (lights="log"), and stay where the current frame's lights are held."""
    scene = sample_scenarios()[0]
    scene = _turned_green(scene, scene.current_frame + 20)

    def moving_share(**kw) -> float:
        state = RolloutState.start("embedded", scene, num_rollouts=4, seed=0, **kw)
        g, s = (state.simulated & (state.agent_type == 0)).nonzero(as_tuple=True)
        dist, line = nearest_line(state, g, s)
        b = state.scene_of_group[g]
        front = dist - state.agent_shape[g, s, 0] / 2
        speed = (state.pose[g, s, :2] - state.previous_pose[g, s, :2]).norm(dim=-1) / 0.5
        at_red = torch.isfinite(dist) & ~state.stop_sign[b, line.clamp(min=0)] & (front < 8.0) & (speed < 1.0)
        g, s = g[at_red], s[at_red]
        assert len(g) >= 4  # standing first at the red lines
        state.run(16)
        return float(((state.pose[g, s, :2] - state.previous_pose[g, s, :2]).norm(dim=-1) / 0.5 > 1.0).float().mean())

    assert moving_share(lights="log") >= 0.5
    assert moving_share(lights="current") <= 0.1  # the challenge's rule: the red holds for the whole rollout


def test_each_scene_of_a_batch_follows_its_own_light_clock_through_refills():
    """lights="log" in a batch: a refilled scene starts at its own current frame while the others go on; the scenes
    whose lights changed are encoded again alone, to the numbers a whole re-encoding gives."""
    from smart_marl.model.batch import light_codes, scene_road
    from smart_marl.rollout.engine import _dummy_road_vocab
    from smart_marl.rollout.stop_lines import line_lights, scene_stop_lines

    model, vocab = load_prior("embedded", "cpu")
    scenes = sample_scenarios()
    scenes = [_turned_green(scenes[0], scenes[0].current_frame + 12), _turned_green(scenes[1], scenes[1].current_frame + 7)]
    state = stack_states([RolloutState.start(model, sc, seed=0, lights="log") for sc in scenes], seed=0)
    state.run(3)
    replace_scenes(state, [1], RolloutState.start(model, scenes[1], seed=0, lights="log"))
    assert state.scene_clock.tolist() == [3, 0]
    for b, (sc, clock) in enumerate(zip(scenes, (3, 0))):
        index = scene_road(sc, _dummy_road_vocab(), model.config.road_settings).light_index
        frame = sc.current_frame + 5 * clock
        assert torch.equal(state.road_light[b, : len(index)], torch.from_numpy(light_codes(sc.traffic_lights, index, frame)))
        red, go, _ = line_lights(sc, scene_stop_lines(sc)[2], 5 * clock)
        assert torch.equal(state.stop_red[b, : len(red)], torch.from_numpy(red)) and torch.equal(state.stop_go[b, : len(go)], torch.from_numpy(go))
    signals = state.stop_valid & ~state.stop_sign
    assert bool(state.stop_go[0][signals[0]].all())  # 1.5 s in: every light green (from 1.2 s on)
    assert not bool(state.stop_go[1][signals[1]].all())  # refilled: its current frame's lights, before its green at 0.7 s
    torch.testing.assert_close(state.road_x, model.encode_road(state), rtol=1e-5, atol=1e-5)


def test_a_rollout_knows_which_vehicles_have_moved_since_their_log_began():
    """``stop_moved`` starts from the history (a token step of 1 m/s or more) and stays true once a slot moves."""
    model, _ = load_prior("embedded", "cpu")
    scene = sample_scenarios()[0]
    state = RolloutState.start(model, scene, seed=0)
    hist_tokens, valid, start, end = state.history
    speed = (end[..., :2] - start[..., :2]).norm(dim=-1) / 0.5
    assert torch.equal(state.stop_moved, (valid & (speed >= 1.0)).any(-1))
    assert 0 < int(state.stop_moved[state.simulated].sum()) < int(state.simulated.sum())  # some stand, some move
    before = state.stop_moved.clone()
    state.step()
    assert bool((state.stop_moved | ~before).all())  # never forgotten
    moved_now = (state.pose[..., :2] - state.previous_pose[..., :2]).norm(dim=-1) / 0.5 >= 1.0
    assert torch.equal(state.stop_moved, before | moved_now)
