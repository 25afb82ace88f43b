"""Scripted policies (agents.scripted.ScriptedPolicy) driving controlled agents of the PettingZoo env
on the package's sample scene sumo-7-000000-02 (44 tracks), with a small random SMART prior as
background (the mechanics need no trained prior). Scene facts used below: vehicle 41 (the SDC) drives
at 12.4 m/s at the current frame, vehicles 26 (6.8 m/s) and 6 (11.9 m/s) elsewhere in the scene."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pettingzoo", reason="the env extra (pettingzoo) is not installed")

from agents.scripted import Manoeuvre, ScriptedPolicy, stop_time_s  # noqa: E402
from envs import smart_traffic_v0  # noqa: E402


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture(scope="module")
def scenes(sample_scenes):
    return sample_scenes[2:3]


@pytest.fixture(scope="module")
def vocab(sample_vocab):
    return sample_vocab  # from all four sample scenes: it has a standing-still vehicle token (one scene's has not)


@pytest.fixture(scope="module")
def model(sample_model):
    return sample_model


def test_scripted_policy_brakes_a_controlled_car_to_a_standstill_and_holds_another(scenes, vocab, model):
    env = smart_traffic_v0.parallel_env(scenarios=scenes, prior=model, motion_vocab=vocab, controlled=[41, 26],
                                        horizon_steps=12, terminate_on=())
    policy = ScriptedPolicy(env, {"vehicle_41": Manoeuvre("brake", at_s=1.0, decel_mps2=8.0),
                                  "vehicle_26": Manoeuvre("hold")})
    obs, infos = env.reset(seed=0)
    track = {n: env.unwrapped.static.name_to_track[n] for n in ("vehicle_41", "vehicle_26")}
    start_26 = env.unwrapped.pose[track["vehicle_26"], :2].copy()
    poses = []
    while env.agents:
        obs, _, _, _, infos = env.step(policy(obs, infos))
        poses.append(env.unwrapped.pose[track["vehicle_41"], :2].copy())
        assert np.linalg.norm(env.unwrapped.pose[track["vehicle_26"], :2] - start_26) < 0.05
    poses = np.array(poses)  # pose at the end of each 0.5 s step
    token_speed = np.linalg.norm(np.diff(poses, axis=0), axis=1) / 0.5
    v0 = np.linalg.norm(poses[1] - poses[0]) / 0.5  # the step before the brake (1.0 s = step 2)
    stop_step = 2 + int(np.ceil(stop_time_s(v0, 8.0) / 0.5)) + 1
    assert v0 > 3.0 and token_speed[stop_step:].max() < 0.3, token_speed.round(2)


def test_scripted_policy_forces_given_tokens_then_hands_back_to_the_fallback(scenes, vocab, model):
    env = smart_traffic_v0.parallel_env(scenarios=scenes, prior=model, motion_vocab=vocab, controlled=[6],
                                        horizon_steps=5, terminate_on=())
    seen = []

    def fallback(observations, infos, agents):
        seen.append(env.unwrapped.step_count)
        return {a: 0 for a in agents}

    policy = ScriptedPolicy(env, {"vehicle_6": Manoeuvre("tokens", at_s=0.5, tokens=[5, 6])}, fallback=fallback)
    obs, infos = env.reset(seed=0)
    taken = []
    while env.agents:
        actions = policy(obs, infos)
        taken.append(actions["vehicle_6"])
        obs, _, _, _, infos = env.step(actions)
    assert taken == [0, 5, 6, 0, 0] and seen == [0, 1, 2, 3, 4]
