"""Environment stage: ``smart_traffic_batched_v0``, the environment for RL at scale: ``num_scenes``
scenes stepped as one TorchRL environment (``EnvBase`` with ``batch_size=[num_scenes]``), one
incremental SMART forward for every background agent of every scene per step, finished scenes
refilled in place from a scene pool of any size.

It is :mod:`envs.smart_traffic_v0` (same scenes, prior, backgrounds, rewards, events, observations,
reference; :class:`envs._core.TrafficCore` underneath both) with tensors instead of dicts:

* one agent group ``"agents"`` of ``max_agents`` padded slots per scene. Keys (the layout
  TorchRL's ``PettingZooWrapper`` gives the one-scene env, so the same fine-tuning code reads both):
  ``("agents", "observation", "observation")`` [B, A, D], ``("agents", "observation",
  "prior_logits")`` [B, A, V] (the prior's logits of the next token; zeros for padded and done
  agents; ``-inf`` on the tokens the shield takes out, ``shield=True``: :mod:`envs._shield`),
  ``("agents", "mask")`` [B, A] (the agents that act at this step), ``("agents",
  "action")`` [B, A] (a token id, Categorical(V)), ``("agents", "reward")``, ``("agents", "done" /
  "terminated" / "truncated")`` [B, A, 1] (true at the step an agent finishes), ``("agents",
  "info", ...)`` (``collision``, ``offroad``, ``goal_reached``, ``route_progress_m``,
  ``action_log_prob``, ``reward_terms`` [B, A, 6]), and the scene's ``"done"`` / ``"terminated"`` /
  ``"truncated"`` [B, 1] (every agent of the scene has finished);
* controlled agents are those of ``controlled`` (default ``"moving_vehicles"``) whose type's
  vocabulary has the group's size ``V`` (the vehicle vocabulary's: the group shares one action
  space), at most ``max_agents`` per scene; a scene with none is skipped;
* ``reset()`` starts ``num_scenes`` scenes; a reset with ``"_reset"`` [B, 1] (what TorchRL's
  collectors send for the scenes that are done) puts the pool's next scenes in those rows only
  (:meth:`envs._core.TrafficCore.refill`), the others go on;
* the pool (:class:`envs._pool.ScenePool`): ``scenarios`` is a scene-cache folder or ``.smsc``
  shard (read a scene at a time), any path ``read_scenarios`` reads, ``"embedded"``, a list of
  Scenario, a list of these, or a ``ScenePool``; ``scene_order`` ``"random"`` (a new permutation per pass, seeded by
  ``set_seed``) or ``"sequential"``. At most ``max_loaded_scenes`` scenes' constants and
  ``prior_cache_size`` freshly started prior states are kept in memory.

``device="cuda"``: the prior, the state and every tensor the environment returns stay on the device.
"""

from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from smart_marl.config_files import check_value, integer
from smart_marl.config_files import seed as seed_rule
from smart_marl.rollout import DEFAULT_TOP_K, reference_name
from smart_marl.scenario import AgentType
from smart_marl.tokens import MotionVocabulary

from ._arguments import check_env_arguments
from ._core import CoreScene, CoreStep, TrafficCore
from ._observation import ObservationConfig, observation_size
from ._pool import ScenePool, next_scenes
from ._reward import REWARD_TERMS, TERMINATION_EVENTS
from ._setup import load_env_prior
from .errors import EnvConfigError

GROUP = "agents"
INFO_KEYS = ("collision", "offroad", "goal_reached", "route_progress_m", "action_log_prob")


class SmartTrafficBatchedEnv(EnvBase):
    """``num_scenes`` scenes as one TorchRL environment (module docstring)."""

    def __init__(self, scenarios="embedded", prior="embedded", num_scenes: int = 8, controlled="moving_vehicles",
                 max_agents: int = 4, background: str = "prior", horizon_steps: int = 16, reward=None,
                 terminate_on: Sequence[str] = TERMINATION_EVENTS, scene_order: str = "random",
                 motion_vocab: MotionVocabulary | None = None, top_k: int = DEFAULT_TOP_K, temperature: float = 1.0,
                 reference_top_k: int | None = None, avoid_collisions: bool = True, observation: ObservationConfig | None = None,
                 shield=(), device="cpu", prior_cache_size: int = 1024, max_loaded_scenes: int = 1024, seed: int = 0,
                 stop_lines: bool = True, lights: str = "log") -> None:
        a = check_env_arguments(background=background, horizon_steps=horizon_steps, scene_order=scene_order,
                                terminate_on=terminate_on, render_mode=None, render_modes=(), max_agents=max_agents, top_k=top_k,
                                temperature=temperature, reference_top_k=reference_top_k, render_size_px=400, render_radius_m=50.0,
                                avoid_collisions=avoid_collisions, reward=reward, observation=observation or "vector",
                                controlled=controlled, device=device, shield=shield, stop_lines=stop_lines,
                                lights=lights)
        if a["max_agents"] is None:
            raise EnvConfigError("max_agents must be an integer >= 1: the batched env's agent group has that many slots per scene")
        for name, value, high in (("num_scenes", num_scenes, 1 << 16), ("prior_cache_size", prior_cache_size, 1 << 20),
                                  ("max_loaded_scenes", max_loaded_scenes, 1 << 20)):
            check_value(name, value, integer(1, high), EnvConfigError)
        check_value("seed", seed, seed_rule, EnvConfigError)
        device = a["device"]
        super().__init__(device=device, batch_size=torch.Size([int(num_scenes)]), allow_done_after_reset=True)
        self.model, self.motion_vocab = load_env_prior(prior, motion_vocab, device)
        if background == "prior" and self.model is None:
            raise EnvConfigError("background='prior' needs a prior (prior=PATH, a model or 'embedded')")
        self.num_scenes, self.max_agents = int(num_scenes), a["max_agents"]
        self.controlled, self.background, self.horizon_steps = a["controlled"], a["background"], a["horizon_steps"]
        self.vocab_size = self.motion_vocab[AgentType.VEHICLE].size
        self.group_types = [int(t) for t, v in self.motion_vocab.types.items() if v.size == self.vocab_size]
        self.temperature = a["temperature"]
        self.reference_top_k = a["reference_top_k"]
        self.reference = reference_name(self.reference_top_k, self.temperature)
        self.obs_config = a["observation"]
        self.pool = scenarios if isinstance(scenarios, ScenePool) else ScenePool(scenarios, scene_order, seed, max_loaded=max_loaded_scenes)
        self.core = TrafficCore(self.model, self.motion_vocab, self.background, self.horizon_steps, a["reward"], a["terminate_on"],
                                self.obs_config, a["top_k"], self.temperature, a["avoid_collisions"], device=device,
                                prior_cache_size=prior_cache_size, shield=a["shield"], shield_top_k=self.reference_top_k,
                                stop_lines=a["stop_lines"], lights=a["lights"])
        self.shield = a["shield"]
        self.scene_indices = [-1] * self.num_scenes  # the pool index each row plays
        self._seed = int(seed)
        self._make_specs()

    # ------------------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        b, a, v, d = self.num_scenes, self.max_agents, self.vocab_size, observation_size(self.obs_config)
        dev = self.device
        group = lambda **kw: Composite(**kw, shape=(b, a), device=dev)  # noqa: E731
        obs = {"observation": Unbounded((b, a, d), device=dev)}
        if self.model is not None:
            obs["prior_logits"] = Unbounded((b, a, v), device=dev)
        info = {k: Binary(n=1, shape=(b, a, 1), device=dev, dtype=torch.bool) for k in ("collision", "offroad", "goal_reached")}
        info.update({k: Unbounded((b, a, 1), device=dev) for k in ("route_progress_m", "action_log_prob")})
        info["reward_terms"] = Unbounded((b, a, len(REWARD_TERMS)), device=dev)
        self.observation_spec = Composite({GROUP: group(observation=Composite(obs, shape=(b, a), device=dev),
                                                        mask=Categorical(2, (b, a), device=dev, dtype=torch.bool),
                                                        info=Composite(info, shape=(b, a), device=dev))}, shape=(b,), device=dev)
        self.action_spec = Composite({GROUP: group(action=Categorical(v, (b, a), device=dev))}, shape=(b,), device=dev)
        self.reward_spec = Composite({GROUP: group(reward=Unbounded((b, a, 1), device=dev))}, shape=(b,), device=dev)
        flag = lambda *shape: Categorical(2, shape, device=dev, dtype=torch.bool)  # noqa: E731
        self.done_spec = Composite({"done": flag(b, 1), "terminated": flag(b, 1), "truncated": flag(b, 1),
                                    GROUP: group(done=flag(b, a, 1), terminated=flag(b, a, 1), truncated=flag(b, a, 1))},
                                   shape=(b,), device=dev)

    # ------------------------------------------------------------------------------ scenes
    def _next_scenes(self, count: int) -> tuple[list[int], list[CoreScene]]:
        return next_scenes(self.pool, count, self.controlled, self.max_agents, self.group_types)

    # ------------------------------------------------------------------------------- TorchRL
    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            check_value("seed", seed, seed_rule, EnvConfigError)
        self._seed = int(seed) if seed is not None else 0
        self.pool.seed(self._seed)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is None or self.core.scenes is None:
            picked, scenes = self._next_scenes(self.num_scenes)
            self.core.reset(scenes, self._seed, num_agents=self.max_agents)
            self.scene_indices = picked
            self._last: CoreStep | None = None
        else:
            rows = reset.reshape(self.num_scenes).nonzero().squeeze(1).tolist()
            if rows:
                picked, scenes = self._next_scenes(len(rows))
                self.core.refill(rows, scenes)
                for r, i in zip(rows, picked):
                    self.scene_indices[r] = i
        return self._output(None)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get((GROUP, "action")).reshape(self.num_scenes, self.max_agents)
        return self._output(self.core.step(actions))

    def _output(self, step: CoreStep | None) -> TensorDictBase:
        core = self.core
        b, a = self.num_scenes, self.max_agents
        obs = {"observation": core.observations()}
        if self.model is not None:
            obs["prior_logits"] = core.prior_logits()[..., : self.vocab_size].to(torch.float32)
        zeros = torch.zeros(b, a, 1, device=self.device)
        no = torch.zeros(b, a, 1, dtype=torch.bool, device=self.device)
        if step is None:
            info = {"collision": no, "offroad": no, "goal_reached": no, "route_progress_m": core.progress_m[..., None].float(),
                    "action_log_prob": zeros, "reward_terms": torch.zeros(b, a, len(REWARD_TERMS), device=self.device)}
            reward, terminated, truncated = zeros, no, no
        else:
            info = {"collision": step.collision[..., None], "offroad": step.offroad[..., None],
                    "goal_reached": step.goal_reached[..., None], "route_progress_m": step.progress_m[..., None].float(),
                    "action_log_prob": step.action_log_prob[..., None].float(), "reward_terms": step.terms.float()}
            reward = step.reward[..., None].float()
            terminated, truncated = step.terminated[..., None], step.truncated[..., None]
        live = core.live
        scene_done = ~live.any(1, keepdim=True)  # [B, 1]
        scene_truncated = scene_done & truncated.any(1) if step is not None else scene_done & False
        group = TensorDict({"observation": TensorDict(obs, batch_size=[b, a]), "mask": live,
                            "info": TensorDict(info, batch_size=[b, a]), "done": terminated | truncated,
                            "terminated": terminated, "truncated": truncated}, batch_size=[b, a], device=self.device)
        if step is not None:
            group["reward"] = reward
        return TensorDict({GROUP: group, "done": scene_done, "terminated": scene_done & ~scene_truncated,
                           "truncated": scene_truncated}, batch_size=[b], device=self.device)


def batched_env(**kwargs) -> SmartTrafficBatchedEnv:
    """The batched TorchRL environment (:class:`SmartTrafficBatchedEnv`; module docstring)."""
    return SmartTrafficBatchedEnv(**kwargs)


__all__ = ["GROUP", "INFO_KEYS", "SmartTrafficBatchedEnv", "batched_env"]
