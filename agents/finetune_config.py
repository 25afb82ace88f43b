"""Fine-tuning stage, the run's configuration: :class:`FinetuneConfig` (every knob of a fine-tuning
run, in one place), what each field takes (:data:`_FINETUNE_RULES`, the project's one set of value
rules) and :func:`load_finetune_config` (a named config, a JSON/TOML file or a dict, plus ``key=value``
overrides). The run itself is :mod:`agents.finetune`."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from envs._arguments import MAX_AGENT_SLOTS, MAX_HORIZON_STEPS, REWARD_RULES, TOP_K_WHY, shield_checks
from envs._reward import RewardConfig
from envs._setup import MOVING_MIN_ROUTE_M
from envs._shield import SHIELD_CHECKS
from envs.errors import EnvConfigError
from envs.smart_traffic_batched_v0 import MAX_CACHED_SCENES
from smart_marl.config_files import (MAX_DISTANCE_M, MAX_GRAD_NORM, MAX_LOSS_WEIGHT, MAX_SCENE_COUNT, MAX_TIME_LIMIT_S,
                                     apply_overrides, check_fields, device_problem, flag, integer, number, one_of, optional,
                                     output_dir_problem, read_config_file, shown, text)
from smart_marl.config_files import seed as seed_rule
from smart_marl.errors import SmartMarlError, UsageError
from smart_marl.model.precision import precision_problem
from smart_marl.model.smart import MAX_VOCAB_SIZE
from smart_marl.rollout import DEFAULT_TOP_K, temperature_rule

from .policy import ACTOR_HEADS

CONFIG_DIR = Path(__file__).resolve().parent / "configs" / "finetune"  # inside the package: a wheel ships them


class FinetuneError(SmartMarlError, ValueError):
    """A fine-tuning run that cannot start: bad config, no usable scene, no prior."""


class FinetuneConfigError(FinetuneError, UsageError):
    """A config key or value that is not a valid FinetuneConfig (the command line exits with 2)."""


@dataclass
class FinetuneConfig:
    """Every knob of a fine-tuning run."""

    # data and prior
    scenes: str | list = "embedded"  # the scene pool: scene-cache folder / file / folder / glob (read_scenarios), "embedded"
    # (the package's sample scenes), or a list of them (their scenes one after the other)
    num_scenes: int | None = 4  # train on the first N scenes of the pool (None: all of them)
    prior: str = "embedded"  # SMART checkpoint (NAME or NAME.json) or "embedded": the prior, and the background's driver
    # environment (envs.smart_traffic_batched_v0)
    num_envs: int = 4  # scenes stepped together (one SMART forward for all of them)
    controlled: str = "moving_vehicles"  # which agents the policy drives: "moving_vehicles" (vehicles whose logged route
    # from the current frame is longer than moving_min_route_m: parked cars are left to the background; none already
    # inside another agent's box at the current frame) or the env's
    # "vehicles", "all", "predict", "sdc"; only the types of the vehicles' vocabulary size (one action space per group)
    moving_min_route_m: float = MOVING_MIN_ROUTE_M
    max_agents: int = 4  # controlled agent slots per scene (the nearest to the SDC); scenes with fewer leave slots empty
    background: str = "prior"  # how the others move: "prior", "log", "constant_velocity"
    horizon_steps: int = 16  # token steps (0.5 s each) per episode
    reward: dict = field(default_factory=dict)  # RewardConfig weights, e.g. {"collision": -1.0}
    terminate_on: tuple = ("collision", "offroad", "goal")
    top_k: int = DEFAULT_TOP_K  # the background's top-k sampling
    temperature: float = 1.0  # the prior's temperature T
    reference_top_k: int | None = 3  # the reference the policy starts from and is pulled toward: softmax(prior_logits / T)
    # on the prior's top-k tokens, renormalised (the prior as it drives; also the policy's action mask); None: full softmax
    shield: tuple = ()  # the env's shield (envs._shield): tokens that run a controlled agent into another ("collision") or a
    # vehicle off the road ("offroad") taken out of the prior's logits, so of the action mask and the reference; in training
    # and evaluation alike (every row but the expert's); () none, ("collision", "offroad") both
    # policy and critic
    init: str | None = None  # a policy checkpoint to start from (NAME, NAME.json or "embedded"): its actor and critic weights;
    # its network (the fields of POLICY_NETWORK_FIELDS, observation and action sizes) and its prior must be this run's
    residual: bool = True  # logits = prior_logits / T + f(obs), f starting at 0
    actor_head: str = "per_token"  # f(obs): "per_token" (one output per token id) or "motion" (token_motion_features)
    hidden: int = 128
    depth: int = 2
    obs_scale: float = 0.1  # the observation (metres, m/s) times this before the MLPs
    critic: str = "mappo"  # "mappo" (centralised) or "ippo" (decentralised)
    # PPO and the prior KL
    beta: float = 0.1  # KL(pi || reference) coefficient
    imitation: float = 0.0  # weight of the cross-entropy to the expert's token within the reference's top-k (the log-following
    # expert restricted to the policy's action space, agents.policy.expert_within_top_k) on the states the policy reaches
    # (DAgger's data): imitation before and beside the reward; 0: none
    gamma: float = 0.99
    lmbda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.0
    critic_coeff: float = 0.5
    normalize_advantage: bool = True
    lr: float = 3e-4
    max_grad_norm: float = 1.0
    frames_per_batch: int = 256  # scene-steps per iteration, all scenes together (a multiple of num_envs)
    iterations: int = 50
    time_limit_s: float = 0.0  # stop after the iteration that passes this many seconds of training (0: no limit)
    ppo_epochs: int = 4
    minibatch_size: int = 64  # scene-steps per minibatch (x max_agents agent-steps)
    # evaluation (held-out scenes, full horizon, no termination) and bookkeeping
    eval_episodes: int = 8  # rollouts (seeds) per held-out scene for every policy (0: no evaluation); WOSAC uses 32
    eval_seed: int = 1000  # evaluation seeds are eval_seed, eval_seed + 1, ...
    eval_scenes: str | list | None = None  # held-out scenes; None: the scenes of `scenes` after those used for fine-tuning
    eval_num_scenes: int = 4  # the first N held-out scenes with a controllable agent
    eval_rules: str = "2024"  # the sim-agents rules of the realism metrics ("2024" or "2025")
    out_dir: str = "runs/finetune"
    checkpoint_every: int = 10  # iterations (the last one is always saved)
    seed: int = 0
    device: str = "cpu"  # the env (prior, state) and the policy
    precision: str = "float32"  # the prior's arithmetic in the env and the evaluation: "float32" or "bfloat16"
    # (smart_marl.model.precision; the policy, its loss and the prior's logits stay float32)
    tensorboard: bool = True
    torch_threads: int = 0  # 0: leave torch's default
    prior_cache_size: int = 1024  # scenes whose freshly started prior state is kept (memory: ~1-2 MB each)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["terminate_on"], d["shield"] = list(self.terminate_on), list(self.shield)
        return d


# ------------------------------------------------------------------------------------- config
def named_configs() -> list[str]:
    return sorted(p.stem for p in CONFIG_DIR.glob("*.json")) if CONFIG_DIR.is_dir() else []


def load_finetune_config(config: str | Mapping[str, Any] | None = None, overrides: Sequence[str] | Mapping[str, Any] = ()) -> FinetuneConfig:
    """A :class:`FinetuneConfig` from a JSON/TOML file, a named config (``configs/finetune/NAME.json``:
    ``tiny``, ``default``, ``scale``; keys starting with ``_`` are comments) or a dict, plus ``key=value``
    overrides (values parsed as JSON when they parse; ``reward.NAME=W`` sets one reward weight)."""
    values: dict[str, Any] = {}
    if isinstance(config, Mapping):
        values.update(config)
    elif config:
        p = Path(config)
        if not p.is_file() and (CONFIG_DIR / f"{config}.json").is_file():
            p = CONFIG_DIR / f"{config}.json"
        if not p.is_file():
            raise FinetuneError(f"unknown fine-tuning config {config!r}: neither a file nor a named config ({', '.join(named_configs())})")
        values.update(read_config_file(p, "fine-tuning", FinetuneError))
    values = {k: v for k, v in values.items() if not k.startswith("_")}  # "_comment" and the like
    values = apply_overrides(values, overrides, FinetuneConfig, "reward", "reward", "fine-tuning", FinetuneConfigError)
    if isinstance(values.get("terminate_on"), (list, tuple)):
        values["terminate_on"] = tuple(values["terminate_on"])
    if "shield" in values:  # the env's own reading of it: true, false, a name or a list of names
        try:
            values["shield"] = shield_checks(values["shield"])
        except EnvConfigError as exc:
            raise FinetuneConfigError(f"fine-tuning config: {exc}") from None
    cfg = FinetuneConfig(**values)
    check_fields(cfg, _FINETUNE_RULES, "fine-tuning", FinetuneConfigError)
    if cfg.critic not in ("mappo", "ippo"):
        raise FinetuneConfigError(f"critic must be 'mappo' or 'ippo', got {cfg.critic!r}")
    if cfg.frames_per_batch < cfg.num_envs:
        raise FinetuneConfigError(f"frames_per_batch ({cfg.frames_per_batch}) must be at least num_envs ({cfg.num_envs})")
    if cfg.frames_per_batch < cfg.minibatch_size:
        raise FinetuneConfigError(f"minibatch_size ({cfg.minibatch_size}) must be in 1..frames_per_batch ({cfg.frames_per_batch})")
    try:
        RewardConfig.from_any(cfg.reward or None)
    except SmartMarlError as exc:
        raise FinetuneConfigError(str(exc)) from exc
    return cfg


def _scenes_rule(value) -> str | None:
    if isinstance(value, str) or (isinstance(value, list) and value and all(isinstance(v, str) for v in value)):
        return None
    return f"must be a path, a list of paths or 'embedded', got {value!r}"


def _reward_rule(value) -> str | None:
    """Reward weights by term: each within the env's bounds (:data:`envs._arguments.REWARD_RULES`); unknown terms are
    named by :meth:`envs._reward.RewardConfig.from_any`."""
    if not isinstance(value, dict):
        return f"must map reward terms to finite weights, got {shown(value)}"
    return next((f"term {k!r} {problem}" for k, w in value.items() if (problem := REWARD_RULES.get(k, number())(w))), None)


MAX_EVAL_EPISODES = 1024
"""The most evaluation rollouts (seeds) per held-out scene (WOSAC uses 32)."""
MAX_EVAL_SCENES = 100_000
"""The most held-out scenes an evaluation takes (``eval_num_scenes``): all of them are read and held at once
(a scene's arrays, ~0.3 MB: ~30 GB) and each is rolled out ``eval_episodes`` times for each policy; twice WOSAC's
validation split (44,097 scenes)."""
MAX_ITERATIONS = 10**6
"""The most PPO iterations of a run (a million: four months at the shield config's 11 s an iteration on the CPU), and
so the longest ``checkpoint_every`` (a longer period saves only the last policy)."""
MAX_LR = 1.0
"""The largest learning rate: Adam moves every weight by about ``lr`` each step, so a rate above 1 throws
the weights (which start near 0.1) off by more than their size at every step and training diverges."""
MAX_CLIP_EPSILON = 1.0
"""The widest PPO clip: TorchRL clips the log of the policy ratio at ``log(1 - clip_epsilon)``, which is NaN
above 1 (and with it every loss); 1 leaves the ratio unclipped below."""
MAX_OBS_SCALE = 1e3
"""The largest observation scale, 10,000x the default 0.1: the observation (metres and m/s, up to a few hundred)
enters the MLPs at 1e5 and beyond, where one Adam step (every weight moved by about ``lr``) moves a hidden unit by
tens: the policy's logits jump by more than the prior's whole range at every step."""
POLICY_NETWORK_FIELDS = ("hidden", "depth", "residual", "actor_head", "obs_scale", "temperature", "reference_top_k", "max_agents")
"""The FinetuneConfig fields a saved policy's network is built with: fixed by its checkpoint."""


def network_differences(cfg: FinetuneConfig, saved: Mapping[str, Any]) -> list[str]:
    """``"field=value (the checkpoint's: value)"`` for each of :data:`POLICY_NETWORK_FIELDS` where ``cfg`` differs
    from a checkpoint's config ``saved`` (a field it does not hold is not compared)."""
    return [f"{k}={getattr(cfg, k)!r} (the checkpoint's: {saved[k]!r})" for k in POLICY_NETWORK_FIELDS
            if k in saved and saved[k] != getattr(cfg, k)]


_LOSS_WEIGHT = number(0.0, MAX_LOSS_WEIGHT, why="1,000x the PPO objective's")
_FINETUNE_RULES = {
    "scenes": _scenes_rule, "num_scenes": optional(integer(1, MAX_SCENE_COUNT, "20x WOMD's training split")), "prior": text,
    "init": optional(text), "num_envs": integer(1, 4096, "scenes in one batch"), "controlled": text,
    "moving_min_route_m": number(0.0, MAX_DISTANCE_M, why="metres, farther than any scene reaches"),
    "max_agents": integer(1, MAX_AGENT_SLOTS, "the batched env's most agent slots"),
    "background": text, "horizon_steps": integer(1, MAX_HORIZON_STEPS, "the env's longest episode"), "reward": _reward_rule,
    "terminate_on": lambda v: None if isinstance(v, tuple) and all(isinstance(e, str) for e in v) else f"must be a list of event names, got {v!r}",
    "top_k": optional(integer(1, MAX_VOCAB_SIZE, TOP_K_WHY)), "temperature": temperature_rule,
    "reference_top_k": optional(integer(1, MAX_VOCAB_SIZE, TOP_K_WHY)), "residual": flag,
    "shield": lambda v: None if isinstance(v, tuple) and set(v) <= set(SHIELD_CHECKS) else f"must be a list of {list(SHIELD_CHECKS)}, got {v!r}",
    "actor_head": one_of(*ACTOR_HEADS), "hidden": integer(1, 4096, "16x the default"), "depth": integer(1, 16, "8x the default"),
    "obs_scale": number(0.0, MAX_OBS_SCALE, low_open=True, why="10,000x the default"), "critic": text, "beta": _LOSS_WEIGHT,
    "imitation": _LOSS_WEIGHT, "gamma": number(0.0, 1.0), "lmbda": number(0.0, 1.0),
    "clip_epsilon": number(0.0, MAX_CLIP_EPSILON, low_open=True, why="log(1 - clip_epsilon) is NaN above"),
    "entropy_coeff": _LOSS_WEIGHT, "critic_coeff": _LOSS_WEIGHT, "normalize_advantage": flag,
    "lr": number(0.0, MAX_LR, low_open=True, why="Adam moves every weight by about lr a step"),
    # max_grad_norm > 0: clip_grad_norm_ at 0 scales every gradient to 0, a run that silently never learns
    "max_grad_norm": number(0.0, MAX_GRAD_NORM, low_open=True, why="a larger clip never clips"),
    "frames_per_batch": integer(1, 10**6, "a million env steps per iteration"),
    "iterations": integer(1, MAX_ITERATIONS, "a million iterations"),
    "time_limit_s": number(0.0, MAX_TIME_LIMIT_S, why="30 days; 0: no limit"),
    "ppo_epochs": integer(1, 1000, "passes over one batch"), "minibatch_size": integer(1, 10**6, "frames_per_batch's largest"),
    "eval_episodes": integer(0, MAX_EVAL_EPISODES, "32x WOSAC's 32"), "eval_seed": seed_rule, "eval_scenes": lambda v: None if v is None else _scenes_rule(v),
    "eval_num_scenes": integer(1, MAX_EVAL_SCENES, "scenes held at once"),
    "eval_rules": lambda v: None if v in ("2024", "2025") else f"must be '2024' or '2025', got {v!r}",
    "out_dir": lambda v: text(v) or output_dir_problem(v), "checkpoint_every": integer(1, MAX_ITERATIONS, "the most iterations"),
    "seed": seed_rule, "device": device_problem, "tensorboard": flag, "torch_threads": integer(0, 1024, "threads of one process"),
    "prior_cache_size": integer(1, MAX_CACHED_SCENES, "~1-2 MB a scene: ~130 GB"), "precision": precision_problem,
}
"""What each FinetuneConfig field takes (the env checks ``controlled``, ``background`` and the reward terms by name); each
number bounded on both sides (issue 56), its upper bound named with what breaks above it."""


__all__ = ["CONFIG_DIR", "FinetuneConfig", "FinetuneConfigError", "FinetuneError", "MAX_CLIP_EPSILON", "MAX_EVAL_EPISODES",
           "MAX_EVAL_SCENES", "MAX_ITERATIONS", "MAX_LR", "MAX_OBS_SCALE", "POLICY_NETWORK_FIELDS",
           "network_differences",
           "load_finetune_config", "named_configs"]
