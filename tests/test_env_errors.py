"""The environment's errors (issue 15 item 3): every bad action or call is a SmartMarlError that keeps
the builtin base a Gym/PettingZoo caller catches; NaN and infinite actions are named, not turned
into tokens or raw OverflowErrors; a refused step leaves the episode as it was."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pettingzoo", reason="pettingzoo is a core dependency; this checks an install without it")

from envs import smart_traffic_v0  # noqa: E402
from envs.errors import (ActionError, ActionTypeError, EnvConfigError, EnvStateError, NoPriorLogitsError,  # noqa: E402
                         UnknownAgentError)
from smart_marl.errors import SmartMarlError  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture(scope="module")
def env(sample_scenes, sample_vocab, tiny_smart):
    env = smart_traffic_v0.parallel_env(scenarios=sample_scenes[:1], prior=tiny_smart(sample_vocab), motion_vocab=sample_vocab,
                                        controlled="vehicles", max_agents=2, horizon_steps=2, background="log")
    env.reset(seed=0)
    return env


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf"), np.float32("nan"), 2.5, "3", [1, 2], None])
def test_a_nan_infinite_or_non_integer_action_is_a_named_action_error(env, bad):
    a = env.agents[0]
    before = (env.frame, list(env.agents))
    with pytest.raises(ActionError, match=f"action of {a} must be one integer token id") as info:
        env.step({**{x: 0 for x in env.agents}, a: bad})
    assert isinstance(info.value, ValueError) and isinstance(info.value, SmartMarlError)
    assert (env.frame, list(env.agents)) == before  # nothing moved


def test_env_errors_keep_their_builtin_bases(env, sample_scenes, sample_vocab, tiny_smart):
    good = {x: 0 for x in env.agents}
    with pytest.raises(UnknownAgentError) as info:
        env.step({**good, "vehicle_999999": 0})
    assert isinstance(info.value, KeyError) and str(info.value).startswith("unknown agent(s) ['vehicle_999999']")
    with pytest.raises(KeyError):
        env.action_space("vehicle_999999")
    with pytest.raises(ActionTypeError) as info:
        env.step([0, 0])
    assert isinstance(info.value, TypeError) and isinstance(info.value, ValueError)
    with pytest.raises(EnvConfigError, match="observation kind"):
        smart_traffic_v0.parallel_env(scenarios=sample_scenes[:1], prior=None, motion_vocab=sample_vocab, background="log",
                                      observation="pixels")
    with pytest.raises(EnvConfigError, match="unknown reward term"):
        smart_traffic_v0.parallel_env(scenarios=sample_scenes[:1], prior=None, motion_vocab=sample_vocab, background="log",
                                      reward={"speed": 1.0})
    done = smart_traffic_v0.parallel_env(scenarios=sample_scenes[:1], prior=tiny_smart(sample_vocab), motion_vocab=sample_vocab,
                                         controlled="sdc", horizon_steps=1, background="log")
    done.reset(seed=0)
    done.step({a: 0 for a in done.agents})
    with pytest.raises(EnvStateError) as info:
        done.step({})
    assert isinstance(info.value, RuntimeError) and "call reset()" in str(info.value)


def test_prior_logits_of_an_env_without_a_prior_is_a_named_key_error(sample_scenes, sample_vocab):
    from agents.prior_policy import prior_logits_of

    env = smart_traffic_v0.parallel_env(scenarios=sample_scenes[:1], prior=None, motion_vocab=sample_vocab, background="log",
                                        controlled="sdc")
    observations, infos = env.reset(seed=0)
    with pytest.raises(NoPriorLogitsError, match="needs a prior") as info:
        prior_logits_of(env.agents[0], observations, infos)
    assert isinstance(info.value, KeyError)
