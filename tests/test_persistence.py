"""Speed persistence (smart_marl.rollout.persistence): the tilt of a vehicle's draw toward the change of speed it is
in, its bounds, what it leaves alone (pedestrians, steady vehicles, unknown speeds, the reported log-probabilities),
the speed it remembers across steps, and every surface refusing a bad strength by name. The rollouts with it off are
the rollouts of before bit for bit: tests/test_rollout_pinned.py's plain pin is drawn with persistence 0."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from smart_marl.rollout import RolloutState, rollout
from smart_marl.rollout.persistence import (CHANGE_CLIP_MPS, DEFAULT_PERSISTENCE, TOKEN_CHANGE_CLIP_MPS, mean_speed, tilted,
                                            token_speeds)
from smart_marl.rollout.sampling import reference_log_probs

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _state(speed_now, speed_before, agent_type, persistence=1.0):
    """A stand-in state of one group: slot i moved ``speed_now[i] * 0.5`` m along x over its last token."""
    now = torch.tensor(speed_now, dtype=torch.float32)
    n = len(now)
    pose = torch.zeros(1, n, 3)
    pose[0, :, 0] = now * 0.5
    speeds = torch.arange(0.0, 20.0, 0.5)  # 40 tokens, 0 .. 19.5 m/s
    poses = torch.zeros(3, len(speeds), 6, 3)
    poses[:, :, 5, 0] = speeds * 0.5
    return SimpleNamespace(pose=pose, previous_pose=torch.zeros(1, n, 3), speed_before=torch.tensor([speed_before]),
                           agent_type=torch.tensor([agent_type]), token_speeds=token_speeds(poses), persistence=persistence)


def test_the_tilt_leans_toward_the_change_a_vehicle_is_in_and_is_bounded():
    # slot 0 speeding up (8 -> 10 m/s), 1 slowing (10 -> 8), 2 steady, 3 a pedestrian speeding up, 4 unknown before,
    # 5 a vehicle whose token jumped 20 m/s (clamped)
    state = _state([10.0, 8.0, 9.0, 2.0, 9.0, 25.0], [8.0, 10.0, 9.0, 1.0, math.nan, 5.0], [0, 0, 0, 1, 0, 0])
    logits = torch.zeros(6, 40)
    out = tilted(state, torch.arange(6), logits)
    speeds = state.token_speeds[0]
    faster, slower = speeds > 11.0, speeds < 8.0
    assert (out[0, faster] > 0).all() and (out[0, slower] < 0).all()
    assert (out[1, faster] < 0).all() and (out[1, slower] > 0).all()
    assert torch.equal(out[2:5], logits[2:5])  # steady, a pedestrian, an unknown speed before: the model's logits
    bound = state.persistence * CHANGE_CLIP_MPS * TOKEN_CHANGE_CLIP_MPS
    assert out.abs().max() <= bound + 1e-6 and out[5].abs().max() == pytest.approx(bound)
    # linear in the change: the same speed now and the opposite change mirror it
    mirrored = tilted(_state([10.0], [12.0], [0]), torch.arange(1), torch.zeros(1, 40))
    assert torch.allclose(mirrored[0], -out[0])


def test_nothing_to_tilt_leaves_the_logits_tensor_itself():
    state = _state([9.0, 2.0], [9.0, 1.0], [0, 1])
    logits = torch.randn(2, 40)
    assert tilted(state, torch.arange(2), logits) is logits
    one = logits[:1]
    assert tilted(_state([10.0], [8.0], [0], persistence=0.0), torch.arange(1), one) is one


def test_a_rollout_reports_the_models_log_probs_and_remembers_the_speed_before(embedded_prior, sample_scenes):
    model, vocab = embedded_prior
    state = RolloutState.start(model, sample_scenes[2:3], num_rollouts=4, seed=3, motion_vocab=vocab, persistence=2.0)
    for _ in range(4):
        pose, previous = state.pose.clone(), state.previous_pose.clone()
        out = state.step()
        sim = out.simulated
        model_log_probs = torch.log_softmax(out.logits[sim], -1).gather(1, out.tokens[sim][:, None])[:, 0]
        assert torch.allclose(out.log_probs[sim], model_log_probs, atol=1e-6)
        # the token just taken becomes "the token before" the next one's
        assert torch.allclose(state.speed_before[sim], mean_speed(pose, previous)[sim], equal_nan=True)


def test_a_vehicle_speeding_up_draws_faster_tokens_on_average(embedded_prior, sample_scenes):
    """On a sample scene's first step: for every vehicle whose last token was faster than the one before, the mean
    token speed of the distribution the draw samples (top-k of the tilted logits) is at least the model's."""
    model, vocab = embedded_prior
    state = RolloutState.start(model, sample_scenes[:3], num_rollouts=1, seed=0, motion_vocab=vocab, persistence=1.0)
    logits = state.logits().reshape(-1, state.logits().shape[-1])
    rows = state.simulated.reshape(-1).nonzero().squeeze(1)
    now = mean_speed(state.pose, state.previous_pose).reshape(-1)[rows]
    change = now - state.speed_before.reshape(-1)[rows]
    vehicle = state.agent_type.reshape(-1)[rows] == 0
    up, down = vehicle & (change > 0.2), vehicle & (change < -0.2)
    assert up.any() and down.any()
    speeds = state.token_speeds[0, : logits.shape[1]]
    expected = lambda lg: (reference_log_probs(lg, state.top_k).exp() * speeds).sum(-1)  # noqa: E731
    plain, leaning = expected(logits[rows]), expected(tilted(state, rows, logits[rows]))
    assert (leaning[up] >= plain[up] - 1e-4).all() and (leaning[up] > plain[up] + 1e-3).any()
    assert (leaning[down] <= plain[down] + 1e-4).all() and (leaning[down] < plain[down] - 1e-3).any()


@pytest.mark.parametrize("bad", [-0.5, float("nan"), float("inf"), "0.25", True])
def test_every_surface_refuses_a_bad_persistence_by_name(bad, sample_scenes):
    from agents.whatif import load_script, run_whatif
    from agents.whatif.edits import EXAMPLES_DIR
    from envs.smart_traffic_batched_v0 import SmartTrafficBatchedEnv
    from envs.smart_traffic_v0 import parallel_env

    script = load_script(sorted(EXAMPLES_DIR.glob("*.yaml"))[0])
    calls = {
        "rollout": lambda: rollout("embedded", sample_scenes[:1], num_rollouts=1, persistence=bad),
        "RolloutState.start": lambda: RolloutState.start("embedded", sample_scenes[:1], persistence=bad),
        "parallel_env": lambda: parallel_env(scenarios="embedded", persistence=bad),
        "batched env": lambda: SmartTrafficBatchedEnv(scenarios="embedded", num_scenes=1, max_agents=1, persistence=bad),
        "run_whatif": lambda: run_whatif(None, sample_scenes[0], script, num_rollouts=1, persistence=bad),
    }
    for where, call in calls.items():
        with pytest.raises(Exception) as err:
            call()
        assert "persistence" in str(err.value), f"{where}: {err.value}"


def test_the_commands_refuse_a_negative_persistence(tmp_path, capsys):
    from test_commands_consistency import _exit_code

    for argv in (["eval", "--scenes", "x", "--policy", "prior", "--persistence", "-1"],
                 ["whatif", "x", "--script", "brake_hard", "--out", str(tmp_path / "w"), "--persistence", "-1"]):
        code, _, err = _exit_code(argv, capsys)
        assert code == 2 and "--persistence" in err and "-1" in err, (argv, err)


def test_the_default_is_documented_where_users_set_it():
    import inspect

    from envs.smart_traffic_v0 import parallel_env

    assert f"default {DEFAULT_PERSISTENCE:g}" in inspect.getdoc(parallel_env)
