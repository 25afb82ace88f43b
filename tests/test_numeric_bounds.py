"""Nothing taken silently (issue 56): every number a run divides, loops, allocates or multiplies weights by is
bounded on both sides. For each bounded knob of the fine-tuning and training configs, the environments'
constructors, the what-if scripts and ``run_whatif``, and the command line's numeric flags: the bound itself is
accepted; the value just above it and huge ones (1e308, 10**12, inf) are refused with the project's error naming
the knob; at the command line, with exit 2 and one ``error:`` line."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import pytest

from agents.finetune_config import (MAX_CLIP_EPSILON, MAX_EVAL_SCENES, MAX_ITERATIONS, MAX_OBS_SCALE, FinetuneConfigError,
                                    load_finetune_config)
from envs._arguments import MAX_AGENT_SLOTS, MAX_REWARD_WEIGHT
from envs.smart_traffic_batched_v0 import MAX_CACHED_SCENES
from smart_marl.config_files import MAX_DISTANCE_M, MAX_GRAD_NORM, MAX_LOSS_WEIGHT, MAX_SCENE_COUNT, MAX_TIME_LIMIT_S
from smart_marl.model.smart import MAX_VOCAB_SIZE
from smart_marl.train_config import MAX_CACHE_SCENES, MAX_STEPS, TrainConfigError, load_train_config
from test_commands_consistency import _exit_code as _run  # (exit code, stdout, stderr) of the command line

ROOT = Path(__file__).resolve().parents[1]
HUGE = (1e308, 10**12, math.inf)
"""What a hostile user passes: the largest float, a trillion, infinity."""


def _above(bound):
    """The value just above ``bound``: the next integer, or the next float64."""
    return bound + 1 if isinstance(bound, int) else math.nextafter(bound, math.inf)


def _cases(bounds: dict) -> list:
    """(knob, value, accepted) for each ``knob: (bound, extra)`` of ``bounds``: the bound, just above it, and :data:`HUGE`."""
    return [pytest.param(k, v, v == b, x, id=f"{k}={v!r}") for k, (b, x) in bounds.items() for v in (b, _above(b), *HUGE)]


# ------------------------------------------------------------------------------------------ fine-tuning
FINETUNE_BOUNDS = {  # field: (its upper bound, other overrides the bound needs to load)
    "max_grad_norm": (MAX_GRAD_NORM, {}), "clip_epsilon": (MAX_CLIP_EPSILON, {}), "beta": (MAX_LOSS_WEIGHT, {}),
    "critic_coeff": (MAX_LOSS_WEIGHT, {}), "entropy_coeff": (MAX_LOSS_WEIGHT, {}), "imitation": (MAX_LOSS_WEIGHT, {}),
    "obs_scale": (MAX_OBS_SCALE, {}), "time_limit_s": (MAX_TIME_LIMIT_S, {}), "moving_min_route_m": (MAX_DISTANCE_M, {}),
    "minibatch_size": (10**6, {"frames_per_batch": 10**6}), "checkpoint_every": (MAX_ITERATIONS, {}),
    "iterations": (MAX_ITERATIONS, {}), "eval_num_scenes": (MAX_EVAL_SCENES, {}), "num_scenes": (MAX_SCENE_COUNT, {}),
    "top_k": (MAX_VOCAB_SIZE, {}), "reference_top_k": (MAX_VOCAB_SIZE, {}), "max_agents": (MAX_AGENT_SLOTS, {}),
    "prior_cache_size": (MAX_CACHED_SCENES, {}), "reward.collision": (MAX_REWARD_WEIGHT, {}),
    "reward.progress": (MAX_REWARD_WEIGHT, {}), "reward.goal_radius_m": (MAX_DISTANCE_M, {}),
}


@pytest.mark.parametrize("field, value, accepted, extra", _cases(FINETUNE_BOUNDS))
def test_a_finetune_number_is_taken_up_to_its_bound_and_refused_above_by_name(field, value, accepted, extra):
    overrides = {**extra, field: value}
    if accepted:
        cfg = load_finetune_config("tiny", overrides)
        assert (cfg.reward[field[7:]] if field.startswith("reward.") else getattr(cfg, field)) == value
        return
    name = f"reward term '{field[7:]}'" if field.startswith("reward.") else field
    with pytest.raises(FinetuneConfigError, match=f"fine-tuning config: {name} must"):
        load_finetune_config("tiny", overrides)


@pytest.mark.parametrize("field, value, accepted", [
    ("reward.collision", -MAX_REWARD_WEIGHT, True), ("reward.collision", math.nextafter(-MAX_REWARD_WEIGHT, -math.inf), False),
    ("reward.collision", -1e308, False), ("max_grad_norm", 0.0, False), ("max_grad_norm", -1e308, False), ("clip_epsilon", 0.0, False),
])
def test_a_finetune_number_is_bounded_below_too(field, value, accepted):
    """Reward weights go down to -1000; a gradient clip or a PPO clip of 0 is refused (each zeroes every update)."""
    if accepted:
        assert load_finetune_config("tiny", {field: value}).reward["collision"] == value
        return
    name = f"reward term '{field[7:]}'" if field.startswith("reward.") else field
    with pytest.raises(FinetuneConfigError, match=f"fine-tuning config: {name} must be >"):
        load_finetune_config("tiny", {field: value})


def test_every_shipped_finetune_config_and_the_shipped_policys_config_still_load():
    import json

    from agents.finetune_config import named_configs

    assert {"tiny", "default", "scale", "shield"} <= set(named_configs())
    for name in named_configs():
        load_finetune_config(name)
    saved = json.loads(next((ROOT / "agents" / "checkpoints").glob("*.json")).read_text())["config"]
    load_finetune_config({k: v for k, v in saved.items() if k != "out_dir"})


# --------------------------------------------------------------------------------------------- training
TRAIN_BOUNDS = {
    "grad_clip": (MAX_GRAD_NORM, {}), "time_limit_s": (MAX_TIME_LIMIT_S, {}), "token_noise_topk": (MAX_VOCAB_SIZE, {}),
    "catk_top_k": (MAX_VOCAB_SIZE, {}), "catk_max_drift_m": (MAX_DISTANCE_M, {"catk_top_k": 3}),
    "vocab_scenes": (MAX_SCENE_COUNT, {}), "val_scenes": (MAX_SCENE_COUNT, {}), "cache_scenes": (MAX_CACHE_SCENES, {}),
    "log_every": (MAX_STEPS, {}), "val_every": (MAX_STEPS, {}), "ckpt_every": (MAX_STEPS, {}),
    "road_keep_radius_m": (MAX_DISTANCE_M, {}),
}


@pytest.mark.parametrize("field, value, accepted, extra", _cases(TRAIN_BOUNDS))
def test_a_training_number_is_taken_up_to_its_bound_and_refused_above_by_name(field, value, accepted, extra):
    if accepted:
        assert getattr(load_train_config("smart-1m", {**extra, field: value}), field) == value
        return
    with pytest.raises(TrainConfigError, match=f"training config: {field} must"):
        load_train_config("smart-1m", {**extra, field: value})


@pytest.mark.parametrize("weights, accepted", [([MAX_LOSS_WEIGHT, 1, 0], True), ([_above(MAX_LOSS_WEIGHT), 1, 1], False),
                                               ([1e308, 1, 1], False), ([1, 10**12, 1], False), ([1, 1, math.inf], False)])
def test_speed_trend_weights_are_loss_weights_bounded_by_1000(weights, accepted):
    if accepted:
        assert load_train_config("smart-1m", {"speed_trend_weights": weights}).speed_trend_weights == weights
    else:
        with pytest.raises(TrainConfigError, match="speed_trend_weights must be three numbers in"):
            load_train_config("smart-1m", {"speed_trend_weights": weights})


# ---------------------------------------------------------------------------------------- environments
@pytest.fixture(scope="module")
def env_inputs():
    from smart_marl.embedded import sample_scenarios
    from smart_marl.tokens.vocab_io import load_motion_vocabulary

    vocab = load_motion_vocabulary(ROOT / "smart_marl" / "checkpoints" / "embedded" / "smart-1m-sumo.motion_vocab")
    return sample_scenarios()[:1], vocab


ENV_BOUNDS = {"max_agents": (MAX_AGENT_SLOTS, None), "top_k": (MAX_VOCAB_SIZE, None), "reference_top_k": (MAX_VOCAB_SIZE, None),
              "collision": (MAX_REWARD_WEIGHT, None), "comfort": (MAX_REWARD_WEIGHT, None),
              "goal_radius_m": (MAX_DISTANCE_M, None)}


@pytest.mark.parametrize("arg, value, accepted, _", _cases(ENV_BOUNDS))
def test_an_env_number_is_taken_up_to_its_bound_and_refused_above_by_name(env_inputs, arg, value, accepted, _):
    from envs import smart_traffic_v0
    from envs.errors import EnvConfigError

    scenes, vocab = env_inputs
    reward = arg in ("collision", "comfort", "goal_radius_m")
    kwargs = {"reward": {arg: value}} if reward else {arg: value}
    make = lambda: smart_traffic_v0.parallel_env(scenarios=scenes, prior=None, motion_vocab=vocab, background="log", **kwargs)  # noqa: E731
    if accepted:
        env = make()
        assert (getattr(env.reward_config, arg) if reward else getattr(env, arg)) == value
        return
    with pytest.raises(EnvConfigError, match=f"reward\\['{arg}'\\] must" if reward else f"{arg} must"):
        make()


@pytest.mark.parametrize("arg", ["prior_cache_size", "max_loaded_scenes"])
@pytest.mark.parametrize("value", [MAX_CACHED_SCENES + 1, *HUGE])
def test_the_batched_envs_caches_are_bounded_by_name(env_inputs, arg, value):
    from envs.errors import EnvConfigError
    from envs.smart_traffic_batched_v0 import SmartTrafficBatchedEnv

    scenes, vocab = env_inputs
    with pytest.raises(EnvConfigError, match=f"{arg} must"):
        SmartTrafficBatchedEnv(scenarios=scenes, prior=None, motion_vocab=vocab, background="log", num_scenes=1, **{arg: value})


# -------------------------------------------------------------------------------------------- what-if
WHATIF_BOUNDS = {  # key: (an edit with that key, its bound)
    "decel_mps2": ("{kind: brake, agent: 52, at_s: 1.0, decel_mps2: %s}", 20.0),
    "lateral_m": ("{kind: cut_in, agent: 52, at_s: 1.0, lateral_m: %s}", 20.0),
    "at_s": ("{kind: remove, agents: [52], at_s: %s}", 32.0),
    "lanes": ("{kind: traffic_light, lanes: [%s], state: stop}", 2**62),
}


def _yaml_number(value) -> str:
    """``value`` as YAML reads it back as a number (PyYAML takes 1e+308 for a string: it wants a dot)."""
    if isinstance(value, int) or math.isinf(value):
        return str(value) if isinstance(value, int) else ".inf"
    return repr(value) if "." in repr(value) else repr(value).replace("e", ".0e")


@pytest.mark.parametrize("key, value, accepted", [
    pytest.param(k, v, v == b or (k == "lanes" and v == 10**12), id=f"{k}={v!r}")  # a lane id of 10**12 is an id like any other
    for k, (_, b) in WHATIF_BOUNDS.items() for v in (b, _above(b), *HUGE)])
def test_a_whatif_scripts_numbers_are_taken_up_to_their_bound_and_refused_above_by_name(tmp_path, key, value, accepted):
    from agents.whatif import WhatIfError, load_script

    path = tmp_path / "script.yaml"
    path.write_text(f"edits:\n  - {WHATIF_BOUNDS[key][0] % _yaml_number(value)}\n")
    if accepted:
        assert load_script(path).edits
        return
    with pytest.raises(WhatIfError, match=f"edit 0: .*{key} must"):
        load_script(path)


@pytest.mark.parametrize("arg, value", [("num_rollouts", 1025), ("num_rollouts", 10**12), ("top_k", MAX_VOCAB_SIZE + 1),
                                        ("top_k", 10**12), ("temperature", 1e308), ("temperature", math.inf)])
def test_run_whatif_refuses_a_huge_count_or_temperature_by_name_before_loading_the_prior(arg, value):
    from agents.whatif import EXAMPLES_DIR, WhatIfError, load_script, run_whatif

    script = load_script(EXAMPLES_DIR / "brake_hard.yaml")
    with pytest.raises(WhatIfError, match=f"{arg} must"):
        run_whatif("no-such-prior.json", None, script, **{arg: value})


# ------------------------------------------------------------------------------------------ command line
@pytest.mark.parametrize("kind, bound", [("top_k", MAX_VOCAB_SIZE), ("rollouts", 1024)])
def test_the_command_lines_counts_are_taken_up_to_their_bound_and_refused_above(kind, bound):
    from smart_marl.commands import arguments

    convert = getattr(arguments, kind)
    assert convert(str(bound)) == bound
    for text in (str(bound + 1), str(10**12), "1e308", "inf"):
        with pytest.raises(argparse.ArgumentTypeError):
            convert(text)


@pytest.mark.parametrize("argv, names", [
    (["finetune", "--config", "tiny", "max_grad_norm=1e300"], "fine-tuning config: max_grad_norm must be <= 1000000.0"),
    (["finetune", "--config", "tiny", "reward.collision=-1e308"], "fine-tuning config: reward term 'collision' must be >= -1000"),
    (["finetune", "--evaluate", "embedded", "--episodes", "1025"], "--episodes: must be at most 1024"),
    (["train", "--config", "smart-1m", "grad_clip=1e300", "--print-config"], "training config: grad_clip must be <= 1000000.0"),
    (["eval", "--scenes", "SRC", "--policy", "prior", "--top-k", "8193"], "--top-k: must be at most 8192"),
    (["eval", "--scenes", "SRC", "--policy", "prior", "--out", "OUT", "--chunk-size", "1001"], "--chunk-size: must be at most 1000"),
    (["generate-sumo", "--scenes", str(10**12), "--out", "OUT"], "--scenes: must be at most 1000000"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--speed-limits", "30,50", "--speed-weights", "1e308,1e308"],
     "--speed-weights: every value must be <= 1000000.0"),
], ids=lambda a: " ".join(a) if isinstance(a, list) else None)
def test_a_huge_number_at_the_command_line_exits_2_with_one_line_naming_it(argv, names, tmp_path, capsys):
    argv = [str(tmp_path / a) if a in ("OUT", "SRC") else a for a in argv]
    code, _, err = _run(argv, capsys)
    assert code == 2, err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and errors[0].startswith(f"smart-marl {argv[0]}") and names in errors[0], err
    assert "Traceback" not in err and not (tmp_path / "OUT").exists()
