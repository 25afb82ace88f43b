"""Rollout stage, incremental MotionNet: one new token step of every agent through the model's
layers against a KV cache (docs/architecture.md, "Inference is incremental").

What comes in: a SMART model, road encodings computed once per scene, and per token step the new
tokens of ``G`` groups (scene x rollout copies) of ``N`` agent slots: token ids, the pose each token
starts at and the pose it reaches, and which slots are valid. What goes out: the features
``[G, N, d]`` of that step (the same numbers as the model's full forward over every step so far,
see ``tests/test_rollout.py``), from which the heads give next-token logits.

Why this is exact: MotionNet's step s depends only on steps <= s. Per block it runs temporal
attention over the agent's own steps s - 6 .. s, map-agent attention to road encodings and
agent-agent attention among the agents *at step s*. So a new step needs, per block, only

* the projected key/value rows (``NeighbourAttention.project_source``) of the block's temporal
  input at the agent's last ``temporal_window_tokens`` steps, with the poses they were at (the
  cache, kept here as ``[G * N, W, inner]`` per block, newest first),
* the road encodings' key/value rows of the map attention (projected once per scene),
* the new step's own rows for everything else (agent-agent neighbourhoods are rebuilt from the
  new poses).

A step costs O(agents x (window + map neighbours + agent neighbours)), independent of how many
steps came before. The module calls the model's own submodules (embeddings, RPE, attentions);
it adds no weights.
"""

from __future__ import annotations

import torch

from ..model.layers import knn_within, relative_pose_features, wrap_angle
from ..model.motionnet import NUM_MOTION_TYPES, TOKEN_SECONDS


def _trim(index: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Neighbour lists [Q, K] cut to the largest number of real neighbours (slots are nearest first)."""
    k = int(mask.sum(-1).max()) if mask.numel() else 0
    return index[:, :k], mask[:, :k]


class IncrementalMotionNet:
    """MotionNet one token step at a time, with a per-block temporal KV cache.

    road_x [B, R, d] (RoadNet encodings), road_pose [B, R, 3], road_valid [B, R]: the B scenes.
    scene_of_group [G] (long): the scene each group (a rollout copy of a scene) belongs to.
    agent_type [G, N] (0..2 for every slot; padding slots are never valid), agent_shape [G, N, 3].
    """

    def __init__(self, model, road_x: torch.Tensor, road_pose: torch.Tensor, road_valid: torch.Tensor,
                 scene_of_group: torch.Tensor, agent_type: torch.Tensor, agent_shape: torch.Tensor) -> None:
        self.model = model
        self.net = model.motion_net
        cfg = self.cfg = model.config
        g, n = agent_type.shape
        self.num_groups, self.num_slots = g, n
        self.window = int(cfg.temporal_window_tokens)
        self.inner = cfg.num_heads * cfg.head_dim
        dev = road_x.device
        self.device = dev
        b, r, d = road_x.shape
        self.num_road = r
        self.scene_of_group = scene_of_group.to(dev)
        self.agent_type = agent_type.to(dev)
        self.agent_type_flat = self.agent_type.reshape(-1)
        net = self.net
        with torch.no_grad():
            # per-scene constants: road rows per group (for the neighbour search) and, per block,
            # the projected key/value rows of the road encodings (map-agent attention)
            self.road_pose_g = road_pose[self.scene_of_group]  # (G, R, 3)
            self.road_valid_g = road_valid[self.scene_of_group]  # (G, R)
            self.road_pose_flat = road_pose.reshape(-1, 3)  # (B*R, 3)
        self.set_road(road_x)
        with torch.no_grad():
            # token embedding tables (as MotionNet.embed_tokens builds them) and the per-agent
            # categorical part of the motion features (type + shape)
            tables = [mlp(c.flatten(1)) for mlp, c in zip(net.token_mlp, model.motion_contours)]
            vmax = max(t.shape[0] for t in tables)
            self.token_table = torch.stack([torch.nn.functional.pad(t, (0, 0, 0, vmax - t.shape[0])) for t in tables])  # (3, Vmax, d)
            self.agent_cat = (net.type_emb(self.agent_type) + net.shape_mlp(agent_shape.to(dev))).reshape(g * n, d)  # (G*N, d)
        blocks = cfg.num_agent_blocks
        w = self.window
        self.cache_k = [torch.zeros(g * n, w, self.inner, device=dev) for _ in range(blocks)]
        self.cache_v = [torch.zeros(g * n, w, self.inner, device=dev) for _ in range(blocks)]
        self.cache_pose = torch.zeros(g * n, w, 3, device=dev)  # pose at the end of each cached step, newest first
        self.cache_valid = torch.zeros(g * n, w, dtype=torch.bool, device=dev)
        self.steps_done = 0

    # --------------------------------------------------------------------------------- inputs
    def _embed(self, rows: torch.Tensor, tokens: torch.Tensor, start_pose: torch.Tensor, end_pose: torch.Tensor) -> torch.Tensor:
        """MotionNet.embed_agents for the query rows only: (Q,) rows, flat (G*N,) tokens,
        (G*N, 3) poses -> (Q, d)."""
        net = self.net
        motion = end_pose[rows, :2] - start_pose[rows, :2]  # (Q, 2)
        speed = motion.norm(dim=-1) / TOKEN_SECONDS
        angle = wrap_angle(torch.atan2(motion[:, 1], motion[:, 0]) - end_pose[rows, 2])
        angle = torch.where(speed > 0.1, angle, torch.zeros_like(angle))
        feat = net.motion_feat(torch.stack([speed, angle], -1), categorical=self.agent_cat[rows])  # (Q, d)
        tok = self.token_table[self.agent_type_flat[rows], tokens[rows]]  # (Q, d)
        return net.fusion(torch.cat([tok, feat], -1))

    # ----------------------------------------------------------------------------------- step
    def set_road(self, road_x: torch.Tensor) -> None:
        """Use new road encodings [B, R, d] (same pieces) from the next step on: re-projects the
        map-attention keys and values of every block (e.g. after a traffic-light change)."""
        with torch.no_grad():
            flat = road_x.reshape(-1, road_x.shape[-1])
            self.road_kv = [m.project_source(flat) for m in self.net.map_attn]  # per block 2 x (B*R, inner)

    @torch.no_grad()
    def step(self, tokens: torch.Tensor, start_pose: torch.Tensor, end_pose: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Run one token step: tokens [G, N] (ids in each slot's type vocabulary), start_pose and
        end_pose [G, N, 3] (where each token starts and the pose it reaches), valid [G, N].

        Returns (rows [Q] (flat slot index g * N + n of the valid slots), features [Q, d]) and
        pushes this step into the cache.
        """
        cfg, net = self.cfg, self.net
        g, n = self.num_groups, self.num_slots
        dev = self.device
        w = self.window
        valid_flat = valid.reshape(-1).to(dev)
        rows = valid_flat.nonzero().squeeze(1)  # (Q,)
        nq = rows.numel()
        tokens_flat = tokens.reshape(-1).to(dev)
        start_flat = start_pose.reshape(-1, 3).to(dev, torch.float32)
        end_flat = end_pose.reshape(-1, 3).to(dev, torch.float32)
        q_pose = end_flat[rows]  # (Q, 3)
        h = self._embed(rows, tokens_flat, start_flat, end_flat)  # (Q, d)

        # 1. temporal neighbours: the step itself (dt = 0) then the cached steps dt = 1 .. w
        key_pose = torch.cat([q_pose[:, None], self.cache_pose[rows]], 1)  # (Q, W+1, 3)
        t_mask = torch.cat([torch.ones(nq, 1, dtype=torch.bool, device=dev), self.cache_valid[rows]], 1)  # (Q, W+1)
        dts = torch.arange(w + 1, device=dev, dtype=torch.float32)
        t_feat = torch.cat([relative_pose_features(q_pose[:, None], key_pose), dts.expand(nq, -1)[..., None]], -1)  # (Q, W+1, 4)
        t_rpe = net.rpe_temporal(t_feat)  # (Q, W+1, d)
        t_index = torch.arange(nq * (w + 1), device=dev).view(nq, w + 1)  # rows of the per-block key table

        # 2. map -> agent: the K nearest road tokens of each new pose (rows of the B*R road table)
        m_idx, m_mask = knn_within(end_flat.view(g, n, 3)[..., :2], self.road_pose_g[..., :2], cfg.map_radius_m,
                                   cfg.map_neighbours, valid_flat.view(g, n), self.road_valid_g)  # (G, N, Km)
        m_idx = (m_idx + (self.scene_of_group * self.num_road)[:, None, None]).reshape(g * n, -1)[rows]  # (Q, Km)
        m_mask = m_mask.reshape(g * n, -1)[rows]
        m_idx, m_mask = _trim(m_idx, m_mask)
        m_rpe = net.rpe_map(relative_pose_features(q_pose[:, None], self.road_pose_flat[m_idx]))  # (Q, Km, d)

        # 3. agent -> agent at this step, rebuilt from the new poses
        a_idx, a_mask = knn_within(end_flat.view(g, n, 3)[..., :2], end_flat.view(g, n, 3)[..., :2], cfg.agent_radius_m,
                                   cfg.agent_neighbours, valid_flat.view(g, n), valid_flat.view(g, n))  # (G, N, Ka)
        a_full = (a_idx + (torch.arange(g, device=dev) * n)[:, None, None]).reshape(g * n, -1)[rows]  # (Q, Ka) flat slots
        a_mask = a_mask.reshape(g * n, -1)[rows]
        a_full, a_mask = _trim(a_full, a_mask)
        compact = torch.zeros(g * n, dtype=torch.long, device=dev)
        compact[rows] = torch.arange(nq, device=dev)
        a_rows = compact[a_full]  # (Q, Ka) query rows (masked slots point anywhere valid)
        a_rpe = net.rpe_agent(relative_pose_features(q_pose[:, None], end_flat[a_full]))  # (Q, Ka, d)

        new_kv = []
        for blk, (t_attn, m_attn, a_attn) in enumerate(zip(net.temporal_attn, net.map_attn, net.agent_attn)):
            k_self, v_self = t_attn.project_source(h)  # (Q, inner)
            new_kv.append((k_self, v_self))
            k_tab = torch.cat([k_self[:, None], self.cache_k[blk][rows]], 1).reshape(-1, self.inner)  # (Q*(W+1), inner)
            v_tab = torch.cat([v_self[:, None], self.cache_v[blk][rows]], 1).reshape(-1, self.inner)
            h = t_attn(h, (k_tab, v_tab), t_index, t_mask, t_rpe)
            h = m_attn(h, self.road_kv[blk], m_idx, m_mask, m_rpe)
            h = a_attn(h, h, a_rows, a_mask, a_rpe)

        # push this step into the cache (newest first; the oldest step falls out of the window)
        for blk, (k_self, v_self) in enumerate(new_kv):
            k_new = torch.zeros(g * n, 1, self.inner, device=dev).index_copy_(0, rows, k_self[:, None])
            v_new = torch.zeros(g * n, 1, self.inner, device=dev).index_copy_(0, rows, v_self[:, None])
            self.cache_k[blk] = torch.cat([k_new, self.cache_k[blk][:, : w - 1]], 1)
            self.cache_v[blk] = torch.cat([v_new, self.cache_v[blk][:, : w - 1]], 1)
        self.cache_pose = torch.cat([end_flat[:, None], self.cache_pose[:, : w - 1]], 1)
        self.cache_valid = torch.cat([valid_flat[:, None], self.cache_valid[:, : w - 1]], 1)
        self.steps_done += 1
        return rows, h

    @torch.no_grad()
    def logits(self, rows: torch.Tensor, features: torch.Tensor) -> list[torch.Tensor]:
        """Each row's own type head: per type t, logits [Q_t, V_t] of the rows of type t (in row order)."""
        types = self.agent_type_flat[rows]
        return [self.model.motion_heads[t](features[types == t]) for t in range(NUM_MOTION_TYPES)]
