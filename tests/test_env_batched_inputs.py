"""Hostile inputs to the batched TorchRL environment (envs.smart_traffic_batched_v0): a step's actions
and a reset's ``"_reset"`` mask are taken by the PettingZoo env's rules or refused with the env's
errors (envs.errors) naming the key, the scene row, the agent slot and the value, and a refused call
leaves the state as it was; the constructor refuses a wrong ``scenarios`` and sizes beyond what a
scene can fill or a device can hold before anything is built.

Property tests (hypothesis) draw dtypes, values and shapes and compare the env with an independent
rule in plain Python: what it takes steps, each live agent taking exactly its token (the prior's
log-probability of it is the step's ``action_log_prob``); what it refuses raises exactly the class
the rule names, nothing else escapes."""

from __future__ import annotations

import math
import time
import warnings

import numpy as np
import pytest
import torch

pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from hypothesis import event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from envs._setup import moving_vehicles_mask  # noqa: E402
from envs.errors import ActionError, ActionTypeError, EnvConfigError, EnvConfigTypeError, EnvError, EnvStateError  # noqa: E402
from envs.smart_traffic_batched_v0 import (FLOAT_DTYPES, INTEGER_DTYPES, MAX_AGENT_SLOTS, MAX_SCENES,  # noqa: E402
                                           SmartTrafficBatchedEnv)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py

B, A = 2, 2
PROPERTY = settings(max_examples=60, deadline=None, database=None)
DTYPES = [*INTEGER_DTYPES, *FLOAT_DTYPES, torch.bool, torch.complex64, torch.float8_e4m3fn]


def one_or_two(scenario) -> np.ndarray:
    """The moving vehicles to control, only the first of them in scenes -00 and -02: the rows of those
    scenes have a padded agent slot, the others none."""
    mask = moving_vehicles_mask(scenario)
    if scenario.scenario_id.endswith(("0", "2")):
        mask[np.flatnonzero(mask)[1:]] = False
    return mask


@pytest.fixture(scope="module")
def env():
    """One env for the module: 2 scene rows of 2 agent slots, scenes in order (row 0 has a padded slot
    after a full reset), agents finishing only at the horizon (2 steps)."""
    env = SmartTrafficBatchedEnv(scenarios="embedded", prior="embedded", num_scenes=B, max_agents=A, horizon_steps=2,
                                 controlled=one_or_two, scene_order="sequential", terminate_on=())
    env.reset()
    return env


def fresh(env) -> TensorDict:
    """A full reset to the same scenes and seed (row 0: one agent and a padded slot; row 1: two agents)."""
    env.set_seed(0)
    td = env.reset()
    assert td["agents", "mask"].tolist() == [[True, False], [True, True]]
    return td


def with_actions(actions) -> TensorDict:
    """A step's input holding only ``("agents", "action")`` (its group of batch [B], so any shape reaches the env)."""
    return TensorDict({"agents": TensorDict({"action": actions}, batch_size=[B])}, batch_size=[B])


def refused(env, td, error: type, *says: str) -> str:
    """``env.step(td)`` raises exactly ``error`` whose message holds ``says``; the state is as it was."""
    steps, indices = env.core.step_count.clone(), list(env.scene_indices)
    with pytest.raises(EnvError) as info:
        env.step(td)
    assert type(info.value) is error, f"{type(info.value).__name__}: {info.value}"
    for part in says:
        assert part in str(info.value), str(info.value)
    assert torch.equal(env.core.step_count, steps) and env.scene_indices == indices
    return str(info.value)


# ------------------------------------------------------------------------------ each finding
@pytest.mark.parametrize("value, says", [
    (-1, "scene row 1, agent slot 0 is -1: a negative id is not an action"),
    (float("nan"), "scene row 1, agent slot 0 is nan: NaN and infinities are not token ids"),
    (float("inf"), "is inf: NaN and infinities"),
    (-math.inf, "is -inf: NaN and infinities"),
    (3.7, "scene row 1, agent slot 0 is 3.7: a fraction is not a token id"),
    (1024, "scene row 1, agent slot 0 is 1024: beyond the vocabulary; token ids are 0..1023"),
    (10**12, "is 1000000000000: beyond the vocabulary"),
])
def test_a_live_agents_action_that_is_not_a_token_id_is_refused_naming_row_slot_and_value(env, value, says):
    fresh(env)
    actions = torch.tensor([[5, 5], [value, 5]])
    message = refused(env, with_actions(actions), ActionError, "('agents', 'action')", says)
    assert "more live agent" not in message  # slot 1 of row 0 is padded: its 5 is not looked at


def test_a_bool_action_tensor_is_refused_true_is_not_token_1(env):
    fresh(env)
    refused(env, with_actions(torch.ones(B, A, dtype=torch.bool)), ActionTypeError, "torch.bool tensor (True is not token 1)")


def test_a_step_without_an_action_is_refused(env):
    td = fresh(env)
    refused(env, td, ActionError, "no ('agents', 'action') in the TensorDict", "[B, A] = [2, 2] tensor of token ids 0..1023")


@pytest.mark.parametrize("shape", [(B,), (B, A + 1), (B, A, 2), (B, A, 1, 1)])
def test_an_action_of_another_shape_is_refused(env, shape):
    fresh(env)
    refused(env, with_actions(torch.zeros(shape, dtype=torch.long)), ActionError, f"got {list(shape)}")


def test_a_step_before_reset_is_refused():
    env = SmartTrafficBatchedEnv(scenarios="embedded", prior="embedded", num_scenes=B, max_agents=A, horizon_steps=2)
    with pytest.raises(EnvStateError, match=r"step\(\) before reset\(\)"):
        env.step(with_actions(torch.zeros(B, A, dtype=torch.long)))


def test_whole_floats_and_a_trailing_1_step_exactly_as_the_integer_tokens(env):
    tokens = torch.tensor([[7, 0], [300, 1023]])
    outs = []
    for actions in (tokens, tokens.double(), tokens.float()[..., None], tokens.to(torch.int16)):
        td = fresh(env)
        td["agents", "action"] = actions
        outs.append(env.step(td)["next", "agents"])
    for out in outs[1:]:
        assert torch.equal(out["observation", "observation"], outs[0]["observation", "observation"])
        assert torch.equal(out["info", "action_log_prob"], outs[0]["info", "action_log_prob"])


def test_padded_and_done_slots_are_ignored_nan_and_negative_ids_included(env):
    td = fresh(env)
    td["agents", "action"] = torch.tensor([[7.0, 0.0], [300.0, 1023.0]])
    reference = env.step(td)["next"]
    td = fresh(env)
    td["agents", "action"] = torch.tensor([[7.0, math.nan], [300.0, 1023.0]])  # row 0, slot 1 is padded
    out = env.step(td)["next"]
    assert torch.equal(out["agents", "observation", "observation"], reference["agents", "observation", "observation"])
    assert torch.equal(out["agents", "reward"], reference["agents", "reward"])
    # at the horizon every agent is done: whatever their slots hold is ignored, the rows stay done
    td = out.clone()
    td["agents", "action"] = torch.zeros(B, A, dtype=torch.long)
    out = env.step(td)["next"]
    assert out["done"].all() and not out["agents", "mask"].any()
    for junk in (torch.full((B, A), math.nan), torch.full((B, A), -1), torch.full((B, A), 10**9)):
        td = out.clone()
        td["agents", "action"] = junk
        after = env.step(td)["next"]
        assert after["done"].all() and not after["agents", "mask"].any()


@pytest.mark.parametrize("mask, error, says", [
    (torch.tensor([0.5, 0.0]), EnvConfigTypeError, "got torch.float32 (scene row 0 holds 0.5)"),
    (torch.tensor([0.0, math.nan]), EnvConfigTypeError, "(scene row 1 holds nan)"),
    (torch.tensor([[-1], [0]]), EnvConfigTypeError, "got torch.int64 (scene row 0 holds -1)"),
    (torch.tensor([0, 7]), EnvConfigTypeError, "(scene row 1 holds 7)"),
    (torch.tensor([1, 0]), EnvConfigTypeError, "0/1 values: pass mask.bool()"),
    (torch.tensor([[True, False]] * B), EnvConfigError,
     "'_reset' must have shape [2] or [2, 1] (one flag per scene row), got [2, 2]"),
    (torch.ones(B, 1, 1, dtype=torch.bool), EnvConfigError, "got [2, 1, 1]"),
])
def test_a_reset_mask_that_is_not_a_bool_per_scene_row_is_refused_and_no_row_restarts(env, mask, error, says):
    td = fresh(env)
    td["agents", "action"] = torch.zeros(B, A, dtype=torch.long)
    env.step(td)
    steps, indices = env.core.step_count.clone(), list(env.scene_indices)
    with pytest.raises(EnvError) as info:
        env.reset(TensorDict({"_reset": mask}, batch_size=[B]))
    assert type(info.value) is error and says in str(info.value), str(info.value)
    assert torch.equal(env.core.step_count, steps) and env.scene_indices == indices


# ------------------------------------------------------------------------------ properties
def expected_action_error(actions: torch.Tensor, live: torch.Tensor, vocab_size: int) -> type | None:
    """The rule in plain Python: the error class the env must raise for ``actions``, or None."""
    if actions.dtype not in INTEGER_DTYPES + FLOAT_DTYPES:
        return ActionTypeError
    if tuple(actions.shape) not in ((B, A), (B, A, 1)):
        return ActionError
    values = (actions.double() if actions.is_floating_point() else actions).reshape(B, A).tolist()
    for row, row_live in zip(values, live.tolist()):
        for v, alive in zip(row, row_live):
            if alive and not (math.isfinite(v) and float(v).is_integer() and 0 <= v < vocab_size):
                return ActionError
    return None


def action_values(vocab_size: int):
    return st.one_of(st.integers(0, vocab_size - 1), st.integers(-2**40, -1), st.integers(vocab_size, 2**40),
                     st.sampled_from([math.nan, math.inf, -math.inf, 3.7, -0.5, vocab_size - 0.5, 0.0, 12.0]))


@PROPERTY
@given(data=st.data())
def test_any_action_tensor_steps_with_its_tokens_or_raises_the_envs_action_error(env, data):
    v = env.vocab_size
    if not env.core.live.any():
        env.reset()
    dtype = data.draw(st.sampled_from(DTYPES), label="dtype")
    shape = data.draw(st.sampled_from([(B, A), (B, A), (B, A, 1), (B,), (B, A + 1)]), label="shape")
    n = math.prod(shape)
    tokens_only = data.draw(st.booleans(), label="token ids only")  # else mixed with what is not a token id
    value = st.integers(0, v - 1) if tokens_only else action_values(v)
    values = data.draw(st.lists(value, min_size=n, max_size=n), label="values")
    raw = torch.tensor(values, dtype=torch.float64).reshape(shape)
    actions = raw.to(dtype) if dtype.is_floating_point or dtype.is_complex else raw.nan_to_num(0, 0, 0).to(torch.int64).to(dtype)
    live = env.core.live.clone()
    logits = env.core.prior_logits()[..., :v].float()
    want = expected_action_error(actions, live, v)
    event(f"refused: {want.__name__}" if want else "stepped")  # pytest --hypothesis-show-statistics
    steps = env.core.step_count.clone()
    if want is not None:
        with pytest.raises(EnvError) as info:
            env.step(with_actions(actions))
        assert type(info.value) is want, f"{type(info.value).__name__}: {info.value}"
        assert torch.equal(env.core.step_count, steps)
        return
    out = env.step(with_actions(actions))["next", "agents"]
    tokens = (actions.double() if actions.is_floating_point() else actions).reshape(B, A).to(torch.int64).masked_fill(~live, 0)
    taken = torch.log_softmax(logits, -1).gather(-1, tokens[..., None])[..., 0]
    assert torch.allclose(out["info", "action_log_prob"][..., 0][live], taken[live], atol=1e-4)
    assert torch.equal(env.core.step_count, steps + 1)


@PROPERTY
@given(data=st.data())
def test_any_reset_mask_restarts_exactly_its_true_rows_or_raises_the_envs_config_error(env, data):
    if not env.core.live.any():
        env.reset()
    td = env.reset(TensorDict({"_reset": torch.ones(B, dtype=torch.bool)}, batch_size=[B]))
    td["agents", "action"] = torch.zeros(B, A, dtype=torch.long)
    env.step(td)  # every row one step in
    dtype = data.draw(st.sampled_from([torch.bool] * 3 + [torch.int64, torch.uint8, torch.float32, torch.float64]), label="dtype")
    shape = data.draw(st.sampled_from([(B,), (B, 1)] * 2 + [(B, 2), (B, 1, 1)]), label="shape")
    n = math.prod(shape)
    if dtype == torch.bool:
        mask = torch.tensor(data.draw(st.lists(st.booleans(), min_size=n, max_size=n)), dtype=torch.bool).reshape(shape)
    else:
        values = data.draw(st.lists(st.sampled_from([0.0, 1.0, 0.5, math.nan, -1.0, 7.0]), min_size=n, max_size=n))
        raw = torch.tensor(values, dtype=torch.float64).reshape(shape)
        mask = raw.to(dtype) if dtype.is_floating_point else raw.nan_to_num(0).to(dtype)
    steps, indices = env.core.step_count.clone(), list(env.scene_indices)
    want = (EnvConfigError if tuple(shape) not in ((B,), (B, 1)) else EnvConfigTypeError if dtype != torch.bool else None)
    event(f"refused: {want.__name__}" if want else "restarted")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TorchRL: a partial reset without the done keys in its input
        if want is not None:
            with pytest.raises(EnvError) as info:
                env.reset(TensorDict({"_reset": mask}, batch_size=[B]))
            assert type(info.value) is want, f"{type(info.value).__name__}: {info.value}"
            assert torch.equal(env.core.step_count, steps) and env.scene_indices == indices
            return
        env.reset(TensorDict({"_reset": mask}, batch_size=[B]))
    marked = mask.reshape(B)
    assert torch.equal(env.core.step_count, torch.where(marked, 0, steps))
    kept = [r for r, m in enumerate(marked.tolist()) if not m]
    assert [env.scene_indices[r] for r in kept] == [indices[r] for r in kept]


# ------------------------------------------------------------------------------ the constructor
@pytest.mark.parametrize("scenarios, says", [
    (123, "scenarios must be a path, 'embedded', a Scenario, a list of these or a ScenePool, got 123 (int)"),
    (b"embedded", "scenarios must be a path"),
    ({"a": 1}, "scenarios must be a path"),
    (["embedded", 123], "scenarios[1] must be a path, 'embedded' or a Scenario, got 123 (int)"),
])
def test_scenarios_of_a_wrong_type_are_refused_naming_the_argument(scenarios, says):
    with pytest.raises(EnvConfigTypeError) as info:
        SmartTrafficBatchedEnv(scenarios=scenarios, prior="embedded", num_scenes=B, max_agents=A)
    assert says in str(info.value)


@pytest.mark.parametrize("kwargs, error, says", [
    (dict(max_agents=10**9), EnvConfigError,
     f"max_agents must be at most {MAX_AGENT_SLOTS} (the most agents of a scene), got 1000000000"),
    (dict(max_agents=MAX_AGENT_SLOTS + 1), EnvConfigError, "max_agents must be at most 1024"),
    (dict(num_scenes=65536), EnvConfigError, f"num_scenes must be at most {MAX_SCENES} (~13 MB of device memory a scene"),
    (dict(num_scenes=MAX_SCENES + 1), EnvConfigError, "num_scenes must be at most 8192"),
    (dict(num_scenes="8"), EnvConfigTypeError, "num_scenes must be an integer, got '8'"),
    (dict(num_scenes=0), EnvConfigError, "num_scenes must be at least 1"),
])
def test_sizes_beyond_a_scene_or_a_device_are_refused_before_anything_is_built(kwargs, error, says):
    start = time.perf_counter()
    with pytest.raises(EnvConfigError) as info:
        SmartTrafficBatchedEnv(scenarios="embedded", prior="embedded", **{"num_scenes": B, "max_agents": A, **kwargs})
    assert type(info.value) is error and says in str(info.value), str(info.value)
    assert time.perf_counter() - start < 5.0  # refused before the prior is loaded or a tensor allocated
