"""Property tests (issue 34 item 4): any value given to the environment's constructor and ``reset``, or to a
field of any config dataclass (training, fine-tuning, SUMO, the model, the reward and observation, every
what-if edit), is either accepted with its documented meaning or refused with a named SmartMarlError that
names the argument; never a raw exception, a NaN that gets through, or a hang.

Hypothesis runs with a fixed seed (``derandomize=True``) and a fixed budget of examples per property, so
the default run is reproducible and takes a few seconds per property. Environments are built with
``prior=None`` and the embedded motion vocabulary on the embedded sample scenes: cheap (a few ms each)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agents.finetune import FinetuneConfig
from agents.whatif.edits import KINDS
from fuzzing import DEEP_MARKER, WRONG_VALUES
from smart_marl.config_files import MAX_SEED, is_integer, unruled_fields
from smart_marl.errors import SmartMarlError
from smart_marl.model.smart import SmartConfig
from smart_marl.sources.sumo_sim import SumoConfig
from smart_marl.train import TrainConfig

ROOT = Path(__file__).resolve().parents[1]
BUDGET = settings(max_examples=60, derandomize=True, deadline=None, database=None,
                  suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
"""The default run's budget: 60 examples per property, drawn from a fixed seed."""

HOSTILE = st.one_of(
    st.sampled_from([v for v in WRONG_VALUES if v is not DEEP_MARKER]),
    st.integers(-(2**70), 2**70), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=6), st.booleans(),
    st.lists(st.one_of(st.integers(-3, 3), st.floats(allow_nan=True)), max_size=4),
    st.tuples(st.floats(-10, 10), st.floats(-10, 10)), st.sampled_from([np.float32("nan"), np.int64(-1), np.bool_(True)]),
)
"""Values of the wrong type, non-finite, huge, negative, fractional, empty or nested."""


def _accepts_or_names(make, error: type[Exception], *names: str):
    """``make()`` succeeds (returns its result) or raises ``error`` (a SmartMarlError) naming one of ``names``."""
    try:
        return make()
    except error as exc:
        assert isinstance(exc, SmartMarlError) and any(n in str(exc) for n in names), \
            f"{type(exc).__name__}: {exc} does not name {names}"
        return None


# -------------------------------------------------------------------------------- every field has a rule
def test_every_field_of_every_config_dataclass_has_a_rule():
    from agents.finetune_config import _FINETUNE_RULES, FinetuneConfig
    from agents.whatif.edits import _EDIT_RULES, _PLACEMENT, KINDS
    from envs._arguments import OBSERVATION_RULES, REWARD_RULES
    from envs._observation import ObservationConfig
    from envs._reward import RewardConfig
    from smart_marl.model.smart import MODEL_RULES, SmartConfig
    from smart_marl.sources.sumo_sim import SUMO_RULES, SumoConfig
    from smart_marl.train import _TRAIN_RULES, TrainConfig

    assert unruled_fields(TrainConfig, _TRAIN_RULES) == ["model"]  # checked against the named configs and SmartConfig
    for cls, rules in ((FinetuneConfig, _FINETUNE_RULES), (SumoConfig, SUMO_RULES), (SmartConfig, MODEL_RULES),
                       (RewardConfig, REWARD_RULES), (ObservationConfig, OBSERVATION_RULES)):
        assert unruled_fields(cls, rules) == [], cls.__name__
    for kind, cls in KINDS.items():
        assert unruled_fields(cls, {**_PLACEMENT, **_EDIT_RULES[cls]}) == [], kind


# ------------------------------------------------------------------------------------- config dataclasses
def _field_and_value(cls: type, skip: tuple[str, ...] = ()):
    names = [f.name for f in dataclasses.fields(cls) if f.name not in skip]
    return st.tuples(st.sampled_from(names), HOSTILE)


@BUDGET
@given(_field_and_value(TrainConfig))
def test_any_training_config_value_is_accepted_or_named(field_value):
    from smart_marl.train import TrainConfigError, TrainError, load_train_config

    name, value = field_value
    cfg = _accepts_or_names(lambda: load_train_config({"data": "x", "out_dir": "runs/never-written", name: value}),
                            TrainError, name, "model")
    if cfg is not None:  # accepted: kept as given (and, a number, finite)
        assert getattr(cfg, name) == value
    assert issubclass(TrainConfigError, TrainError)


@BUDGET
@given(_field_and_value(FinetuneConfig))
def test_any_finetuning_config_value_is_accepted_or_named(field_value):
    from agents.finetune import FinetuneError, load_finetune_config

    name, value = field_value
    cfg = _accepts_or_names(lambda: load_finetune_config("tiny", {name: value}), FinetuneError, name)
    if cfg is not None and isinstance(value, float):
        assert math.isfinite(value)  # no NaN or infinity is ever accepted


@BUDGET
@given(_field_and_value(SumoConfig))
def test_any_sumo_config_value_is_accepted_or_named(field_value):
    from smart_marl.sources.sumo_sim import SumoConfigError

    name, value = field_value
    cfg = _accepts_or_names(lambda: SumoConfig(**{name: value}), SumoConfigError, name,
                            *(("walker_sway_m",) if name.startswith(("walker_", "cyclist_")) else ()))
    if cfg is not None and isinstance(value, float):
        assert math.isfinite(value)


@BUDGET
@given(_field_and_value(SmartConfig))
def test_any_model_config_value_is_accepted_or_named(field_value):
    """Every accepted config makes a model of a size the machine holds (checked on the meta device)."""
    import torch

    from smart_marl.model.smart import MAX_MODEL_PARAMETERS, SMART, ModelConfigError, get_config

    name, value = field_value
    cfg = _accepts_or_names(lambda: get_config("smart-1m", **{name: value}), ModelConfigError, name)
    if cfg is not None:
        with torch.device("meta"):
            assert sum(p.numel() for p in SMART(cfg).parameters()) < MAX_MODEL_PARAMETERS


@BUDGET
@given(st.sampled_from(sorted(KINDS)), st.data())
def test_any_what_if_edit_value_is_accepted_or_named(kind, data):
    from agents.whatif import WhatIf, WhatIfError

    name, value = data.draw(_field_and_value(KINDS[kind]), label="field and value")
    whatif = _accepts_or_names(lambda: WhatIf.from_dict({"edits": [{"kind": kind, name: value}]}), WhatIfError, name)
    if whatif is not None and isinstance(value, float):
        assert math.isfinite(value) and abs(value) <= 1e6


# ------------------------------------------------------------------------------------------- the env
@pytest.fixture(scope="module")
def env_inputs():
    from smart_marl.embedded import sample_scenarios
    from smart_marl.tokens.vocab_io import load_motion_vocabulary

    vocab = load_motion_vocabulary(ROOT / "smart_marl" / "checkpoints" / "embedded" / "smart-1m-sumo.motion_vocab")
    return sample_scenarios()[:2], vocab


ENV_ARGUMENTS = {
    "horizon_steps": st.one_of(st.integers(1, 40), HOSTILE), "max_agents": st.one_of(st.none(), st.integers(1, 4), HOSTILE),
    "temperature": st.one_of(st.floats(0.001, 1000.0), HOSTILE), "top_k": st.one_of(st.integers(0, 8), HOSTILE),
    "reference_top_k": st.one_of(st.none(), st.integers(1, 8), HOSTILE),
    "terminate_on": st.one_of(st.lists(st.sampled_from(["collision", "offroad", "goal"]), max_size=3), HOSTILE),
    "render_size_px": st.one_of(st.integers(16, 64), HOSTILE), "render_radius_m": st.one_of(st.floats(1.0, 100.0), HOSTILE),
    "avoid_collisions": st.one_of(st.booleans(), HOSTILE), "scene_order": st.one_of(st.sampled_from(["sequential", "random"]), HOSTILE),
    "background": st.one_of(st.sampled_from(["log", "constant_velocity"]), HOSTILE),
    "controlled": st.one_of(st.sampled_from(["sdc", "vehicles", "all", "predict"]), HOSTILE),
    "reward": st.one_of(st.none(), st.dictionaries(st.sampled_from(["collision", "progress", "goal_radius_m"]), HOSTILE, max_size=2),
                        HOSTILE),
    "observation": st.one_of(st.sampled_from(["vector", "dict"]), HOSTILE), "render_mode": st.one_of(st.none(), HOSTILE),
}


@BUDGET
@given(st.sets(st.sampled_from(sorted(ENV_ARGUMENTS)), min_size=1, max_size=3), st.data())
def test_any_env_constructor_argument_is_accepted_with_its_meaning_or_named(env_inputs, names, data):
    from envs import smart_traffic_v0
    from envs.errors import EnvConfigError

    scenes, vocab = env_inputs
    kwargs = {name: data.draw(ENV_ARGUMENTS[name], label=name) for name in sorted(names)}
    kwargs.setdefault("background", "log")
    env = None
    try:
        env = smart_traffic_v0.parallel_env(scenarios=scenes, prior=None, motion_vocab=vocab, **kwargs)
    except EnvConfigError as exc:
        assert any(name in str(exc) for name in kwargs), f"{exc} names none of {sorted(kwargs)}"
        return
    # accepted: the documented meanings
    assert isinstance(env.horizon_steps, int) and 1 <= env.horizon_steps <= 10_000
    assert math.isfinite(env.temperature) and 1e-3 <= env.temperature <= 1e3
    assert env.max_agents is None or (isinstance(env.max_agents, int) and env.max_agents >= 1)
    assert env.reference_top_k is None or (isinstance(env.reference_top_k, int) and env.reference_top_k >= 1)
    assert isinstance(env.top_k, int) and env.top_k >= 0 and isinstance(env.avoid_collisions, bool)
    assert np.isfinite(env.reward_config.weights()).all()
    assert isinstance(env.render_size_px, int) and 16 <= env.render_size_px <= 4096 and math.isfinite(env.render_radius_m)
    obs, _ = env.reset(seed=0)
    assert set(obs) == set(env.agents) and env.agents


RESET_SEEDS = st.one_of(st.none(), st.integers(0, MAX_SEED), HOSTILE)
RESET_OPTIONS = st.one_of(st.none(), st.fixed_dictionaries({"scene_index": st.one_of(st.integers(-2, 3), HOSTILE)}),
                          st.dictionaries(st.text(max_size=4), HOSTILE, max_size=2), HOSTILE)


@BUDGET
@given(RESET_SEEDS, RESET_OPTIONS)
def test_any_reset_seed_and_options_are_accepted_with_their_meaning_or_named(env_inputs, seed, options):
    from envs import smart_traffic_v0
    from envs.errors import EnvConfigError

    scenes, vocab = env_inputs
    env = smart_traffic_v0.parallel_env(scenarios=scenes, prior=None, motion_vocab=vocab, background="log", scene_order="random")
    try:
        env.reset(seed=seed, options=options)
    except EnvConfigError as exc:
        assert "seed" in str(exc) or "options" in str(exc) or "scene_index" in str(exc), str(exc)
        return
    index = options.get("scene_index") if isinstance(options, dict) else None
    if index is not None:  # accepted: exactly the scene asked for (never a truncated 2.7 or True)
        assert is_integer(index) and env.scene_index == index
    if seed is not None:  # accepted: a seed that reproduces the episode (the random scene order included)
        first = env.scene_index
        env.reset(seed=seed, options=options)
        assert env.scene_index == first
