"""The environment's constructor and ``reset`` arguments (issue 34): each example of the issue, raw tracebacks
and silently wrong values alike, is a named EnvConfigError (a TypeError too for a value of the wrong type) or
keeps its documented meaning; the checks are pure functions (envs/_arguments.py) the batched env can reuse."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from envs import smart_traffic_v0
from envs._arguments import check_env_arguments, check_reset_arguments
from envs.errors import EnvConfigError, EnvConfigTypeError
from smart_marl.errors import SmartMarlError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def make_env():
    from smart_marl.embedded import sample_scenarios
    from smart_marl.tokens.vocab_io import load_motion_vocabulary

    vocab = load_motion_vocabulary(ROOT / "smart_marl" / "checkpoints" / "embedded" / "smart-1m-sumo.motion_vocab")
    scenes = sample_scenarios()[:2]
    return lambda **kw: smart_traffic_v0.parallel_env(**{"scenarios": scenes, "prior": None, "motion_vocab": vocab,
                                                          "background": "log", **kw})


@pytest.mark.parametrize("name, value, message", [
    ("horizon_steps", "abc", "horizon_steps must be an integer, got 'abc' (allowed: 1..10000)"),
    ("horizon_steps", float("nan"), "horizon_steps must be an integer, got nan"),
    ("horizon_steps", float("inf"), "horizon_steps must be an integer, got inf"),
    ("horizon_steps", None, "horizon_steps must be an integer, got None"),
    ("horizon_steps", 2.7, "horizon_steps must be an integer, got 2.7"),  # was truncated to 2
    ("horizon_steps", 10**9, "horizon_steps must be at most 10000"),
    ("max_agents", "abc", "max_agents must be an integer, got 'abc'"),
    ("temperature", "hot", "temperature must be a finite number, got 'hot'"),
    ("temperature", 0, "temperature must be >= 0.001, got 0"),  # was refused only at reset
    ("temperature", -1, "temperature must be >= 0.001, got -1"),
    ("temperature", float("nan"), "temperature must be a finite number, got nan"),
    ("temperature", float("inf"), "temperature must be a finite number, got inf"),
    ("reference_top_k", float("nan"), "reference_top_k must be an integer, got nan"),
    ("reference_top_k", 2.5, "reference_top_k must be an integer, got 2.5"),  # was truncated to 2
    ("terminate_on", 5, "terminate_on must be a list of event names"),
    ("terminate_on", "collision", "terminate_on must be a list of event names"),
    ("render_size_px", 0, "render_size_px must be at least 16, got 0"),
    ("render_size_px", -5, "render_size_px must be at least 16, got -5"),
    ("render_radius_m", float("nan"), "render_radius_m must be a finite number, got nan"),
    ("reward", {"collision": float("nan")}, "reward['collision'] must be a finite number, got nan"),  # gave NaN rewards
    ("avoid_collisions", "false", "avoid_collisions must be true or false, got 'false'"),  # was truthy
    ("controlled", [2.7], "controlled: a list holds track ids (integers) and agent names (strings)"),
    ("observation", "pixels", "observation kind must be 'vector' or 'dict'"),
])
def test_a_bad_constructor_argument_is_a_named_env_config_error(make_env, name, value, message):
    with pytest.raises(EnvConfigError) as info:
        make_env(**{name: value})
    assert message in str(info.value) and isinstance(info.value, (ValueError, SmartMarlError))


@pytest.mark.parametrize("name, value", [("horizon_steps", "abc"), ("max_agents", "abc"), ("temperature", "hot"),
                                         ("terminate_on", 5), ("avoid_collisions", "false"), ("horizon_steps", None)])
def test_a_value_of_the_wrong_type_is_a_type_error_too(make_env, name, value):
    with pytest.raises(EnvConfigTypeError) as info:
        make_env(**{name: value})
    assert isinstance(info.value, TypeError)


@pytest.mark.parametrize("kwargs, message", [
    ({"options": {"scene_index": "abc"}}, "options['scene_index'] must be an integer, got 'abc'"),
    ({"options": {"scene_index": 2.7}}, "options['scene_index'] must be an integer, got 2.7"),  # was truncated to 2
    ({"options": {"scene_index": True}}, "options['scene_index'] must be an integer, got True"),  # was scene 1
    ({"options": {"scene_index": 2}}, "options['scene_index'] must be at most 1 (the last scene), got 2"),
    ({"options": "abc"}, "reset options must be None or a dict"),  # was ignored
    ({"seed": -1}, "reset seed must be at least 0, got -1"),
    ({"seed": "abc"}, "reset seed must be an integer, got 'abc'"),
    ({"seed": 2.5}, "reset seed must be an integer, got 2.5"),
    ({"seed": 2**64}, "reset seed must be at most 9223372036854775807"),
])
def test_a_bad_reset_argument_is_a_named_env_config_error(make_env, kwargs, message):
    env = make_env()
    with pytest.raises(EnvConfigError) as info:
        env.reset(**kwargs)
    assert message in str(info.value)


def test_valid_arguments_keep_their_meaning(make_env):
    env = make_env(horizon_steps=np.int64(3), temperature=np.float32(0.5), top_k=None, reference_top_k=2,
                   terminate_on=["collision"], avoid_collisions=np.bool_(False), reward={"collision": -2.0})
    assert (env.horizon_steps, env.top_k, env.reference_top_k, env.terminate_on) == (3, 0, 2, frozenset({"collision"}))
    assert type(env.horizon_steps) is int and env.temperature == 0.5 and env.avoid_collisions is False
    assert env.reward_config.collision == -2.0
    env.reset(seed=np.int64(7), options={"scene_index": np.int64(1), "unknown": "ignored, as Gymnasium envs do"})
    assert env.scene_index == 1


def test_the_checks_are_pure_functions_the_batched_env_can_call():
    args = check_env_arguments(background="log", horizon_steps=4, scene_order="random", terminate_on=("goal",),
                               render_mode=None, render_modes=["rgb_array"], max_agents=None, top_k=5, temperature=1,
                               reference_top_k=None, render_size_px=64, render_radius_m=30, avoid_collisions=True, reward=None,
                               observation="vector", controlled="sdc")
    assert args["temperature"] == 1.0 and type(args["temperature"]) is float and args["render_radius_m"] == 30.0
    assert check_reset_arguments(None, None, 3) == (None, None)
    assert check_reset_arguments(5, {"scene_index": 2}, 3) == (5, 2)
    with pytest.raises(EnvConfigError, match=r"options\['scene_index'\] must be at most 2"):
        check_reset_arguments(None, {"scene_index": 3}, 3)
