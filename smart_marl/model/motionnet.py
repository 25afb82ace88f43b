"""Model stage, MotionNet: motion tokens of every agent + road encodings -> per-(agent, step)
features, from which the heads give next-motion-token logits (SMART sec. 3.2).

Input per agent a and token step s: the token it took (its contour, embedded by a per-type MLP),
its motion features (speed and the angle between heading and motion, Fourier-embedded) with type
and shape embeddings, and the pose it reached at the end of token s. Each block applies, in turn:

1. temporal attention over the agent's own tokens s - w .. s (w = ``temporal_window_tokens``),
2. map-to-agent attention to the K nearest road tokens within ``map_radius_m``,
3. agent-agent attention to the K nearest agents at the same step within ``agent_radius_m``,

each with RPE (distance, bearing in the query's frame, heading difference, and the time gap for
temporal edges) added to keys and values. Step s's features depend only on steps <= s, so one new
step can be run against cached key/value rows of the last w steps (the KV cache of a later issue):
every attention projects its key rows with :meth:`NeighbourAttention.project_source`, per step.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from .layers import FourierEmbedding, NeighbourAttention, knn_within, mlp, relative_pose_features, wrap_angle

NUM_MOTION_TYPES = 3  # vehicle, pedestrian, cyclist (AgentType 0..2)
TOKEN_SECONDS = 0.5


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
        self.rpe_temporal = FourierEmbedding(4, d, cfg.num_freq_bands)
        self.rpe_map = FourierEmbedding(3, d, cfg.num_freq_bands)
        self.rpe_agent = FourierEmbedding(3, d, cfg.num_freq_bands)
        att = lambda bip: NeighbourAttention(d, cfg.num_heads, cfg.head_dim, cfg.dropout, bipartite=bip)  # noqa: E731
        self.temporal_attn = nn.ModuleList(att(False) for _ in range(cfg.num_agent_blocks))
        self.map_attn = nn.ModuleList(att(True) for _ in range(cfg.num_agent_blocks))
        self.agent_attn = nn.ModuleList(att(False) for _ in range(cfg.num_agent_blocks))

    # ------------------------------------------------------------------------------ inputs
    def embed_tokens(self, tokens: torch.Tensor, agent_type: torch.Tensor, contours: list[torch.Tensor]) -> torch.Tensor:
        """tokens [B, N, S] (ids in the agent's type vocabulary), agent_type [B, N] (0..2),
        contours: per type [V_t, 6, 4, 2] -> [B, N, S, d]."""
        tables = [m(c.flatten(1)) for m, c in zip(self.token_mlp, contours)]  # each (V_t, d)
        vmax = max(t.shape[0] for t in tables)
        table = torch.stack([nn.functional.pad(t, (0, 0, 0, vmax - t.shape[0])) for t in tables])  # (3, Vmax, d)
        return table[agent_type[:, :, None].expand_as(tokens), tokens]  # (B, N, S, d)

    def embed_agents(self, tokens, agent_type, agent_shape, start_pose, end_pose, contours) -> torch.Tensor:
        """The fused input features [B, N, S, d] of every (agent, step)."""
        motion = end_pose[..., :2] - start_pose[..., :2]  # (B, N, S, 2)
        speed = motion.norm(dim=-1) / TOKEN_SECONDS
        angle = wrap_angle(torch.atan2(motion[..., 1], motion[..., 0]) - end_pose[..., 2])
        angle = torch.where(speed > 0.1, angle, torch.zeros_like(angle))  # undefined when (nearly) still
        cat = (self.type_emb(agent_type) + self.shape_mlp(agent_shape))[:, :, None].expand(-1, -1, tokens.shape[2], -1)
        feat = self.motion_feat(torch.stack([speed, angle], -1), categorical=cat)  # (B, N, S, d)
        return self.fusion(torch.cat([self.embed_tokens(tokens, agent_type, contours), feat], -1))

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
        rows = valid_flat.nonzero().squeeze(1)  # (Q,) full row of each query
        compact = torch.full_like(valid_flat, -1, dtype=torch.long)
        compact[rows] = torch.arange(rows.numel(), device=dev)
        pose_flat = pose.reshape(-1, 3)
        q_pose = pose_flat[rows]  # (Q, 3)
        q_step = rows % s

        def trim(idx, mask):
            k = int(mask.sum(-1).max()) if mask.numel() else 0
            return idx[:, :k], mask[:, :k]

        # 1. temporal: own tokens s - dt, dt = 0 .. w (causal)
        dts = torch.arange(cfg.temporal_window_tokens + 1, device=dev)  # (W,)
        ok = (q_step[:, None] - dts) >= 0  # (Q, W)
        t_full = torch.where(ok, rows[:, None] - dts, rows[:, None])
        t_mask = ok & valid_flat[t_full]
        t_feat = torch.cat([relative_pose_features(q_pose[:, None], pose_flat[t_full]),
                            dts.to(pose.dtype).expand(rows.numel(), -1)[..., None]], -1)  # (Q, W, 4)
        temporal = (compact[t_full].clamp(min=0), t_mask, self.rpe_temporal(t_feat))
        # 2. map -> agent: K nearest road tokens within map_radius_m of the agent's pose at step s
        m_idx, m_mask = knn_within(pose.reshape(b, n * s, 3)[..., :2], road_pose[..., :2], cfg.map_radius_m,
                                   cfg.map_neighbours, valid.reshape(b, n * s), road_valid)  # (B, N*S, Km)
        m_idx = (m_idx + (torch.arange(b, device=dev) * r)[:, None, None]).reshape(b * n * s, -1)[rows]
        m_idx, m_mask = trim(m_idx, m_mask.reshape(b * n * s, -1)[rows])  # (Q, Km)
        m_rpe = self.rpe_map(relative_pose_features(q_pose[:, None], road_pose.reshape(-1, 3)[m_idx]))  # (Q, Km, d)
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
        a_full, a_mask = trim(unperm(a_full), unperm(a_mask))  # (Q, Ka)
        a_rpe = self.rpe_agent(relative_pose_features(q_pose[:, None], pose_flat[a_full]))  # (Q, Ka, d)
        agents = (compact[a_full].clamp(min=0), a_mask, a_rpe)
        return rows, temporal, mapa, agents

    # ----------------------------------------------------------------------------- forward
    def forward(self, x: torch.Tensor, road_x: torch.Tensor, nbrs) -> torch.Tensor:
        """x [B, N, S, d] fused inputs, road_x [B, R, d] (RoadNet), nbrs from :meth:`neighbourhoods`
        -> features [B, N, S, d] (zeros on invalid (agent, step) rows)."""
        shape = x.shape
        rows, temporal, mapa, agents = nbrs
        h = x.reshape(-1, shape[-1])[rows]  # (Q, d) the valid (agent, step) rows
        road = road_x.reshape(-1, road_x.shape[-1])  # (B*R, d)
        for t_attn, m_attn, a_attn in zip(self.temporal_attn, self.map_attn, self.agent_attn):
            h = t_attn(h, h, *temporal)
            h = m_attn(h, road, *mapa)
            h = a_attn(h, h, *agents)
        out = h.new_zeros(shape[0] * shape[1] * shape[2], shape[3])
        return out.index_copy(0, rows, h).view(shape)
