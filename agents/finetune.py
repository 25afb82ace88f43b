"""Fine-tuning stage: KL-regularised multi-agent PPO (MAPPO / IPPO) of controlled agents against
the SMART prior, with TorchRL, on many scenes at once. One entry point, :func:`finetune`, read from
top to bottom (CleanRL style); every knob is a field of :class:`FinetuneConfig`.

What comes in: scenes (a scene pool: scene-cache folders of any size, any path ``read_scenarios``
reads, ``"embedded"``, or a list of them), a SMART checkpoint (the prior, which also drives the
background agents) and the config. What goes out, in ``out_dir``: ``finetune.csv`` (one row per
iteration), ``tensorboard/``, ``config.json``, policy checkpoints
``checkpoints/policy_NNNN.{safetensors,json}`` (+ ``policy_last``), which :func:`load_policy` reads, and
the state a run started again in the same ``out_dir`` resumes from (``checkpoints/resume.*``).

The pipeline:

1. env: the batched TorchRL environment :mod:`envs.smart_traffic_batched_v0` over the training
   scenes (the first ``num_scenes`` of ``scenes``), ``num_envs`` scenes stepped together, one agent
   group ``"agents"`` of ``max_agents`` slots with a mask; a scene that finishes is refilled in
   place with the pool's next one (random order, a new permutation per pass), so every batch is
   full and the policy sees scene after scene; every iteration starts from a full reset, so that a
   run resumes exactly (:mod:`agents.finetune_state`);
2. actor and critic (:mod:`agents.policy`): logits ``prior_logits / T + f(obs)`` (residual, starting
   exactly at the reference) restricted to the reference's support, a ``ProbabilisticActor`` with a
   Categorical; a ``MultiAgentMLP`` value, centralised (``critic="mappo"``) or per agent (``"ippo"``);
3. loss: :class:`agents.kl_ppo.PriorKLPPOLoss` = TorchRL's ``ClipPPOLoss`` + ``beta *
   KL(pi || reference)``, agents that are done masked out of every term; GAE advantages. The
   reference is the prior as it drives: ``softmax(prior_logits / T)`` on its top
   ``reference_top_k`` tokens (the env stores the prior's logits with every step, so the KL is
   computed from the batch, never by re-running the model);
4. a TorchRL ``Collector``; PPO epochs over shuffled minibatches; logging
   (:class:`smart_marl.runlog.RunLog`); checkpoints. Under ``torchrun --nproc_per_node=N`` every
   process collects on its own env (its own scene order) and the gradients are averaged over the
   processes (``torch.distributed``: all-reduce), so the learners stay identical; process 0 logs,
   saves and evaluates;
5. evaluation on held-out scenes (:func:`evaluate_finetuned`, :mod:`agents.evaluate`): the expert
   (log-following), the prior top-k, the prior's full softmax and the fine-tuned policy on the same
   scenes and seeds, full horizon, no termination, many scenes at once; rates, progress, KL, who hit
   whom, and the controlled agents' realism. Rows compare in one environment: with the shield, the
   table leads with the shielded prior at the policy's top-k and at top-3, and ends with those two
   with the shield off, labelled as another environment.

Logged per iteration (CSV and TensorBoard, names say what they are): ``return_per_agent_episode``,
``goal_rate``, ``collision_rate``, ``offroad_rate`` (per agent-episode that ended in the batch),
``kl_to_prior`` (mean per agent-step of the batch, the exact categorical KL to the reference), the
PPO losses, ``entropy``, ``frames`` and ``scenes_seen`` (distinct training scenes played so far).
Training episodes remove an agent at its first collision, offroad or goal (``terminate_on``); the
evaluation does not, so that every controlled agent drives the 8 s the realism metrics score.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.data import Categorical
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import ValueEstimators

from envs._core import CoreScene, TrafficCore
from envs._pool import ScenePool
from envs._reward import RewardConfig
from envs._setup import moving_vehicles_mask, select_controlled
from envs.smart_traffic_batched_v0 import GROUP, SmartTrafficBatchedEnv
from smart_marl.config_files import check_value, integer, optional
from smart_marl.config_files import seed as seed_rule
from smart_marl.errors import SmartMarlError
from smart_marl.model.checkpoint import CheckpointError
from smart_marl.model.checkpoint import load_prior as load_smart_prior
from smart_marl.runlog import RunLog
from smart_marl.scenario import AgentType
from smart_marl.train import init_distributed, leave_distributed, resolve_device

from .evaluate import evaluate_policies, same_environment_policies
from .finetune_state import Progress, episode_seed, load_run_state, logged_rows, save_run_state
from .finetune_config import (MAX_EVAL_EPISODES, FinetuneConfig, FinetuneConfigError, FinetuneError, load_finetune_config,
                              network_differences)
from .kl_ppo import PriorKLPPOLoss
from .policy import (Critic, ExpertTensorPolicy, FinetunedTensorPolicy, PolicyError, PolicyLogits, PriorTensorPolicy,
                     TensorPolicy, actor_from_weights, check_policy_tensors, expert_within_top_k, policy_files,
                     policy_tensor_shapes, prior_digest, read_policy, save_policy, token_motion_features)
from .prior_policy import kl_to_prior

OBS_KEY = (GROUP, "observation", "observation")
PRIOR_KEY = (GROUP, "observation", "prior_logits")
EXPERT_KEY = (GROUP, "expert_action")


# ------------------------------------------------------------------------------ scenes, env
def load_prior(path: str, device="cpu"):
    """(SMART model in eval mode, motion vocabulary) of the run's prior: a checkpoint or
    ``"embedded"`` (:func:`smart_marl.model.checkpoint.load_prior`), its errors as FinetuneError."""
    if not path:
        raise FinetuneError("prior: no SMART checkpoint given (prior=PATH)")
    try:
        return load_smart_prior(path, device)
    except CheckpointError as exc:
        raise FinetuneError(f"prior: {exc}") from exc


def controlled_selection(cfg: FinetuneConfig):
    """The env's ``controlled`` argument of the run."""
    if cfg.controlled == "moving_vehicles":
        return lambda sc: moving_vehicles_mask(sc, cfg.moving_min_route_m)
    return cfg.controlled


def group_types(vocab) -> list[int]:
    """The agent types of the group: those whose vocabulary has the vehicles' size (one action space)."""
    size = vocab[AgentType.VEHICLE].size
    return [int(t) for t, v in vocab.types.items() if v.size == size]


def _pool(spec, key: str, max_loaded: int = 64) -> ScenePool:
    if not spec:
        raise FinetuneError(f"{key}: no scenes given ({key}=PATH)")
    try:
        return ScenePool(spec, max_loaded=max_loaded)
    except SmartMarlError as exc:
        raise FinetuneError(f"{key}: {exc}") from exc


def training_pool(cfg: FinetuneConfig) -> ScenePool:
    """The fine-tuning scenes: the first ``num_scenes`` of ``scenes`` (all with None); the constants of
    as many scenes are kept in memory as the prior's started states (``prior_cache_size``)."""
    pool = _pool(cfg.scenes, "scenes", max_loaded=cfg.prior_cache_size)
    if cfg.num_scenes is None:
        return pool
    if cfg.num_scenes > len(pool):
        raise FinetuneError(f"num_scenes={cfg.num_scenes}: {cfg.scenes!r} holds {len(pool)} scene(s)")
    return pool.subset(range(cfg.num_scenes))


def core_scenes(cfg: FinetuneConfig, pool: ScenePool, vocab, count: int, exclude: set | None = None) -> list[CoreScene]:
    """The first ``count`` scenes of ``pool`` (not in ``exclude``, scenario ids) with an agent to control."""
    out, types = [], group_types(vocab)
    for i in range(len(pool)):
        sc = pool.scenario(i)
        if exclude and sc.scenario_id in exclude:
            continue
        static = pool.static(i)
        ctrl = select_controlled(controlled_selection(cfg), static, cfg.max_agents, types)
        if len(ctrl):
            out.append(CoreScene(static, ctrl, key=("eval", i)))
        if len(out) == count:
            break
    return out


class ExpertLabelledEnv(SmartTrafficBatchedEnv):
    """The batched env that also hands out, at every state, the restricted expert's token of each
    agent (``EXPERT_KEY`` [B, A]: :func:`agents.policy.expert_within_top_k` at the reference's top-k):
    the labels of the imitation term, for the states the policy itself reaches (DAgger's data)."""

    def _make_specs(self) -> None:
        super()._make_specs()
        self.observation_spec[EXPERT_KEY] = Categorical(self.vocab_size, (self.num_scenes, self.max_agents), device=self.device)

    def _output(self, step):
        td = super()._output(step)
        td.set(EXPERT_KEY, expert_within_top_k(self.core, td.get(PRIOR_KEY), self.reference_top_k))
        return td


def training_env(cfg: FinetuneConfig, pool: ScenePool, model, vocab, seed: int) -> SmartTrafficBatchedEnv:
    """The batched env of the run over the training pool (with the expert's labels when the run imitates)."""
    env_class = ExpertLabelledEnv if cfg.imitation > 0 else SmartTrafficBatchedEnv
    return env_class(
        scenarios=pool.subset(range(len(pool)), order="random", seed=seed), prior=model, motion_vocab=vocab, num_scenes=cfg.num_envs,
        controlled=controlled_selection(cfg), max_agents=cfg.max_agents, background=cfg.background, horizon_steps=cfg.horizon_steps,
        reward=dict(cfg.reward) or None, terminate_on=tuple(cfg.terminate_on), top_k=cfg.top_k, temperature=cfg.temperature,
        reference_top_k=cfg.reference_top_k, shield=cfg.shield, device=cfg.device, prior_cache_size=cfg.prior_cache_size, seed=seed,
        precision=cfg.precision)


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


def load_policy(path: str | Path = "embedded") -> tuple[FinetuneConfig, PolicyLogits, dict]:
    """(config, actor logits net with its weights, meta) of a policy checkpoint (NAME or NAME.json), or of
    the package's fine-tuned policy (``"embedded"``: trained against the embedded prior, see
    docs/policy_card.md). The file is checked whole before use, each problem a :class:`FinetuneError`
    naming the file and the field or tensor: its sizes and tensors (:func:`agents.policy.read_policy`),
    its config by the fine-tuning config's rules (``n_agents`` its ``max_agents``), and exactly the
    tensors, with the shapes, of the networks its config builds
    (:func:`agents.policy.check_policy_tensors`). A policy saved with the digest of its prior
    (``prior_sha256``) is refused when its config's prior is another one."""
    try:
        jpath, wpath = policy_files(path)
        meta, weights = read_policy(path)
    except PolicyError as exc:
        raise FinetuneError(str(exc)) from exc
    known = {f.name for f in dataclasses.fields(FinetuneConfig)}
    config = {k: v for k, v in meta["config"].items() if k in known}
    config.setdefault("reference_top_k", None)  # policies saved before the top-k reference were trained on the full softmax
    if path == "embedded":
        config["prior"] = "embedded"  # the package's policy goes with the package's prior
    config["device"] = "cpu"  # where it trained is no promise of where it runs: the weights load on the CPU
    try:
        cfg = load_finetune_config(config)
    except FinetuneError as exc:
        raise FinetuneError(f"{jpath}: {exc}") from exc
    if meta["n_agents"] != cfg.max_agents:
        raise FinetuneError(f"{jpath}: n_agents {meta['n_agents']} is not its config's max_agents {cfg.max_agents}")
    network = {k: getattr(cfg, k) for k in ("hidden", "depth", "residual", "actor_head", "critic")}
    try:
        check_policy_tensors(weights, policy_tensor_shapes(meta, **network), wpath,
                             ", ".join(f"{k}={v!r}" for k, v in network.items()))
    except PolicyError as exc:
        raise FinetuneError(str(exc)) from exc
    want = meta.get("prior_sha256")
    if want is not None:
        model, _ = load_prior(cfg.prior)
        if prior_digest(model) != want:
            raise FinetuneError(f"{path}: the policy was fine-tuned against another prior than {cfg.prior!r} (weights digest "
                                f"{want[:12]}...); evaluate it with prior=THAT_CHECKPOINT or fine-tune a new policy")
    try:
        net = actor_from_weights(meta, weights, cfg.hidden, cfg.depth, cfg.residual, cfg.obs_scale, cfg.temperature,
                                 cfg.reference_top_k, cfg.actor_head, path)
    except PolicyError as exc:
        raise FinetuneError(str(exc)) from exc
    return cfg, net, meta


# ---------------------------------------------------------------------------------- logging
COLUMNS = ["iteration", "frames", "seconds", "scenes_seen", "return_per_agent_episode", "goal_rate", "collision_rate",
           "offroad_rate", "kl_to_prior", "agent_episodes", "loss_objective", "loss_critic", "loss_entropy", "loss_prior_kl",
           "entropy", "clip_fraction", "loss_imitation"]


def batch_stats(batch, temperature: float = 1.0, reference_top_k: int | None = None) -> dict[str, float]:
    """Episode statistics of one collected batch [envs, T] (group [envs, T, A]): per agent-episode
    that ended in the batch, its return (the part of it inside the batch), goal / collision /
    offroad rates; and the mean KL(pi || reference) per agent-step that acted."""
    acted = batch[GROUP, "mask"]  # [E, T, A] agents that took this step's action
    nxt = batch["next", GROUP]
    ended = acted & nxt["done"].squeeze(-1)
    n = int(ended.sum())
    reward = torch.where(acted, nxt["reward"].squeeze(-1), torch.zeros((), device=acted.device))
    info = nxt["info"]
    prior = batch[PRIOR_KEY]
    kl = kl_to_prior(torch.log_softmax(batch[GROUP, "logits"], -1), prior, temperature, reference_top_k)
    valid = acted & prior.ne(0).any(-1)
    den = max(n, 1)
    events = lambda key: float((info[key].squeeze(-1).bool() & acted).sum()) / den  # noqa: E731
    return {
        "agent_episodes": n,
        "return_per_agent_episode": float(reward.sum()) / den,
        "goal_rate": events("goal_reached"), "collision_rate": events("collision"), "offroad_rate": events("offroad"),
        "kl_to_prior": float(torch.where(valid, kl, torch.zeros((), device=kl.device)).sum() / valid.sum().clamp_min(1)),
    }


# ------------------------------------------------------------------------------ distributed
def _average_gradients(params, world: int) -> None:
    for p in params:
        if p.grad is not None:
            dist.all_reduce(p.grad)
            p.grad /= world


def _mean_over_ranks(stats: dict[str, float], world: int, device) -> dict[str, float]:
    keys = sorted(k for k, v in stats.items() if isinstance(v, (int, float)))
    t = torch.tensor([float(stats[k]) for k in keys], dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return {**stats, **{k: float(v) / world for k, v in zip(keys, t.tolist())}}


# ---------------------------------------------------------------------------------- the run
@dataclass
class FinetuneResult:
    out_dir: Path
    checkpoint: Path | None  # None on processes other than 0 of a distributed run
    history: list[dict]
    evaluation: dict | None
    scene_ids: list[str]
    policy: PolicyLogits | None = None  # the trained actor (every process of a distributed run has the same)


def finetune(cfg: FinetuneConfig, on_iteration=None) -> FinetuneResult:
    """Run the whole pipeline (module docstring); ``on_iteration(row)`` is called after each
    iteration's log row. With ``eval_episodes > 0`` the fine-tuned policy is evaluated on held-out
    scenes at the end, next to the expert and the prior (:func:`evaluate_finetuned`)."""
    with warnings.catch_warnings():
        # the advantage is normalised over agents and steps together, on purpose
        warnings.filterwarnings("ignore", message="You requested advantage normalization")
        warnings.filterwarnings("ignore", message="Creating .*WeightUpdater")
        return _finetune(cfg, on_iteration)


@dataclass
class _Learner:
    """What a run trains: the actor's network, the TorchRL modules, the loss and its optimiser."""

    net: PolicyLogits
    critic: TensorDictModule
    actor: ProbabilisticActor
    loss: PriorKLPPOLoss
    params: list
    optimizer: torch.optim.Optimizer
    dims: dict


def _learner(cfg: FinetuneConfig, env: SmartTrafficBatchedEnv, model, vocab, device, world: int) -> _Learner:
    """2-3. the actor and critic (every process starting from process 0's weights) and the loss:
    clipped PPO + beta * KL(pi || reference), GAE."""
    obs_dim, vocab_size = int(env.observation_spec[OBS_KEY].shape[-1]), int(env.observation_spec[PRIOR_KEY].shape[-1])
    dims = {"obs_dim": obs_dim, "vocab_size": vocab_size, "n_agents": cfg.max_agents, "prior_sha256": prior_digest(model)}
    net, actor, critic = build_modules(cfg, obs_dim, vocab_size, cfg.max_agents, vocab)
    if cfg.init is not None:
        start_from(cfg.init, cfg, dims, net, critic.module)
    actor, critic = actor.to(device), critic.to(device)
    loss = PriorKLPPOLoss(actor, critic, beta=cfg.beta, prior_logits_key=PRIOR_KEY, agent_mask_key=(GROUP, "mask"),
                          prior_temperature=cfg.temperature, reference_top_k=cfg.reference_top_k, clip_epsilon=cfg.clip_epsilon,
                          entropy_bonus=cfg.entropy_coeff > 0, entropy_coeff=cfg.entropy_coeff, critic_coeff=cfg.critic_coeff,
                          normalize_advantage=cfg.normalize_advantage, imitation=cfg.imitation, expert_action_key=EXPERT_KEY)
    loss.set_keys(reward=(GROUP, "reward"), action=(GROUP, "action"), sample_log_prob=(GROUP, "action_log_prob"),
                  value=(GROUP, "state_value"), done=(GROUP, "done"), terminated=(GROUP, "terminated"),
                  advantage=(GROUP, "advantage"), value_target=(GROUP, "value_target"))
    loss.make_value_estimator(ValueEstimators.GAE, gamma=cfg.gamma, lmbda=cfg.lmbda)
    params = list(loss.parameters())
    if world > 1:  # every learner starts from process 0's weights
        for p in params:
            dist.broadcast(p.data, 0)
    return _Learner(net, critic, actor, loss, params, torch.optim.Adam(params, lr=cfg.lr), dims)


def start_from(path, cfg: FinetuneConfig, dims: dict, net: PolicyLogits, critic: nn.Module) -> None:
    """Loads the actor and critic weights of the policy checkpoint ``path`` (``init``) into ``net`` and
    ``critic``, after checking that it is this run's network (``POLICY_NETWORK_FIELDS``, the observation and
    action sizes of ``dims``) on this run's prior (its weights digest)."""
    try:
        meta, weights = read_policy(path)
    except PolicyError as exc:
        raise FinetuneError(f"init: {exc}") from exc
    differ = network_differences(cfg, meta.get("config", {}))
    differ += [f"{k} {dims[k]} (the checkpoint's: {meta.get(k)})" for k in ("obs_dim", "vocab_size", "n_agents") if meta.get(k) != dims[k]]
    if meta.get("prior_sha256") not in (None, dims["prior_sha256"]):
        differ.append(f"the prior (weights digest {dims['prior_sha256'][:12]}..., the checkpoint's: {meta['prior_sha256'][:12]}...)")
    if differ:
        raise FinetuneConfigError(f"init={path!r}: the checkpoint is another network than this run's: {', '.join(differ)}")
    for prefix, module in (("actor.", net), ("critic.", critic)):
        try:
            module.load_state_dict({k[len(prefix):]: v for k, v in weights.items() if k.startswith(prefix)})
        except RuntimeError as exc:
            raise FinetuneError(f"init={path!r}: its {prefix[:-1]} weights do not fit this run's ({str(exc)[:300]})") from exc


def _ppo_update(cfg: FinetuneConfig, learner: _Learner, batch, device, world: int) -> dict[str, float]:
    """GAE on the batch, then ``ppo_epochs`` passes over shuffled minibatches (gradients averaged over
    the processes); the mean of each loss term over the minibatches."""
    loss = learner.loss
    with torch.no_grad():
        loss.value_estimator(batch, params=loss.critic_network_params, target_params=loss.target_critic_network_params)
    data = batch.reshape(-1)
    sums: dict[str, float] = {}
    steps, mb_size = 0, max(1, cfg.minibatch_size)
    for _ in range(cfg.ppo_epochs):
        perm = torch.randperm(data.shape[0])
        for i in range(0, data.shape[0], mb_size):
            out = loss(data[perm[i : i + mb_size]].to(device))
            total = out["loss_objective"] + out["loss_critic"] + out["loss_prior_kl"]
            for extra in ("loss_entropy", "loss_imitation"):
                if extra in out.keys():
                    total = total + out[extra]
            learner.optimizer.zero_grad()
            total.backward()
            if world > 1:
                _average_gradients(learner.params, world)
            torch.nn.utils.clip_grad_norm_(learner.params, cfg.max_grad_norm)
            learner.optimizer.step()
            steps += 1
            for k in ("loss_objective", "loss_critic", "loss_entropy", "loss_prior_kl", "loss_imitation", "entropy", "clip_fraction"):
                if k in out.keys():
                    sums[k] = sums.get(k, 0.0) + float(out[k].detach())
    return {k: v / max(steps, 1) for k, v in sums.items()}


def _finetune(cfg: FinetuneConfig, on_iteration=None) -> FinetuneResult:
    device = resolve_device(cfg.device)
    info = init_distributed(device)  # under torchrun: gloo on the CPU, nccl on CUDA
    rank, world = info.rank, info.world_size
    if cfg.torch_threads > 0:
        torch.set_num_threads(cfg.torch_threads)
    torch.manual_seed(cfg.seed + rank)
    np.random.seed(cfg.seed + rank)
    out_dir = Path(cfg.out_dir)

    # 1. env: the training scenes, num_envs at a time (each process its own order of them)
    model, vocab = load_prior(cfg.prior, device)
    pool = training_pool(cfg)
    env = training_env(cfg, pool, model, vocab, seed=cfg.seed + rank)
    env.set_seed(cfg.seed + rank)
    # 2-3. actor, critic, loss
    learner = _learner(cfg, env, model, vocab, device, world)
    # 4. collector (every iteration from a full reset: agents.finetune_state), PPO epochs, logging, checkpoints
    steps_per_env = max(1, cfg.frames_per_batch // cfg.num_envs)
    frames_per_batch = steps_per_env * cfg.num_envs
    done = {"iterations": 0}  # iterations finished: the next one's sampler seed
    collector = Collector(env, learner.actor, frames_per_batch=frames_per_batch, total_frames=frames_per_batch * cfg.iterations,
                          policy_device=device, env_device=device, storing_device=device, reset_at_each_iter=True,
                          pre_collect_hook=lambda: env.set_episode_seed(episode_seed(cfg.seed, rank, done["iterations"] + 1), forget_starts=True),
                          auto_register_policy_transforms=False)  # a feed-forward policy: no InitTracker
    # after the collector's first reset (which draws nothing the next iteration's reset does not overwrite)
    progress = load_run_state(out_dir, rank, world, cfg, learner.loss, learner.optimizer, env.pool) or Progress()
    done["iterations"] = progress.iteration
    collector.update_policy_weights_()
    if rank == 0:  # only now: a run refused above (its prior, scenes, starting policy, saved state) writes nothing
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
    if progress.iteration:
        print(f"finetune: resuming {out_dir} after iteration {progress.iteration} of {cfg.iterations}", flush=True)
    log = (RunLog(out_dir, {"finetune": COLUMNS}, "iteration", resume_step=progress.iteration, tensorboard=cfg.tensorboard)
           if rank == 0 else None)
    history: list[dict] = logged_rows(out_dir, progress.iteration) if rank == 0 else []
    ckpt_dir = out_dir / "checkpoints"
    start = time.perf_counter() - progress.seconds
    for it, batch in enumerate(itertools.islice(collector, max(cfg.iterations - progress.iteration, 0)), start=progress.iteration + 1):
        progress.frames += batch.numel() * world
        progress.seen.update(env.scene_indices)
        stats = batch_stats(batch, cfg.temperature, cfg.reference_top_k)
        losses = _ppo_update(cfg, learner, batch, device, world)
        collector.update_policy_weights_()
        row = {"iteration": it, "frames": progress.frames, "seconds": time.perf_counter() - start, "scenes_seen": len(progress.seen),
               **stats, **losses}
        if world > 1:
            row = _mean_over_ranks(row, world, device)
            row["iteration"], row["frames"] = it, progress.frames
        history.append(row)
        if rank == 0:
            log.write("finetune", row)
            if on_iteration is not None:
                on_iteration(row)
            if it % max(cfg.checkpoint_every, 1) == 0 or it == cfg.iterations:
                save_policy(ckpt_dir / f"policy_{it:04d}", cfg.to_dict(), learner.net, learner.critic.module, learner.dims, it, stats)
        progress.iteration, progress.seconds, done["iterations"] = it, row["seconds"], it
        save_run_state(out_dir, rank, world, cfg, learner.loss, learner.optimizer, env.pool, progress)
        if cfg.time_limit_s and row["seconds"] >= cfg.time_limit_s:  # every rank sees the same (averaged) seconds
            break
    collector.shutdown()
    leave_distributed(info)
    scene_ids = pool.scenario_ids()
    if rank != 0:
        return FinetuneResult(out_dir, None, history, None, scene_ids, learner.net)
    log.close()
    if not history:
        raise FinetuneError("the run collected no batch (iterations=0?)")
    final = save_policy(ckpt_dir / "policy_last", cfg.to_dict(), learner.net, learner.critic.module, learner.dims, len(history),
                        history[-1])
    evaluation = None
    if cfg.eval_episodes > 0:
        evaluation = evaluate_finetuned(cfg, learner.net, training=scene_ids, model=model, vocab=vocab)
        (out_dir / "evaluation.json").write_text(json.dumps(evaluation, indent=1, default=float))
    return FinetuneResult(out_dir, final, history, evaluation, scene_ids, learner.net)


# ------------------------------------------------------------------------------- evaluation
def held_out_scenes(cfg: FinetuneConfig, vocab, training: Sequence[str]) -> list[CoreScene]:
    """The evaluation's scenes: the first ``eval_num_scenes`` of ``cfg.eval_scenes`` (default: the
    scenes of ``cfg.scenes`` after the fine-tuning ones) that are not fine-tuning scenes
    (``training``: scenario ids) and have an agent to control."""
    if cfg.eval_scenes:
        pool = _pool(cfg.eval_scenes, "eval_scenes")
    else:
        pool = _pool(cfg.scenes, "scenes")
        first = cfg.num_scenes if cfg.num_scenes is not None else len(pool)
        if first >= len(pool):
            raise FinetuneError(f"eval_scenes: every scene of {cfg.scenes!r} is a fine-tuning scene; give eval_scenes=PATH")
        pool = pool.subset(range(first, len(pool)))
    chosen = core_scenes(cfg, pool, vocab, cfg.eval_num_scenes, exclude=set(training))
    if not chosen:
        raise FinetuneError(f"eval_scenes: no held-out scene (the {len(training)} fine-tuning scene(s) excluded) has an agent to "
                            f"control (controlled={cfg.controlled!r}); give eval_scenes=PATH")
    return chosen


def evaluation_policies(cfg: FinetuneConfig, net: PolicyLogits | None) -> dict[str, TensorPolicy]:
    """The evaluation's rows: the expert (log-following), the prior at the reference's top-k (and at
    the background's, when it differs), the prior's full softmax and, with ``net``, the fine-tuned policy.
    With the shield (``cfg.shield``), in one environment: the shielded prior at the reference's top-k and
    at top-3 first, and those two with the shield off last, as rows of another environment
    (:func:`agents.evaluate.same_environment_policies`)."""
    policies: dict[str, TensorPolicy] = {ExpertTensorPolicy.name: ExpertTensorPolicy()}
    for k in dict.fromkeys((cfg.reference_top_k, cfg.top_k, None)):
        p = PriorTensorPolicy(top_k=k, temperature=cfg.temperature)
        policies[p.name] = p
    if net is not None:
        policies[FinetunedTensorPolicy.name] = FinetunedTensorPolicy(net)
    return same_environment_policies(policies, cfg.shield, cfg.reference_top_k, cfg.temperature)


def evaluation_core(cfg: FinetuneConfig, model, vocab, num_scenes: int) -> TrafficCore:
    """The core the evaluation runs on: the run's background and prior, no termination, recorded."""
    return TrafficCore(model, vocab, cfg.background, cfg.horizon_steps, RewardConfig.from_any(dict(cfg.reward) or None),
                       terminate_on=(), top_k=cfg.top_k, temperature=cfg.temperature, device=cfg.device,
                       prior_cache_size=max(num_scenes, 1), record=True, shield=cfg.shield, shield_top_k=cfg.reference_top_k,
                       precision=cfg.precision)


def evaluate_finetuned(cfg: FinetuneConfig, net: PolicyLogits | None, training: Sequence[str] | None = None, model=None,
                       vocab=None, episodes: int | None = None, seed: int | None = None, baselines: bool = True) -> dict:
    """The expert, the prior top-k, the prior's full softmax and the fine-tuned actor ``net`` on the
    held-out scenes (:func:`held_out_scenes`; ``training``: the fine-tuning scenes' ids, default those
    of the config) with the same seeds ``eval_seed ..`` (``episodes`` of them), the full horizon and no
    termination, ``num_envs`` episodes at a time (:func:`agents.evaluate.evaluate_policies`, which
    says what every row holds). ``baselines=False`` runs the fine-tuned policy alone."""
    if model is None or vocab is None:
        model, vocab = load_prior(cfg.prior, cfg.device)
    if training is None:
        training = training_pool(cfg).scenario_ids()
    scenes = held_out_scenes(cfg, vocab, training)
    episodes = cfg.eval_episodes if episodes is None else int(episodes)
    if episodes < 1:
        raise FinetuneError(f"the evaluation needs at least one episode (seed) per scene, got {episodes}")
    seed0 = cfg.eval_seed if seed is None else int(seed)
    policies = evaluation_policies(cfg, net)
    if not baselines:
        policies = {FinetunedTensorPolicy.name: policies[FinetunedTensorPolicy.name]}
    core = evaluation_core(cfg, model, vocab, len(scenes))
    result = evaluate_policies(core, scenes, policies, list(range(seed0, seed0 + episodes)), num_envs=cfg.num_envs,
                               vocab_size=vocab[AgentType.VEHICLE].size, num_agents=cfg.max_agents, rules=cfg.eval_rules,
                               temperature=cfg.temperature, reference_top_k=cfg.reference_top_k)
    result["training_scenes"] = list(training)
    return result


def evaluate_checkpoint(path, overrides: Sequence[str] = (), episodes: int | None = None, seed: int | None = None) -> dict:
    """:func:`evaluate_finetuned` for a policy checkpoint, with its run's config (``key=value``
    overrides, e.g. ``eval_scenes=OTHER`` to evaluate on other held-out scenes; the network's own
    sizes cannot be overridden)."""
    check_value("--episodes", episodes, optional(integer(1, MAX_EVAL_EPISODES)), FinetuneConfigError)
    check_value("--seed", seed, optional(seed_rule), FinetuneConfigError)
    cfg, net, meta = load_policy(path)
    if overrides:
        saved, cfg = cfg, load_finetune_config(cfg.to_dict(), overrides)
        fixed = network_differences(cfg, saved.to_dict())
        if fixed:
            raise FinetuneConfigError(f"{', '.join(fixed)}: the policy's network was built with the checkpoint's value, "
                                      f"which evaluation keeps; fine-tune a new policy to change it")
    result = evaluate_finetuned(cfg, net.to(cfg.device), episodes=episodes, seed=seed)
    result["checkpoint"] = str(path)
    result["iteration"] = meta.get("iteration")
    return result


__all__ = ["FinetuneConfig", "FinetuneConfigError", "FinetuneError", "FinetuneResult", "build_modules", "controlled_selection",
           "core_scenes", "evaluate_checkpoint", "evaluate_finetuned", "evaluation_core", "evaluation_policies", "finetune",
           "held_out_scenes", "load_finetune_config", "load_policy", "load_prior", "start_from", "training_env", "training_pool"]
