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
  "info", ...)`` (``collision``, ``offroad``, ``goal_reached``, ``shield_replaced``, ``route_progress_m``,
  ``action_log_prob``, ``reward_terms`` [B, A, 8]), and the scene's ``"done"`` / ``"terminated"`` /
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
``precision="bfloat16"``: the prior runs in bfloat16 (:mod:`smart_marl.model.precision`); its logits, the
observations and the state stay float32. ``stop_lines``, ``lights`` and ``persistence`` (the background's traffic
control and speed persistence) as the PettingZoo env's.

What it refuses (:mod:`envs.errors`), by the PettingZoo env's rules: the constructor's arguments as
:mod:`envs._arguments` checks them, ``max_agents`` in 1..:data:`~envs._arguments.MAX_AGENT_SLOTS`, ``num_scenes`` in
1..:data:`MAX_SCENES`, ``prior_cache_size`` and ``max_loaded_scenes`` in 1..:data:`MAX_CACHED_SCENES`, ``scenarios``
of another type than the ones above (an ``EnvConfigError``, an ``EnvConfigTypeError`` for a wrong type, naming the
argument). Every step, once and vectorised
(:func:`check_actions`: no loop over agents, one ``.any()`` the only host sync): a missing
``("agents", "action")``, one of another shape than [B, A] or [B, A, 1], of a dtype that is neither
integer nor float (a bool tensor is refused: ``True`` is not token 1), or a live agent's entry that is
not a token id 0..V-1 (negative, ``>= V``, NaN, inf, a fraction: a float tensor is taken where its
live entries are whole numbers, as ``smart_traffic_v0`` takes 3.0): an ``ActionError`` (an
``ActionTypeError`` for the dtype) naming the key, the scene row, the agent slot and the value.
Entries of padded and done agent slots are ignored, NaN included. A ``"_reset"`` (:func:`check_reset_mask`)
must be a bool tensor of shape [B] or [B, 1]; anything else (0.5, NaN, -1, 7, 0/1 integers, which
TorchRL's own reset would read as row indices) is an ``EnvConfigError`` and no row is restarted.
A refused step or reset leaves the state as it was.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping
from typing import Any, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from smart_marl.config_files import check_value, integer, is_integer, shown
from smart_marl.config_files import seed as seed_rule
from smart_marl.rollout import DEFAULT_TOP_K, reference_name
from smart_marl.rollout.persistence import DEFAULT_PERSISTENCE
from smart_marl.scenario import AgentType, Scenario
from smart_marl.tokens import MotionVocabulary

from ._arguments import MAX_AGENT_SLOTS, check_env_arguments
from ._core import CoreScene, CoreStep, TrafficCore
from ._observation import ObservationConfig, observation_size
from ._pool import ScenePool, next_scenes
from ._reward import REWARD_TERMS, TERMINATION_EVENTS
from ._setup import load_env_prior
from .errors import ActionError, ActionTypeError, EnvConfigError, EnvConfigTypeError, EnvStateError

GROUP = "agents"
ACTION_KEY = (GROUP, "action")
INFO_KEYS = ("collision", "offroad", "goal_reached", "shield_replaced", "route_progress_m", "action_log_prob")
MAX_SCENES = 8192
"""The most scenes stepped together (``num_scenes``): a scene takes about 13 MB of the device's memory (its prior's
KV cache, constants and state: 54 GB at 4,096 generated scenes on an H200, docs/scale.md), so 8,192 take about
110 GB, what the largest GPU the project runs on (an H200, 141 GB) holds; the earlier bound, 65,536, would ask
~860 GB. On a CPU the machine's memory is the limit, and may be lower."""
MAX_CACHED_SCENES = 65_536
"""The most scenes whose freshly started prior state (``prior_cache_size``, ~1-2 MB each) or constants
(``max_loaded_scenes``) are kept: up to ~130 GB of prior states, what an H200 (141 GB) holds; the earlier bound,
2**20, let a cache grow to 1-2 TB."""
INTEGER_DTYPES = (torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64, torch.uint16, torch.uint32, torch.uint64)
FLOAT_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64)
"""The dtypes an action tensor may have: token ids as integers, or as floats that are whole numbers."""


class SmartTrafficBatchedEnv(EnvBase):
    """``num_scenes`` scenes as one TorchRL environment (module docstring)."""

    def __init__(self, scenarios="embedded", prior="embedded", num_scenes: int = 8, controlled="moving_vehicles",
                 max_agents: int = 4, background: str = "prior", horizon_steps: int = 16, reward=None,
                 terminate_on: Sequence[str] = TERMINATION_EVENTS, scene_order: str = "random",
                 motion_vocab: MotionVocabulary | None = None, top_k: int = DEFAULT_TOP_K, temperature: float = 1.0,
                 reference_top_k: int | None = None, avoid_collisions: bool = True, observation: ObservationConfig | None = None,
                 shield=(), device="cpu", prior_cache_size: int = 1024, max_loaded_scenes: int = 1024, seed: int = 0,
                 stop_lines: bool = True, lights: str = "log", precision: str = "float32",
                 persistence: float = DEFAULT_PERSISTENCE) -> None:
        a = check_env_arguments(background=background, horizon_steps=horizon_steps, scene_order=scene_order,
                                terminate_on=terminate_on, render_mode=None, render_modes=(), max_agents=max_agents, top_k=top_k,
                                temperature=temperature, reference_top_k=reference_top_k, render_size_px=400, render_radius_m=50.0,
                                avoid_collisions=avoid_collisions, reward=reward, observation=observation or "vector",
                                controlled=controlled, device=device, shield=shield, stop_lines=stop_lines,
                                lights=lights, precision=precision, persistence=persistence)
        if a["max_agents"] is None:
            raise EnvConfigError("max_agents must be an integer >= 1: the batched env's agent group has that many slots per scene")
        for name, value, high, why in (("max_agents", a["max_agents"], MAX_AGENT_SLOTS, "the most agents of a scene"),
                                       ("num_scenes", num_scenes, MAX_SCENES, "~13 MB of device memory a scene: ~110 GB"),
                                       ("prior_cache_size", prior_cache_size, MAX_CACHED_SCENES, "~1-2 MB a scene: ~130 GB"),
                                       ("max_loaded_scenes", max_loaded_scenes, MAX_CACHED_SCENES, "scenes held in memory")):
            check_value(name, value, integer(1, high, why), EnvConfigError if is_integer(value) else EnvConfigTypeError)
        check_value("seed", seed, seed_rule, EnvConfigError)
        if not isinstance(scenarios, ScenePool):
            scenarios = scenario_sources(scenarios)
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
                                stop_lines=a["stop_lines"], lights=a["lights"], precision=a["precision"],
                                persistence=a["persistence"])
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
        info = {k: Binary(n=1, shape=(b, a, 1), device=dev, dtype=torch.bool)
                for k in ("collision", "offroad", "goal_reached", "shield_replaced")}
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

    def set_episode_seed(self, seed: int, forget_starts: bool = False) -> None:
        """The seed of the prior's sampler at the next full reset (``reset()`` without ``_reset``), without
        restarting the scene order as ``set_seed`` does: a trainer that starts every batch from a reset
        gives each batch its own draws. ``forget_starts``: also drop the prior's started scenes kept from
        earlier episodes (``prior_cache_size``), so that what follows depends on the seed and the scene order
        alone (a scene started in another batch of scenes can differ in the last bit of a float)."""
        check_value("seed", seed, seed_rule, EnvConfigError)
        self._seed = int(seed)
        if forget_starts:
            self.core.forget_starts()

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is not None:
            reset = check_reset_mask(reset, self.num_scenes)  # refused before any row is touched
        if reset is None or self.core.scenes is None:
            picked, scenes = self._next_scenes(self.num_scenes)
            self.core.reset(scenes, self._seed, num_agents=self.max_agents)
            self.scene_indices = picked
            self._last: CoreStep | None = None
        else:
            rows = reset.nonzero().squeeze(1).tolist()
            if rows:
                picked, scenes = self._next_scenes(len(rows))
                self.core.refill(rows, scenes)
                for r, i in zip(rows, picked):
                    self.scene_indices[r] = i
        return self._output(None)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.core.scenes is None:
            raise EnvStateError("step() before reset(): call reset() to start the scenes")
        actions = check_actions(tensordict.get(ACTION_KEY, None), self.core.live, self.vocab_size)  # [B, A] long
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
            info = {"collision": no, "offroad": no, "goal_reached": no, "shield_replaced": no,
                    "route_progress_m": core.progress_m[..., None].float(),
                    "action_log_prob": zeros, "reward_terms": torch.zeros(b, a, len(REWARD_TERMS), device=self.device)}
            reward, terminated, truncated = zeros, no, no
        else:
            info = {"collision": step.collision[..., None], "offroad": step.offroad[..., None],
                    "goal_reached": step.goal_reached[..., None], "shield_replaced": step.replaced[..., None],
                    "route_progress_m": step.progress_m[..., None].float(),
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


# ------------------------------------------------------------------------------ input checks
def scenario_sources(value: Any) -> Any:
    """``scenarios`` as :class:`~envs._pool.ScenePool` takes it (a path, ``"embedded"``, a Scenario, or a list of
    these); :class:`~envs.errors.EnvConfigTypeError` naming the argument (and the entry of a list) for another type."""
    kinds = "a path, 'embedded', a Scenario, a list of these or a ScenePool"
    if isinstance(value, (str, os.PathLike, Scenario)):
        return value
    if isinstance(value, (bytes, Mapping)) or not isinstance(value, Iterable):
        raise EnvConfigTypeError(f"scenarios must be {kinds}, got {shown(value)} ({type(value).__name__})")
    sources = list(value)
    for i, source in enumerate(sources):
        if not isinstance(source, (str, os.PathLike, Scenario)):
            raise EnvConfigTypeError(f"scenarios[{i}] must be a path, 'embedded' or a Scenario, got {shown(source)} "
                                     f"({type(source).__name__})")
    return sources


def check_actions(actions: Any, live: torch.Tensor, vocab_size: int) -> torch.Tensor:
    """[B, A] long: the token ids of ``actions`` (a step's ``("agents", "action")``) for the live agents ``live``
    [B, A] bool, 0 in the slots of padded and done agents whatever they hold (NaN there is ignored).

    The PettingZoo env's rules, vectorised (no loop over agents; the one host sync is the ``.any()``): a tensor of
    shape [B, A] or [B, A, 1], of an integer dtype or a float one whose live entries are whole numbers (3.0 is
    token 3); every live entry in 0..``vocab_size`` - 1. :class:`~envs.errors.ActionTypeError` for another
    type or dtype (a bool tensor: ``True`` is not token 1); :class:`~envs.errors.ActionError` for a missing
    action, another shape, or a live entry that is not a token id (negative, ``>= V``, NaN, inf, a fraction),
    naming the first such entry's scene row, agent slot and value."""
    b, a = live.shape
    ids = f"token ids 0..{vocab_size - 1}"
    if actions is None:
        raise ActionError(f"step: no {ACTION_KEY} in the TensorDict: every step needs a [B, A] = [{b}, {a}] tensor of {ids} "
                          f"(entries of padded and done agent slots are ignored)")
    if not isinstance(actions, torch.Tensor):
        raise ActionTypeError(f"{ACTION_KEY} must be a tensor of {ids}, got {type(actions).__name__}")
    if actions.dtype not in INTEGER_DTYPES + FLOAT_DTYPES:
        raise ActionTypeError(f"{ACTION_KEY} must hold integer {ids}, got a {actions.dtype} tensor"
                              + (" (True is not token 1)" if actions.dtype == torch.bool else ""))
    if tuple(actions.shape) not in ((b, a), (b, a, 1)):
        raise ActionError(f"{ACTION_KEY} must have shape [B, A] = [{b}, {a}] (or [{b}, {a}, 1]): one token id per scene row "
                          f"and agent slot, got {list(actions.shape)}")
    raw = actions.reshape(b, a).to(live.device)
    if raw.dtype.is_floating_point:
        tokens = raw
        ok = (raw >= 0) & (raw < vocab_size) & (raw == raw.trunc())  # NaN fails every comparison, inf the bound
    else:
        tokens = raw.to(torch.int64)  # a uint8's comparison with 1024 would wrap, unsigned 16-64 bits have none
        ok = (tokens >= 0) & (tokens < vocab_size)
    bad = live & ~ok  # [B, A]
    if bool(bad.any()):
        raise ActionError(_refused_action(raw, bad, vocab_size))
    return tokens.masked_fill(~live, 0).to(torch.long)


def _refused_action(raw: torch.Tensor, bad: torch.Tensor, vocab_size: int) -> str:
    """The message of a step whose live agents' entries ``bad`` [B, A] of ``raw`` [B, A] are refused (the first named)."""
    rows, slots = bad.nonzero(as_tuple=True)
    r, s = int(rows[0]), int(slots[0])
    value = raw[r, s].item()
    shown_value = str(np.float32(value)) if raw.dtype in FLOAT_DTYPES[:3] else repr(value)  # 3.7, not 3.700000047683716
    if isinstance(value, float) and not math.isfinite(value):
        why = "NaN and infinities are not token ids"
    elif isinstance(value, float) and not value.is_integer():
        why = "a fraction is not a token id"
    elif value < 0:
        why = "a negative id is not an action"
    else:
        why = "beyond the vocabulary"
    more = f" ({len(rows) - 1} more live agent(s) with a refused entry)" if len(rows) > 1 else ""
    return (f"{ACTION_KEY} of the live agent in scene row {r}, agent slot {s} is {shown_value}: {why}; token ids are "
            f"0..{vocab_size - 1}{more}")


def check_reset_mask(reset: Any, num_scenes: int) -> torch.Tensor:
    """[B] bool: the scene rows a ``"_reset"`` entry marks for a restart. It must be a bool tensor of shape [B] or
    [B, 1] (what TorchRL's collectors send); :class:`~envs.errors.EnvConfigTypeError` for another type or dtype
    (0/1 integers included: TorchRL's own reset, after this one, reads a non-bool ``"_reset"`` as row indices),
    :class:`~envs.errors.EnvConfigError` for another shape, naming the first row that holds neither 0 nor 1."""
    b = num_scenes
    if not isinstance(reset, torch.Tensor):
        raise EnvConfigTypeError(f"'_reset' must be a bool tensor of shape [{b}] or [{b}, 1] marking the scene rows to "
                                 f"restart, got {type(reset).__name__}")
    if tuple(reset.shape) not in ((b,), (b, 1)):
        raise EnvConfigError(f"'_reset' must have shape [{b}] or [{b}, 1] (one flag per scene row), got {list(reset.shape)}")
    if reset.dtype != torch.bool:
        flags = reset.detach().reshape(b).cpu()
        values = (flags.to(torch.float64) if flags.dtype.is_floating_point else flags).tolist()  # float8 has no tolist
        odd = next(((i, v) for i, v in enumerate(values) if v not in (0, 1)), None)  # NaN is neither
        what = f"scene row {odd[0]} holds {odd[1]!r}" if odd else "0/1 values: pass mask.bool()"
        raise EnvConfigTypeError(f"'_reset' must be a bool tensor (True: restart that scene row), got {reset.dtype} ({what}); "
                                 f"TorchRL reads a '_reset' of another dtype as row indices, not as a mask")
    return reset.reshape(b)


def batched_env(**kwargs) -> SmartTrafficBatchedEnv:
    """The batched TorchRL environment (:class:`SmartTrafficBatchedEnv`; module docstring)."""
    return SmartTrafficBatchedEnv(**kwargs)


__all__ = ["ACTION_KEY", "GROUP", "INFO_KEYS", "MAX_AGENT_SLOTS", "MAX_CACHED_SCENES", "MAX_SCENES", "SmartTrafficBatchedEnv",
           "batched_env", "check_actions", "check_reset_mask", "scenario_sources"]
