"""Model stage, RoadNet: road-vector tokens -> road encodings (SMART sec. 3.2).

Each road token (a road piece of at most 5 m) is embedded from its points (in the piece's own
frame) plus road-type and traffic-light embeddings, then refined by self-attention among road
tokens within ``road_radius_m`` (10 m), with RPE from the relative poses. The encodings are
computed once per scene and read by MotionNet's map-to-agent attention; a head on them predicts
the next road token along a road sequence (the road next-token task).
"""

from __future__ import annotations

import torch
import torch.nn as nn

from .layers import FourierEmbedding, NeighbourAttention, knn_within, mlp, normalise, relative_pose_features, trim_neighbours, valid_rows

NUM_ROAD_TYPES = 64  # ids given by the batch builder: feature type * 9 + subtype (see batch.py)
NUM_LIGHT_STATES = 10  # SignalState 0..8 plus 9 = no light on this piece
# RPE inputs whose values repeat (FourierEmbedding's repeated_dims): a pair and its reverse share the distance
# (half of the WOMD road pairs' distances are distinct); pieces of straight lanes share heading differences (79%
# distinct on the WOMD scenes, where FourierEmbedding embeds them per row; fewer on SUMO's straight roads)
ROAD_REPEATS = (0, 2)


class RoadNet(nn.Module):
    def __init__(self, cfg) -> None:
        super().__init__()
        d = cfg.hidden_dim
        self.cfg = cfg
        self.piece_mlp = mlp(2 * cfg.road_piece_points, d, d)  # points of the piece in its frame
        self.type_emb = nn.Embedding(NUM_ROAD_TYPES, d)
        self.light_emb = nn.Embedding(NUM_LIGHT_STATES, d)
        self.mask_emb = nn.Parameter(torch.zeros(d))  # replaces a masked piece's content (road task)
        self.rpe = FourierEmbedding(3, d, cfg.num_freq_bands)
        self.layers = nn.ModuleList(
            NeighbourAttention(d, cfg.num_heads, cfg.head_dim, cfg.dropout, bipartite=False) for _ in range(cfg.num_road_layers)
        )

    def forward(self, points: torch.Tensor, pose: torch.Tensor, road_type: torch.Tensor, light: torch.Tensor,
                valid: torch.Tensor, masked: torch.Tensor | None = None, needed: torch.Tensor | None = None) -> torch.Tensor:
        """points [B, R, P, 2], pose [B, R, 3], road_type [B, R], light [B, R], valid [B, R],
        masked [B, R] (pieces whose content is hidden) -> road encodings [B, R, d] (zeros on padded
        pieces: only the valid pieces are encoded, and no piece attends to a padded one).

        ``needed`` [B, R] (bool): the pieces whose encodings the caller reads (training: the pieces the
        agents attend to and those the road loss predicts from). Then each layer runs only for the pieces
        that a later layer or the caller reads, every other piece's encoding is zero, and the needed ones
        are what they would be with every piece computed: a piece's encoding depends only on its
        neighbours' in the layer before."""
        b, r = valid.shape
        rows, compact = valid_rows(valid)  # (V,) the valid pieces, rows of the flat B*R table
        x = self.piece_mlp(points.reshape(b * r, -1)[rows])  # (V, d)
        if masked is not None:
            x = torch.where(masked.reshape(-1)[rows, None], self.mask_emb.to(x.dtype).expand_as(x), x)
        x = x + self.type_emb(road_type.reshape(-1)[rows]) + self.light_emb(light.reshape(-1)[rows])
        idx, nmask = knn_within(pose[..., :2], pose[..., :2], self.cfg.road_radius_m, self.cfg.road_neighbours, valid, valid)  # (B, R, K)
        flat_idx = (idx + torch.arange(b, device=idx.device)[:, None, None] * r).view(b * r, -1)[rows]  # (V, K) flat rows
        nmask = nmask.view(b * r, -1)[rows]
        index = compact[flat_idx].clamp(min=0)  # (V, K) rows of x
        queries = self._layer_queries(index, nmask, None if needed is None else needed.reshape(-1)[rows])
        # the RPE of the first layer's pieces: the most of any layer (each layer's are among the layer before's)
        first = slice(None) if queries[0] is None else queries[0]
        q_idx, q_mask = trim_neighbours(flat_idx[first], nmask[first])
        pose_flat = pose.reshape(-1, 3)
        rpe = normalise(self.rpe(relative_pose_features(pose_flat[rows[first]][:, None], pose_flat[q_idx]), valid=q_mask,
                                 repeated_dims=ROAD_REPEATS))  # (V', K, d), shared by the layers
        q_index = compact[q_idx].clamp(min=0)  # (V', K) rows of x
        place = torch.full((x.shape[0],), -1, dtype=torch.long, device=x.device)
        place[first] = torch.arange(q_idx.shape[0], device=x.device)  # each piece's row in the RPE
        for layer, sel in zip(self.layers, queries):
            if sel is None:  # every piece
                x = layer(x, (q_index, rpe), q_mask)
                continue
            i = place[sel]
            l_index, l_mask = trim_neighbours(q_index[i], q_mask[i])
            x = x.index_copy(0, sel, layer(x[sel], (l_index, rpe[i, : l_index.shape[1]]), l_mask, source=x))
        last = slice(None) if queries[-1] is None else queries[-1]
        return x.new_zeros(b * r, x.shape[-1]).index_copy(0, rows[last], x[last]).view(b, r, -1)

    def _layer_queries(self, index: torch.Tensor, mask: torch.Tensor, needed: torch.Tensor | None) -> list:
        """The pieces (rows of the valid-piece table) each layer must compute, first layer first: the
        last layer's are ``needed`` [V] (bool), each earlier layer's add the neighbours that the next
        reads. None for every layer when ``needed`` is None (all pieces)."""
        if needed is None:
            return [None] * len(self.layers)
        need, out = needed, [needed.nonzero().squeeze(1)]
        for _ in self.layers[1:]:
            need = need.clone()
            need[index[out[-1]][mask[out[-1]]]] = True
            out.append(need.nonzero().squeeze(1))
        return out[::-1]
