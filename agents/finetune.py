"""Fine-tuning stage: KL-regularised multi-agent PPO (MAPPO / IPPO) of controlled agents against
the SMART prior, with TorchRL. One entry point, :func:`finetune`, read from top to bottom
(CleanRL style); every knob is a field of :class:`FinetuneConfig`.

What comes in: scenes (any path ``read_scenarios`` reads), a SMART checkpoint (the prior, which
also drives the background agents) and the config. What goes out, in ``out_dir``:
``finetune.csv`` (one row per iteration), ``tensorboard/``, ``config.json``, and policy
checkpoints ``checkpoints/policy_NNNN.{safetensors,json}`` (+ ``policy_last``), which
:func:`load_policy` and :mod:`agents.evaluate` read.

The pipeline:

1. env: one ``envs.smart_traffic_v0`` per scene (``observation="dict"``, so the prior's logits
   ride in the observation), each wrapped by TorchRL's ``PettingZooWrapper`` with every agent in
   one group ``"agents"`` (keys ``("agents", "action")``, ``("agents", "observation",
   "observation")``, ``("agents", "observation", "prior_logits")``, ``("agents", "mask")``...);
   a wrapper fixes its agent set, so there is one per scene, all with ``max_agents`` controlled
   agents, run side by side by a ``SerialEnv``;
2. actor: logits over the motion vocabulary, ``prior_logits / T + f(obs)`` (``residual=True``,
   ``f`` a shared-parameter ``MultiAgentMLP`` whose last layer starts at 0, so training starts
   exactly at the reference) or ``f(obs)`` alone, restricted to the reference's support (the
   prior's top ``reference_top_k`` tokens, the env's ``action_mask``); a ``ProbabilisticActor``
   with a Categorical. ``actor_head="per_token"``: ``f`` has one output per token id;
   ``"motion"``: ``f`` weighs a few features of each token's motion (where it ends after 0.5 s:
   forward, left, turn, and their squares; :func:`token_motion_features`), so what is learnt about
   one token carries over to tokens that move alike;
3. critic: a ``MultiAgentMLP`` value, centralised (``critic="mappo"``: each agent's value sees
   every agent's observation) or decentralised (``"ippo"``);
4. loss: :class:`agents.kl_ppo.PriorKLPPOLoss` = TorchRL's ``ClipPPOLoss`` + ``beta *
   KL(pi || reference)``, agents that are done masked out of every term; GAE advantages. The
   reference is the prior as it drives: ``softmax(prior_logits / T)`` on its top
   ``reference_top_k`` tokens, renormalised (``reference_top_k=None``: the full softmax);
5. a TorchRL ``Collector``; PPO epochs over shuffled minibatches; logging
   (:class:`smart_marl.runlog.RunLog`); checkpoints;
6. evaluation on held-out scenes (not used for fine-tuning), as the literature does it:
   :func:`evaluate_finetuned` runs the expert (log-following), the prior top-k, the prior's full
   softmax and the fine-tuned policy for the full horizon without termination on the same scenes
   and seeds and scores rates, progress, KL and the controlled agents' realism
   (:mod:`agents.evaluate`).

Logged per iteration (CSV and TensorBoard, names say what they are): ``return_per_agent_episode``,
``goal_rate``, ``collision_rate``, ``offroad_rate`` (per agent-episode that ended in the batch),
``kl_to_prior`` (mean per agent-step of the batch, the exact categorical KL to the reference), the
PPO losses, ``entropy`` and ``frames``. Training episodes remove an agent at its first collision,
offroad or goal (``terminate_on``); the evaluation does not, so that every controlled agent drives
the 8 s the realism metrics score.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import PettingZooWrapper, SerialEnv
from torchrl.envs.utils import MarlGroupMapType
from torchrl.modules import MultiAgentMLP, ProbabilisticActor
from torchrl.objectives import ValueEstimators

from envs import smart_traffic_v0
from smart_marl.config_files import (apply_overrides, check_fields, device_problem, flag, integer, number, optional,
                                     output_dir_problem, read_config_file, text)
from smart_marl.embedded import SAMPLES_DIR
from smart_marl.errors import SmartMarlError, UsageError
from smart_marl.model.checkpoint import EMBEDDED, CheckpointError
from smart_marl.model.checkpoint import load_prior as load_smart_prior
from smart_marl.readers import read_scenarios
from smart_marl.rollout import DEFAULT_TOP_K, top_k_mask
from smart_marl.runlog import RunLog
from smart_marl.scenario import AgentType

from .evaluate import evaluate_policies
from .kl_ppo import PriorKLPPOLoss
from .prior_policy import PriorPolicy, SampledPolicy, kl_to_prior
from .scripted import LogFollowingPolicy

CONFIG_DIR = Path(__file__).resolve().parent / "configs" / "finetune"  # inside the package: a wheel ships them
GROUP = "agents"
OBS_KEY = (GROUP, "observation", "observation")
PRIOR_KEY = (GROUP, "observation", "prior_logits")
ACTOR_HEADS = ("per_token", "motion")


class FinetuneError(SmartMarlError, ValueError):
    """A fine-tuning run that cannot start: bad config, no usable scene, no prior."""


class FinetuneConfigError(FinetuneError, UsageError):
    """A config key or value that is not a valid FinetuneConfig (the command line exits with 2)."""


@dataclass
class FinetuneConfig:
    """Every knob of a fine-tuning run."""

    # data and prior
    scenes: str | list = "embedded"  # scene file / folder / glob (read_scenarios), a list of them, or "embedded" (the
    # package's sample scenes)
    num_scenes: int = 4  # the first N scenes with max_agents controllable agents
    prior: str = "embedded"  # SMART checkpoint (NAME or NAME.json) or "embedded": the prior, and the background's driver
    # environment (envs.smart_traffic_v0)
    controlled: str = "moving_vehicles"  # which agents the policy drives: "moving_vehicles" (vehicles whose logged route
    # from the current frame is longer than moving_min_route_m: parked cars are left to the background) or the env's
    # "vehicles", "all", "predict", "sdc"
    moving_min_route_m: float = 10.0
    max_agents: int = 4  # controlled agents per scene (the nearest to the SDC); scenes with fewer are skipped
    background: str = "prior"  # how the others move: "prior", "log", "constant_velocity"
    horizon_steps: int = 16  # token steps (0.5 s each) per episode
    reward: dict = field(default_factory=dict)  # RewardConfig weights, e.g. {"collision": -1.0}
    terminate_on: tuple = ("collision", "offroad", "goal")
    top_k: int = DEFAULT_TOP_K  # the background's top-k sampling
    temperature: float = 1.0  # the prior's temperature T
    reference_top_k: int | None = 3  # the reference the policy starts from and is pulled toward: softmax(prior_logits / T)
    # on the prior's top-k tokens, renormalised (the prior as it drives; also the policy's action mask); None: full softmax.
    # 3: with the embedded prior, its top 3 drove held-out scenes safer, nearer their goals and more realistically than its
    # top 5 or 10 (README, Fine-tuning)
    # policy and critic
    residual: bool = True  # logits = prior_logits / T + f(obs), f starting at 0
    actor_head: str = "per_token"  # f(obs): "per_token" (one output per token id) or "motion" (weights of each token's
    # motion features, token_motion_features: shared by tokens that move alike)
    hidden: int = 128
    depth: int = 2
    obs_scale: float = 0.1  # the observation (metres, m/s) times this before the MLPs
    critic: str = "mappo"  # "mappo" (centralised) or "ippo" (decentralised)
    # PPO and the prior KL
    beta: float = 0.1  # KL(pi || reference) coefficient
    gamma: float = 0.99
    lmbda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.0
    critic_coeff: float = 0.5
    normalize_advantage: bool = True
    lr: float = 3e-4
    max_grad_norm: float = 1.0
    frames_per_batch: int = 256  # env steps per iteration, all scenes together
    iterations: int = 50
    ppo_epochs: int = 4
    minibatch_size: int = 64  # env steps per minibatch (x max_agents agent-steps)
    # evaluation (held-out scenes, full horizon, no termination) and bookkeeping
    eval_episodes: int = 8  # rollouts (seeds) per held-out scene for every policy (0: no evaluation); WOSAC uses 32
    eval_seed: int = 1000  # evaluation seeds are eval_seed, eval_seed + 1, ...
    eval_scenes: str | list | None = None  # held-out scenes; None: the scenes of `scenes` after those used for fine-tuning
    eval_num_scenes: int = 4  # the first N held-out scenes with a controllable agent
    eval_rules: str = "2024"  # the sim-agents rules of the realism metrics ("2024" or "2025")
    out_dir: str = "runs/finetune"
    checkpoint_every: int = 10  # iterations (the last one is always saved)
    seed: int = 0
    device: str = "cpu"
    tensorboard: bool = True
    torch_threads: int = 0  # 0: leave torch's default

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["terminate_on"] = list(self.terminate_on)
        return d


# ------------------------------------------------------------------------------------- config
def named_configs() -> list[str]:
    return sorted(p.stem for p in CONFIG_DIR.glob("*.json")) if CONFIG_DIR.is_dir() else []


def load_finetune_config(config: str | Mapping[str, Any] | None = None, overrides: Sequence[str] | Mapping[str, Any] = ()) -> FinetuneConfig:
    """A :class:`FinetuneConfig` from a JSON/TOML file, a named config (``configs/finetune/NAME.json``:
    ``tiny``, ``default``; keys starting with ``_`` are comments) or a dict, plus ``key=value`` overrides (values parsed as JSON when
    they parse; ``reward.NAME=W`` sets one reward weight)."""
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
    cfg = FinetuneConfig(**values)
    check_fields(cfg, _FINETUNE_RULES, "fine-tuning", FinetuneConfigError)
    if cfg.critic not in ("mappo", "ippo"):
        raise FinetuneConfigError(f"critic must be 'mappo' or 'ippo', got {cfg.critic!r}")
    if cfg.frames_per_batch < cfg.minibatch_size:
        raise FinetuneConfigError(f"minibatch_size ({cfg.minibatch_size}) must be in 1..frames_per_batch ({cfg.frames_per_batch})")
    return cfg


def _scenes_rule(value) -> str | None:
    if isinstance(value, str) or (isinstance(value, list) and value and all(isinstance(v, str) for v in value)):
        return None
    return f"must be a path, a list of paths or 'embedded', got {value!r}"


_FINETUNE_RULES = {
    "scenes": _scenes_rule, "num_scenes": integer(1), "prior": text, "controlled": text, "moving_min_route_m": number(0.0),
    "max_agents": integer(1), "background": text, "horizon_steps": integer(1),
    "reward": lambda v: None if isinstance(v, dict) and all(number()(w) is None for w in v.values())
    else f"must map reward terms to finite weights, got {v!r}",
    "terminate_on": lambda v: None if isinstance(v, tuple) and all(isinstance(e, str) for e in v) else f"must be a list of event names, got {v!r}",
    "top_k": optional(integer(1)), "temperature": number(0.0, low_open=True), "reference_top_k": optional(integer(1)), "residual": flag,
    "actor_head": lambda v: None if v in ACTOR_HEADS else f"must be one of {', '.join(ACTOR_HEADS)}, got {v!r}", "hidden": integer(1), "depth": integer(1),
    "obs_scale": number(0.0, low_open=True), "critic": text, "beta": number(0.0), "gamma": number(0.0, 1.0),
    "lmbda": number(0.0, 1.0), "clip_epsilon": number(0.0, low_open=True), "entropy_coeff": number(0.0),
    "critic_coeff": number(0.0), "normalize_advantage": flag, "lr": number(0.0, low_open=True), "max_grad_norm": number(0.0),
    "frames_per_batch": integer(1), "iterations": integer(1), "ppo_epochs": integer(1), "minibatch_size": integer(1),
    "eval_episodes": integer(0), "eval_seed": integer(), "eval_scenes": lambda v: None if v is None else _scenes_rule(v),
    "eval_num_scenes": integer(1), "eval_rules": lambda v: None if v in ("2024", "2025") else f"must be '2024' or '2025', got {v!r}", "out_dir": lambda v: text(v) or output_dir_problem(v),
    "checkpoint_every": integer(1), "seed": integer(), "device": device_problem, "tensorboard": flag, "torch_threads": integer(0),
}
"""What each FinetuneConfig field takes (the env checks ``controlled``, ``background`` and the reward terms by name)."""


# ---------------------------------------------------------------------------------- the env
def load_prior(path: str):
    """(SMART model in eval mode, motion vocabulary) of the run's prior: a checkpoint or
    ``"embedded"`` (:func:`smart_marl.model.checkpoint.load_prior`), its errors as FinetuneError."""
    if not path:
        raise FinetuneError("prior: no SMART checkpoint given (prior=PATH)")
    try:
        return load_smart_prior(path, "cpu")
    except CheckpointError as exc:
        raise FinetuneError(f"prior: {exc}") from exc


def moving_vehicles(min_route_m: float):
    """A ``controlled`` selection for the env: vehicles present at the current frame whose logged
    position moves more than ``min_route_m`` between the current frame and their last valid frame."""
    def select(sc) -> np.ndarray:
        tr, cf = sc.tracks, sc.current_frame
        last = tr.valid.shape[1] - 1 - np.argmax(tr.valid[:, ::-1], axis=1)  # [N] last valid frame
        route_m = np.linalg.norm(tr.position[np.arange(tr.num_tracks), last, :2] - tr.position[:, cf, :2], axis=1)
        return tr.valid[:, cf] & (tr.types == int(AgentType.VEHICLE)) & (route_m > min_route_m)

    return select


def scene_env(cfg: FinetuneConfig, scenes, model, vocab, render_mode: str | None = None, terminate_on=None):
    """The PettingZoo env of the run's settings over ``scenes`` (a list of Scenario);
    ``terminate_on`` replaces the config's (``()`` for the evaluation)."""
    controlled = moving_vehicles(cfg.moving_min_route_m) if cfg.controlled == "moving_vehicles" else cfg.controlled
    return smart_traffic_v0.parallel_env(
        scenarios=list(scenes), prior=model, motion_vocab=vocab, controlled=controlled, max_agents=cfg.max_agents,
        background=cfg.background, horizon_steps=cfg.horizon_steps, reward=dict(cfg.reward) or None, observation="dict",
        terminate_on=tuple(cfg.terminate_on if terminate_on is None else terminate_on), top_k=cfg.top_k,
        temperature=cfg.temperature, reference_top_k=cfg.reference_top_k, render_mode=render_mode)


def _scene_stream(spec, key: str):
    """Every scene of ``spec`` (a path, a list of them, or "embedded": the package's samples), in order."""
    if not spec:
        raise FinetuneError(f"{key}: no scenes given ({key}=PATH)")
    sources = [spec] if isinstance(spec, str) else list(spec)
    if EMBEDDED in sources:
        files = sorted(str(p) for p in SAMPLES_DIR.glob("*.smsc"))
        if not files:
            raise FinetuneError(f"{key}='embedded': the package ships no sample scenes ({SAMPLES_DIR}); give {key}=PATH")
        i = sources.index(EMBEDDED)
        sources[i : i + 1] = files
    return (sc for src in sources for sc in read_scenarios(src))


def _pick_scenes(cfg: FinetuneConfig, spec, key: str, count: int, model, vocab, exact: bool, exclude: set) -> tuple[list, list]:
    """(the first ``count`` scenes of ``spec`` not in ``exclude`` (ids) whose controlled agents
    share one vocabulary size and number exactly ``max_agents`` (``exact``) or at least one,
    the skipped ones with why)."""
    chosen, skipped = [], []
    for sc in _scene_stream(spec, key):
        if sc.scenario_id in exclude:
            continue
        try:
            env = scene_env(cfg, [sc], None if cfg.background != "prior" else model, vocab)
        except SmartMarlError as exc:
            skipped.append(f"{sc.scenario_id} ({exc})")
            continue
        sizes = {env.action_space(a).n for a in env.possible_agents}
        n = len(env.possible_agents)
        if (n == cfg.max_agents if exact else n >= 1) and len(sizes) == 1:
            chosen.append(sc)
        else:
            skipped.append(f"{sc.scenario_id} ({n} controlled agents)")
        if len(chosen) == count:
            break
    return chosen, skipped


def select_scenes(cfg: FinetuneConfig, model, vocab) -> list:
    """The first ``num_scenes`` scenes of ``cfg.scenes`` with exactly ``max_agents`` controlled
    agents of one vocabulary size (TorchRL stacks the group's agents): the fine-tuning scenes."""
    chosen, skipped = _pick_scenes(cfg, cfg.scenes, "scenes", cfg.num_scenes, model, vocab, True, set())
    if not chosen:
        raise FinetuneError(f"scenes: no scene of {cfg.scenes} has {cfg.max_agents} controllable agents "
                            f"(controlled={cfg.controlled!r}); skipped: {skipped[:5]}")
    return chosen


def held_out_scenes(cfg: FinetuneConfig, model, vocab, training: Sequence) -> list:
    """The evaluation's scenes: the first ``eval_num_scenes`` of ``cfg.eval_scenes`` (default: the
    scenes of ``cfg.scenes`` after the fine-tuning ones) that are not fine-tuning scenes
    (``training``: Scenario objects or ids) and have 1 to ``max_agents`` controlled agents."""
    exclude = {t if isinstance(t, str) else t.scenario_id for t in training}
    spec = cfg.eval_scenes if cfg.eval_scenes else cfg.scenes
    chosen, skipped = _pick_scenes(cfg, spec, "eval_scenes", cfg.eval_num_scenes, model, vocab, False, exclude)
    if not chosen:
        raise FinetuneError(f"eval_scenes: no held-out scene in {spec} (the {len(exclude)} fine-tuning scene(s) excluded) has a "
                            f"controllable agent (controlled={cfg.controlled!r}); give eval_scenes=PATH; skipped: {skipped[:5]}")
    return chosen


def torchrl_env(cfg: FinetuneConfig, scenes, model, vocab):
    """One PettingZooWrapper per scene (group "agents"), side by side in a SerialEnv."""
    def make(sc):
        def fn():
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="PettingZoo in TorchRL is tested")
                return PettingZooWrapper(scene_env(cfg, [sc], model, vocab), use_mask=True, done_on_any=False,
                                         categorical_actions=True, group_map=MarlGroupMapType.ALL_IN_ONE_GROUP)
        return fn

    return SerialEnv(len(scenes), [make(sc) for sc in scenes])


# ------------------------------------------------------------------------- actor and critic
def token_motion_features(vocab, vocab_size: int) -> torch.Tensor:
    """[3, V, 6] features of every token of each type's vocabulary (vehicle, pedestrian, cyclist):
    where the token ends after 0.5 s in its start frame (forward m, left m, turn rad) and their
    squares (a weight on both can favour a band: -a (x - c)^2), each standardised over the type's
    tokens.
    A type whose vocabulary has another size than ``vocab_size`` (the group's action space) gets
    zeros: its agents are not in the group."""
    out = torch.zeros(3, vocab_size, 6)
    for t in range(3):
        tv = vocab[AgentType(t)]
        if tv.size != vocab_size:
            continue
        end = torch.as_tensor(tv.poses[:, -1], dtype=torch.float32)  # (V, 3)
        feat = torch.cat([end, end.square()], -1)
        out[t] = (feat - feat.mean(0)) / feat.std(0).clamp(min=1e-6)
    return out


class PolicyLogits(nn.Module):
    """Logits over the motion vocabulary for every agent of the group: ``prior_logits / T + f(obs)``
    (residual) or ``f(obs)``, ``-inf`` outside the prior's ``top_k`` tokens (the reference's
    support, :func:`smart_marl.rollout.top_k_mask`; None: every token). observation [..., A, O],
    prior_logits [..., A, V] -> [..., A, V].

    ``motion_features`` None: ``f(obs)`` has one output per token. Else ([3, V, P],
    :func:`token_motion_features`): ``f(obs)`` gives P weights and a token's output is their dot
    product with its type's features (the type read from the observation's ``ego_type`` one-hot;
    a padded agent's zeros give 0)."""

    def __init__(self, obs_dim: int, vocab_size: int, n_agents: int, hidden: int, depth: int, residual: bool = True,
                 obs_scale: float = 0.1, temperature: float = 1.0, top_k: int | None = None,
                 motion_features: torch.Tensor | None = None) -> None:
        super().__init__()
        self.residual, self.obs_scale, self.temperature = bool(residual), float(obs_scale), float(temperature)
        self.top_k = None if top_k is None else int(top_k)
        if motion_features is not None:
            if tuple(motion_features.shape[:2]) != (3, vocab_size):
                raise FinetuneError(f"motion_features must be [3, {vocab_size}, P], got {list(motion_features.shape)}")
            self.register_buffer("motion_features", motion_features.float())
            layout = {name: (off, size) for name, off, size in smart_traffic_v0.observation_layout(smart_traffic_v0.ObservationConfig())}
            off, size = layout["ego_type"]
            self.type_slice = slice(off, off + size)
        else:
            self.motion_features = None
        out_dim = vocab_size if motion_features is None else int(motion_features.shape[-1])
        self.f = MultiAgentMLP(obs_dim, out_dim, n_agents, centralized=False, share_params=True, depth=depth,
                               num_cells=hidden, activation_class=nn.Tanh)
        if self.residual:  # start exactly at the prior
            last = max(int(name.split(".")[1]) for name, _ in self.f.named_parameters())
            with torch.no_grad():
                for name, p in self.f.named_parameters():
                    if int(name.split(".")[1]) == last:
                        p.zero_()

    def forward(self, observation: torch.Tensor, prior_logits: torch.Tensor) -> torch.Tensor:
        delta = self.f(observation * self.obs_scale)
        if self.motion_features is not None:  # P weights per agent -> one output per token of its type
            delta = torch.einsum("...ap,...at,tvp->...av", delta, observation[..., self.type_slice], self.motion_features)
        logits = prior_logits / self.temperature + delta if self.residual else delta
        if self.top_k is None:
            return logits
        return logits.masked_fill(~top_k_mask(prior_logits, self.top_k), float("-inf"))


class Critic(nn.Module):
    """State value per agent [..., A, 1]: centralised (MAPPO) or per agent (IPPO)."""

    def __init__(self, obs_dim: int, n_agents: int, hidden: int, depth: int, centralized: bool, obs_scale: float = 0.1) -> None:
        super().__init__()
        self.obs_scale = float(obs_scale)
        self.v = MultiAgentMLP(obs_dim, 1, n_agents, centralized=centralized, share_params=True, depth=depth, num_cells=hidden,
                               activation_class=nn.Tanh)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.v(observation * self.obs_scale)


def build_modules(cfg: FinetuneConfig, obs_dim: int, vocab_size: int, n_agents: int, vocab=None):
    """(logits net, TorchRL ProbabilisticActor, TorchRL critic module). ``vocab``: the prior's motion
    vocabulary, which ``actor_head="motion"`` needs."""
    features = None
    if cfg.actor_head == "motion":
        if vocab is None:
            raise FinetuneConfigError("actor_head='motion' needs the prior's motion vocabulary")
        features = token_motion_features(vocab, vocab_size)
    net = PolicyLogits(obs_dim, vocab_size, n_agents, cfg.hidden, cfg.depth, cfg.residual, cfg.obs_scale, cfg.temperature,
                       cfg.reference_top_k, features)
    actor = ProbabilisticActor(
        TensorDictModule(net, in_keys=[OBS_KEY, PRIOR_KEY], out_keys=[(GROUP, "logits")]),
        in_keys={"logits": (GROUP, "logits")}, out_keys=[(GROUP, "action")], distribution_class=torch.distributions.Categorical,
        return_log_prob=True, log_prob_key=(GROUP, "action_log_prob"))
    critic_net = Critic(obs_dim, n_agents, cfg.hidden, cfg.depth, centralized=cfg.critic == "mappo", obs_scale=cfg.obs_scale)
    critic = TensorDictModule(critic_net, in_keys=[OBS_KEY], out_keys=[(GROUP, "state_value")])
    return net, actor, critic


# ------------------------------------------------------------------------------ checkpoints
def save_policy(path: Path, cfg: FinetuneConfig, net: PolicyLogits, critic: nn.Module, dims: dict, iteration: int,
                metrics: dict) -> Path:
    """``path.safetensors`` (actor and critic weights) + ``path.json`` (config, sizes, step, metrics)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = {f"actor.{k}": v.detach().contiguous() for k, v in net.state_dict().items()}
    tensors.update({f"critic.{k}": v.detach().contiguous() for k, v in critic.state_dict().items()})
    tmp = path.with_name(path.name + ".safetensors.tmp")
    save_file(tensors, str(tmp))
    tmp.replace(path.with_name(path.name + ".safetensors"))
    meta = {"format": "smart-marl-policy", "version": 1, "config": cfg.to_dict(), **dims, "iteration": iteration,
            "metrics": metrics}
    jtmp = path.with_name(path.name + ".json.tmp")
    jtmp.write_text(json.dumps(meta, indent=1, default=float))
    jtmp.replace(path.with_name(path.name + ".json"))
    return path.with_name(path.name + ".json")


def load_policy(path: str | Path) -> tuple[FinetuneConfig, PolicyLogits, dict]:
    """(config, actor logits net with its weights, meta) of a policy checkpoint (NAME or NAME.json)."""
    p = Path(path)
    stem = p.with_suffix("") if p.suffix in (".json", ".safetensors") else p
    jpath, wpath = stem.with_name(stem.name + ".json"), stem.with_name(stem.name + ".safetensors")
    if not jpath.is_file() or not wpath.is_file():
        raise FinetuneError(f"{path}: not a policy checkpoint (needs {jpath.name} and {wpath.name})")
    meta = json.loads(jpath.read_text())
    if meta.get("format") != "smart-marl-policy":
        raise FinetuneError(f"{jpath}: not a smart-marl policy checkpoint (format {meta.get('format')!r})")
    config = {k: v for k, v in meta["config"].items() if k in {f.name for f in dataclasses.fields(FinetuneConfig)}}
    config.setdefault("reference_top_k", None)  # policies saved before the top-k reference were trained on the full softmax
    cfg = load_finetune_config(config)
    weights = load_file(str(wpath))
    features = weights.get("actor.motion_features")  # saved with the weights (a buffer): no vocabulary needed here
    if (features is not None) != (cfg.actor_head == "motion"):
        raise FinetuneError(f"{wpath}: actor_head {cfg.actor_head!r} does not match the saved weights")
    net = PolicyLogits(meta["obs_dim"], meta["vocab_size"], meta["n_agents"], cfg.hidden, cfg.depth, cfg.residual, cfg.obs_scale,
                       cfg.temperature, cfg.reference_top_k, None if features is None else torch.zeros_like(features))
    net.load_state_dict({k[len("actor."):]: v for k, v in weights.items() if k.startswith("actor.")})
    return cfg, net.eval(), meta


class FinetunedPolicy(SampledPolicy):
    """A fine-tuned actor acting directly on the PettingZoo env (dict observations), with the same
    calling convention and sampler as :class:`agents.prior_policy.PriorPolicy` (sampled with the
    reference's top-k, so that at its start it draws exactly what the prior top-k draws)."""

    name = "fine-tuned"

    def __init__(self, net: PolicyLogits, seed: int = 0) -> None:
        super().__init__(seed)
        self.net = net.eval()
        self.top_k = net.top_k

    @torch.no_grad()
    def logits(self, agents: list[str], observations: Mapping, infos: Mapping) -> torch.Tensor:
        """[A, V] logits of the live ``agents``. The group's network has one slot per agent it was
        trained with; its parameters are shared and each agent's output depends on its own
        observation only, so the live agents fill the first slots and the rest are zeros."""
        n = self.net.f.n_agents
        if len(agents) > n:
            raise FinetuneError(f"the policy was trained for {n} agents per scene, got {len(agents)}")
        obs = np.zeros((n, observations[agents[0]]["observation"].shape[-1]), np.float32)
        prior = np.zeros((n, observations[agents[0]]["prior_logits"].shape[-1]), np.float32)
        for i, a in enumerate(agents):
            obs[i] = observations[a]["observation"]
            prior[i] = observations[a]["prior_logits"]
        dev = next(self.net.parameters()).device
        return self.net(torch.from_numpy(obs).to(dev), torch.from_numpy(prior).to(dev))[: len(agents)].cpu()

    def log_probs(self, agents: list[str], observations: Mapping, infos: Mapping) -> torch.Tensor:
        return torch.log_softmax(self.logits(agents, observations, infos), -1)


# ---------------------------------------------------------------------------------- logging
COLUMNS = ["iteration", "frames", "seconds", "return_per_agent_episode", "goal_rate", "collision_rate", "offroad_rate",
           "kl_to_prior", "agent_episodes", "loss_objective", "loss_critic", "loss_entropy", "loss_prior_kl", "entropy",
           "clip_fraction"]


def batch_stats(batch, temperature: float = 1.0, reference_top_k: int | None = None) -> dict[str, float]:
    """Episode statistics of one collected batch [envs, T] (group [envs, T, A]): per agent-episode
    that ended in the batch, its return (the part of it inside the batch), goal / collision /
    offroad rates; and the mean KL(pi || reference) per agent-step that acted."""
    acted = batch[GROUP, "mask"]  # [E, T, A] agents that took this step's action
    nxt = batch["next", GROUP]
    ended = acted & nxt["done"].squeeze(-1)
    n = int(ended.sum())
    reward = torch.where(acted, nxt["reward"].squeeze(-1), torch.zeros(()))
    info = nxt["info"]
    prior = batch[PRIOR_KEY]
    kl = kl_to_prior(torch.log_softmax(batch[GROUP, "logits"], -1), prior, temperature, reference_top_k)
    valid = acted & prior.ne(0).any(-1)
    den = max(n, 1)
    return {
        "agent_episodes": n,
        "return_per_agent_episode": float(reward.sum()) / den,
        "goal_rate": float((info["goal_reached"].bool() & acted).sum()) / den,
        "collision_rate": float((info["collision"].bool() & acted).sum()) / den,
        "offroad_rate": float((info["offroad"].bool() & acted).sum()) / den,
        "kl_to_prior": float(torch.where(valid, kl, torch.zeros(())).sum() / valid.sum().clamp_min(1)),
    }


# ---------------------------------------------------------------------------------- the run
@dataclass
class FinetuneResult:
    out_dir: Path
    checkpoint: Path
    history: list[dict]
    evaluation: dict | None
    scene_ids: list[str]


def finetune(cfg: FinetuneConfig, on_iteration=None) -> FinetuneResult:
    """Run the whole pipeline (module docstring); ``on_iteration(row)`` is called after each
    iteration's log row. With ``eval_episodes > 0`` the fine-tuned policy is evaluated on held-out
    scenes at the end, next to the expert and the prior (:func:`evaluate_finetuned`)."""
    with warnings.catch_warnings():
        # the advantage is normalised over agents and steps together, on purpose
        warnings.filterwarnings("ignore", message="You requested advantage normalization")
        warnings.filterwarnings("ignore", message="PettingZoo in TorchRL is tested")
        return _finetune(cfg, on_iteration)


def _finetune(cfg: FinetuneConfig, on_iteration=None) -> FinetuneResult:
    if cfg.torch_threads > 0:
        torch.set_num_threads(cfg.torch_threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    device = torch.device(cfg.device)
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))

    # 1. env
    model, vocab = load_prior(cfg.prior)
    scenes = select_scenes(cfg, model, vocab)
    env = torchrl_env(cfg, scenes, model, vocab)
    env.set_seed(cfg.seed)
    obs_dim = int(env.observation_spec[OBS_KEY].shape[-1])
    vocab_size = int(env.observation_spec[PRIOR_KEY].shape[-1])
    n_agents = int(env.observation_spec[OBS_KEY].shape[-2])
    dims = {"obs_dim": obs_dim, "vocab_size": vocab_size, "n_agents": n_agents}

    # 2-3. actor and critic
    net, actor, critic = build_modules(cfg, obs_dim, vocab_size, n_agents, vocab)
    actor, critic = actor.to(device), critic.to(device)

    # 4. loss: clipped PPO + beta * KL(pi || reference), GAE
    loss = PriorKLPPOLoss(actor, critic, beta=cfg.beta, prior_logits_key=PRIOR_KEY, agent_mask_key=(GROUP, "mask"),
                          prior_temperature=cfg.temperature, reference_top_k=cfg.reference_top_k, clip_epsilon=cfg.clip_epsilon, entropy_bonus=cfg.entropy_coeff > 0,
                          entropy_coeff=cfg.entropy_coeff, critic_coeff=cfg.critic_coeff, normalize_advantage=cfg.normalize_advantage)
    loss.set_keys(reward=(GROUP, "reward"), action=(GROUP, "action"), sample_log_prob=(GROUP, "action_log_prob"),
                  value=(GROUP, "state_value"), done=(GROUP, "done"), terminated=(GROUP, "terminated"),
                  advantage=(GROUP, "advantage"), value_target=(GROUP, "value_target"))
    loss.make_value_estimator(ValueEstimators.GAE, gamma=cfg.gamma, lmbda=cfg.lmbda)
    optimizer = torch.optim.Adam(loss.parameters(), lr=cfg.lr)

    # 5. collector, PPO epochs, logging, checkpoints
    frames_per_batch = max(len(scenes), cfg.frames_per_batch // len(scenes) * len(scenes))
    collector = Collector(env, actor, frames_per_batch=frames_per_batch, total_frames=frames_per_batch * cfg.iterations,
                          policy_device=device, env_device="cpu", storing_device=device,  # the env steps numpy on the CPU
                          auto_register_policy_transforms=False)  # a feed-forward policy: no InitTracker
    log = RunLog(out_dir, {"finetune": COLUMNS}, "iteration", tensorboard=cfg.tensorboard)
    history: list[dict] = []
    ckpt_dir = out_dir / "checkpoints"
    start = time.perf_counter()
    frames = 0
    last_ckpt = None
    mb_size = max(1, cfg.minibatch_size)
    for it, batch in enumerate(collector, start=1):
        frames += batch.numel()
        stats = batch_stats(batch, cfg.temperature, cfg.reference_top_k)
        with torch.no_grad():
            loss.value_estimator(batch, params=loss.critic_network_params, target_params=loss.target_critic_network_params)
        data = batch.reshape(-1)
        sums: dict[str, float] = {}
        steps = 0
        for _ in range(cfg.ppo_epochs):
            perm = torch.randperm(data.shape[0])
            for i in range(0, data.shape[0], mb_size):
                out = loss(data[perm[i : i + mb_size]].to(device))
                total = out["loss_objective"] + out["loss_critic"] + out["loss_prior_kl"]
                if "loss_entropy" in out.keys():
                    total = total + out["loss_entropy"]
                optimizer.zero_grad()
                total.backward()
                torch.nn.utils.clip_grad_norm_(loss.parameters(), cfg.max_grad_norm)
                optimizer.step()
                steps += 1
                for k in ("loss_objective", "loss_critic", "loss_entropy", "loss_prior_kl", "entropy", "clip_fraction"):
                    if k in out.keys():
                        sums[k] = sums.get(k, 0.0) + float(out[k].detach())
        collector.update_policy_weights_()
        row = {"iteration": it, "frames": frames, "seconds": time.perf_counter() - start, **stats,
               **{k: v / max(steps, 1) for k, v in sums.items()}}
        log.write("finetune", row)
        history.append(row)
        if on_iteration is not None:
            on_iteration(row)
        if it % max(cfg.checkpoint_every, 1) == 0 or it == cfg.iterations:
            last_ckpt = save_policy(ckpt_dir / f"policy_{it:04d}", cfg, net, critic.module, dims, it, stats)
    collector.shutdown()
    log.close()
    if last_ckpt is None:
        raise FinetuneError("the run collected no batch (iterations=0?)")
    final = save_policy(ckpt_dir / "policy_last", cfg, net, critic.module, dims, len(history), history[-1])
    evaluation = None
    if cfg.eval_episodes > 0:
        evaluation = evaluate_finetuned(cfg, net, training=scenes, model=model, vocab=vocab)
        (out_dir / "evaluation.json").write_text(json.dumps(evaluation, indent=1, default=float))
    return FinetuneResult(out_dir, final, history, evaluation, [sc.scenario_id for sc in scenes])


# ------------------------------------------------------------------------------- evaluation
def evaluation_policies(cfg: FinetuneConfig, env, net: PolicyLogits | None) -> dict[str, SampledPolicy]:
    """The evaluation's rows: the expert (log-following), the prior at the reference's top-k (and at
    the background's, when it differs), the prior's full softmax and, with ``net``, the fine-tuned
    policy."""
    policies = {LogFollowingPolicy.name: LogFollowingPolicy(env)}
    for k in dict.fromkeys((cfg.reference_top_k, cfg.top_k, None)):
        p = PriorPolicy(top_k=k, temperature=cfg.temperature)
        policies[p.name] = p
    if net is not None:
        policies[FinetunedPolicy.name] = FinetunedPolicy(net)
    return policies


def evaluate_finetuned(cfg: FinetuneConfig, net: PolicyLogits | None, training=None, model=None, vocab=None,
                       episodes: int | None = None, seed: int | None = None, baselines: bool = True) -> dict:
    """The expert, the prior top-k, the prior's full softmax and the fine-tuned actor ``net`` on the
    held-out scenes (:func:`held_out_scenes`; ``training``: the fine-tuning scenes, default those of
    the config) with the same seeds ``eval_seed ..`` (``episodes`` of them), the full horizon and no
    termination (:func:`agents.evaluate.evaluate_policies`, which says what every row holds).
    ``baselines=False`` runs the fine-tuned policy alone (the baselines do not depend on beta)."""
    if model is None or vocab is None:
        model, vocab = load_prior(cfg.prior)
    if training is None:
        training = select_scenes(cfg, model, vocab)
    scenes = held_out_scenes(cfg, model, vocab, training)
    episodes = cfg.eval_episodes if episodes is None else int(episodes)
    seed0 = cfg.eval_seed if seed is None else int(seed)
    seeds = list(range(seed0, seed0 + max(episodes, 1)))
    env = scene_env(cfg, scenes, model, vocab, terminate_on=())
    policies = evaluation_policies(cfg, env, net)
    if not baselines:
        policies = {FinetunedPolicy.name: policies[FinetunedPolicy.name]}
    result = evaluate_policies(env, policies, list(range(len(scenes))), seeds, rules=cfg.eval_rules)
    result["training_scenes"] = [t if isinstance(t, str) else t.scenario_id for t in training]
    return result


def evaluate_checkpoint(path, overrides: Sequence[str] = (), episodes: int | None = None, seed: int | None = None) -> dict:
    """:func:`evaluate_finetuned` for a policy checkpoint, with its run's config (``key=value``
    overrides, e.g. ``eval_scenes=OTHER`` to evaluate on other held-out scenes)."""
    cfg, net, meta = load_policy(path)
    if overrides:
        cfg = load_finetune_config(cfg.to_dict(), overrides)
    result = evaluate_finetuned(cfg, net, episodes=episodes, seed=seed)
    result["checkpoint"] = str(path)
    result["iteration"] = meta.get("iteration")
    return result
