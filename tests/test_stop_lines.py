"""Stopping at stop lines (smart_marl.rollout.stop_lines): which line holds a vehicle, which tokens it may not
draw, that rollouts with the rule do not run the red lines that held them, and that batching keeps the lines."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from smart_marl.embedded import sample_scenarios
from smart_marl.model.checkpoint import load_prior
from smart_marl.rollout import RolloutState
from smart_marl.rollout.refill import replace_scenes, split_state, stack_states
from smart_marl.rollout.stop_lines import STOP_DECEL_MPS2, line_groups, nearest_line, served_after_step, stop_line_test

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def _lines_state(**extra) -> SimpleNamespace:
    """One scene, two vehicles at the origin heading +x, and six lines: a red one 20 m ahead, a green one 10 m ahead,
    a red one 5 m to the side, a red one behind, a red one whose lane runs the other way, a stop sign 12 m ahead."""
    xy = torch.tensor([[[20.0, 0.0], [10.0, 0.0], [6.0, 5.0], [-5.0, 0.0], [15.0, 0.0], [12.0, 0.5]]])
    direction = torch.tensor([[[1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [1.0, 0.0]]])
    state = SimpleNamespace(
        scene_of_group=torch.tensor([0]), pose=torch.zeros(1, 2, 3), previous_pose=torch.zeros(1, 2, 3),
        stop_xy=xy, stop_dir=direction, stop_valid=torch.ones(1, 6, dtype=torch.bool), stop_group=torch.arange(6)[None],
        stop_red=torch.tensor([[True, False, True, True, True, False]]),
        stop_sign=torch.tensor([[False, False, False, False, False, True]]),
        stop_served=torch.tensor([[-1, 5]]), agent_type=torch.zeros(1, 2, dtype=torch.long),
        agent_shape=torch.tensor([[[4.0, 2.0, 1.5], [4.0, 2.0, 1.5]]]), simulated=torch.ones(1, 2, dtype=torch.bool), num_slots=2)
    for name, value in extra.items():
        setattr(state, name, value)
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
                         stop_red=torch.tensor([[True, False, True, True]]))
    _, line = nearest_line(state, torch.tensor([0]), torch.tensor([0]))
    assert line.tolist() == [2]  # the through lane is green: the next line, 23 m on, holds it
    state.stop_red[0, 1] = True
    _, line = nearest_line(state, torch.tensor([0]), torch.tensor([0]))
    assert line.tolist() == [0]


def test_a_held_vehicle_may_draw_only_the_tokens_after_which_it_can_stop():
    # five tokens ending 0, 2, 5, 8 and 12 m ahead at 0, 4, 10, 16 and 24 m/s; the sign's line 12 m ahead (front 10 m)
    ends = (torch.tensor([[0.0, 2.0, 5.0, 8.0, 12.0]]), torch.tensor([[0.0, 4.0, 10.0, 16.0, 24.0]]))
    state = _lines_state(stop_token_ends=ends, vocab_sizes=torch.tensor([5]))
    test = stop_line_test(state, torch.tensor([0]))  # slot 0: held by the sign 12 m ahead
    # needs 0, 16 / 16 = 1.0, 100 / 10 = 10, 256 / 4 = 64 m/s2 and an overrun of 2 m
    assert test(torch.tensor([0]), torch.arange(5)[None]).tolist() == [[False, False, True, True, True]]
    assert STOP_DECEL_MPS2 == 3.0
    state.stop_red[:] = False
    state.stop_served[:] = 5
    assert stop_line_test(state, torch.tensor([0, 1])) is None  # nothing holds either: the plain search


def test_a_vehicle_that_stood_at_a_stop_sign_has_served_it():
    state = _lines_state()
    state.pose = torch.tensor([[[7.5, 0.0, 0.0], [9.0, 0.0, 0.0]]])
    state.previous_pose = torch.tensor([[[7.4, 0.0, 0.0], [4.0, 0.0, 0.0]]])  # slot 0 stands, slot 1 drives on
    assert served_after_step(state).tolist() == [[5, 5]]
    state.stop_served = torch.tensor([[-1, -1]])
    assert served_after_step(state).tolist() == [[5, -1]]


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
    one.stop_served = torch.full_like(one.stop_served, 3)
    replace_scenes(both, [1], one)
    assert (both.stop_served[1, : one.num_slots] == 3).all() and (both.stop_served[0] == -1).all()
    k = one.stop_xy.shape[1]
    assert torch.equal(both.stop_red[1, :k], one.stop_red[0]) and not both.stop_valid[1, k:].any()
    with pytest.raises(ValueError, match="stop lines"):
        replace_scenes(both, [0], RolloutState.start(model, scenes[2], seed=0))


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
