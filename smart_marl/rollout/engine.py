"""Rollout stage: closed-loop generation with the SMART prior (history -> 8 s of joint futures).

What comes in: scenes (:class:`~smart_marl.scenario.Scenario`, history up to the current frame is
all that is read) and a SMART model (or a checkpoint). What goes out: a :class:`RolloutResult`
(10 Hz trajectories of every agent valid at the current frame, in the scene's *source* frame, with
the sampled tokens and their log-probabilities), or, step by step for the environment, a
:class:`RolloutState` whose :meth:`RolloutState.step` advances every agent by one 0.5 s token.

How a rollout runs:

1. History: each scene's tracks up to the current frame are tokenized by rolling matching (no
   noise; the future is never read). Agent *slots* are the vehicle/pedestrian/cyclist tracks with a
   valid history token or valid at the current frame. The last history step of every agent valid
   at the current frame is re-anchored at its logged current pose (so rollouts start exactly where
   the log is); an agent that is valid at the current frame but has no valid last history token
   (it appeared less than 0.5 s ago) gets a synthetic one: the token whose end best matches its
   logged velocity, placed so that it ends at the current pose.
2. Scenes x rollouts form one batch of ``G = scenes * num_rollouts`` groups (rollouts are batch
   copies; road encodings are computed once per scene and shared by its rollouts).
3. Every step: each simulated agent's next token is drawn from its type's distribution
   (:func:`~smart_marl.rollout.sampling.sample_tokens`: top-k with renormalised probabilities and a
   temperature; collision-aware by default: tokens whose frames would overlap another agent are not
   drawn, :mod:`~smart_marl.rollout.avoidance`, ``avoid_collisions=False`` samples plainly; traffic control,
   ``stop_lines=True`` by default: a vehicle does not draw tokens after which it could not stop before a red light's
   or an unserved stop sign's line ahead, and a standing vehicle that nothing holds any more (a green, a served sign,
   its leader driving off) does not draw the tokens that leave it standing, :mod:`~smart_marl.rollout.stop_lines`)
   or forced; the token's 6 poses (its contour's centre and heading) are placed at the
   agent's current pose; its last pose is where the agent is 0.5 s later (the next token starts
   there); the tokens go back in. The 10 Hz frames in between (:mod:`~smart_marl.rollout.frames`;
   ``interpolation="spline"``, the default) follow a cubic Hermite curve from the current pose to
   the token's end, whose tangent at each end is the displacement over the previous token and over
   this one: the frames are smooth across token boundaries (the token contours' own in-between poses
   come from other snippets, whose speed and yaw rate jump at every boundary), use no later step (a
   state stepped one token at a time gives the same frames as a whole rollout), and never change
   what the model sees (collision-aware sampling checks them, so they can change which token is drawn).
   ``interpolation="contour"`` keeps the token's own in-between poses.
   ``mode="cached"`` runs the new step through the model's KV-cached step
   (:meth:`SMART.step <smart_marl.model.SMART.step>`); ``mode="full"`` re-runs MotionNet over the
   whole history and every generated step (road encodings are reused in both modes: they do not
   change). The engine never reaches into the model: it calls ``encode_road``, ``start_cache``,
   ``step``, ``agent_features`` and ``next_token_logits``.

Agents: *simulated* = vehicle, pedestrian or cyclist valid at the current frame (WOSAC's rule:
an agent invalid at the current frame is not simulated). Agents of type OTHER valid at the current
frame are not driven by the model (it has no vocabulary for them); they get a constant-velocity
trajectory (their logged velocity at the current frame, heading held), so that every agent valid
at the current frame has a trajectory. z is carried from each agent's last valid frame.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..model.batch import light_codes, scene_road
from ..model.checkpoint import load_prior
from ..model.motionnet import NUM_MOTION_TYPES
from ..model.precision import check_precision, inference_model
from ..padding import pad_stack
from ..scenario import DT_S, Scenario
from ..tokens import FRAMES_PER_TOKEN, MOTION_TYPES, MotionVocabulary
from ..tokens.road import RoadVocabulary
from .drawing import Draw, check_forced, complete, draw_tokens
from .frames import INTERPOLATIONS, token_frames
from .history import scene_history
from .persistence import DEFAULT_PERSISTENCE, check_persistence, mean_speed, speed_before_history, token_speeds
from .sampling import DEFAULT_TOP_K
from .stop_lines import (lights_at, logged_light_steps, served_after_step, stood_after_step, stood_in_history, stop_line_tensors,
                         token_ends)

MODES = ("cached", "full")
LIGHTS = ("current", "log")
"""What the model and the stop lines see of the traffic lights in closed loop: "current" (the light states of the
current frame, held for the whole rollout: what training showed the model, and the sim-agents challenge's rule) or
"log" (before every step, the scene's logged states of the frame that step starts at, held after the scene's last
logged frame: lights that follow the clock; each scene of a batch on its own clock, so that a refilled scene starts
at its own current frame)."""


# ------------------------------------------------------------------------------ model inputs
def _dummy_road_vocab() -> RoadVocabulary:
    """Rollouts do not read road token ids (RoadNet embeds the pieces' points): a 1-token stand-in."""
    return RoadVocabulary(points=np.zeros((1, 11, 2), np.float32), tolerance_m=0.0, requested_size=1)


# ------------------------------------------------------------------------------------ state
@dataclass
class _RoadPart:
    """Some scenes' road inputs, for :meth:`SMART.encode_road <smart_marl.model.SMART.encode_road>`."""

    road_points: torch.Tensor
    road_pose: torch.Tensor
    road_type: torch.Tensor
    road_light: torch.Tensor
    road_valid: torch.Tensor


@dataclass
class StepOutput:
    """What one token step produced, for ``G`` groups and ``N`` agent slots.

    ``logits`` [G, N, Vmax]: the next-token logits the step's tokens were chosen from (raw, before
    the temperature), each row over its slot's type vocabulary, ``-inf`` beyond the type's size
    (``vocab_sizes[agent_type]``) and on rows of slots that are not simulated.
    """

    logits: torch.Tensor  # [G, N, Vmax]
    tokens: torch.Tensor  # [G, N] int64, -1 where not simulated
    log_probs: torch.Tensor  # [G, N] under log_softmax(logits / temperature), 0 where not simulated
    poses: torch.Tensor  # [G, N, 5, 3] the 5 new 10 Hz poses (local frame), x, y, heading
    simulated: torch.Tensor  # [G, N] bool
    forced: torch.Tensor  # [G, N] bool, simulated slots whose token was given, not sampled


class RolloutState:
    """A batch of running rollouts (the environment's handle on the prior). Make one with
    :meth:`start`; read :meth:`logits` for the next step's distribution; :meth:`step` to advance.

    Slots: ``G = scenes * num_rollouts`` groups (group ``g`` is rollout ``g % R`` of scene
    ``g // R``), ``N`` agent slots each (padded); ``agent_ids``, ``agent_type``, ``track_index``
    say who each slot is (``-1`` ids and track indices on padding).

    Public attributes: ``agent_ids`` [G, N], ``track_index`` [G, N], ``agent_type`` [G, N] (0..2),
    ``vocab_sizes`` [3] (so slot ``(g, n)``'s vocabulary has ``vocab_sizes[agent_type[g, n]]``
    tokens), ``valid`` / ``simulated`` [G, N], ``current_pose`` [G, N, 3] (local frame),
    ``generator`` (the sampler's ``torch.Generator``; replace it to reseed), ``num_groups``,
    ``num_slots``, ``step_index`` (token steps taken), ``scenes``, ``mode``, ``cache`` (the model's
    :class:`~smart_marl.model.MotionCache` in mode "cached"), ``log_probs_of`` (``"all"``; ``"forced"``: the
    forced slots' :attr:`StepOutput.log_probs` only, 0 elsewhere, for the environments). :meth:`run` steps in a loop,
    :meth:`fork` copies a state. Slots that are never simulated (agents seen in the history but gone at the current frame) are
    kept as context: the history's features of the others depend on them.
    """

    def __init__(self, model, vocab: MotionVocabulary, scenes: Sequence[Scenario], num_rollouts: int, seed: int, top_k: int,
                 temperature: float, device, mode: str, road_vocab: RoadVocabulary | None = None,
                 interpolation: str = "spline", avoid_collisions: bool = True, lights: str = "current",
                 stop_lines: bool = True, persistence: float = DEFAULT_PERSISTENCE) -> None:
        if lights not in LIGHTS:
            raise ValueError(f"lights must be one of {LIGHTS}, got {lights!r}")
        self.lights = lights
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
        self.model, self.vocab, self.mode, self.interpolation = model, vocab, mode, interpolation
        self.scenes = list(scenes)
        self.top_k, self.temperature = int(top_k), float(temperature)
        self.avoid_collisions, self.stop_lines, self.log_probs_of = bool(avoid_collisions), bool(stop_lines), "all"
        self.persistence = check_persistence(persistence)  # speed persistence (:mod:`~smart_marl.rollout.persistence`)
        self.device = torch.device(device)
        self.generator = torch.Generator(device=self.device).manual_seed(int(seed))
        self.num_rollouts = r = int(num_rollouts)
        cfg = model.config
        self.vocab_sizes = torch.tensor(cfg.motion_vocab_sizes, dtype=torch.long)
        dev = self.device
        # ---- per-scene history, padded to N slots and S steps, repeated R times
        hists = [scene_history(sc, vocab) for sc in self.scenes]
        n = max(max(len(h.track_index) for h in hists), 1)
        s = max(h.tokens.shape[1] for h in hists)
        # right-align the history steps so that every scene's last step is the current frame
        def right(a, fill=0):
            pad = s - a.shape[1]
            return np.concatenate([np.full((a.shape[0], pad, *a.shape[2:]), fill, a.dtype), a], 1) if pad else a
        rep = lambda a: torch.from_numpy(np.repeat(a, r, axis=0)).to(dev)  # noqa: E731  (B, ...) -> (G, ...)
        self.track_index = rep(pad_stack([h.track_index for h in hists], (n,), -1))
        self.agent_type = rep(pad_stack([h.agent_type for h in hists], (n,), 0))
        self.agent_shape = rep(pad_stack([h.agent_shape for h in hists], (n, 3)))
        self.simulated = rep(pad_stack([h.simulated for h in hists], (n,), False))
        hist_tokens = rep(pad_stack([right(h.tokens) for h in hists], (n, s)))
        hist_valid = rep(pad_stack([right(h.valid, False) for h in hists], (n, s), False))
        hist_start = rep(pad_stack([right(h.start_pose) for h in hists], (n, s, 3)))
        hist_end = rep(pad_stack([right(h.end_pose) for h in hists], (n, s, 3)))
        ids = [np.where(h.track_index >= 0, sc.tracks.ids[h.track_index], -1) for h, sc in zip(hists, self.scenes)]
        self.agent_ids = rep(pad_stack(ids, (n,), -1))
        self.num_groups, self.num_slots, self.num_history_steps = len(self.scenes) * r, n, s
        self.scene_of_group = torch.arange(len(self.scenes), device=dev).repeat_interleave(r)
        # ---- road: pieces per scene, encoded once per scene
        rv = road_vocab or _dummy_road_vocab()
        roads = [scene_road(sc, rv, cfg.road_settings) for sc in self.scenes]
        rmax = max(max(len(rd.token) for rd in roads), 1)
        p = cfg.road_piece_points
        t = lambda a: torch.from_numpy(a).to(dev)  # noqa: E731
        self.road_pose = t(pad_stack([rd.pose.astype(np.float32) for rd in roads], (rmax, 3)))
        self.road_valid = t(pad_stack([np.ones(len(rd.token), bool) for rd in roads], (rmax,), False))
        self.road_points = t(pad_stack([rd.local.astype(np.float32).reshape(-1, p, 2) for rd in roads], (rmax, p, 2)))
        self.road_type = t(pad_stack([rd.type_id for rd in roads], (rmax,)))
        self.road_light = t(pad_stack([rd.light for rd in roads], (rmax,)))
        self.scene_clock = torch.zeros(len(self.scenes), dtype=torch.long, device=dev)  # token steps each scene has run
        steps = max(logged_light_steps(sc) for sc in self.scenes) if lights == "log" else 1
        self.road_light_steps = None  # [B, S, R] the pieces' light codes on each logged token step (lights="log")
        if lights == "log":
            self.road_light_steps = t(pad_stack([np.stack([light_codes(sc.traffic_lights, rd.light_index, sc.current_frame + FRAMES_PER_TOKEN * k)
                                                             for k in range(steps)]) for sc, rd in zip(self.scenes, roads)], (steps, rmax)))
        self.light_config = self.light_config_steps = self.road_x_configs = None
        if lights == "log":
            self._encode_light_configs()
        else:
            with torch.no_grad():  # (B, R, d), once per scene
                self.road_x = model.encode_road(self)
        # ---- token poses per type (padded to Vmax) for placing tokens
        vmax = int(self.vocab_sizes.max())
        tp = torch.zeros(NUM_MOTION_TYPES, vmax, FRAMES_PER_TOKEN + 1, 3)
        for k, tt in enumerate(MOTION_TYPES):
            tp[k, : vocab[tt].size] = torch.from_numpy(vocab[tt].poses)
        self.token_poses = tp.to(dev)
        self.token_speeds = token_speeds(self.token_poses)  # [types, Vmax] m/s
        # ---- stop lines (:mod:`~smart_marl.rollout.stop_lines`): per scene, and the stop sign each slot has served
        self.stop_xy = self.stop_dir = self.stop_group = self.stop_sign = self.stop_valid = None
        self.stop_red = self.stop_go = self.stop_turn_red = self.stop_red_steps = self.stop_go_steps = self.stop_turn_red_steps = None
        self.stop_served = self.stop_stood = self.stop_moved = None
        self.stop_token_ends = None
        if self.stop_lines:
            for name, t in stop_line_tensors(self.scenes, dev, steps).items():
                setattr(self, name, t)
            self.stop_served = torch.zeros(*self.track_index.shape, self.stop_xy.shape[1], dtype=torch.bool, device=dev)
            self.stop_stood, self.stop_moved = stood_in_history(hist_valid, hist_start, hist_end)  # steps stood in a row
            self.stop_token_ends = token_ends(self.token_poses, interpolation)
            self._stop_lights_now()
        # ---- history through the model
        self.history = [hist_tokens, hist_valid, hist_start, hist_end]  # grows by one step per token step (full mode)
        self.pose = hist_end[:, :, -1].clone()  # (G, N, 3) where each slot's next token starts
        self.previous_pose = torch.where(hist_valid[:, :, -1, None], hist_start[:, :, -1], self.pose)  # 0.5 s before it
        self.speed_before = speed_before_history(hist_valid, hist_start, hist_end)  # the token before the current one's
        self.step_index = 0
        self._logits: torch.Tensor | None = None
        self._ahead: Draw | None = None  # the next step's tokens drawn ahead (draw_ahead)
        self.cache = None  # the model's KV cache (mode "cached")
        if mode == "cached":
            self.cache = model.start_cache(self.road_x, self.road_pose, self.road_valid, self.scene_of_group, self.agent_type,
                                           self.agent_shape)
            for k in range(s - 1):  # prefill the cache with all history steps but the last
                model.step(self.cache, hist_tokens[:, :, k], hist_start[:, :, k], hist_end[:, :, k], hist_valid[:, :, k])
        self._pending = (hist_tokens[:, :, -1], hist_start[:, :, -1], hist_end[:, :, -1], hist_valid[:, :, -1])

    # ------------------------------------------------------------------------------- creation
    @classmethod
    def start(cls, model, scenes: Scenario | Sequence[Scenario], num_rollouts: int = 1, seed: int = 0, top_k: int = DEFAULT_TOP_K,
              temperature: float = 1.0, device="cpu", mode: str = "cached", motion_vocab: MotionVocabulary | None = None,
              interpolation: str = "spline", avoid_collisions: bool = True, lights: str = "current",
              stop_lines: bool = True, precision: str = "float32", persistence: float = DEFAULT_PERSISTENCE) -> "RolloutState":
        """Tokenize the scenes' histories and run them through the model. ``model``: anything
        :func:`~smart_marl.model.checkpoint.load_prior` takes (a SMART model, a Checkpoint, a Prior, a checkpoint path or
        ``"embedded"``); ``motion_vocab`` overrides the vocabulary used to tokenize the history and place tokens (by
        default the checkpoint's, or the model's contours); ``interpolation`` draws the 10 Hz frames between token ends
        (module docstring); ``avoid_collisions`` keeps sampled tokens from ending in another agent's box
        (:mod:`~smart_marl.rollout.avoidance`; False: plain top-k sampling); ``lights``: :data:`LIGHTS`;
        ``stop_lines`` (default True; False: the prior alone): vehicles do not draw tokens after which they could not
        stop before a red light's or a stop sign's line ahead, and a standing vehicle whose light turned green, whose
        stop sign it has served or whose leader drives off does not draw the tokens that leave it standing
        (:mod:`~smart_marl.rollout.stop_lines`); ``precision``: ``"float32"`` or ``"bfloat16"`` (:mod:`~smart_marl.model.precision`);
        ``persistence`` (default :data:`~smart_marl.rollout.persistence.DEFAULT_PERSISTENCE`, 0: off): a vehicle's
        draw leans toward going on with the change of speed it is in (:mod:`~smart_marl.rollout.persistence`)."""
        check_precision(precision)
        m, vocab = load_prior(model, device)
        m = inference_model(m, precision)  # the model itself in float32, its bfloat16 copy (made once) in bfloat16
        scenes = [scenes] if isinstance(scenes, Scenario) else list(scenes)
        if not scenes:
            raise ValueError("no scenes to roll out")
        return cls(m, motion_vocab or vocab, scenes, num_rollouts, seed, top_k, temperature, device, mode, interpolation=interpolation,
                   avoid_collisions=avoid_collisions, lights=lights, stop_lines=stop_lines, persistence=persistence)

    # ------------------------------------------------------------------------------ accessors
    @property
    def current_pose(self) -> torch.Tensor:
        """[G, N, 3] every slot's pose (x, y, heading, local frame) where its next token starts."""
        return self.pose

    @property
    def valid(self) -> torch.Tensor:
        """[G, N] bool, the slots that are simulated (driven and present) now."""
        return self.simulated

    def set_agent_valid(self, mask: torch.Tensor) -> None:
        """Remove agents (``mask`` [G, N] false): they stop being simulated from the next step on
        and vanish from everyone's neighbourhoods. Only agents simulated now can stay valid."""
        self.simulated = self.simulated & mask.to(self.device, torch.bool)
        self._ahead = None  # an edit between draw_ahead and step: the step draws again
        if self._pending is not None and self._logits is None:  # the step not yet run sees the removal
            tok, st, en, va = self._pending
            self._pending = (tok, st, en, va & self.simulated)
            if self.mode == "full":
                self.history[1][:, :, -1] &= self.simulated

    def set_road_light(self, road_light: torch.Tensor) -> None:
        """Replace the road pieces' light codes [B, R] (``SignalState``; B scenes, the pieces in the
        order of the state's road tokens) and re-encode the road: every later step's map attention
        sees the new lights (the KV cache's road keys and values are re-projected)."""
        light = road_light.to(self.device, self.road_light.dtype)
        if light.shape != self.road_light.shape:
            raise ValueError(f"road_light must have shape {tuple(self.road_light.shape)}, got {tuple(light.shape)}")
        self.road_light = light
        self._ahead = None
        with torch.no_grad():
            self.road_x = self.model.encode_road(self)
        if self.cache is not None:
            self.model.motion_net.cache_road(self.cache, self.road_x)

    def _encode_light_configs(self) -> None:
        """``lights="log"``: each scene's road encoded once for every distinct light configuration its log goes
        through (most scenes have one, a few up to five in 8 s): ``road_x_configs`` [B, K, R, d], the configuration of
        each logged step ``light_config_steps`` [B, S] and the one in use ``light_config`` [B]. A change of lights in
        closed loop is then a gather, not a RoadNet pass (one pass per scene and configuration, when the scene starts)."""
        b_, s_ = self.road_light_steps.shape[:2]
        configs, of_step = [], torch.zeros(b_, s_, dtype=torch.long, device=self.device)
        for b in range(b_):
            distinct, of_step[b] = torch.unique(self.road_light_steps[b], dim=0, return_inverse=True)  # [K_b, R], [S]
            configs.append(distinct)
        k_max = max(len(c) for c in configs)
        with torch.no_grad():
            for b, distinct in enumerate(configs):  # one scene at a time: RoadNet's memory grows with its pieces squared
                k = len(distinct)
                part = _RoadPart(*(t[b : b + 1].expand(k, *t.shape[1:]) for t in (self.road_points, self.road_pose, self.road_type)),
                                 distinct, self.road_valid[b : b + 1].expand(k, -1))
                encoded = self.model.encode_road(part)  # [K_b, R, d]
                if b == 0:
                    self.road_x_configs = encoded.new_zeros(b_, k_max, *encoded.shape[1:])
                self.road_x_configs[b, :k] = encoded
        self.light_config_steps, self.light_config = of_step, of_step[:, 0].clone()
        self.road_light = lights_at(self.road_light_steps, self.scene_clock)
        self.road_x = self.road_x_configs[torch.arange(b_, device=self.device), self.light_config]

    def _follow_logged_lights(self) -> None:
        """``lights="log"``: each scene's pieces' codes at the frame its next step starts at (its own clock), and their
        road encodings (:meth:`_encode_light_configs`) where they changed."""
        config = lights_at(self.light_config_steps, self.scene_clock)  # [B]
        if torch.equal(config, self.light_config):
            return
        rows = torch.arange(len(config), device=self.device)
        self.light_config = config
        self.road_light = lights_at(self.road_light_steps, self.scene_clock)  # new tensors: a fork shares the old ones
        self.road_x = self.road_x_configs[rows, config]
        if self.cache is not None:
            self.model.motion_net.cache_road(self.cache, self.road_x)

    def _stop_lights_now(self) -> None:
        """The stop lines' red and green lanes at each scene's clock (held at its last logged step)."""
        self.stop_red, self.stop_go, self.stop_turn_red = (lights_at(t, self.scene_clock) for t in (
            self.stop_red_steps, self.stop_go_steps, self.stop_turn_red_steps))

    def set_agent_pose(self, pose: torch.Tensor, mask: torch.Tensor) -> None:
        """Override the current pose [G, N, 3] of the slots where ``mask`` [G, N] is true: their next
        token starts there. When the next step's logits were already computed (:meth:`logits` was
        called), those logits stay as they were; the new pose is seen from the following step on."""
        m = mask.to(self.device, torch.bool)
        self.pose = torch.where(m[..., None], pose.to(self.device, self.pose.dtype), self.pose)
        self._ahead = None
        self.previous_pose = torch.where(m[..., None], torch.nan, self.previous_pose)  # moved: no motion to continue
        if self._pending is not None and self._logits is None:
            tok, st, en, va = self._pending
            self._pending = (tok, st, torch.where(m[..., None], self.pose, en), va)
            if self.mode == "full":
                self.history[3][:, :, -1] = self._pending[2]

    # ---------------------------------------------------------------------------------- model
    def logits(self) -> torch.Tensor:
        """[G, N, Vmax] next-token logits of every slot (see :class:`StepOutput`), computed on demand."""
        if self._logits is None:
            tok, st, en, va = self._pending
            g, n = self.num_groups, self.num_slots
            if self.mode == "cached":
                rows, feats = self.model.step(self.cache, tok, st, en, va)
            else:
                rows, feats = self._full_features()
            out = torch.full((g * n, int(self.vocab_sizes.max())), float("-inf"), device=self.device)
            out[rows] = self.model.next_token_logits(feats, self.agent_type.reshape(-1)[rows])  # (Q, Vmax)
            self._logits = out.view(g, n, -1)
            self._pending = None
        return self._logits

    @torch.no_grad()
    def _full_features(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Full re-computation: MotionNet over every step so far (history + generated)."""
        tok, valid, start, end = self.history
        sog = self.scene_of_group
        feats = self.model.agent_features(tok, self.agent_type, self.agent_shape, start, end, valid, self.road_x[sog],
                                          self.road_pose[sog], self.road_valid[sog])  # (G, N, S, d)
        feats = feats[:, :, -1].reshape(-1, feats.shape[-1])  # (G*N, d)
        rows = valid[:, :, -1].reshape(-1).nonzero().squeeze(1)
        return rows, feats[rows]

    def fork(self, seed: int) -> "RolloutState":
        """An independent copy of this state whose sampler is seeded with ``seed`` (e.g. a fresh
        episode from a state started once). The model, vocabulary, scenes and constant tensors are
        shared; what steps and edits change (the KV cache, the history of mode "full", the poses,
        the pending step) is the copy's own."""
        out = copy.copy(self)
        out.generator = torch.Generator(device=self.device).manual_seed(int(seed))
        out._ahead = None  # drawn with this state's generator
        out.history = [t.clone() for t in self.history]  # mode "full" writes into its last step
        out.cache = self.cache.fork() if self.cache is not None else None
        return out

    def draw_ahead(self, forced_tokens: torch.Tensor) -> Draw:
        """Draw the next step's tokens now, before the tokens of the slots marked :data:`~smart_marl.rollout.drawing.FORCED_LATER` in
        ``forced_tokens`` [G, N] are known (the rest as :meth:`step` takes them: ``-1`` drawn, a token id
        imposed; :mod:`~smart_marl.rollout.drawing`). The next :meth:`step` takes these draws, given a token
        exactly where this had ``FORCED_LATER`` (and the same tokens elsewhere); an edit of the state in between
        (:meth:`set_agent_valid`, :meth:`set_agent_pose`, :meth:`set_road_light`) drops them, and the step
        draws afresh. Returns the draw (:meth:`Draw.frames <smart_marl.rollout.drawing.Draw.frames>`: where the
        drawn agents will be on the step's frames)."""
        self._ahead = None
        self._ahead = draw_tokens(self, check_forced(self, forced_tokens, later=True))
        return self._ahead

    def drawn_ahead(self) -> Draw | None:
        """The draw of :meth:`draw_ahead` if the next step will take it (made from the current logits), else None."""
        ahead = self._ahead
        return ahead if ahead is not None and ahead.logits is self._logits else None

    def step(self, forced_tokens: torch.Tensor | None = None) -> StepOutput:
        """Advance every simulated agent by one token (0.5 s). ``forced_tokens`` [G, N] int64: ``-1``
        where the token is sampled (top-k, temperature, this state's generator), a token id in the
        slot's type vocabulary where it is imposed. Non-simulated slots are left where they are. After
        :meth:`draw_ahead`, the tokens it drew are taken and ``forced_tokens`` completes them."""
        logits = self.logits()
        g, n = self.num_groups, self.num_slots
        sim = self.simulated
        if forced_tokens is not None:
            forced_tokens = check_forced(self, forced_tokens)
        ahead = self.drawn_ahead()
        if ahead is not None:  # drawn before the forced-later tokens were known (draw_ahead); a refused step keeps it
            rows = ahead.rows
            tok_rows, logp_rows = complete(self, ahead, forced_tokens)
            self._ahead = None
        else:
            draw = draw_tokens(self, forced_tokens)
            rows, tok_rows, logp_rows = draw.rows, draw.tokens, draw.log_probs
        tokens = torch.full((g * n,), -1, dtype=torch.long, device=self.device)
        tokens[rows] = tok_rows
        log_probs = torch.zeros(g * n, device=self.device)
        log_probs[rows] = logp_rows
        tokens, log_probs = tokens.view(g, n), log_probs.view(g, n)
        # place each simulated slot's token at its current pose (the other slots stay where they are)
        placed = self.pose[:, :, None, :].expand(g, n, FRAMES_PER_TOKEN, 3).clone()  # (G, N, 5, 3)
        local = self.token_poses[self.agent_type.reshape(-1)[rows], tok_rows]  # (R, 6, 3)
        placed.view(g * n, FRAMES_PER_TOKEN, 3)[rows] = token_frames(local, self.pose.reshape(-1, 3)[rows],
                                                                      self.previous_pose.reshape(-1, 3)[rows], self.interpolation)
        new_pose = placed[:, :, -1].clone()
        start = self.pose
        self.speed_before = torch.where(sim, mean_speed(self.pose, self.previous_pose), self.speed_before)
        self.previous_pose = torch.where(sim[..., None], self.pose, self.previous_pose)
        self._pending = (tokens.clamp(min=0), start, new_pose, sim.clone())
        if self.mode == "full":
            h = self.history
            self.history = [torch.cat([h[0], tokens.clamp(min=0)[..., None]], 2), torch.cat([h[1], sim[..., None]], 2),
                            torch.cat([h[2], start[:, :, None]], 2), torch.cat([h[3], new_pose[:, :, None]], 2)]
        self.pose = new_pose
        self._logits = None
        self.step_index += 1
        self.scene_clock = self.scene_clock + 1
        if self.road_light_steps is not None:  # the next step's logits see the lights of the frame it starts at
            self._follow_logged_lights()
        if self.stop_lines:
            self.stop_served, (self.stop_stood, self.stop_moved) = served_after_step(self), stood_after_step(self)
            self._stop_lights_now()
        forced = sim & (forced_tokens >= 0) if forced_tokens is not None else torch.zeros_like(sim)
        return StepOutput(logits=logits, tokens=tokens, log_probs=log_probs, poses=placed, simulated=sim.clone(), forced=forced)

    def run(self, num_steps: int, before_step=None) -> list[StepOutput]:
        """``num_steps`` token steps (the rollout loop). ``before_step(state, k, last)``, when given,
        is called before step ``k`` with the previous step's :class:`StepOutput` (None before the
        first): it may edit the state (:meth:`set_agent_valid`, :meth:`set_road_light`, ...) and
        returns the step's forced tokens [G, N] (``-1``: sample) or None."""
        outs: list[StepOutput] = []
        for k in range(num_steps):
            forced = before_step(self, k, outs[-1] if outs else None) if before_step is not None else None
            outs.append(self.step(forced))
        return outs


# ----------------------------------------------------------------------------------- result
@dataclass
class RolloutResult:
    """Rollouts of ``B`` scenes x ``R`` rollouts (``G = B * R`` groups, group ``g`` = rollout
    ``g % R`` of scene ``g // R``), over ``A`` agents (every track of the scene, padded; agent ``a``
    of group ``g`` is track ``a`` of its scene) and ``T = 5 * num_steps`` future frames at 10 Hz
    (frames current + 1 .. current + T)."""

    scenario_ids: list[str]  # [B]
    scene_index: np.ndarray  # [G]
    rollout_index: np.ndarray  # [G]
    agent_ids: np.ndarray  # [G, A] int64, -1 on padding
    agent_types: np.ndarray  # [G, A] int8 AgentType, -1 on padding
    has_trajectory: np.ndarray  # [G, A] bool: valid at the current frame (simulated or constant velocity)
    simulated: np.ndarray  # [G, A] bool: driven by the model
    trajectory: np.ndarray  # [G, A, T, 4] float64 x, y, z, heading in the scene's source frame (0 where no trajectory)
    tokens: np.ndarray  # [G, A, num_steps] int64 sampled token ids, -1 where not simulated
    log_probs: np.ndarray  # [G, A, num_steps] float32 under log_softmax(logits / temperature), 0 where not simulated

    @property
    def num_rollouts(self) -> int:
        return int(self.rollout_index.max()) + 1 if len(self.rollout_index) else 0


def rollout(model_or_checkpoint, scenes: Scenario | Sequence[Scenario], num_rollouts: int = 32, num_steps: int = 16,
            top_k: int = DEFAULT_TOP_K, temperature: float = 1.0, seed: int = 0, device="cpu", mode: str = "cached",
            motion_vocab: MotionVocabulary | None = None, interpolation: str = "spline", avoid_collisions: bool = True,
            lights: str = "current", stop_lines: bool = True, precision: str = "float32",
            persistence: float = DEFAULT_PERSISTENCE) -> RolloutResult:
    """Generate ``num_rollouts`` joint futures of ``num_steps`` tokens (0.5 s each) for every scene
    in one batch (see the module docstring). Same seed, same rollouts (on the CPU). ``lights``: :data:`LIGHTS`;
    ``stop_lines``, ``precision``, ``persistence``: :meth:`RolloutState.start`."""
    state = RolloutState.start(model_or_checkpoint, scenes, num_rollouts=num_rollouts, seed=seed, top_k=top_k, temperature=temperature,
                               device=device, mode=mode, motion_vocab=motion_vocab, interpolation=interpolation,
                               avoid_collisions=avoid_collisions, lights=lights, stop_lines=stop_lines, precision=precision,
                               persistence=persistence)
    outs = state.run(num_steps)
    return collect_result(state, outs)


@dataclass
class TrackFrames:
    """A state's steps per *track* of each group's scene (``A`` = the most tracks of any scene),
    10 Hz frames current + 1 .. current + T, local frame."""

    poses: np.ndarray  # [G, A, T, 3] float64 x, y, heading; NaN where the track's slot was not simulated
    present: np.ndarray  # [G, A, T] bool, simulated on that frame
    forced: np.ndarray  # [G, A, T] bool, moved by a given (forced) token on that frame


def track_frames(state: RolloutState, outs: list[StepOutput]) -> TrackFrames:
    """The slots of ``outs`` (a state's :class:`StepOutput` s in order) mapped back to tracks."""
    g = state.num_groups
    a = max(sc.num_tracks for sc in state.scenes)
    t_frames = FRAMES_PER_TOKEN * len(outs)
    poses = np.full((g, a, t_frames, 3), np.nan)
    present = np.zeros((g, a, t_frames), bool)
    forced = np.zeros((g, a, t_frames), bool)
    track_index = state.track_index.cpu().numpy()  # [G, N]
    for k, out in enumerate(outs):
        frames = slice(FRAMES_PER_TOKEN * k, FRAMES_PER_TOKEN * (k + 1))
        gi, slot = np.nonzero(out.simulated.cpu().numpy() & (track_index >= 0))
        ti = track_index[gi, slot]
        poses[gi, ti, frames] = out.poses.cpu().numpy().astype(np.float64)[gi, slot]
        present[gi, ti, frames] = True
        forced[gi, ti, frames] = out.forced.cpu().numpy()[gi, slot, None]
    return TrackFrames(poses=poses, present=present, forced=forced)


def collect_result(state: RolloutState, outs: list[StepOutput]) -> RolloutResult:
    """The :class:`RolloutResult` of a state's steps: slots mapped back to tracks
    (:func:`track_frames`), source frame, OTHER agents at constant velocity, z carried."""
    scenes = state.scenes
    r = state.num_rollouts
    g, n = state.num_groups, state.num_slots
    k = len(outs)
    t_frames = FRAMES_PER_TOKEN * k
    a = max(sc.num_tracks for sc in scenes)
    poses = track_frames(state, outs).poses  # (G, A, T, 3)
    tokens = torch.stack([o.tokens for o in outs], -1).cpu().numpy() if k else np.zeros((g, n, 0), np.int64)
    logps = torch.stack([o.log_probs for o in outs], -1).cpu().numpy() if k else np.zeros((g, n, 0), np.float32)
    track_index = state.track_index.cpu().numpy()
    slot_sim = state.simulated.cpu().numpy()
    out_traj = np.zeros((g, a, t_frames, 4))
    out_tokens = np.full((g, a, k), -1, np.int64)
    out_logp = np.zeros((g, a, k), np.float32)
    agent_ids = np.full((g, a), -1, np.int64)
    agent_types = np.full((g, a), -1, np.int8)
    has_traj = np.zeros((g, a), bool)
    simulated = np.zeros((g, a), bool)
    dt_s = DT_S * np.arange(1, t_frames + 1)
    for b, sc in enumerate(scenes):
        tr, cf = sc.tracks, sc.current_frame
        nt = tr.num_tracks
        groups = np.arange(b * r, (b + 1) * r)
        agent_ids[groups, :nt] = tr.ids
        agent_types[groups, :nt] = tr.types
        has_traj[groups, :nt] = tr.valid[:, cf]
        # z: each track's last valid z at or before the current frame
        seen = tr.valid[:, : cf + 1]
        last = np.where(seen.any(1), cf - np.argmax(seen[:, ::-1], axis=1), 0)
        z = tr.position[np.arange(nt), last, 2].astype(np.float64)  # [nt]
        # agents valid at the current frame but not driven by the model: constant velocity, heading held
        cv = tr.valid[:, cf] & ~np.isin(tr.types, [int(x) for x in MOTION_TYPES])
        xy_cv = tr.position[cv, cf, None, :2].astype(np.float64) + tr.velocity[cv, cf, None].astype(np.float64) * dt_s[:, None]
        local = np.zeros((nt, t_frames, 4))
        local[cv, :, :2] = xy_cv
        local[cv, :, 3] = tr.heading[cv, cf, None]
        local[:, :, 2] = z[:, None]
        for gi in groups:
            slots = np.flatnonzero((track_index[gi] >= 0) & slot_sim[gi])
            ti = track_index[gi, slots]
            loc = local.copy()
            loc[ti, :, :2] = poses[gi, ti, :, :2]
            loc[ti, :, 3] = poses[gi, ti, :, 2]
            traj = np.zeros_like(loc)
            traj[..., :3] = sc.frame.to_source(loc[..., :3])
            traj[..., 3] = sc.frame.heading_to_source(loc[..., 3])
            traj[~tr.valid[:, cf]] = 0.0
            out_traj[gi, :nt] = traj
            out_tokens[gi, ti] = tokens[gi, slots]
            out_logp[gi, ti] = logps[gi, slots]
            simulated[gi, ti] = True
    return RolloutResult(scenario_ids=[sc.scenario_id for sc in scenes], scene_index=np.repeat(np.arange(len(scenes)), r),
                         rollout_index=np.tile(np.arange(r), len(scenes)), agent_ids=agent_ids, agent_types=agent_types,
                         has_trajectory=has_traj, simulated=simulated, trajectory=out_traj, tokens=out_tokens, log_probs=out_logp)
