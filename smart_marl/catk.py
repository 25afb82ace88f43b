"""Training stage, closed-loop targets: CAT-K ("closest among top-K", Zhang et al., CVPR 2025).

Teacher forcing trains SMART on the logged token sequences (with token noise); in closed loop the
model then meets states of its own making. CAT-K fine-tunes it on its own rollouts kept near the
log: the history is the logged one (rolling matching, no noise) and, from the scene's current
frame on, every token step of every agent is taken *among the model's K most likely tokens* as the
one whose placed poses come closest to the logged ones (the tokenizer's mean corner distance over
the token's frames). The training targets are, as in teacher forcing, the nearest token of the
whole vocabulary from the pose the sequence reached, so they lead back toward the log.

What comes in: scenes (Scenario), their road arrays (:func:`~smart_marl.model.batch.scene_road`)
and the current model. What goes out: per scene the :class:`~smart_marl.tokens.MotionTokens` of
the CAT-K rollout, which :func:`~smart_marl.model.batch.scene_tensors` turns into a training
batch like any other. The rollout runs the model's KV-cached step (:meth:`SMART.start_cache
<smart_marl.model.SMART.start_cache>`, ``step``, ``next_token_logits``) in eval mode without gradients,
all scenes of a batch at once, interleaved with the tokenizer's step loop (its ``candidates`` hook).

With ``avoid`` the rollout keeps gaps (``catk_avoid``): the candidates are the top-K of the model's
distribution with every token taken out that the rollouts' collision rule takes out
(:func:`~smart_marl.rollout.avoidance.excluded_tokens`: the token's frames overlap one of the agent's
nearest neighbours, each seen on its logged motion of the step from where it is), and where the target
(the token back toward the log) would overlap a neighbour and the taken token would not, the target is
the taken token. A
follower whose logged leader brakes harder than in the log (:mod:`smart_marl.braking`) then learns
to brake where its own log drives on.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Sequence

import numpy as np
import torch

from .model.batch import RoadArrays
from .model.motionnet import NUM_MOTION_TYPES
from .model.smart import RoadInputs
from .geometry_torch import RoadEdgeTensors, boxes_off_road, scene_road_edges
from .rollout.avoidance import excluded_tokens, off_road_test
from .rollout.sampling import sample_tokens
from .scenario import AgentType, Scenario
from .tokens import FRAMES_PER_TOKEN, MOTION_TYPES, MotionTokens, MotionVocabulary, token_boundaries, tokenize_tracks


def first_future_step(scenario: Scenario) -> int:
    """The index of the first token that starts at or after the scene's current frame."""
    return int(scenario.current_frame) // FRAMES_PER_TOKEN


def _agent_shapes(scenario: Scenario, rows: np.ndarray) -> np.ndarray:
    """Median (length, width, height) [M, 3] of tracks ``rows`` over their valid frames (as the batch builder)."""
    tr = scenario.tracks
    size = np.where(tr.valid[rows][..., None], tr.size[rows], np.nan)
    with np.errstate(all="ignore"):
        return np.nan_to_num(np.nanmedian(size, axis=1)).astype(np.float32) if len(rows) else np.zeros((0, 3), np.float32)


@torch.no_grad()
def catk_tokens(model, scenes: Sequence[Scenario], roads: Sequence[RoadArrays], vocab: MotionVocabulary, top_k: int,
                device: torch.device | str = "cpu", avoid: bool = False) -> list[MotionTokens]:
    """CAT-K token sequences of ``scenes`` (see the module docstring) under ``model``.

    ``roads[i]`` are scene i's road pieces. Scenes that share a token grid (same current frame
    modulo 5 and frame count, as every 9.1 s scene) run as one batch through the model. Returns
    one :class:`MotionTokens` per scene, in order, with a row per track like
    :func:`~smart_marl.tokens.tokenize_motion`. ``avoid``: keep gaps (module docstring).
    """
    if top_k < 1:
        raise ValueError(f"CAT-K needs top_k >= 1, got {top_k}")
    return _by_token_grid(model, scenes, lambda idx: _catk_group(model, [scenes[i] for i in idx], [roads[i] for i in idx], vocab,
                                                                 top_k, torch.device(device), avoid))


@torch.no_grad()
def sampled_tokens(model, scenes: Sequence[Scenario], roads: Sequence[RoadArrays], vocab: MotionVocabulary, top_k: int,
                   generator: torch.Generator, follow_log: Sequence[np.ndarray] | None = None,
                   device: torch.device | str = "cpu", excluded: dict | None = None, offroad: bool = False) -> list[MotionTokens]:
    """Sampled rollouts of ``scenes`` under ``model`` as token sequences (the history logged, every
    later token drawn from the model's top ``top_k``, as the simulator draws), in the format of
    :func:`catk_tokens`. ``follow_log[i]`` [tracks of scene i] bool: those tracks follow their log
    (the closest token of the whole vocabulary: scripted agents). One scene list may repeat a scene:
    each copy is a rollout of its own.

    ``excluded``: a dict that receives, for each scene index i, bool [tracks, S, Vmax]: at each drawn
    token step the tokens the simulator's collision rule would not have let the track draw
    (:func:`~smart_marl.rollout.avoidance.excluded_tokens` as the rollout engine calls it: spline frames, the
    others at constant velocity, the ``follow_log`` tracks on their logged motion); with ``offroad`` also the
    tokens that end with a vehicle on the road at the current frame off it (the shield's test). The draw itself is plain."""
    def group(idx: list[int]) -> list[MotionTokens]:
        follow = None if follow_log is None else np.concatenate([np.asarray(follow_log[i], bool) for i in idx])
        rule = [] if excluded is not None else None
        out = _catk_group(model, [scenes[i] for i in idx], [roads[i] for i in idx], vocab, top_k, torch.device(device),
                          sample=generator, follow_log=follow, rule_out=rule, rule_offroad=offroad)
        if rule is not None:
            excluded.update(zip(idx, rule))
        return out

    return _by_token_grid(model, scenes, group)


def _by_token_grid(model, scenes: Sequence[Scenario], run) -> list[MotionTokens]:
    """``run(indices)`` on each group of scenes that share a token grid (same current frame and frame
    count), the model in eval mode meanwhile; the groups' token sequences back in scene order."""
    out: list[MotionTokens | None] = [None] * len(scenes)
    groups: dict[tuple, list[int]] = defaultdict(list)
    for i, sc in enumerate(scenes):
        groups[(int(sc.current_frame), int(sc.num_frames))].append(i)
    was_training = model.training
    model.eval()
    try:
        for idx in groups.values():
            for i, tokens in zip(idx, run(idx)):
                out[i] = tokens
    finally:
        model.train(was_training)
    return out  # type: ignore[return-value]


def drifted(scenario: Scenario, tokens: MotionTokens, max_drift_m: float) -> np.ndarray:
    """bool [N, S]: the tokens of ``tokens`` (a CAT-K sequence of ``scenario``) that start farther than
    ``max_drift_m`` from the logged position of their first frame. From there no token leads back to the
    log in 0.5 s, and the nearest one (the target) is a swerve: on 16 generated scenes, 1% of the moving
    vehicles' CAT-K tokens start 10 m or more off the log (the log's own rolling matching: 1.7 m), and
    their targets end 13 m from the logged pose (``benchmarks/catk_targets.py``)."""
    tr = scenario.tracks
    start = tokens.boundaries[:-1]
    off = np.linalg.norm(tokens.start_pose[..., :2] - tr.position[:, start, :2], axis=-1)  # [N, S]
    return tokens.valid & tr.valid[:, start] & (off > max_drift_m)


class _GapKeeper:
    """The collision rule inside a CAT-K rollout (``avoid``, module docstring): the slots' poses at the
    token step being chosen (:meth:`at_step`), the candidates it leaves (:meth:`mask`) and the targets it
    replaces (:meth:`relabel`). Slots are the flat ``g * n + j`` of :func:`_catk_group`; rows the
    concatenated tracks' (``slot_of_row``, -1 for tracks without a slot)."""

    def __init__(self, vocab: MotionVocabulary, scenes: list[Scenario], agent_type: torch.Tensor, agent_shape: torch.Tensor,
                 slot_of_row: torch.Tensor, bounds: np.ndarray, top_k: int, device: torch.device,
                 known_rows: np.ndarray | None = None, interpolation: str = "contour") -> None:
        vmax = max(vocab[t].size for t in MOTION_TYPES)
        tp = torch.zeros(NUM_MOTION_TYPES, vmax, FRAMES_PER_TOKEN + 1, 3)
        for i, t in enumerate(MOTION_TYPES):
            tp[i, : vocab[t].size] = torch.from_numpy(vocab[t].poses)
        self.token_poses, self.agent_type, self.agent_shape = tp.to(device), agent_type.to(device), agent_shape.to(device)
        self.slot_of_row, self.has_slot = slot_of_row, (slot_of_row >= 0).numpy()
        self.flat = slot_of_row[slot_of_row >= 0]  # the slot of each row that has one
        hs = self.has_slot  # the log of the rows with a slot (the only ones read): [rows with a slot, T, ...]
        self.log_pose = np.concatenate([np.concatenate([sc.tracks.position[..., :2], sc.tracks.heading[..., None]], -1)
                                        for sc in scenes])[hs]
        self.log_valid = np.concatenate([sc.tracks.valid for sc in scenes])[hs]
        # the rows seen on their logged motion (None: every row; the others at constant velocity, as in rollouts)
        self.known_rows = None if known_rows is None else np.asarray(known_rows, bool)[hs]
        self.bounds, self.top_k, self.device, self.interpolation = bounds, top_k, device, interpolation
        self.state: tuple | None = None
        self.edges: RoadEdgeTensors | None = None  # with keep_on_road: the scenes' road edges

    def at_step(self, k: int, partial: MotionTokens) -> None:
        """Every slot's pose where token ``k`` starts (reached by the rollout, else logged), its pose a token
        before (NaN: none), whether it is on the road then, and its frames of the step as the others see
        them: its logged motion of the step moved to where it is (the rollouts stay near the log, and a
        leader that brakes in the log is seen braking, not at constant velocity)."""
        g, n = self.agent_type.shape
        hs, b0 = self.has_slot, int(self.bounds[k])
        now = np.where(partial.reached_valid[hs, k][:, None], partial.reached[hs, k], self.log_pose[:, b0])
        before = np.where(partial.valid[hs, k - 1][:, None], partial.start_pose[hs, k - 1], np.nan)
        flat = self.flat
        pose, prev = torch.zeros(g * n, 3), torch.full((g * n, 3), float("nan"))
        present = torch.zeros(g * n, dtype=torch.bool)
        pose[flat], prev[flat] = torch.from_numpy(now).float(), torch.from_numpy(before).float()
        present[flat] = torch.from_numpy(self.log_valid[:, b0])
        # where the others go during the step: their logged motion of the step, from where they are
        frames = np.arange(b0 + 1, b0 + FRAMES_PER_TOKEN + 1)
        moved = self.log_pose[:, frames] + (now - self.log_pose[:, b0])[:, None]  # [rows, 5, 3]
        known = torch.zeros(g * n, dtype=torch.bool)
        known_frames = torch.zeros(g * n, FRAMES_PER_TOKEN, 3)
        logged = self.log_valid[:, np.r_[b0, frames]].all(1)
        known[flat] = torch.from_numpy(logged if self.known_rows is None else logged & self.known_rows)
        known_frames[flat] = torch.from_numpy(moved).float()
        d = self.device
        self.state = (pose.view(g, n, 3).to(d), prev.view(g, n, 3).to(d), present.view(g, n).to(d),
                      known_frames.view(g, n, FRAMES_PER_TOKEN, 3).to(d), known.view(g, n).to(d))

    def start_recording(self, vmax: int, offroad_scenes: list[Scenario] | None = None) -> None:
        """Keep what :meth:`record` finds in ``recorded`` (bool [rows, steps, vmax]); with ``offroad_scenes`` (the
        group's scenes) the road test too (:meth:`keep_on_road`)."""
        self.row_of_slot = np.full(self.agent_type.numel(), -1, np.int64)
        self.row_of_slot[self.flat.numpy()] = np.flatnonzero(self.has_slot)
        self.recorded = np.zeros((len(self.slot_of_row), len(self.bounds) - 1, vmax), bool)
        if offroad_scenes is not None:
            self.keep_on_road(offroad_scenes)

    def record(self, k: int, partial: MotionTokens, logits: torch.Tensor, rows: torch.Tensor) -> None:
        """The tokens the rule excludes at step ``k`` for slots ``rows`` [Q] whose ``logits`` are [Q, Vmax]."""
        self.at_step(k, partial)
        self.recorded[self.row_of_slot[rows.cpu().numpy()], k] = self._excluded(logits, rows, self.top_k).cpu().numpy()

    def keep_on_road(self, scenes: list[Scenario]) -> None:
        """Also exclude the tokens that end with a vehicle's box off the road (the shield's ``"offroad"``,
        :mod:`envs._shield`), for the vehicles on the road at the scenes' current frame."""
        g, n = self.agent_type.shape
        self.edges = RoadEdgeTensors.from_segments([scene_road_edges(sc.road_map) for sc in scenes], device=self.device)
        rows = self.flat.to(self.device)  # the slots that have a row
        cf = int(scenes[0].current_frame)
        z = torch.zeros(g * n, device=self.device)
        z[rows] = torch.from_numpy(np.concatenate([sc.tracks.position[:, cf, 2] for sc in scenes])[self.has_slot]).float().to(self.device)
        self.z = z
        pose = torch.from_numpy(self.log_pose[:, cf]).float().to(self.device)
        size = self.agent_shape.reshape(-1, 3)[rows]
        vehicle = self.agent_type.reshape(-1)[rows] == int(AgentType.VEHICLE)
        off = boxes_off_road(self.edges, rows // n, pose[:, None, :2], pose[:, None, 2], size, z[rows])[:, 0]
        self.on_road = torch.zeros(g * n, dtype=torch.bool, device=self.device)
        self.on_road[rows] = vehicle & ~off & torch.from_numpy(self.log_valid[:, cf]).to(self.device)

    def _off_road(self, rows: torch.Tensor):
        """``also`` of :func:`excluded_tokens` for slots ``rows`` [Q] (ascending, as the model's step gives them;
        :meth:`keep_on_road`)."""
        n = self.agent_type.shape[1]
        ends = self.token_poses[self.agent_type.reshape(-1)[rows], :, -1]  # [Q, V, 3]
        return off_road_test(self.edges, rows // n, self.state[0].reshape(-1, 3)[rows], ends, self.agent_shape.reshape(-1, 3)[rows],
                             self.z[rows], self.on_road[rows])

    def _excluded(self, logits: torch.Tensor, rows: torch.Tensor, top_k: int) -> torch.Tensor:
        pose, prev, present, known_frames, known = self.state
        also = self._off_road(rows) if self.edges is not None else None
        return excluded_tokens(logits, rows, pose, prev, self.agent_shape, present, self.agent_type, self.token_poses, top_k,
                               interpolation=self.interpolation, known_frames=known_frames, known=known, also=also)

    def mask(self, logits: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """``logits`` [Q, Vmax] of slots ``rows`` [Q] with the tokens the rule excludes at ``-inf``."""
        return logits.masked_fill(self._excluded(logits, rows, self.top_k), float("-inf"))

    def relabel(self, k: int, nearest: np.ndarray, ids: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Targets ``nearest`` [N_rows] of step ``k``, with the taken token ``ids`` where the target would
        overlap a neighbour and the taken token would not."""
        if self.state is None:
            return nearest
        r = np.flatnonzero(ok & self.has_slot & (nearest != ids))
        if not len(r):
            return nearest
        q = torch.arange(len(r))
        label, taken = torch.from_numpy(nearest[r]), torch.from_numpy(ids[r])
        logits = torch.full((len(r), self.token_poses.shape[1]), float("-inf"))
        logits[q, label], logits[q, taken] = 0.0, -1.0  # the target checked first, the taken token next
        hit = self._excluded(logits.to(self.device), self.slot_of_row[r].to(self.device), 1).cpu()[q, label].numpy()
        nearest[r[hit]] = ids[r[hit]]
        return nearest


def _candidates(logits: torch.Tensor, rows: torch.Tensor, types: torch.Tensor, sizes: list[int], top_k: int,
                sample: torch.Generator | None, slots: int) -> torch.Tensor:
    """bool [slots, Vmax]: the candidates of slots ``rows`` [Q] (of types ``types``) at this step, from their
    ``logits`` [Q, Vmax]: their top ``top_k`` finite tokens, or with ``sample`` one token drawn from them."""
    allowed = torch.zeros(slots, max(sizes), dtype=torch.bool)
    for t in range(NUM_MOTION_TYPES):
        sel_t = types == t
        if not sel_t.any():
            continue
        if sample is not None:  # the simulator's draw: one candidate
            drawn, _ = sample_tokens(logits[sel_t, : sizes[t]].float().cpu(), sample, top_k)
            allowed[rows[sel_t].cpu(), drawn] = True
            continue
        top = logits[sel_t, : sizes[t]].topk(min(top_k, sizes[t]), dim=-1)
        allowed[rows[sel_t].cpu()[:, None], top.indices.cpu()] = torch.isfinite(top.values).cpu()
    return allowed


def _start_cache(model, roads: list[RoadArrays], agent_type: torch.Tensor, agent_shape: torch.Tensor, device: torch.device):
    """The model's KV cache for groups with road pieces ``roads`` (every piece of each scene, encoded once: no piece
    is hidden, this is not the road task) and agents of ``agent_type`` / ``agent_shape`` [G, N(, 3)]."""
    rmax = max(max(len(rd.token) for rd in roads), 1)
    p = model.config.road_piece_points

    def pad(arrays, size, fill=0):
        o = np.full((len(arrays), *size), fill, dtype=np.asarray(arrays[0]).dtype)
        for i, a in enumerate(arrays):
            o[(i, *[slice(0, k) for k in np.shape(a)])] = a
        return torch.from_numpy(o).to(device)

    road_pose = pad([rd.pose.astype(np.float32) for rd in roads], (rmax, 3))
    road_valid = pad([np.ones(len(rd.token), bool) for rd in roads], (rmax,), False)
    road_points = pad([rd.local.astype(np.float32).reshape(-1, p, 2) for rd in roads], (rmax, p, 2))
    road_x = model.encode_road(RoadInputs(road_points, road_pose, pad([rd.type_id for rd in roads], (rmax,)),
                                          pad([rd.light for rd in roads], (rmax,)), road_valid))  # (G, R, d)
    return model.start_cache(road_x, road_pose, road_valid, torch.arange(len(roads), device=device), agent_type.to(device),
                             agent_shape.to(device))


def _catk_group(model, scenes: list[Scenario], roads: list[RoadArrays], vocab: MotionVocabulary, top_k: int,
                device: torch.device, avoid: bool = False, sample: torch.Generator | None = None,
                follow_log: np.ndarray | None = None, rule_out: list | None = None, rule_offroad: bool = False) -> list[MotionTokens]:
    """Scenes on one token grid: their tracks concatenated into one rolling matching, the model
    stepped once per token step for all scenes (group g = scene g, slots = its motion agents).
    ``sample``: each token is drawn from the model's top-k instead (a plain sampled rollout, the
    closest-token rule left with one candidate); ``follow_log`` [rows of the concatenated tracks]:
    those tracks take the token closest to their log among the whole vocabulary (scripted agents).
    ``rule_out``: a list that receives each scene's excluded tokens (:func:`sampled_tokens`)."""
    cfg, sc0 = model.config, scenes[0]
    bounds, kc = token_boundaries(sc0.current_frame, sc0.num_frames), first_future_step(sc0)
    motion_types = np.array([int(t) for t in vocab.types])
    # slots: per scene, the motion-type tracks with at least one valid token, in track order
    slot_rows, offsets = [], []
    for sc in scenes:
        tr = sc.tracks
        ok = tr.valid[:, bounds[:-1]] & tr.valid[:, bounds[1:]]
        slot_rows.append(np.flatnonzero(np.isin(tr.types, motion_types) & ok.any(1)))
    g, n = len(scenes), max(max((len(r) for r in slot_rows), default=0), 1)
    total = 0
    flat_of_row = []  # per scene: row of the concatenated tracks -> flat slot g * n + j (or -1)
    for b, sc in enumerate(scenes):
        m = np.full(sc.num_tracks, -1, np.int64)
        m[slot_rows[b]] = b * n + np.arange(len(slot_rows[b]))
        flat_of_row.append(m)
        offsets.append(total)
        total += sc.num_tracks
    slot_of_row = torch.from_numpy(np.concatenate(flat_of_row))  # [N_total]
    has_slot = slot_of_row >= 0
    agent_type = torch.zeros(g, n, dtype=torch.long)
    agent_shape = torch.zeros(g, n, 3)
    for b, (sc, rows) in enumerate(zip(scenes, slot_rows)):
        agent_type[b, : len(rows)] = torch.from_numpy(sc.tracks.types[rows].astype(np.int64))
        agent_shape[b, : len(rows)] = torch.from_numpy(_agent_shapes(sc, rows))
    cache = _start_cache(model, roads, agent_type, agent_shape, device)
    sizes = list(cfg.motion_vocab_sizes)
    vmax = max(sizes)
    flat_type = agent_type.reshape(-1).to(device)

    keeper = _GapKeeper(vocab, scenes, agent_type, agent_shape, slot_of_row, bounds, top_k, device) if avoid else None
    rule = None
    if rule_out is not None:  # the simulator's rule, recorded beside the plain draw
        rule = _GapKeeper(vocab, scenes, agent_type, agent_shape, slot_of_row, bounds, top_k, device,
                          known_rows=np.zeros(len(slot_of_row), bool) if follow_log is None else follow_log, interpolation="spline")
        rule.start_recording(vmax, scenes if rule_offroad else None)

    def candidates(k: int, partial: MotionTokens):
        if keeper is not None:
            keeper.state = None  # set again below on the steps that choose among candidates
        if k == 0:
            return None
        # feed token k - 1 of every slot: its features give the distribution of token k
        sel = slot_of_row[has_slot]
        tok = torch.zeros(g * n, dtype=torch.long)
        start = torch.zeros(g * n, 3)
        end = torch.zeros(g * n, 3)
        valid = torch.zeros(g * n, dtype=torch.bool)
        tok[sel] = torch.from_numpy(partial.ids[has_slot.numpy(), k - 1])
        start[sel] = torch.from_numpy(partial.start_pose[has_slot.numpy(), k - 1]).float()
        end[sel] = torch.from_numpy(partial.reached[has_slot.numpy(), k]).float()
        valid[sel] = torch.from_numpy(partial.valid[has_slot.numpy(), k - 1])
        rows, feats = model.step(cache, tok.view(g, n).to(device), start.view(g, n, 3).to(device), end.view(g, n, 3).to(device),
                                 valid.view(g, n).to(device))
        if k < kc or rows.numel() == 0:
            return None  # history: the logged tokens
        types = flat_type[rows]
        logits = model.next_token_logits(feats, types)  # (Q, Vmax), each row under its type's head
        if keeper is not None:
            keeper.at_step(k, partial)
            logits = keeper.mask(logits, rows)
        if rule is not None:
            rule.record(k, partial, logits, rows)
        allowed_slots = _candidates(logits, rows, types, sizes, top_k, sample, g * n)
        allowed = np.zeros((len(slot_of_row), vmax), bool)
        allowed[has_slot.numpy()] = allowed_slots[slot_of_row[has_slot]].numpy()
        if follow_log is not None:
            allowed[follow_log] = False  # no candidate: the closest token of the whole vocabulary
        return allowed

    pos = np.concatenate([sc.tracks.position for sc in scenes])
    heading = np.concatenate([sc.tracks.heading for sc in scenes])
    valid = np.concatenate([sc.tracks.valid for sc in scenes])
    types = np.concatenate([sc.tracks.types for sc in scenes])
    mt = tokenize_tracks(pos, heading, valid, types, vocab, bounds, candidates=candidates,
                         relabel=keeper.relabel if keeper is not None else None)
    if rule is not None and follow_log is not None:
        rule.recorded[follow_log] = False  # scripted: they draw nothing
    per_scene = []
    for b, sc in enumerate(scenes):
        r = slice(offsets[b], offsets[b] + sc.num_tracks)
        per_scene.append(MotionTokens(ids=mt.ids[r], valid=mt.valid[r], start_pose=mt.start_pose[r], reached=mt.reached[r],
                                      reached_valid=mt.reached_valid[r], types=mt.types[r], boundaries=mt.boundaries,
                                      nearest_ids=mt.nearest_ids[r]))
        if rule_out is not None:
            rule_out.append(rule.recorded[r])
    return per_scene
