"""Model stage, MotionNet: motion tokens of every agent + road encodings -> per-(agent, step)
features, from which the heads give next-motion-token logits (SMART sec. 3.2).

Input per agent a and token step s: the token it took (its contour, embedded by a per-type MLP),
its motion features (speed and the angle between heading and motion, Fourier-embedded) with type
and shape embeddings, and the pose it reached at the end of token s; with ``speed_change_input``, also
its speed change against token s - 1 (an MLP whose last layer starts at zero, so that a trained model
given the input answers as before until the input is trained). Each block applies, in turn:

1. temporal attention over the agent's own tokens s - w .. s (w = ``temporal_window_tokens``),
2. map-to-agent attention to the K nearest road tokens within ``map_radius_m``,
3. agent-agent attention to the K nearest agents at the same step within ``agent_radius_m``,

each with RPE (distance, bearing in the query's frame, heading difference, and the time gap for
temporal edges) added to keys and values. Step s's features depend only on steps <= s, so one new
step can be run against the cached source rows of the last w steps: every attention reads its
source rows through :func:`~.layers.normalise`, per step. :meth:`MotionNet.forward` runs every
step at once (training, and the rollout's ``mode="full"``); :meth:`MotionNet.step` runs one new step
against a :class:`MotionCache` (inference), through the same embeddings, neighbour search, RPE and
attention layers, so the two give the same features (``tests/test_rollout.py``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn as nn

from ..scenario import wrap_angle
from ..padding import grow, put_rows
from ..tokens.motion import TOKEN_S
from .layers import (FourierEmbedding, NeighbourAttention, knn_grouped, knn_within, mlp, neighbour_keys, normalise,
                     relative_pose_features, trim_neighbours, valid_rows)

NUM_MOTION_TYPES = 3  # vehicle, pedestrian, cyclist (AgentType 0..2)
SPEED_CHANGE_SCALE_MPS = 2.0  # speed_change_input: the change is divided by this before its embedding
STILL_SPEED_MPS = 0.1  # below this speed over a token the heading-vs-motion angle is set to 0
# RPE inputs whose values repeat (FourierEmbedding's repeated_dims): of (distance, bearing, heading difference[, time gap])
PAIR_REPEATS = (0, 2)  # a pair and its reverse share the distance; agents on one lane share a heading difference
TEMPORAL_REPEATS = (0, 2, 3)  # the step itself (distance 0, heading difference 0) and the 7 time gaps


def token_speed(start_pose: torch.Tensor, end_pose: torch.Tensor) -> torch.Tensor:
    """[...] the speed over a token (m/s) from where it starts to the pose it reaches, [..., 3] each."""
    return (end_pose[..., :2] - start_pose[..., :2]).norm(dim=-1) / TOKEN_S


def speed_change(start_pose: torch.Tensor, end_pose: torch.Tensor, speed_before: torch.Tensor, had: torch.Tensor) -> torch.Tensor:
    """[Q] a token's speed change (m/s): its speed (:func:`token_speed` of ``start_pose``, ``end_pose`` [Q, 3])
    less the token before's, ``speed_before`` [Q]; 0 where ``had`` [Q] is false (no token before)."""
    return torch.where(had, token_speed(start_pose, end_pose) - speed_before, torch.zeros_like(speed_before))


class MotionNet(nn.Module):
    def __init__(self, cfg) -> None:
        super().__init__()
        d = cfg.hidden_dim
        self.cfg = cfg
        self.token_mlp = nn.ModuleList(mlp(6 * 4 * 2, d, d) for _ in range(NUM_MOTION_TYPES))  # contour [6, 4, 2]
        self.type_emb = nn.Embedding(NUM_MOTION_TYPES, d)
        self.shape_mlp = mlp(3, d, d)  # length, width, height
        self.motion_feat = FourierEmbedding(2, d, cfg.num_freq_bands)  # speed, heading-vs-motion angle
        self.fusion = mlp(2 * d, d, d)
        if cfg.speed_change_input:  # added to the fused input; its last layer starts at zero (a model without it at first)
            self.speed_change = mlp(1, d, d)
            nn.init.zeros_(self.speed_change[-1].weight)
            nn.init.zeros_(self.speed_change[-1].bias)
        self.rpe_temporal = FourierEmbedding(4, d, cfg.num_freq_bands)
        self.rpe_map = FourierEmbedding(3, d, cfg.num_freq_bands)
        self.rpe_agent = FourierEmbedding(3, d, cfg.num_freq_bands)
        att = lambda bip: NeighbourAttention(d, cfg.num_heads, cfg.head_dim, cfg.dropout, bipartite=bip)  # noqa: E731
        self.temporal_attn = nn.ModuleList(att(False) for _ in range(cfg.num_agent_blocks))
        self.map_attn = nn.ModuleList(att(True) for _ in range(cfg.num_agent_blocks))
        self.agent_attn = nn.ModuleList(att(False) for _ in range(cfg.num_agent_blocks))

    # ------------------------------------------------------------------------------ inputs
    def token_table(self, contours: list[torch.Tensor]) -> torch.Tensor:
        """The token embeddings of every type's vocabulary: contours per type [V_t, 6, 4, 2] ->
        (3, Vmax, d), rows beyond a type's size zero."""
        tables = [m(c.flatten(1)) for m, c in zip(self.token_mlp, contours)]  # each (V_t, d)
        vmax = max(t.shape[0] for t in tables)
        return torch.stack([nn.functional.pad(t, (0, 0, 0, vmax - t.shape[0])) for t in tables])  # (3, Vmax, d)

    def agent_categorical(self, agent_type: torch.Tensor, agent_shape: torch.Tensor) -> torch.Tensor:
        """The per-agent part of the motion features: type and shape embeddings, [..., d]."""
        return self.type_emb(agent_type) + self.shape_mlp(agent_shape)

    def fuse(self, token_emb: torch.Tensor, start_pose: torch.Tensor, end_pose: torch.Tensor,
             categorical: torch.Tensor, speed_change: torch.Tensor | None = None) -> torch.Tensor:
        """The fused input of (agent, step) rows: the token embedding [..., d] with the motion features
        (speed and the angle between heading and motion over the token, from start_pose and
        end_pose [..., 3], Fourier-embedded with ``categorical`` [..., d]) -> [..., d]; with
        ``speed_change_input``, plus the embedding of ``speed_change`` [...] (:func:`speed_change`)."""
        motion = end_pose[..., :2] - start_pose[..., :2]  # (..., 2)
        speed = token_speed(start_pose, end_pose)
        angle = wrap_angle(torch.atan2(motion[..., 1], motion[..., 0]) - end_pose[..., 2])
        angle = torch.where(speed > STILL_SPEED_MPS, angle, torch.zeros_like(angle))  # undefined when (nearly) still
        feat = self.motion_feat(torch.stack([speed, angle], -1), categorical=categorical)  # (..., d)
        out = self.fusion(torch.cat([token_emb, feat], -1))
        if self.cfg.speed_change_input:
            out = out + self.speed_change(speed_change[..., None] / SPEED_CHANGE_SCALE_MPS)
        return out

    def embed_agents(self, tokens, agent_type, agent_shape, start_pose, end_pose, contours, rows: torch.Tensor,
                     valid: torch.Tensor | None = None) -> torch.Tensor:
        """The fused input features [Q, d] of the (agent, step) rows ``rows`` [Q] (full rows
        ((b * N + n) * S + s) of tokens [B, N, S], as :meth:`neighbourhoods` gives them); ``valid`` [B, N, S]
        the rows that exist (read with ``speed_change_input``)."""
        s = tokens.shape[2]
        agent = rows // s  # (Q,) rows of the B*N agent table
        cat = self.agent_categorical(agent_type, agent_shape).reshape(-1, self.cfg.hidden_dim)[agent]  # (Q, d)
        token_emb = self.token_table(contours)[agent_type.reshape(-1)[agent], tokens.reshape(-1)[rows]]  # (Q, d)
        start_flat, end_flat = start_pose.reshape(-1, 3), end_pose.reshape(-1, 3)
        change = None
        if self.cfg.speed_change_input:
            back = (rows - 1).clamp(min=0)
            had = ((rows % s) >= 1) & valid.reshape(-1)[back]
            change = speed_change(start_flat[rows], end_flat[rows], token_speed(start_flat[back], end_flat[back]), had)
        return self.fuse(token_emb, start_flat[rows], end_flat[rows], cat, change)

    # ----------------------------------------------------------------------- neighbourhoods
    def neighbourhoods(self, pose: torch.Tensor, valid: torch.Tensor, road_pose: torch.Tensor, road_valid: torch.Tensor):
        """Queries (the valid (agent, step) rows only) and, for the three attentions, neighbour
        indices into the query table (or the road table), masks and RPE.

        pose [B, N, S, 3] (pose at the end of each token), valid [B, N, S]; road_pose [B, R, 3].
        Full rows are ((b * N + n) * S + s), road rows (b * R + r). Returns (rows [Q] (full row of
        each query), temporal, map, agents), each a triple (index [Q, K], mask [Q, K], rpe [Q, K, d]).
        Neighbour lists are trimmed to the largest number of real neighbours in the batch.
        """
        cfg = self.cfg
        b, n, s, _ = pose.shape
        r = road_pose.shape[1]
        dev = pose.device
        valid_flat = valid.reshape(-1)
        rows, compact = valid_rows(valid)  # (Q,) full row of each query
        pose_flat = pose.reshape(-1, 3)
        q_pose = pose_flat[rows]  # (Q, 3)
        q_step = rows % s

        # 1. temporal: own tokens s - dt, dt = 0 .. w (causal)
        dts = torch.arange(cfg.temporal_window_tokens + 1, device=dev)  # (W,)
        ok = (q_step[:, None] - dts) >= 0  # (Q, W)
        t_full = torch.where(ok, rows[:, None] - dts, rows[:, None])
        t_mask = ok & valid_flat[t_full]
        t_feat = torch.cat([relative_pose_features(q_pose[:, None], pose_flat[t_full]),
                            dts.to(pose.dtype).expand(rows.numel(), -1)[..., None]], -1)  # (Q, W, 4)
        t_rpe = normalise(self.rpe_temporal(t_feat, valid=t_mask, repeated_dims=TEMPORAL_REPEATS))  # (Q, W, d)
        temporal = (compact[t_full].clamp(min=0), t_mask, t_rpe)
        # 2. map -> agent: K nearest road tokens within map_radius_m of the agent's pose at step s
        q_scene = rows // (n * s)
        m_idx, m_mask = knn_grouped(q_pose[:, :2], q_scene, road_pose[..., :2], cfg.map_radius_m, cfg.map_neighbours,
                                    road_valid)  # (Q, Km)
        m_idx, m_mask = trim_neighbours(m_idx + (q_scene * r)[:, None], m_mask)  # rows of the B*R road table
        m_rpe = normalise(self.rpe_map(relative_pose_features(q_pose[:, None], road_pose.reshape(-1, 3)[m_idx]),
                                       valid=m_mask))  # (Q, Km, d)
        mapa = (m_idx, m_mask, m_rpe)
        # 3. agent -> agent at the same step: K nearest within agent_radius_m
        pose_bs = pose.permute(0, 2, 1, 3).reshape(b * s, n, 3)  # (B*S, N, 3)
        valid_bs = valid.permute(0, 2, 1).reshape(b * s, n)
        a_idx, a_mask = knn_within(pose_bs[..., :2], pose_bs[..., :2], cfg.agent_radius_m, cfg.agent_neighbours, valid_bs, valid_bs)
        # neighbour n' at the same (b, s) is full row (b * N + n') * S + s; back to full row order
        bb = torch.arange(b, device=dev).repeat_interleave(s)[:, None, None]
        ss = torch.arange(s, device=dev).repeat(b)[:, None, None]
        a_full = (bb * n + a_idx) * s + ss  # (B*S, N, Ka)
        unperm = lambda t: t.view(b, s, n, -1).transpose(1, 2).reshape(b * n * s, -1)[rows]  # noqa: E731
        a_full, a_mask = trim_neighbours(unperm(a_full), unperm(a_mask))  # (Q, Ka)
        a_rpe = normalise(self.rpe_agent(relative_pose_features(q_pose[:, None], pose_flat[a_full]), valid=a_mask,
                                         repeated_dims=PAIR_REPEATS))  # (Q, Ka, d)
        agents = (compact[a_full].clamp(min=0), a_mask, a_rpe)
        return rows, temporal, mapa, agents

    # ----------------------------------------------------------------------------- forward
    def forward(self, x: torch.Tensor, road_x: torch.Tensor, nbrs, grid: tuple[int, int, int]) -> torch.Tensor:
        """x [Q, d] fused inputs of the query rows (:meth:`embed_agents`), road_x [B, R, d] (RoadNet),
        nbrs from :meth:`neighbourhoods` of the (B, N, S) ``grid`` -> features [B, N, S, d] (zeros on the
        rows that are not queries)."""
        rows, (t_idx, t_mask, t_rpe), (m_idx, m_mask, m_rpe), (a_idx, a_mask, a_rpe) = nbrs
        h = x  # (Q, d)
        map_keys = neighbour_keys(normalise(road_x.reshape(-1, road_x.shape[-1])), m_idx, m_rpe)  # (Q, Km, 2d)
        for t_attn, m_attn, a_attn in zip(self.temporal_attn, self.map_attn, self.agent_attn):
            h = t_attn(h, (t_idx, t_rpe), t_mask)
            h = m_attn(h, map_keys, m_mask)  # the same key-side inputs for every block
            h = a_attn(h, (a_idx, a_rpe), a_mask)
        out = h.new_zeros(grid[0] * grid[1] * grid[2], h.shape[-1])
        return out.index_copy(0, rows, h).view(*grid, h.shape[-1])

    # ------------------------------------------------------------------ the cached step (inference)
    @torch.no_grad()
    def start_cache(self, road_x: torch.Tensor, road_pose: torch.Tensor, road_valid: torch.Tensor, scene_of_group: torch.Tensor,
                    agent_type: torch.Tensor, agent_shape: torch.Tensor, contours: list[torch.Tensor]) -> "MotionCache":
        """An empty KV cache for ``G`` groups of ``N`` agent slots over ``B`` scenes.

        road_x [B, R, d] (RoadNet encodings), road_pose [B, R, 3], road_valid [B, R]; scene_of_group
        [G] (long): the scene of each group (a rollout copy of a scene); agent_type [G, N] (0..2 for
        every slot; padding slots are never valid), agent_shape [G, N, 3]; contours per type.
        """
        cfg = self.cfg
        g, n = agent_type.shape
        dev = road_x.device
        scene_of_group, agent_type = scene_of_group.to(dev), agent_type.to(dev)
        w = int(cfg.temporal_window_tokens)
        cache = MotionCache(
            num_groups=g, num_slots=n, scene_of_group=scene_of_group, agent_type=agent_type.reshape(-1),
            agent_categorical=self.agent_categorical(agent_type, agent_shape.to(dev)).reshape(g * n, -1),  # (G*N, d)
            token_table=self.token_table(contours),  # (3, Vmax, d)
            road_pose=road_pose[scene_of_group], road_valid=road_valid[scene_of_group], road_pose_flat=road_pose.reshape(-1, 3),
            road_rows=road_x.new_zeros(0),
            src=[road_x.new_zeros(g * n, w, cfg.hidden_dim) for _ in range(cfg.num_agent_blocks)],  # at the model's precision
            pose=torch.zeros(g * n, w, 3, device=dev), valid=torch.zeros(g * n, w, dtype=torch.bool, device=dev),
            speed=torch.zeros(g * n, device=dev),
        )
        self.cache_road(cache, road_x)
        return cache

    @torch.no_grad()
    def cache_road(self, cache: "MotionCache", road_x: torch.Tensor) -> None:
        """Use new road encodings [B, R, d] (same pieces) from the next step on (e.g. after a
        traffic-light change): the map attentions read them through :func:`normalise`."""
        cache.road_rows = normalise(road_x.reshape(-1, road_x.shape[-1]))  # (B*R, d)

    @torch.no_grad()
    def step(self, cache: "MotionCache", tokens: torch.Tensor, start_pose: torch.Tensor, end_pose: torch.Tensor,
             valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One new token step of every agent against the cache: the same numbers as :meth:`forward`
        over every step so far (``tests/test_rollout.py``), at the cost of one step.

        tokens [G, N] (ids in each slot's type vocabulary), start_pose and end_pose [G, N, 3] (where
        each token starts and the pose it reaches), valid [G, N]. Returns (rows [Q] (flat slot
        index g * N + n of the valid slots), features [Q, d]) and pushes this step into the cache.

        Why this is exact: step s depends only on steps <= s. Per block it runs temporal attention
        over the agent's own steps s - W .. s (the cached source rows of the block's input at the
        last W steps, with the poses they ended at), map-agent attention to the road encodings
        (normalised once per scene) and agent-agent attention among the agents at
        step s (rebuilt from the new poses).
        """
        cfg = self.cfg
        g, n = cache.num_groups, cache.num_slots
        dev = cache.agent_type.device
        w = int(cfg.temporal_window_tokens)
        valid_flat = valid.reshape(-1).to(dev)
        rows, compact = valid_rows(valid_flat)  # (Q,) the valid slots; compact: each slot's query row
        nq = rows.numel()
        tokens_flat = tokens.reshape(-1).to(dev)
        start_flat = start_pose.reshape(-1, 3).to(dev, torch.float32)
        end_flat = end_pose.reshape(-1, 3).to(dev, torch.float32)
        q_pose = end_flat[rows]  # (Q, 3)
        token_emb = cache.token_table[cache.agent_type[rows], tokens_flat[rows]]  # (Q, d)
        change = None
        if cfg.speed_change_input:  # the speed of the agent's token before, from the cache
            change = speed_change(start_flat[rows], q_pose, cache.speed[rows], cache.valid[rows, 0])
        h = self.fuse(token_emb, start_flat[rows], q_pose, cache.agent_categorical[rows], change)  # (Q, d)

        # 1. temporal neighbours: the step itself (dt = 0) then the cached steps dt = 1 .. w
        key_pose = torch.cat([q_pose[:, None], cache.pose[rows]], 1)  # (Q, W+1, 3)
        t_mask = torch.cat([torch.ones(nq, 1, dtype=torch.bool, device=dev), cache.valid[rows]], 1)  # (Q, W+1)
        dts = torch.arange(w + 1, device=dev, dtype=torch.float32)
        t_feat = torch.cat([relative_pose_features(q_pose[:, None], key_pose), dts.expand(nq, -1)[..., None]], -1)  # (Q, W+1, 4)
        t_rpe = normalise(self.rpe_temporal(t_feat, valid=t_mask, repeated_dims=TEMPORAL_REPEATS))  # (Q, W+1, d)

        # 2. map -> agent: the K nearest road tokens of each new pose (rows of the B*R road table)
        m_idx, m_mask = knn_within(end_flat.view(g, n, 3)[..., :2], cache.road_pose[..., :2], cfg.map_radius_m,
                                   cfg.map_neighbours, valid_flat.view(g, n), cache.road_valid)  # (G, N, Km)
        m_idx = (m_idx + (cache.scene_of_group * cache.road_pose.shape[1])[:, None, None]).reshape(g * n, -1)[rows]  # (Q, Km)
        m_idx, m_mask = trim_neighbours(m_idx, m_mask.reshape(g * n, -1)[rows])
        m_rpe = normalise(self.rpe_map(relative_pose_features(q_pose[:, None], cache.road_pose_flat[m_idx]),
                                       valid=m_mask))  # (Q, Km, d)

        # 3. agent -> agent at this step, rebuilt from the new poses
        a_idx, a_mask = knn_within(end_flat.view(g, n, 3)[..., :2], end_flat.view(g, n, 3)[..., :2], cfg.agent_radius_m,
                                   cfg.agent_neighbours, valid_flat.view(g, n), valid_flat.view(g, n))  # (G, N, Ka)
        a_full = (a_idx + (torch.arange(g, device=dev) * n)[:, None, None]).reshape(g * n, -1)[rows]  # (Q, Ka) flat slots
        a_full, a_mask = trim_neighbours(a_full, a_mask.reshape(g * n, -1)[rows])
        a_rows = compact[a_full].clamp(min=0)  # (Q, Ka) query rows (masked slots point at row 0)
        a_rpe = normalise(self.rpe_agent(relative_pose_features(q_pose[:, None], end_flat[a_full]), valid=a_mask,
                                         repeated_dims=PAIR_REPEATS))  # (Q, Ka, d)

        map_keys = neighbour_keys(cache.road_rows, m_idx, m_rpe)  # (Q, Km, 2d), shared by the blocks
        new_rows = []
        for blk, (t_attn, m_attn, a_attn) in enumerate(zip(self.temporal_attn, self.map_attn, self.agent_attn)):
            own = normalise(h)  # (Q, d) this step's row of the block's temporal input
            new_rows.append(own)
            t_keys = torch.cat([torch.cat([own[:, None], cache.src[blk][rows]], 1), t_rpe], -1)  # (Q, W+1, 2d)
            h = t_attn(h, t_keys, t_mask)
            h = m_attn(h, map_keys, m_mask)
            h = a_attn(h, (a_rows, a_rpe), a_mask)

        # push this step into the cache (newest first; the oldest step falls out of the window)
        for blk, own in enumerate(new_rows):
            src_new = own.new_zeros(g * n, 1, own.shape[-1]).index_copy_(0, rows, own[:, None])
            cache.src[blk] = torch.cat([src_new, cache.src[blk][:, : w - 1]], 1)
        cache.pose = torch.cat([end_flat[:, None], cache.pose[:, : w - 1]], 1)
        cache.valid = torch.cat([valid_flat[:, None], cache.valid[:, : w - 1]], 1)
        if cfg.speed_change_input:
            cache.speed = torch.where(valid_flat, token_speed(start_flat, end_flat), torch.zeros_like(cache.speed))
        cache.steps_done += 1
        return rows, h


# -------------------------------------------------------------------------- the cached step
@dataclass
class MotionCache:
    """What :meth:`MotionNet.step` keeps between token steps of ``G`` groups (scene x rollout
    copies) of ``N`` agent slots: per-scene and per-agent constants, and the KV cache.

    The cache (newest step first, the oldest falls out of the window of ``W`` =
    ``temporal_window_tokens`` steps): per block the rows of the block's temporal input as its
    attention reads them (through :func:`~.layers.normalise`), ``src`` [G * N, W, d], and the
    pose each cached step ended at and its validity, ``pose`` [G * N, W, 3], ``valid`` [G * N, W]; and the speed
    over the newest step's token, ``speed`` [G * N] (kept with ``speed_change_input``, which reads it; 0 where the
    step was not valid, and always without it).
    A step replaces these tensors (it never writes into them), so :meth:`fork` shares them until
    either copy steps. The per-slot tensors are named in :data:`PER_SLOT` (with ``src``): stacking,
    taking and replacing groups carry each of them, so a new one is added there once.
    """

    PER_SLOT: ClassVar[dict[str, object]] = {"agent_type": 0, "agent_categorical": 0, "pose": 0, "valid": False, "speed": 0}
    """The flat ``[G * N, ...]`` tensors kept per agent slot besides ``src``, and the fill of a padded slot."""

    num_groups: int
    num_slots: int
    scene_of_group: torch.Tensor  # [G] long, the scene (row of the road tensors) of each group
    agent_type: torch.Tensor  # [G * N] long, 0..2
    agent_categorical: torch.Tensor  # [G * N, d] type + shape embeddings
    token_table: torch.Tensor  # [3, Vmax, d] token embeddings
    road_pose: torch.Tensor  # [G, R, 3] each group's scene's road pieces (for the neighbour search)
    road_valid: torch.Tensor  # [G, R]
    road_pose_flat: torch.Tensor  # [B * R, 3] rows of the road table
    road_rows: torch.Tensor  # [B * R, d] the road encodings through normalise (what every map attention reads)
    src: list  # per block [G * N, W, d]: the block's temporal input through normalise at the last W steps
    pose: torch.Tensor  # [G * N, W, 3]
    valid: torch.Tensor  # [G * N, W] bool
    speed: torch.Tensor  # [G * N] the speed over the newest step's token
    steps_done: int = 0

    def fork(self) -> "MotionCache":
        """An independent copy that shares every tensor (none is written in place)."""
        out = copy.copy(self)
        out.src = list(self.src)
        return out

    @classmethod
    def stack(cls, caches: list["MotionCache"]) -> "MotionCache":
        """One cache of every group of ``caches`` in order (caches of the same model whose road tables
        are their own scenes'), slots and road pieces padded to the largest: a state started on
        several scenes at once gives the same numbers."""
        n = max(c.num_slots for c in caches)
        r = max(c.num_road_pieces for c in caches)

        def slots(c: "MotionCache", t: torch.Tensor, fill=0) -> torch.Tensor:  # flat [G * N, ...] -> [G, n, ...]
            return grow(t.view(c.num_groups, c.num_slots, *t.shape[1:]), {1: n}, fill)

        def scene_rows(c: "MotionCache", t: torch.Tensor) -> torch.Tensor:  # flat [B * R, ...] -> [B, r, ...]
            return grow(t.view(-1, max(c.num_road_pieces, 1), *t.shape[1:]), {1: r})

        cat = lambda parts: torch.cat(parts).flatten(0, 1)  # noqa: E731
        first = caches[0]
        offsets = [0]
        for c in caches[:-1]:
            offsets.append(offsets[-1] + c.road_pose_flat.shape[0] // max(c.num_road_pieces, 1))
        return cls(
            num_groups=sum(c.num_groups for c in caches), num_slots=n,
            scene_of_group=torch.cat([c.scene_of_group + o for c, o in zip(caches, offsets)]), token_table=first.token_table,
            road_pose=torch.cat([grow(c.road_pose, {1: r}) for c in caches]),
            road_valid=torch.cat([grow(c.road_valid, {1: r}, False) for c in caches]),
            road_pose_flat=cat([scene_rows(c, c.road_pose_flat) for c in caches]),
            road_rows=cat([scene_rows(c, c.road_rows) for c in caches]),
            src=[cat([slots(c, c.src[k]) for c in caches]) for k in range(len(first.src))], steps_done=first.steps_done,
            **{name: cat([slots(c, getattr(c, name), fill) for c in caches]) for name, fill in cls.PER_SLOT.items()})

    def take(self, groups: torch.Tensor, scenes: torch.Tensor, num_slots: int, num_pieces: int) -> "MotionCache":
        """A cache of groups ``groups`` of this one (whose scenes are ``scenes``, in the order of the
        groups' ``scene_of_group``), cut to their first ``num_slots`` slots and ``num_pieces`` road pieces."""
        n, r, b = self.num_slots, self.num_road_pieces, self.road_pose_flat.shape[0] // max(self.num_road_pieces, 1)
        slots = lambda t: t.view(self.num_groups, n, *t.shape[1:])[groups, :num_slots].flatten(0, 1)  # noqa: E731
        pieces = lambda t: t.view(b, r, *t.shape[1:])[scenes, :num_pieces].flatten(0, 1)  # noqa: E731
        local = torch.full((b,), -1, dtype=torch.long, device=scenes.device)
        local[scenes] = torch.arange(len(scenes), device=scenes.device)
        return MotionCache(
            num_groups=len(groups), num_slots=num_slots, scene_of_group=local[self.scene_of_group[groups]], token_table=self.token_table,
            road_pose=self.road_pose[groups, :num_pieces], road_valid=self.road_valid[groups, :num_pieces],
            road_pose_flat=pieces(self.road_pose_flat), road_rows=pieces(self.road_rows), src=[slots(t) for t in self.src],
            steps_done=self.steps_done, **{name: slots(getattr(self, name)) for name in self.PER_SLOT})

    @property
    def num_road_pieces(self) -> int:
        return int(self.road_pose.shape[1])

    def replace(self, groups: torch.Tensor, scenes: torch.Tensor, other: "MotionCache") -> None:
        """Put every group of ``other`` (a cache of the same model) in place of this cache's groups
        ``groups`` [G_o] and its scenes' road rows in place of scenes ``scenes`` [B_o] (the scene of
        ``groups[i]`` must be ``scenes[other.scene_of_group[i]]``): their KV cache, constants and
        road, so that they step on as ``other``'s would. Slots and road pieces grow to the larger of
        the two (padding is never valid). Unlike a step this writes into the tensors: :meth:`fork`
        copies that share them see it, so replace in a state no fork of which is still used."""
        n, r = max(self.num_slots, other.num_slots), max(self.num_road_pieces, other.num_road_pieces)
        g, b = self.num_groups, self.road_pose_flat.shape[0] // max(self.num_road_pieces, 1)
        if n > self.num_slots:  # per-slot tensors are flat [G * N, ...]: grow as [G, N, ...]
            per_slot = lambda t, fill=0: grow(t.view(g, self.num_slots, *t.shape[1:]), {1: n}, fill).reshape(g * n, *t.shape[1:])  # noqa: E731
            for name, fill in self.PER_SLOT.items():
                setattr(self, name, per_slot(getattr(self, name), fill))
            self.src = [per_slot(t) for t in self.src]
            self.num_slots = n
        if r > self.num_road_pieces:
            self.road_pose_flat = grow(self.road_pose_flat.view(b, -1, 3), {1: r}).reshape(b * r, 3)
            self.road_rows = grow(self.road_rows.view(b, -1, self.road_rows.shape[-1]), {1: r}).reshape(b * r, -1)
            self.road_pose, self.road_valid = grow(self.road_pose, {1: r}), grow(self.road_valid, {1: r}, False)
        go, no = other.num_groups, other.num_slots
        slot = lambda t: t.view(g, n, *t.shape[1:])  # noqa: E731
        theirs = lambda t: t.view(go, no, *t.shape[1:])  # noqa: E731
        for name, fill in self.PER_SLOT.items():
            put_rows(slot(getattr(self, name)), groups, theirs(getattr(other, name)), fill)
        for mine, their_src in zip(self.src, other.src):
            put_rows(slot(mine), groups, theirs(their_src))
        put_rows(self.road_pose, groups, other.road_pose)
        put_rows(self.road_valid, groups, other.road_valid, False)
        bo, ro = other.road_pose_flat.shape[0] // max(other.num_road_pieces, 1), other.num_road_pieces
        put_rows(self.road_pose_flat.view(b, r, 3), scenes, other.road_pose_flat.view(bo, ro, 3))
        put_rows(self.road_rows.view(b, r, -1), scenes, other.road_rows.view(bo, ro, -1))
