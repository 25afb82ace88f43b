"""Environment stage, the batched core: ``B`` scenes stepped as one (GPUDrive's worlds, Waymax's
batched state). Both faces of the environment run on it: the PettingZoo ``smart_traffic_v0`` (one
scene, dict views) and the TorchRL ``smart_traffic_batched_v0`` (tensors, ``batch_size=[B]``).

What comes in: scenes with their controlled agents (:class:`CoreScene`), the prior (a SMART model
and its motion vocabulary, or None) and the settings. What goes out, every step: per controlled
agent slot ``[B, C]`` the reward, termination, truncation, events and reward terms
(:class:`CoreStep`); on demand the observations ``[B, C, D]`` and the prior's next-token logits
``[B, C, Vmax]``.

State (tensors on ``device``, a leading scene dimension, agents in padded slots with masks): every
track's pose, velocity, presence and pose history ``[B, N, ...]``; the controlled agents' slots
``ctrl_track [B, C]`` (-1: padding), whether they are done, their route progress ``[B, C]``; the
clock ``frame``, ``step_count`` ``[B]``; the prior's :class:`~smart_marl.rollout.RolloutState` (one
group per scene) and each track's slot in it.

One :meth:`TrafficCore.step`, with no loop over scenes or agents: the dynamics
(:func:`envs._dynamics.move`: one incremental SMART step for every agent of every scene, the
controlled agents' tokens forced), the state update, the events and rewards
(:func:`envs._reward.step_reward`), the prior releasing agents that are done
(:func:`envs._dynamics.release`). A finished scene is replaced in place (:meth:`TrafficCore.refill`:
its rows of the state, of the scene constants and of the prior's KV cache), so the batch stays full.
Starting a scene's prior (tokenizing its history, encoding its road) is the expensive part of a
reset; the core keeps the freshly started prior state of up to ``prior_cache_size`` scenes (by their
``key``) and hands out copies of it.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Hashable, Sequence

import numpy as np
import torch

from smart_marl.cpu_memory import keep_freed_memory
from smart_marl.model.precision import inference_model
from smart_marl.padding import grow
from smart_marl.rollout import DEFAULT_TOP_K, RolloutState
from smart_marl.rollout.persistence import DEFAULT_PERSISTENCE
from smart_marl.rollout.refill import replace_scenes, split_state, stack_states
from smart_marl.scenario import DT_S
from smart_marl.tokens import FRAMES_PER_TOKEN, MOTION_TYPES, MotionVocabulary

from ._dynamics import BACKGROUNDS, Motion, draw_background, move, release
from ._observation import HISTORY_FRAMES, ObservationConfig, build_observations
from ._reward import TERMINATION_EVENTS, RewardConfig, StepReward, route_progress_m, step_reward
from ._scene import SceneStatic
from ._scene_batch import SceneBatch, gather_tracks
from ._shield import joint_actions, unsafe_tokens


START_CHUNK = 16
"""Scenes whose prior states are started in one batch (the road encoder's memory grows with the square of a
scene's road tokens: ~80 MB a generated scene)."""


@dataclass
class CoreScene:
    """A scene for the core: its constants, its controlled agents and a key for the prior cache."""

    static: SceneStatic
    controlled: np.ndarray  # [C_b] int64 track indices of the controlled agents, in order
    key: Hashable | None = None  # the scene's identity for the prior-state cache (None: not cached)


@dataclass
class CoreStep:
    """One step's outcome per controlled slot [B, C] (padded and already-done slots: zeros, False)."""

    acted: torch.Tensor  # [B, C] bool, the agents that took this step's action
    reward: torch.Tensor  # [B, C] float64
    terminated: torch.Tensor  # [B, C] bool
    truncated: torch.Tensor  # [B, C] bool (live at the horizon, not terminated)
    collision: torch.Tensor  # [B, C] bool
    offroad: torch.Tensor  # [B, C] bool
    goal_reached: torch.Tensor  # [B, C] bool
    progress_m: torch.Tensor  # [B, C] route progress after the step
    terms: torch.Tensor  # [B, C, 8] reward terms (REWARD_TERMS order)
    action_log_prob: torch.Tensor  # [B, C] the prior's full-softmax log-probability of the token taken
    replaced: torch.Tensor  # [B, C] bool, the shield's "joint" check took another token than the one chosen


def token_pose_table(vocab: MotionVocabulary, device) -> torch.Tensor:
    """[3, Vmax, 6, 3] every type's token poses (zeros beyond a type's vocabulary)."""
    vmax = max(vocab[t].size for t in MOTION_TYPES)
    out = torch.zeros(len(MOTION_TYPES), vmax, FRAMES_PER_TOKEN + 1, 3)
    for k, t in enumerate(MOTION_TYPES):
        out[k, : vocab[t].size] = torch.from_numpy(vocab[t].poses)
    return out.to(device)


class TrafficCore:
    """``B`` scenes stepped as one (module docstring). Build it, :meth:`reset` it on ``B`` scenes,
    then :meth:`step` / :meth:`refill`."""

    def __init__(self, model, motion_vocab: MotionVocabulary, background: str = "prior", horizon_steps: int = 16,
                 reward: RewardConfig | None = None, terminate_on: Sequence[str] = TERMINATION_EVENTS,
                 observation: ObservationConfig | None = None, top_k: int = DEFAULT_TOP_K, temperature: float = 1.0,
                 avoid_collisions: bool = True, device="cpu", dtype=torch.float32, prior_cache_size: int = 8,
                 record: bool = False, shield: Sequence[str] = (), shield_top_k: int | None = None, stop_lines: bool = True,
                 lights: str = "log", precision: str = "float32", persistence: float = DEFAULT_PERSISTENCE) -> None:
        if background not in BACKGROUNDS:
            raise ValueError(f"background must be one of {BACKGROUNDS}, got {background!r}")
        # the prior at its precision (smart_marl.model.precision: a bfloat16 copy is made once and kept)
        self.model = None if model is None else inference_model(model, precision)
        self.motion_vocab, self.background, self.precision = motion_vocab, background, precision
        self.horizon_steps = int(horizon_steps)
        self.reward_config = reward or RewardConfig()
        self.terminate_on = frozenset(terminate_on)
        self.obs_config = observation or ObservationConfig()
        self.top_k, self.temperature, self.avoid_collisions = int(top_k), float(temperature), bool(avoid_collisions)
        self.stop_lines = bool(stop_lines)  # the background stops at red lights and stop signs (smart_marl.rollout.stop_lines)
        self.lights = lights  # what the prior and the stop lines see of the lights: the log's clock, or the current frame's
        self.persistence = float(persistence)  # the background's speed persistence (smart_marl.rollout.persistence)
        self.device, self.dtype = torch.device(device), dtype
        self.shield, self.shield_top_k = tuple(shield), shield_top_k  # envs._shield: checks, and the k the policy draws from
        self._unsafe: tuple[torch.Tensor, torch.Tensor] | None = None  # (the logits it was computed on, the shield's mask)
        if self.device.type == "cpu":
            # a step allocates and frees tensors of megabytes (attention edges, their embeddings): kept in the
            # process, their pages are not faulted in afresh every step (smart_marl.cpu_memory)
            keep_freed_memory()
        self.token_poses = token_pose_table(motion_vocab, self.device).to(dtype)
        self.vocab_sizes = torch.tensor([motion_vocab[t].size for t in MOTION_TYPES], dtype=torch.long)
        self.prior_cache_size = int(prior_cache_size)
        self._pristine: OrderedDict[Hashable, RolloutState] = OrderedDict()
        self.record = bool(record)
        self.timing = {"forward_s": 0.0}  # time spent in the prior's forward (the model), for benchmarks
        self.prior: RolloutState | None = None
        self.scenes: SceneBatch | None = None

    # ------------------------------------------------------------------------------ sizes
    @property
    def num_scenes(self) -> int:
        return 0 if self.scenes is None else self.scenes.num_scenes

    @property
    def num_agents(self) -> int:
        """C, the controlled slots per scene."""
        return int(self.ctrl_track.shape[1])

    @property
    def live(self) -> torch.Tensor:
        """[B, C] bool, the controlled agents that act at the next step."""
        return (self.ctrl_track >= 0) & ~self.ctrl_done

    # ---------------------------------------------------------------------- reset, refill
    def reset(self, scenes: Sequence[CoreScene], seed: int, num_agents: int | None = None) -> None:
        """Start ``B = len(scenes)`` episodes, one per row; the prior's sampler is seeded with
        ``seed``. ``num_agents``: the controlled slots C (default: the most controlled agents of any
        scene); a refill must fit in them."""
        if not scenes:
            raise ValueError("reset needs at least one scene")
        c = max(len(s.controlled) for s in scenes) if num_agents is None else int(num_agents)
        if any(len(s.controlled) > c for s in scenes):
            raise ValueError(f"a scene has more than num_agents={c} controlled agents")
        self.scenes = SceneBatch.build([s.static for s in scenes], self.dtype, self.device)
        b, n = self.scenes.num_scenes, self.scenes.num_tracks
        dev, dt = self.device, self.dtype
        self.ctrl_track = torch.full((b, c), -1, dtype=torch.long, device=dev)
        self.pose, self.velocity = torch.zeros(b, n, 3, dtype=dt, device=dev), torch.zeros(b, n, 2, dtype=dt, device=dev)
        self.present = torch.zeros(b, n, dtype=torch.bool, device=dev)
        self.in_sim, self.done_track = torch.zeros_like(self.present), torch.zeros_like(self.present)
        self.hist_pose = torch.zeros(b, n, HISTORY_FRAMES, 3, dtype=dt, device=dev)
        self.hist_valid = torch.zeros(b, n, HISTORY_FRAMES, dtype=torch.bool, device=dev)
        self.frame = torch.zeros(b, dtype=torch.long, device=dev)
        self.step_count = torch.zeros_like(self.frame)
        self.ctrl_done = torch.zeros(b, c, dtype=torch.bool, device=dev)
        self.goal_done, self.progress_m = torch.zeros_like(self.ctrl_done), torch.zeros(b, c, dtype=dt, device=dev)
        self.slot_of_track = torch.full((b, n), -1, dtype=torch.long, device=dev)
        self.episode: list[tuple[torch.Tensor, torch.Tensor]] = []
        self._start_rows(list(range(b)), scenes)
        self.prior = None
        if self.model is not None:
            self.prior = stack_states(self._prior_starts(scenes), seed)
            self.prior.log_probs_of = "forced"  # the controlled agents' log-probabilities are read, the background's are not
            self._map_slots(list(range(b)))

    def refill(self, rows: Sequence[int], scenes: Sequence[CoreScene]) -> None:
        """Put new episodes of ``scenes`` in rows ``rows`` (the others go on untouched)."""
        rows = [int(r) for r in rows]
        if not rows:
            return
        if any(len(s.controlled) > self.num_agents for s in scenes):
            raise ValueError(f"a refill scene has more than the {self.num_agents} controlled slots")
        self.scenes.write(rows, [s.static for s in scenes])
        n = self.scenes.num_tracks
        for name, fill in (("pose", 0.0), ("velocity", 0.0), ("present", False), ("in_sim", False), ("done_track", False),
                           ("hist_pose", 0.0), ("hist_valid", False), ("slot_of_track", -1)):
            setattr(self, name, grow(getattr(self, name), {1: n}, fill))
        self._start_rows(rows, scenes)
        if self.prior is not None:
            replace_scenes(self.prior, rows, stack_states(self._prior_starts(scenes), 0))
            self._map_slots(rows)

    def _start_rows(self, rows: list[int], scenes: Sequence[CoreScene]) -> None:
        """The state of rows ``rows`` at their scenes' current frame."""
        sb, dev = self.scenes, self.device
        idx = torch.tensor(rows, dtype=torch.long, device=dev)
        cf = sb.current_frame[idx]  # [k]
        k, n = len(rows), sb.num_tracks
        log_pose, log_valid = sb.log_pose[idx], sb.log_valid[idx]
        now = cf[:, None, None].expand(k, n, 1)
        self.pose[idx] = log_pose.gather(2, now[..., None].expand(-1, -1, -1, 3))[:, :, 0]
        self.present[idx] = log_valid.gather(2, now)[:, :, 0]
        self.in_sim[idx] = self.present[idx]
        self.done_track[idx] = False
        self.velocity[idx] = sb.cv_velocity[idx]
        f = cf[:, None] + 1 - HISTORY_FRAMES + torch.arange(HISTORY_FRAMES, device=dev)  # [k, H]
        fi = f.clamp(min=0)[:, None].expand(k, n, -1)
        self.hist_pose[idx] = log_pose.gather(2, fi[..., None].expand(-1, -1, -1, 3))
        self.hist_valid[idx] = log_valid.gather(2, fi) & (f >= 0)[:, None]
        self.frame[idx], self.step_count[idx] = cf, 0
        ctrl = torch.full((k, self.num_agents), -1, dtype=torch.long, device=dev)
        for i, s in enumerate(scenes):  # reset path only: one small copy per new scene
            ctrl[i, : len(s.controlled)] = torch.as_tensor(np.asarray(s.controlled, np.int64), device=dev)
        self.ctrl_track[idx] = ctrl
        self.ctrl_done[idx], self.goal_done[idx] = False, False
        start = gather_tracks(self.pose, self.ctrl_track)[..., :2]
        self.progress_m[idx] = route_progress_m(sb, self.ctrl_track, start)[idx].to(self.dtype)

    def forget_starts(self) -> None:
        """Drop the prior's started states kept for scenes played before (``prior_cache_size``)."""
        self._pristine.clear()

    def _prior_starts(self, scenes: Sequence[CoreScene]) -> list[RolloutState]:
        """A freshly started prior state per scene: kept ones for known keys, the others started
        together (one batch) and kept."""
        out: list[RolloutState | None] = [self._pristine.get(s.key) if s.key is not None else None for s in scenes]
        first: dict = {}  # each missing scene is started once, however often it appears
        for i, st in enumerate(out):
            if st is None:
                first.setdefault(scenes[i].key if scenes[i].key is not None else ("row", i), i)
        if first:
            todo, states = list(first.values()), []
            for lo in range(0, len(todo), START_CHUNK):  # the road encoder's neighbour search is quadratic in road tokens
                chunk = todo[lo:lo + START_CHUNK]
                started = RolloutState.start(self.model, [scenes[i].static.scenario for i in chunk], num_rollouts=1, seed=0,
                                             top_k=self.top_k, temperature=self.temperature, device=self.device,
                                             motion_vocab=self.motion_vocab, avoid_collisions=self.avoid_collisions,
                                             stop_lines=self.stop_lines, lights=self.lights, persistence=self.persistence)
                states += split_state(started) if len(chunk) > 1 else [started]
            fresh = dict(zip(first, states))
            for i, st in enumerate(out):
                if st is None:
                    out[i] = fresh[scenes[i].key if scenes[i].key is not None else ("row", i)]
        for s, st in zip(scenes, out):
            if s.key is not None:
                self._pristine[s.key] = st
                self._pristine.move_to_end(s.key)
        while len(self._pristine) > self.prior_cache_size:
            self._pristine.popitem(last=False)
        return out

    def _map_slots(self, rows: list[int]) -> None:
        """``slot_of_track`` of rows ``rows`` from the prior's slots."""
        idx = torch.tensor(rows, dtype=torch.long, device=self.device)
        ti = self.prior.track_index[idx]  # [k, Ns]
        slot_of = torch.full((len(rows), self.scenes.num_tracks), -1, dtype=torch.long, device=self.device)
        kb, ks = (ti >= 0).nonzero(as_tuple=True)
        slot_of[kb, ti[kb, ks]] = ks
        self.slot_of_track = grow(self.slot_of_track, {1: self.scenes.num_tracks}, -1)
        self.slot_of_track[idx] = slot_of

    # --------------------------------------------------------------------------------- step
    def forward(self) -> torch.Tensor | None:
        """The prior's next-token logits of every slot [B, Ns, Vmax] (the model's forward, computed
        once per step; timed in ``timing["forward_s"]``), or None without a prior. With them, the background's
        tokens of the step are drawn (:func:`envs._dynamics.draw_background`): before the policy acts, as SMART
        draws every agent's token from one forward pass, so they do not depend on the controlled agents' tokens."""
        if self.prior is None:
            return None
        if self.prior._logits is None:
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            t0 = time.perf_counter()
            self.prior.logits()
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            self.timing["forward_s"] += time.perf_counter() - t0
        if self.prior.drawn_ahead() is None:  # the background's tokens, drawn before the controlled agents act
            draw_background(self.scenes, self.background, self.token_poses, self.prior, self.slot_of_track, self.pose, self.present,
                            self.in_sim, self.done_track, self.frame, self.ctrl_track, self.live)
        return self.prior.logits()

    def step(self, actions: torch.Tensor) -> CoreStep:
        """One token step of every scene. ``actions`` [B, C] long: the token of each live controlled
        agent (entries of padded and done agents are ignored)."""
        live = self.live
        actions = torch.where(live, actions.to(self.device, torch.long), torch.zeros_like(self.ctrl_track))
        self.forward()
        replaced = torch.zeros_like(live)
        if "joint" in self.shield and self.prior is not None:  # the chosen tokens checked against each other
            slot, has = self._controlled_slots()
            actions, replaced = joint_actions(self.prior, self.scenes, slot, has, actions, self.prior_logits(), self.shield_top_k)
        # 1. dynamics: every agent's 5 new frames (the prior, if any, takes its step here)
        motion = move(self.scenes, self.background, self.token_poses, self.prior, self.slot_of_track, self.pose, self.present,
                      self.in_sim, self.done_track, self.frame, self.ctrl_track, live, actions)
        self._advance(motion)
        # 2. events, rewards and termination of the controlled agents
        logp = gather_tracks(motion.action_log_prob, self.ctrl_track) * live
        r = step_reward(self.scenes, self.reward_config, self.terminate_on, self.ctrl_track, live, motion.frames, motion.present,
                        gather_tracks(self.hist_pose, self.ctrl_track), gather_tracks(self.hist_valid, self.ctrl_track),
                        self.progress_m, self.goal_done, logp)
        truncated = live & ~r.terminated & (self.step_count >= self.horizon_steps)[:, None]
        self._record_outcome(live, r, truncated)
        # 3. the prior forgets done agents and log agents that left
        if self.prior is not None:
            release(self.prior, self.slot_of_track, self.done_track | ~self.present)
        # a terminated controlled agent leaves the scene (truncation ends the episode: everyone stays drawn)
        tb, tc = (r.terminated & live).nonzero(as_tuple=True)
        self.present[tb, self.ctrl_track[tb, tc]] = False
        return CoreStep(acted=live, reward=r.reward, terminated=r.terminated & live, truncated=truncated, collision=r.collision,
                        offroad=r.offroad, goal_reached=r.goal_reached, progress_m=r.progress_m, terms=r.terms,
                        action_log_prob=logp, replaced=replaced)

    def _advance(self, motion: Motion) -> None:
        """The state update of a step: poses, velocities, the pose history, who is present, the clock."""
        frames = motion.frames
        self.pose = frames[:, :, -1].clone()
        self.velocity = (frames[:, :, -1, :2] - frames[:, :, -2, :2]) / DT_S
        self.hist_pose = torch.cat([self.hist_pose[:, :, FRAMES_PER_TOKEN:], frames], 2)
        self.hist_valid = torch.cat([self.hist_valid[:, :, FRAMES_PER_TOKEN:],
                                     motion.present[:, :, None].expand(-1, -1, FRAMES_PER_TOKEN)], 2)
        self.present = motion.present.clone()  # terminated agents leave it below; the record keeps the step's
        self.frame = self.frame + FRAMES_PER_TOKEN
        self.step_count = self.step_count + 1
        if self.record:
            self.episode.append((frames, motion.present))

    def _record_outcome(self, live: torch.Tensor, r: StepReward, truncated: torch.Tensor) -> None:
        self.progress_m = torch.where(live, r.progress_m.to(self.dtype), self.progress_m)
        self.goal_done = self.goal_done | r.goal_reached
        done = live & (r.terminated | truncated)
        self.ctrl_done = self.ctrl_done | done
        db, dc = done.nonzero(as_tuple=True)
        self.done_track[db, self.ctrl_track[db, dc]] = True

    # -------------------------------------------------------------------------------- views
    def observations(self) -> torch.Tensor:
        """[B, C, D] float32 observation of every controlled slot (zeros on padding)."""
        return build_observations(self.obs_config, self.scenes, self.ctrl_track, self.pose, self.velocity, self.present,
                                  self.hist_pose, self.hist_valid, self.progress_m, self.frame,
                                  self.step_count.to(self.dtype) / self.horizon_steps)

    def prior_logits(self) -> torch.Tensor | None:
        """[B, C, Vmax] the prior's logits of each controlled agent's next token (``-inf`` beyond its
        type's vocabulary; all zeros for padded and done agents: the prior has no next token for
        them), or None without a prior. With a shield (:mod:`envs._shield`), ``-inf`` on the tokens it
        takes out."""
        logits = self.forward()
        if logits is None:
            return None
        slot, has = self._controlled_slots()
        out = logits.gather(1, slot[..., None].expand(-1, -1, logits.shape[-1]))
        if self.shield:  # once per step (the logits are a new tensor every step, and after a reset or refill)
            if self._unsafe is None or self._unsafe[0] is not logits:
                self._unsafe = (logits, unsafe_tokens(self.shield, self.prior, self.scenes, self.ctrl_track, slot, has,
                                                      out, self.shield_top_k, self.prior.drawn_ahead()))
            out = out.masked_fill(self._unsafe[1], float("-inf"))
        return torch.where(has[..., None], out, torch.zeros_like(out))

    def _controlled_slots(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each controlled agent's prior slot [B, C] (0 where it has none), and bool [B, C]: it acts and has one."""
        slot = gather_tracks(self.slot_of_track, self.ctrl_track)
        has = self.live & (slot >= 0) & self.prior.valid.gather(1, slot.clamp(min=0))
        return slot.clamp(min=0), has

    def trajectories(self, row: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """The recorded episode of row ``row`` (``record=True``): ([N, 5 * steps, 3] x, y, heading,
        [N, 5 * steps] present) of every track of its scene, frames current + 1 ..."""
        n = self.scenes.statics[row].num_tracks
        if not self.episode:
            return np.zeros((n, 0, 3)), np.zeros((n, 0), bool)
        poses = torch.cat([f[row, :n] for f, _ in self.episode], 1).cpu().numpy().astype(np.float64)
        present = torch.stack([p[row, :n] for _, p in self.episode], 1).cpu().numpy()
        return poses, np.repeat(present, FRAMES_PER_TOKEN, 1)


__all__ = ["CoreScene", "CoreStep", "TrafficCore", "token_pose_table"]
