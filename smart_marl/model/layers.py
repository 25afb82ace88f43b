"""Model stage, building blocks: Fourier features, relative positional embeddings (RPE), dense
K-nearest neighbourhoods and the attention layer that RoadNet and MotionNet stack.

Neighbourhoods are dense and padded (docs/architecture.md): for each query the K nearest keys
within a radius, found with ``torch.cdist`` + ``topk``, as an index tensor ``[Q, K]`` into a flat
table of key rows plus a mask ``[Q, K]``. Keys and values are projected once per key row, then
gathered, so an incremental (KV-cached) caller can keep the projected rows of past steps.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..scenario import wrap_angle


def relative_pose_features(query_pose: torch.Tensor, key_pose: torch.Tensor) -> torch.Tensor:
    """RPE inputs of keys seen from queries: (distance_m, bearing of the key in the query frame,
    heading difference key - query), broadcast over leading dims.

    query_pose [..., 3] (x, y, heading), key_pose [..., 3] -> [..., 3].
    """
    d = key_pose[..., :2] - query_pose[..., :2]
    dist = torch.sqrt(d.square().sum(-1) + 1e-12)
    bearing = wrap_angle(torch.atan2(d[..., 1], d[..., 0]) - query_pose[..., 2])
    dheading = wrap_angle(key_pose[..., 2] - query_pose[..., 2])
    return torch.stack([dist, bearing, dheading], -1)


class FourierEmbedding(nn.Module):
    """Continuous features [..., D] -> [..., hidden]: per input dimension, learned frequencies
    (cos, sin and the raw value) through its own 2-layer MLP; summed over dimensions (plus any
    categorical embeddings), then LayerNorm, ReLU, Linear. (SMART's/QCNet's FourierEmbedding.)"""

    def __init__(self, input_dim: int, hidden_dim: int, num_freq_bands: int) -> None:
        super().__init__()
        self.input_dim, self.hidden_dim = input_dim, hidden_dim
        self.freqs = nn.Parameter(torch.randn(input_dim, num_freq_bands))  # [D, F]
        fin = 2 * num_freq_bands + 1
        # the D per-dimension MLPs as batched weights (the same parameters as D nn.Linear pairs)
        self.w1 = nn.Parameter(torch.empty(input_dim, fin, hidden_dim))
        self.b1 = nn.Parameter(torch.zeros(input_dim, hidden_dim))
        self.ln1 = nn.LayerNorm(hidden_dim)
        self.w2 = nn.Parameter(torch.empty(input_dim, hidden_dim, hidden_dim))
        self.b2 = nn.Parameter(torch.zeros(input_dim, hidden_dim))
        self.out = nn.Sequential(nn.LayerNorm(hidden_dim), nn.ReLU(inplace=True), nn.Linear(hidden_dim, hidden_dim))
        nn.init.xavier_uniform_(self.w1.view(-1, hidden_dim))
        nn.init.xavier_uniform_(self.w2.view(-1, hidden_dim))

    def forward(self, x: torch.Tensor, categorical: torch.Tensor | None = None) -> torch.Tensor:
        lead = x.shape[:-1]
        x = x.reshape(-1, self.input_dim)  # (M, D)
        # one dimension at a time with plain matrix products: on the CPU, 2-D GEMMs run about twice
        # as fast as the batched product over D, and the second layer's sum over D accumulates in place
        h = None
        for d in range(self.input_dim):
            xd = x[:, d, None]  # (M, 1)
            ang = xd * self.freqs[d] * (2 * math.pi)  # (M, F)
            feat = torch.cat([ang.cos(), ang.sin(), xd], -1)  # (M, 2F+1)
            hd = F.relu(self.ln1(torch.addmm(self.b1[d], feat, self.w1[d])))  # (M, H)
            h = torch.addmm(self.b2[d] if h is None else h + self.b2[d], hd, self.w2[d])  # (M, H), summed over D
        if categorical is not None:
            h = h + categorical.reshape(-1, self.hidden_dim)
        return self.out(h).reshape(*lead, self.hidden_dim)


def mlp(in_dim: int, hidden_dim: int, out_dim: int, layers: int = 2) -> nn.Sequential:
    """Linear -> (LayerNorm, ReLU, Linear) x (layers - 1)."""
    mods: list[nn.Module] = [nn.Linear(in_dim, hidden_dim if layers > 1 else out_dim)]
    for i in range(1, layers):
        mods += [nn.LayerNorm(hidden_dim), nn.ReLU(inplace=True), nn.Linear(hidden_dim, hidden_dim if i < layers - 1 else out_dim)]
    return nn.Sequential(*mods)


# ------------------------------------------------------------------------------ neighbourhoods
def knn_within(query_xy: torch.Tensor, key_xy: torch.Tensor, radius_m: float, k: int,
               query_valid: torch.Tensor, key_valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` nearest valid keys within ``radius_m`` of each query, batched.

    query_xy [G, Q, 2], key_xy [G, M, 2], query_valid [G, Q], key_valid [G, M]
    -> (index [G, Q, K] into the M keys of the same group, mask [G, Q, K]); K = min(k, M).
    Padded slots point at key 0 and are masked.
    """
    g, q, m = query_xy.shape[0], query_xy.shape[1], key_xy.shape[1]
    kk = min(int(k), m)
    if kk == 0:
        return query_xy.new_zeros((g, q, 0), dtype=torch.long), torch.zeros((g, q, 0), dtype=torch.bool, device=query_xy.device)
    dist = torch.cdist(query_xy.float(), key_xy.float())  # (G, Q, M)
    ok = query_valid[:, :, None] & key_valid[:, None, :] & (dist <= radius_m)
    dist = dist.masked_fill(~ok, float("inf"))
    d_sel, idx = torch.topk(dist, kk, dim=-1, largest=False)  # (G, Q, K)
    mask = torch.isfinite(d_sel)
    return idx.masked_fill(~mask, 0), mask


def trim_neighbours(index: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Neighbour lists index, mask [Q, K] (nearest first, as :func:`knn_within` gives them) cut to
    the largest number of real neighbours of any query -> [Q, K'], K' <= K."""
    k = int(mask.sum(-1).max()) if mask.numel() else 0
    return index[:, :k], mask[:, :k]


# ---------------------------------------------------------------------------------- attention
class NeighbourAttention(nn.Module):
    """Pre-norm multi-head attention of each query over its gathered neighbours, with RPE added to
    keys and values, a gated residual (SMART/QCNet ``AttentionLayer``) and a feed-forward block.

    ``forward(x_q [Q, d], src [M, d], index [Q, K] (rows of src), mask [Q, K], rpe [Q, K, d])``.
    ``bipartite`` queries and keys come from different sets (map -> agent) and get their own norms.
    """

    def __init__(self, hidden_dim: int, num_heads: int, head_dim: int, dropout: float, bipartite: bool) -> None:
        super().__init__()
        inner = num_heads * head_dim
        self.num_heads, self.head_dim, self.bipartite = num_heads, head_dim, bipartite
        self.norm_q = nn.LayerNorm(hidden_dim)
        self.norm_src = nn.LayerNorm(hidden_dim) if bipartite else None  # self-attention: keys share norm_q
        self.norm_rpe = nn.LayerNorm(hidden_dim)
        self.to_q = nn.Linear(hidden_dim, inner)
        self.to_k = nn.Linear(hidden_dim, inner, bias=False)
        self.to_v = nn.Linear(hidden_dim, inner)
        self.to_k_r = nn.Linear(hidden_dim, inner, bias=False)
        self.to_v_r = nn.Linear(hidden_dim, inner)
        self.to_s = nn.Linear(hidden_dim, inner)
        self.to_g = nn.Linear(inner + hidden_dim, inner)
        self.to_out = nn.Linear(inner, hidden_dim)
        self.attn_drop = nn.Dropout(dropout)
        self.out_drop = nn.Dropout(dropout)
        self.norm_ff = nn.LayerNorm(hidden_dim)
        self.ff = nn.Sequential(nn.Linear(hidden_dim, 4 * hidden_dim), nn.ReLU(inplace=True), nn.Dropout(dropout),
                                nn.Linear(4 * hidden_dim, hidden_dim))
        self.ff_drop = nn.Dropout(dropout)

    def project_source(self, src: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Key and value rows of the source set (what a KV cache keeps): src [M, d] -> 2 x [M, inner]."""
        s = (self.norm_src or self.norm_q)(src)
        return self.to_k(s), self.to_v(s)

    def forward(self, x_q: torch.Tensor, src: torch.Tensor | tuple[torch.Tensor, torch.Tensor], index: torch.Tensor,
                mask: torch.Tensor, rpe: torch.Tensor) -> torch.Tensor:
        q_in = self.norm_q(x_q)
        k_rows, v_rows = self.project_source(src) if isinstance(src, torch.Tensor) else src  # (M, inner)
        r = self.norm_rpe(rpe)  # (Q, K, d)
        nq, kk = index.shape
        h, dh = self.num_heads, self.head_dim
        q = self.to_q(q_in).view(nq, h, dh)  # (Q, h, dh)
        # The RPE enters keys and values through linear maps, so it is never projected per (query,
        # key) pair: q . (W_kr r) = (W_kr^T q) . r and sum_k a_k (W_vr r_k + b_vr) = W_vr (sum_k a_k r_k)
        # + b_vr sum_k a_k. Same numbers as k = k_rows[index] + to_k_r(r), v = v_rows[index] + to_v_r(r),
        # without the two [Q, K, inner] tensors.
        w_kr = self.to_k_r.weight.view(h, dh, -1)  # (h, dh, d)
        w_vr = self.to_v_r.weight.view(h, dh, -1)  # (h, dh, d)
        q_r = torch.einsum("qhe,hec->qhc", q, w_kr)  # (Q, h, d)
        k = k_rows[index].view(nq, kk, h, dh)  # (Q, K, h, dh)
        # per-head dot products of a head dim of 8-16 run faster as a product and a sum than as Q tiny GEMMs
        scores = ((q[:, None] * k).sum(-1).transpose(1, 2) + torch.bmm(q_r, r.transpose(1, 2))) / math.sqrt(dh)  # (Q, h, K)
        m = mask[:, None, :]
        scores = scores.masked_fill(~m, torch.finfo(scores.dtype).min)
        attn = torch.softmax(scores, dim=-1) * m  # queries with no neighbour attend to nothing
        attn = self.attn_drop(attn)
        v = v_rows[index].view(nq, kk, h, dh)  # (Q, K, h, dh)
        r_agg = torch.bmm(attn, r)  # (Q, h, d) attention-weighted RPE
        agg = ((attn.transpose(1, 2)[..., None] * v).sum(1) + torch.einsum("qhc,hec->qhe", r_agg, w_vr)
               + self.to_v_r.bias.view(h, dh) * attn.sum(-1, keepdim=True)).reshape(nq, h * dh)  # (Q, inner)
        g = torch.sigmoid(self.to_g(torch.cat([agg, q_in], -1)))
        agg = agg + g * (self.to_s(q_in) - agg)
        x = x_q + self.out_drop(self.to_out(agg))
        return x + self.ff_drop(self.ff(self.norm_ff(x)))
