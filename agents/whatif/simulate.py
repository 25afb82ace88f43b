"""What-if scenarios, simulation: a prepared what-if rolled out with the SMART prior.

Stage: agents (what-if). What comes in: a SMART model and its motion vocabulary, and a
:class:`~agents.whatif.prepare.Prepared` what-if. What goes out: :class:`SimRollouts`, every track
of the edited scene over the rollout's 10 Hz frames. The rollout loop is the engine's own
(:meth:`smart_marl.rollout.RolloutState.run`, slots mapped back to tracks by
:func:`smart_marl.rollout.track_frames`); what happens here is the what-if's part of each step
(:class:`ScriptedSteps`): removals, light overrides, and the forced tokens of scripted agents, each
the token of its type's vocabulary closest to the next 5 frames of its target path, looking one
token ahead (:func:`smart_marl.tokens.motion.match_token_path`), from the pose it actually reached.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch

from smart_marl.rollout import DEFAULT_TOP_K, RolloutState, StepOutput, track_frames
from smart_marl.rollout.persistence import DEFAULT_PERSISTENCE
from smart_marl.scenario import DT_S, Scenario
from smart_marl.tokens import FRAMES_PER_TOKEN, road_pieces
from smart_marl.tokens.motion import match_token_path, path_heading_weight

from .. import scripted
from .edits import WhatIfError
from .prepare import Prepared, moving_frames


@dataclass
class SimRollouts:
    """R rollouts of one scene: every track of ``scene`` over ``T`` future frames (local frame)."""

    scene: Scenario
    poses: np.ndarray  # [R, A, T, 3] x, y, heading (NaN where absent)
    present: np.ndarray  # [R, A, T] bool: simulated (driven by the prior or a script) on that frame
    scripted: np.ndarray  # [R, A, T] bool: moved by a forced token on that frame
    light_states: np.ndarray  # [T, L] SignalState per future frame (the scene's, after overrides)
    light_present: np.ndarray  # [T, L] bool

    @property
    def track_ids(self) -> np.ndarray:
        return self.scene.tracks.ids

    def speed_mps(self) -> np.ndarray:
        """[R, A, T] speed over each 0.1 s frame (the first from the current pose), NaN where absent."""
        cf = self.scene.current_frame
        tr = self.scene.tracks
        start = np.concatenate([tr.position[:, cf, :2], tr.heading[:, cf, None]], -1).astype(np.float64)
        p = np.concatenate([np.broadcast_to(start[None, :, None], (self.poses.shape[0], len(start), 1, 3)), self.poses], 2)
        return np.linalg.norm(np.diff(p[..., :2], axis=2), axis=-1) / DT_S


def override_road_lights(state, piece_light_index: np.ndarray, lane_indices: np.ndarray, code: int) -> None:
    """Force the light state of the road pieces of ``lane_indices`` (indices into the scene's
    ``traffic_lights``) to ``code`` in a running :class:`~smart_marl.rollout.RolloutState` of one
    scene (:meth:`~smart_marl.rollout.RolloutState.set_road_light`: RoadNet re-runs and the KV
    cache's road keys and values are re-projected), so every later step's map attention sees it.
    ``piece_light_index`` [R]: each road piece's traffic-light lane index (``road_pieces(...).traffic_light_index``,
    the same pieces in the same order as the state's road tokens)."""
    sel = torch.from_numpy(np.isin(piece_light_index, lane_indices) & (piece_light_index >= 0)).to(state.device)
    light = state.road_light.clone()
    light[:, : len(sel)][:, sel] = int(code)
    state.set_road_light(light)


class ScriptedSteps:
    """The what-if's part of every rollout step (``RolloutState.run``'s ``before_step``): the removals
    and light overrides due at step ``k``, then the forced tokens [G, N] of the scripted agents
    (``-1`` elsewhere). Nothing is forced with ``scripted_on=False`` (the unperturbed baseline)."""

    def __init__(self, state: RolloutState, prepared: Prepared, scripted_on: bool = True) -> None:
        scene = prepared.scene
        self.prepared, self.scripted_on = prepared, scripted_on
        g, n = state.num_groups, state.num_slots
        ids = state.agent_ids[0].cpu().numpy()
        self.slot_of = {int(t): k for k, t in enumerate(ids) if t >= 0 and bool(state.simulated[0, k])}
        tr, cf = scene.tracks, scene.current_frame
        ti = state.track_index[0].cpu().numpy()
        self.speed = np.zeros((g, n))  # each slot's speed at the last frame (m/s), for paths that start now
        ok = ti >= 0
        self.speed[:, ok] = np.linalg.norm(tr.velocity[ti[ok], cf].astype(np.float64), axis=-1)[None]
        self.scripts = [dataclasses.replace(s, path=None) for s in prepared.scripts] if scripted_on else []
        for s in self.scripts:
            if s.track_id not in self.slot_of:
                raise WhatIfError(None, f"agent {s.track_id} is not simulated in scene {scene.scenario_id} (not valid at the "
                                        f"current frame, or not a vehicle, pedestrian or cyclist)")
        self.piece_tl = (road_pieces(scene.road_map, scene.traffic_lights).traffic_light_index
                         if (scripted_on and prepared.lights) else None)

    def __call__(self, state: RolloutState, k: int, last: StepOutput | None) -> torch.Tensor:
        if last is not None:
            p = last.poses.cpu().numpy().astype(np.float64)  # (G, N, 5, 3)
            self.speed = np.linalg.norm(p[:, :, -1, :2] - p[:, :, -2, :2], axis=-1) / DT_S
        if self.scripted_on:
            for step, gone in self.prepared.removals:
                if step == k:
                    state.set_agent_valid(~torch.from_numpy(np.isin(state.agent_ids.cpu().numpy(), gone)))
            for step, lanes, code in self.prepared.lights:
                if step == k:
                    override_road_lights(state, self.piece_tl, lanes, code)
        forced = torch.full((state.num_groups, state.num_slots), -1, dtype=torch.long)
        for s in self.scripts:
            slot = self.slot_of[s.track_id]
            j = k - s.start_step
            if j < 0 or (s.end_step is not None and j >= s.end_step):
                continue
            if not bool(state.simulated[0, slot]):
                continue
            atype = int(state.agent_type[0, slot])
            if s.tokens is not None:
                if j < len(s.tokens):
                    forced[:, slot] = s.tokens[j]
                elif s.then == "hold":
                    forced[:, slot] = _nearest(state, atype, slot, _standing(state, slot))
                continue
            if s.path is None:
                onset_pose = state.current_pose[:, slot].cpu().numpy().astype(np.float64)
                s.path = s.make_path(onset_pose, self.speed[:, slot])
                if s.then == "release" and s.end_step is None:  # released once the scripted motion has ended
                    moving = max(moving_frames(np.concatenate([onset_pose[r, None], s.path[r]])) for r in range(len(onset_pose)))
                    s.end_step = int(math.ceil(moving / FRAMES_PER_TOKEN))
            lo = FRAMES_PER_TOKEN * j
            if lo >= s.path.shape[1]:
                if s.then == "hold":  # past the path's end: stand
                    forced[:, slot] = _nearest(state, atype, slot, _standing(state, slot))
                continue
            seg = s.path[:, lo: lo + 2 * FRAMES_PER_TOKEN]  # this token's 5 frames and the next one's (look-ahead)
            if seg.shape[1] < 2 * FRAMES_PER_TOKEN:
                seg = np.concatenate([seg, np.repeat(seg[:, -1:], 2 * FRAMES_PER_TOKEN - seg.shape[1], 1)], 1)
            still = np.ptp(seg[..., :2], axis=1).max(-1) < 1e-6  # [G] the path stands still over both tokens
            if still.any():  # stand where the tokens left the agent, rather than creep onto the path's end point
                seg = np.where(still[:, None, None], _standing(state, slot), seg)
            forced[:, slot] = _nearest(state, atype, slot, seg)
        return forced


def _standing(state: RolloutState, slot: int) -> np.ndarray:
    """Every group's ``slot`` standing still where it is, over a token and the next: [G, 10, 3]."""
    return scripted.hold_path(state.current_pose[:, slot].cpu().numpy(), 2 * FRAMES_PER_TOKEN)


def _nearest(state: RolloutState, atype: int, slot: int, targets: np.ndarray) -> torch.Tensor:
    """Every group's token for ``slot`` toward ``targets`` [G, 5 or 10, 3] (local frame)."""
    return match_token_path(state.token_poses[atype].cpu(), int(state.vocab_sizes[atype]), state.current_pose[:, slot].cpu(),
                            torch.from_numpy(np.asarray(targets, np.float64)), path_heading_weight(atype)).to(torch.long)


def simulate(model, vocab, prepared: Prepared, num_rollouts: int, seed: int, num_steps: int = 16, top_k: int = DEFAULT_TOP_K,
             temperature: float = 1.0, device="cpu", scripted_on: bool = True, avoid_collisions: bool = True,
             stop_lines: bool = True, lights: str = "log", precision: str = "float32",
             persistence: float = DEFAULT_PERSISTENCE) -> SimRollouts:
    """Roll out ``prepared.scene`` with its per-step actions (``scripted_on=False``: the scene as
    it is, no forced tokens, removals or light changes; ``avoid_collisions``: collision-aware sampling
    of the prior's agents, :mod:`smart_marl.rollout.avoidance`; ``stop_lines``, ``lights``: its traffic control,
    :mod:`smart_marl.rollout.stop_lines`; ``precision``: the prior's arithmetic; ``persistence``: its vehicles'
    speed persistence, :mod:`smart_marl.rollout.persistence`)."""
    scene = prepared.scene
    state = RolloutState.start(model, scene, num_rollouts=num_rollouts, seed=seed, top_k=top_k, temperature=temperature,
                               device=device, motion_vocab=vocab, avoid_collisions=avoid_collisions, stop_lines=stop_lines,
                               lights=lights, precision=precision, persistence=persistence)
    outs = state.run(num_steps, ScriptedSteps(state, prepared, scripted_on))
    frames = track_frames(state, outs)
    t_frames = FRAMES_PER_TOKEN * num_steps
    tl = scene.traffic_lights
    cf = scene.current_frame
    fut = slice(cf + 1, cf + 1 + t_frames)
    ls, lp = tl.states[fut], tl.present[fut]
    if len(ls) < t_frames:  # a rollout past the scene's end: lights held
        pad = t_frames - len(ls)
        ls = np.concatenate([ls, np.repeat(tl.states[-1:], pad, 0)]) if len(tl.lane_ids) else np.zeros((t_frames, 0), np.int8)
        lp = np.concatenate([lp, np.repeat(tl.present[-1:], pad, 0)]) if len(tl.lane_ids) else np.zeros((t_frames, 0), bool)
    return SimRollouts(scene=scene, poses=frames.poses, present=frames.present, scripted=frames.forced, light_states=ls,
                       light_present=lp)
