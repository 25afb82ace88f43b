"""Environment stage: ``smart_traffic_v0``, a PettingZoo ParallelEnv whose agents act in SMART's
motion-token action space, with the SMART prior driving (or scoring) everyone.

What comes in: scenes (any path :func:`smart_marl.readers.read_scenarios` reads, a list of
:class:`~smart_marl.scenario.Scenario`, or the package's embedded samples), a prior (a SMART
checkpoint path, a model or Checkpoint, ``"embedded"``, or ``None``) and the controlled-agent
selection. What goes out, every step: per controlled agent an observation, a reward, termination
and truncation flags, and ``infos`` with the prior's logits and events.

One ``step`` = one 0.5 s token step for every agent: controlled agents take their actions (a token
id of their type's vocabulary: Discrete(V)); every other agent follows the background mode:

* ``"prior"``: one incremental SMART step (:class:`smart_marl.rollout.RolloutState`, KV cache)
  samples every background agent's token, conditioned on the controlled agents' chosen tokens
  (they are forced into the same step), collision-aware unless ``avoid_collisions=False``
  (:mod:`smart_marl.rollout.avoidance`: a background agent does not draw a token that runs into
  another agent, the controlled ones included, where they would be at constant velocity); agents
  of type OTHER move at constant velocity;
* ``"log"``: logged poses are replayed (an agent is present on the frames its log is valid; for the
  prior it leaves for good at its first gap);
* ``"constant_velocity"``: the logged velocity at the current frame, heading held.

With a prior and a non-prior background, the prior still runs (for the logits it exposes): the
background agents' moves are fed to it as the nearest token, re-anchored at their true poses.

This module is the environment's PettingZoo face: one scene at a time, dicts keyed by agent name.
Underneath is the batched core (:class:`envs._core.TrafficCore`, here with one scene), which the
TorchRL face :mod:`envs.smart_traffic_batched_v0` runs with many: one step is the dynamics
(:func:`envs._dynamics.move`: every agent's 5 new frames, the prior's step), the state update, the
reward (:func:`envs._reward.step_reward`: events, reward terms, termination), the prior forgetting
agents that are done (:func:`envs._dynamics.release`), and the observations
(:mod:`envs._observation`). Per-scene constants are computed once per scene (:mod:`envs._scene`).

Agents: ``possible_agents`` are the controlled tracks of the current scene, named
``"vehicle_1234"`` (type and track id), in track order. They change when a reset loads another
scene (TorchRL's PettingZooWrapper fixes its agent set at construction: wrap a one-scene env).
A controlled agent that terminates (collision / offroad / goal, as ``terminate_on`` says) leaves
``agents`` and is removed from the scene. Every agent still live at ``horizon_steps`` is truncated.
Background agents replayed from the log are present on the frames where their log is valid.

The reference: ``reference_top_k`` (None: the prior's full ``softmax(logits / temperature)``;
k: that distribution restricted to its top k tokens and renormalised, the prior as it drives,
:func:`smart_marl.rollout.reference_log_probs`). The ``"dict"`` observation's ``action_mask``
is the reference's support (every token without a top-k), ``env.reference`` names it.

The shield (``shield=True``, or a list of :data:`envs._shield.SHIELD_CHECKS`; off by default): the tokens
that would run a controlled agent into another agent or a vehicle off the road (and with ``"gap"``, those that would
leave a vehicle closer to the agent ahead than it can stop) are taken out of its prior logits (``-inf``), so out of the action mask and the reference too
(:mod:`envs._shield`). With ``"joint"``, the controlled agents' chosen tokens are also checked against each other when
the step is taken: one that would run into an earlier agent's token is replaced by the most likely token of its
shielded top k that does not, or that agent yields where this one cannot (``infos[agent]["shield_replaced"]``).

``infos[agent]`` (fixed keys and shapes, so TorchRL can stack them): ``prior_logits`` [V] and
``prior_log_probs`` [V] (the reference's log-probabilities, ``-inf`` outside its top-k) of the
agent's *next* token (zeros once it is done), ``reference_top_k`` (the reference's k, 0 for the
full softmax), ``action_log_prob`` (the prior's full-softmax log-probability of the token just taken),
``collision``, ``offroad``, ``goal_reached``, ``shield_replaced`` (this step), ``route_progress_m`` and
``reward_terms`` [8] (see :mod:`envs._reward`). Without a prior the three prior keys are absent.

Errors: every argument of the constructor and of ``reset`` is checked before any state is built
(:mod:`envs._arguments`: its type, range and integrality, an ``EnvConfigError`` naming it); an
action outside the agent's vocabulary, a name that is not an agent of this episode, a missing action
for a live agent, a step after every agent is done, a scene with no controllable agent and a prior
that cannot be loaded all raise clear errors (:mod:`envs.errors`). Actions given for agents that are already done are ignored (TorchRL sends one for
every agent of its group).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Sequence

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.utils import wrappers
from pettingzoo.utils.conversions import parallel_to_aec_wrapper

from smart_marl.render import BevRenderer, EpisodeRecorder
from smart_marl.rollout import DEFAULT_TOP_K, reference_log_probs, reference_name, top_k_mask
from smart_marl.rollout.persistence import DEFAULT_PERSISTENCE
from smart_marl.scenario import DT_S, AgentType
from smart_marl.tokens import FRAMES_PER_TOKEN, MotionVocabulary

from ._arguments import check_env_arguments, check_reset_arguments
from ._core import CoreScene, CoreStep, TrafficCore
from ._dynamics import BACKGROUNDS
from ._observation import ObservationConfig, observation_layout, observation_size
from ._reward import REWARD_TERMS, TERMINATION_EVENTS, RewardConfig
from ._scene import SceneStatic, scene_static
from ._setup import load_env_prior, load_scenes, select_controlled
from .errors import ActionError, ActionTypeError, EnvConfigError, EnvError, EnvStateError, UnknownAgentError


def _has_display() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


# --------------------------------------------------------------------------------- the env
class SmartTrafficEnv(ParallelEnv):
    """The parallel environment (see the module docstring). Build it with :func:`parallel_env`."""

    metadata = {"render_modes": ["rgb_array", "human"], "name": "smart_traffic_v0", "render_fps": 2, "is_parallelizable": True}
    PRIOR_STATE_CACHE = 8  # scenes whose freshly started prior state is kept for fast resets

    def __init__(self, scenarios="embedded", prior="embedded", controlled="sdc", background: str = "prior",
                 horizon_steps: int = 16, reward=None, observation="vector", render_mode: str | None = None,
                 max_agents: int | None = None, terminate_on: Sequence[str] = TERMINATION_EVENTS,
                 scene_order: str = "sequential", motion_vocab: MotionVocabulary | None = None, top_k: int = DEFAULT_TOP_K,
                 temperature: float = 1.0, render_size_px: int = 400, render_radius_m: float = 50.0,
                 reference_top_k: int | None = None, avoid_collisions: bool = True, shield=(), device="cpu",
                 stop_lines: bool = True, lights: str = "log", precision: str = "float32",
                 persistence: float = DEFAULT_PERSISTENCE) -> None:
        a = check_env_arguments(background=background, horizon_steps=horizon_steps, scene_order=scene_order,
                                terminate_on=terminate_on, render_mode=render_mode, render_modes=self.metadata["render_modes"],
                                max_agents=max_agents, top_k=top_k, temperature=temperature, reference_top_k=reference_top_k,
                                render_size_px=render_size_px, render_radius_m=render_radius_m,
                                avoid_collisions=avoid_collisions, reward=reward, observation=observation, controlled=controlled,
                                device=device, shield=shield, stop_lines=stop_lines, lights=lights, precision=precision,
                                persistence=persistence)
        if render_mode == "human" and not _has_display():
            raise EnvConfigError("render_mode='human' opens a matplotlib window, but there is no display (DISPLAY and "
                                 "WAYLAND_DISPLAY are unset); use render_mode='rgb_array' (and EpisodeRecorder) instead")
        self.device = a["device"]
        self.model, self.motion_vocab = load_env_prior(prior, motion_vocab, self.device)
        if background == "prior" and self.model is None:
            raise EnvConfigError("background='prior' needs a prior (prior=PATH, a model or 'embedded'); with prior=None use "
                                 "background='log' or 'constant_velocity'")
        self.vocab_sizes = {int(t): v.size for t, v in self.motion_vocab.types.items()}
        self.scenes = load_scenes(scenarios)
        self.controlled = a["controlled"]
        self.background = a["background"]
        self.horizon_steps = a["horizon_steps"]
        self.reward_config = a["reward"]
        self.obs_config = a["observation"]
        self.render_mode = a["render_mode"]
        self.max_agents = a["max_agents"]
        self.terminate_on = a["terminate_on"]
        self.scene_order = a["scene_order"]
        self.top_k, self.temperature = a["top_k"], a["temperature"]
        self.avoid_collisions, self.stop_lines, self.lights = a["avoid_collisions"], a["stop_lines"], a["lights"]
        self.persistence = a["persistence"]
        self.reference_top_k = a["reference_top_k"]
        self.reference = reference_name(self.reference_top_k, self.temperature)
        self.render_size_px, self.render_radius_m = a["render_size_px"], a["render_radius_m"]
        self.core = TrafficCore(self.model, self.motion_vocab, self.background, self.horizon_steps, self.reward_config,
                                self.terminate_on, self.obs_config, self.top_k, self.temperature, self.avoid_collisions,
                                device=self.device, dtype=torch.float64, prior_cache_size=self.PRIOR_STATE_CACHE, record=True,
                                shield=a["shield"], shield_top_k=self.reference_top_k, stop_lines=self.stop_lines,
                                lights=self.lights, precision=a["precision"], persistence=self.persistence)
        self.shield = a["shield"]
        self._statics: dict[int, SceneStatic] = {}
        self._obs_spaces: dict[str, spaces.Space] = {}
        self._act_spaces: dict[str, spaces.Space] = {}
        self._np_random = np.random.default_rng()
        self._next_scene = 0
        self._renderer = None
        self._renderer_scene = None
        self._recorder = None
        self._human_fig = None
        self.scene_index = -1
        self.agents: list[str] = []
        self._last: CoreStep | None = None
        # the first scene's agents, so that spaces and possible_agents exist before reset()
        self._select_scene(0)

    # ------------------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Space:
        space = self._obs_spaces.get(agent)
        if space is None:
            t = self._agent_type_of_name(agent)
            box = spaces.Box(-np.inf, np.inf, (observation_size(self.obs_config),), np.float32)
            if self.obs_config.kind == "vector":
                space = box
            else:
                v = self.vocab_sizes[t]
                parts = {"observation": box, "action_mask": spaces.Box(0, 1, (v,), np.int8)}
                if self.model is not None:
                    parts["prior_logits"] = spaces.Box(-np.inf, np.inf, (v,), np.float32)
                space = spaces.Dict(parts)
            self._obs_spaces[agent] = space
        return space

    def action_space(self, agent: str) -> spaces.Space:
        space = self._act_spaces.get(agent)
        if space is None:
            space = spaces.Discrete(self.vocab_sizes[self._agent_type_of_name(agent)])
            self._act_spaces[agent] = space
        return space

    def _agent_type_of_name(self, agent: str) -> int:
        if agent not in self._obs_spaces and agent not in self._act_spaces and agent not in self.possible_agents:
            raise UnknownAgentError(f"unknown agent {agent!r}: the agents of this episode are {self.possible_agents[:8]}"
                                    f"{' ...' if len(self.possible_agents) > 8 else ''}")
        return int(AgentType[agent.rsplit("_", 1)[0].upper()])

    # ------------------------------------------------------------------------------- scenes
    def _static(self, index: int) -> SceneStatic:
        st = self._statics.get(index)
        if st is None:
            st = self._statics[index] = scene_static(self.scenes[index])
        return st

    def _select_scene(self, index: int) -> None:
        st = self._static(index)
        ctrl = select_controlled(self.controlled, st, self.max_agents)
        if len(ctrl) == 0:
            raise EnvConfigError(f"scene {st.scenario.scenario_id} has no controllable agent for controlled={self.controlled!r} "
                                 f"(only vehicles, pedestrians and cyclists present at the current frame can be controlled)")
        self.scene_index = index
        self.static = st
        self.ctrl_tracks = ctrl  # [C] track indices of possible_agents, in order
        self.possible_agents = [st.names[k] for k in ctrl]
        self._agent_track = {name: int(k) for name, k in zip(self.possible_agents, ctrl)}

    # -------------------------------------------------------------------------------- reset
    def reset(self, seed: int | None = None, options: dict | None = None):
        seed, index = check_reset_arguments(seed, options, len(self.scenes))  # envs._arguments: refused with a named error
        if seed is not None:
            self._np_random = np.random.default_rng(seed)
        if index is None:
            index = (int(self._np_random.integers(len(self.scenes))) if self.scene_order == "random"
                     else self._next_scene % len(self.scenes))
        self._next_scene = index + 1
        self._select_scene(index)
        prior_seed = int(seed) if seed is not None else int(self._np_random.integers(2**31))
        self.core.reset([CoreScene(self.static, self.ctrl_tracks, key=index)], prior_seed)
        self.agents = list(self.possible_agents)
        self._last = None
        obs = self._observations(self.agents)
        infos = self._infos(self.agents)
        if self._recorder is not None:
            self._recorder.frames.clear()
            self._recorder.add(self._render_frame())
        if self.render_mode == "human":
            self.render()
        return obs, infos

    # ------------------------------------------------------- the core's state, as numpy (scene 0)
    def _row(self, t: torch.Tensor) -> np.ndarray:
        return t[0, : self.static.num_tracks].cpu().numpy()

    @property
    def pose(self) -> np.ndarray:
        """[N, 3] every track's pose now (x, y, heading, the scene's local frame)."""
        return self._row(self.core.pose)

    @property
    def velocity(self) -> np.ndarray:
        """[N, 2] every track's velocity over the last 0.1 s (m/s)."""
        return self._row(self.core.velocity)

    @property
    def present(self) -> np.ndarray:
        """[N] bool, the tracks in the scene now."""
        return self._row(self.core.present)

    @property
    def hist_pose(self) -> np.ndarray:
        return self._row(self.core.hist_pose)

    @property
    def hist_valid(self) -> np.ndarray:
        return self._row(self.core.hist_valid)

    @property
    def frame(self) -> int:
        """The simulated 10 Hz frame of the scene."""
        return int(self.core.frame[0])

    @property
    def step_count(self) -> int:
        return int(self.core.step_count[0])

    @property
    def slot_of_track(self) -> np.ndarray:
        """[N] each track's slot in the prior's state (-1: none)."""
        return self._row(self.core.slot_of_track)

    @property
    def rollout_state(self):
        """The prior's :class:`~smart_marl.rollout.RolloutState` of this episode (None without a prior)."""
        return self.core.prior

    # ------------------------------------------------------------------------ observations
    def _light_state(self) -> tuple[np.ndarray, np.ndarray]:
        tl = self.static.scenario.traffic_lights
        f = min(self.frame, tl.num_frames - 1)
        return tl.states[f].astype(np.int64), tl.present[f]

    def _slots(self, agents: list[str]) -> list[int]:
        return [self.possible_agents.index(a) for a in agents]

    def _prior_rows(self) -> np.ndarray | None:
        """[C, Vmax] the prior's logits of each controlled agent's next token (zeros when done)."""
        logits = self.core.prior_logits()
        return None if logits is None else logits[0].to(torch.float32).cpu().numpy()

    def _observations(self, agents: list[str]) -> dict[str, Any]:
        if not agents:
            return {}
        vec = self.core.observations()[0].cpu().numpy()
        slots = self._slots(agents)
        if self.obs_config.kind == "vector":
            return {a: vec[i] for a, i in zip(agents, slots)}
        prior = self._prior_rows()
        out = {}
        for a, i in zip(agents, slots):
            v = self.vocab_sizes[int(self.static.types[self.ctrl_tracks[i]])]
            d = {"observation": vec[i], "action_mask": np.ones(v, np.int8)}
            if prior is not None:
                d["prior_logits"] = logits = prior[i, :v].copy()
                if logits.any():  # the reference's support: the shield's -inf out, then its top k
                    mask = np.isfinite(logits)
                    if self.reference_top_k:
                        mask &= top_k_mask(torch.from_numpy(logits), self.reference_top_k).numpy()
                    d["action_mask"] = mask.astype(np.int8)
            out[a] = d
        return out

    def _infos(self, agents: list[str]) -> dict[str, dict]:
        last = self._last
        prior = self._prior_rows() if self.model is not None else None
        out = {}
        for a, i in zip(agents, self._slots(agents)):
            info = {
                "collision": bool(last.collision[0, i]) if last is not None else False,
                "offroad": bool(last.offroad[0, i]) if last is not None else False,
                "goal_reached": bool(last.goal_reached[0, i]) if last is not None else False,
                "shield_replaced": bool(last.replaced[0, i]) if last is not None else False,
                "route_progress_m": float(self.core.progress_m[0, i]),
                "reward_terms": (last.terms[0, i].cpu().numpy() if last is not None else np.zeros(len(REWARD_TERMS))).astype(np.float32),
            }
            if prior is not None:
                v = self.vocab_sizes[int(self.static.types[self.ctrl_tracks[i]])]
                logits = prior[i, :v].copy()
                info["prior_logits"] = logits
                if logits.any():
                    info["prior_log_probs"] = reference_log_probs(torch.from_numpy(logits), self.reference_top_k,
                                                                  self.temperature).numpy()
                else:
                    info["prior_log_probs"] = np.zeros(v, np.float32)
                info["reference_top_k"] = int(self.reference_top_k or 0)
                info["action_log_prob"] = float(last.action_log_prob[0, i]) if last is not None else 0.0
            out[a] = info
        return out

    # --------------------------------------------------------------------------------- step
    def _check_actions(self, actions: dict) -> np.ndarray:
        """Validated token ids [C] of the live agents (-1 for done ones)."""
        if not self.agents:
            raise EnvStateError("step() after every agent is done: call reset() to start a new episode")
        if not isinstance(actions, dict):
            raise ActionTypeError(f"actions must be a dict {{agent name: token id}}, got {type(actions).__name__}")
        unknown = [a for a in actions if a not in self._agent_track]
        if unknown:
            raise UnknownAgentError(f"unknown agent(s) {unknown[:5]}: the agents of this episode are {self.possible_agents[:8]}"
                                    f"{' ...' if len(self.possible_agents) > 8 else ''}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ActionError(f"no action for live agent(s) {missing[:5]}: every agent in env.agents needs a token id")
        tokens = np.full(len(self.possible_agents), -1, np.int64)
        live = set(self.agents)
        for i, a in enumerate(self.possible_agents):
            if a not in live:
                continue  # done agents: their actions are ignored
            act = np.asarray(actions[a])
            whole = act.size == 1 and (np.issubdtype(act.dtype, np.integer) or (
                np.issubdtype(act.dtype, np.floating) and bool(np.isfinite(act).all()) and float(act.reshape(())).is_integer()))
            if not whole:  # NaN, inf, a fraction, a string, a vector...
                raise ActionError(f"action of {a} must be one integer token id, got {actions[a]!r}")
            tok = int(act.reshape(()))
            v = self.vocab_sizes[int(self.static.types[self._agent_track[a]])]
            if not 0 <= tok < v:
                raise ActionError(f"action {tok} of {a} is outside its vocabulary: token ids are 0..{v - 1}")
            tokens[i] = tok
        return tokens

    def step(self, actions: dict):
        tokens = self._check_actions(actions)
        live_names = list(self.agents)
        actions_t = torch.zeros(1, self.core.num_agents, dtype=torch.long)
        actions_t[0, : len(tokens)] = torch.from_numpy(tokens.clip(min=0))
        actions_t = actions_t.to(self.device)
        self._last = r = self.core.step(actions_t)
        slots = self._slots(live_names)
        rewards = {a: float(r.reward[0, i]) for a, i in zip(live_names, slots)}
        terminations = {a: bool(r.terminated[0, i]) for a, i in zip(live_names, slots)}
        truncations = {a: bool(r.truncated[0, i]) for a, i in zip(live_names, slots)}
        obs = self._observations(live_names)
        infos = self._infos(live_names)
        self.agents = [a for a in live_names if not (terminations[a] or truncations[a])]
        if self._recorder is not None:
            self._recorder.add(self._render_frame())
        if self.render_mode == "human":
            self.render()
        return obs, rewards, terminations, truncations, infos

    # ----------------------------------------------------------------------------- results
    def trajectories(self) -> tuple[np.ndarray, np.ndarray]:
        """This episode's 10 Hz poses so far: ([N, 5 * steps, 3] x, y, heading in the scene's local
        frame, [N, 5 * steps] present), every track of the scene (frames current + 1 ...)."""
        return self.core.trajectories(0)

    # --------------------------------------------------------------------------- rendering
    def _render_frame(self) -> np.ndarray:
        st = self.static
        if self._renderer is None or self._renderer_scene != self.scene_index:
            if self._renderer is not None:
                self._renderer.close()
            self._renderer = BevRenderer(st.scenario, size_px=self.render_size_px, view_radius_m=self.render_radius_m, center="sdc")
            self._renderer_scene = self.scene_index
        ctrl = np.zeros(st.num_tracks, bool)
        ctrl[self.ctrl_tracks] = True
        ego = int(self.ctrl_tracks[0])
        state, present = self._light_state()
        text = f"{st.scenario.scenario_id}  step {self.step_count}/{self.horizon_steps}  t={self.step_count * FRAMES_PER_TOKEN * DT_S:.1f} s"
        return self._renderer.render(self.pose[:, :2], self.pose[:, 2], st.box_size, self.present, st.types, controlled=ctrl,
                                     ego_index=ego, trajectories=self.hist_pose[:, :, :2], trajectories_valid=self.hist_valid,
                                     light_states=state, light_present=present, text=text)

    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn("render() without a render_mode: pass render_mode='rgb_array' or 'human' to parallel_env()")
            return None
        if self.core.scenes is None:
            raise EnvStateError("render() before reset()")
        frame = self._render_frame()
        if self.render_mode == "rgb_array":
            return frame
        import matplotlib.pyplot as plt

        if self._human_fig is None:
            self._human_fig, ax = plt.subplots(figsize=(6, 6))
            ax.set_axis_off()
            self._human_image = ax.imshow(frame)
        else:
            self._human_image.set_data(frame)
        plt.pause(1.0 / self.metadata["render_fps"])
        return None

    def start_recording(self, path: str | os.PathLike, fps: float | None = None) -> None:
        """Record one bird's-eye frame per token step (from the next reset or now) to a GIF or MP4."""
        self._recorder = EpisodeRecorder(path, fps=fps or self.metadata["render_fps"])
        if self.core.scenes is not None:
            self._recorder.add(self._render_frame())

    def save_recording(self) -> Path:
        """Write the recorded frames (see :meth:`start_recording`) and stop recording; returns the path."""
        if self._recorder is None:
            raise EnvStateError("save_recording() without start_recording()")
        path = self._recorder.write()
        self._recorder = None
        return path

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._human_fig is not None:
            import matplotlib.pyplot as plt

            plt.close(self._human_fig)
            self._human_fig = None


# --------------------------------------------------------------------------- entry points
def parallel_env(scenarios="embedded", prior="embedded", controlled="sdc", background: str = "prior", horizon_steps: int = 16,
                 reward=None, observation="vector", render_mode: str | None = None, max_agents: int | None = None,
                 **kwargs) -> SmartTrafficEnv:
    """The parallel environment. ``controlled``: "sdc", "predict" (tracks to predict), "vehicles",
    "all", a list of track ids or names, or a callable(scene) -> [N] bool mask; ``max_agents`` keeps
    at most that many controlled agents (the nearest to the self-driving car). ``reward``: a
    :class:`~envs._reward.RewardConfig` or a dict of weights; ``observation``: "vector", "dict"
    or an :class:`~envs._observation.ObservationConfig`. Other keywords: ``terminate_on``,
    ``scene_order`` ("sequential" or "random" with the reset seed), ``motion_vocab`` (needed with
    ``prior=None``), ``top_k``, ``temperature``, ``reference_top_k``, ``avoid_collisions`` (the prior's
    background keeps its sampled tokens out of other agents' boxes, :mod:`smart_marl.rollout.avoidance`;
    default True), ``stop_lines`` (its vehicles stop at red lights and stop signs and move off again when the light
    turns green, the sign is served or the queue ahead drives off, :mod:`smart_marl.rollout.stop_lines`; default True),
    ``lights`` ("log": the prior and the stop lines see the log's light states at every step, held after the scene's
    last logged frame; "current": the current frame's, held), ``precision`` (the prior's arithmetic: "float32", the
    default, or "bfloat16", :mod:`smart_marl.model.precision`), ``persistence`` (its vehicles lean toward going on with
    the change of speed they are in, :mod:`smart_marl.rollout.persistence`; default 0.25, 0: off), ``shield`` (the same for the controlled agents' action masks, plus staying on the road:
    :mod:`envs._shield`; default off), ``render_size_px``, ``render_radius_m``, ``device`` (``"cuda"``: the prior and the state on the
    GPU; what a step returns is numpy as always)."""
    return SmartTrafficEnv(scenarios=scenarios, prior=prior, controlled=controlled, background=background,
                           horizon_steps=horizon_steps, reward=reward, observation=observation, render_mode=render_mode,
                           max_agents=max_agents, **kwargs)


def raw_env(**kwargs):
    """The AEC form without wrappers (agents act in turn; a full step runs when the last one has acted)."""
    return parallel_to_aec_wrapper(parallel_env(**kwargs))


def env(**kwargs):
    """The AEC form with PettingZoo's standard order-enforcing wrapper."""
    return wrappers.OrderEnforcingWrapper(raw_env(**kwargs))


__all__ = ["BACKGROUNDS", "EnvError", "EnvConfigError", "UnknownAgentError", "ActionError", "EnvStateError", "ObservationConfig", "RewardConfig", "SmartTrafficEnv",
           "env", "observation_layout", "observation_size", "parallel_env", "raw_env"]
