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
    categorical embeddings), then LayerNorm, ReLU, Linear. (SMART's/QCNet's FourierEmbedding.)

    Two ways to skip work that cannot change a result, both exact:

    * ``valid`` [...] (bool, the leading shape of ``x``): rows to embed; every other row's output is
      zero. The neighbour lists of the attentions are padded, and a padded pair's embedding is
      never read (its attention weight is exactly 0), so only the real pairs are embedded.
    * ``repeated_dims``: input dimensions whose values repeat (the time gap of temporal attention,
      in whole token steps; a distance, which a pair and its reverse share; the heading difference
      of agents driving one way): each dimension's MLP depends on that dimension alone, so
      it runs once per distinct value and the rows read their value's result (when the distinct
      values are few enough to pay for finding them).
    """

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

    def forward(self, x: torch.Tensor, categorical: torch.Tensor | None = None, valid: torch.Tensor | None = None,
                repeated_dims: tuple[int, ...] = ()) -> torch.Tensor:
        lead = x.shape[:-1]
        x = x.reshape(-1, self.input_dim)  # (M, D)
        rows = None
        if valid is not None:
            rows = valid.reshape(-1).nonzero().squeeze(1)  # (M',) the rows to embed
            x = x[rows]
            if categorical is not None:
                categorical = categorical.reshape(-1, self.hidden_dim)[rows]
        if x.requires_grad or torch.is_autocast_enabled(x.device.type):
            h = self._trunk_autograd(x, repeated_dims)
        else:  # the usual case: geometry carries no gradient; hand-written backward, fewer passes over memory
            h = _FourierTrunk.apply(x, self.freqs, self.w1, self.b1, self.ln1.weight, self.ln1.bias, self.w2, self.b2,
                                    self.ln1.eps, tuple(repeated_dims), torch.is_grad_enabled())
        if categorical is not None:
            h = h + categorical.reshape(-1, self.hidden_dim)
        h = self.out(h)
        if rows is not None:
            h = h.new_zeros(valid.numel(), self.hidden_dim).index_copy(0, rows, h)
        return h.reshape(*lead, self.hidden_dim)

    def _trunk_autograd(self, x: torch.Tensor, repeated_dims: tuple[int, ...]) -> torch.Tensor:
        """The per-dimension MLPs summed, through autograd (inputs that need a gradient; autocast)."""
        h = None
        for d in range(self.input_dim):
            xd, inverse = _distinct(x[:, d], d in repeated_dims)
            xd = xd[:, None]  # (U, 1)
            ang = xd * self.freqs[d] * (2 * math.pi)  # (U, F)
            feat = torch.cat([ang.cos(), ang.sin(), xd], -1)  # (U, 2F+1)
            hd = F.relu(self.ln1(torch.addmm(self.b1[d], feat, self.w1[d]))) @ self.w2[d]  # (U, H)
            hd = hd if inverse is None else hd[inverse]
            h = hd + self.b2[d] if h is None else h + hd + self.b2[d]  # (M, H), summed over D
        return h


def _distinct(col: torch.Tensor, repeated: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(values to embed, index of each row's value or None) of one input dimension: for a repeated
    dimension whose distinct values are at most 3/4 of its rows, the distinct values (a sort costs
    less than the rows it saves); else the column itself."""
    if not repeated:
        return col, None
    values, inverse = torch.unique(col, return_inverse=True)
    if 4 * values.numel() > 3 * col.numel():
        return col, None
    return values, inverse


class _FourierTrunk(torch.autograd.Function):
    """The summed per-dimension MLPs of :class:`FourierEmbedding` for inputs that need no gradient,
    with a hand-written backward: each dimension's cos/sin features are written once into the
    matrix the first product reads and kept for the backward (autograd keeps the angles and
    recomputes cos and sin), and the gradient of the frequencies never forms the gradient of the
    features (see the backward)."""

    @staticmethod
    def forward(ctx, x, freqs, w1, b1, ln_w, ln_b, w2, b2, eps, repeated_dims, keep):
        m, dims = x.shape
        nf, hdim = freqs.shape[1], w2.shape[-1]
        h = b2.sum(0).expand(m, hdim).contiguous()  # (M, H)
        saved = []
        for d in range(dims):
            col, inverse = _distinct(x[:, d].contiguous(), d in repeated_dims)  # (U,)
            feat = x.new_empty(col.shape[0], 2 * nf + 1)  # (U, 2F+1) = [cos, sin, x]
            ang = torch.mul(col[:, None], freqs[d]).mul_(2 * math.pi)  # (U, F)
            torch.cos(ang, out=feat[:, :nf])
            torch.sin(ang, out=feat[:, nf:2 * nf])
            feat[:, 2 * nf] = col
            z = torch.addmm(b1[d], feat, w1[d])  # (U, H)
            y, mean, rstd = torch.native_layer_norm(z, [hdim], ln_w, ln_b, eps)
            y.relu_()
            if inverse is None:
                h.addmm_(y, w2[d])
            else:
                h.add_(torch.mm(y, w2[d]).index_select(0, inverse))
            if keep:  # nothing to keep for inference (no_grad)
                saved.append((col, inverse, feat, z, mean, rstd, y))
        ctx.saved = saved
        ctx.save_for_backward(freqs, w1, ln_w, ln_b, w2)
        return h

    @staticmethod
    def backward(ctx, g):
        freqs, w1, ln_w, ln_b, w2 = ctx.saved_tensors
        nf, hdim = freqs.shape[1], w2.shape[-1]
        g = g.contiguous()
        grads = {k: [] for k in ("freqs", "w1", "b1", "w2")}
        g_lnw, g_lnb = torch.zeros_like(ln_w), torch.zeros_like(ln_b)
        for d, (col, inverse, feat, z, mean, rstd, y) in enumerate(ctx.saved):
            gd = g if inverse is None else g.new_zeros(col.shape[0], hdim).index_add_(0, inverse, g)  # (U, H)
            grads["w2"].append(y.t() @ gd)
            gy = torch.ops.aten.threshold_backward(gd @ w2[d].t(), y, 0)  # through the ReLU
            gz, gw, gb = torch.ops.aten.native_layer_norm_backward(gy, z, [hdim], mean, rstd, ln_w, ln_b, [True, True, True])
            g_lnw += gw
            g_lnb += gb
            grads["b1"].append(gz.sum(0))
            grads["w1"].append(feat.t() @ gz)
            # z = cos(a) W_c + sin(a) W_s + ..., a = 2 pi x f, so dL/df_j = 2 pi sum_h (W_s[j, h] A[j, h] - W_c[j, h] B[j, h])
            # with A, B = (x cos(a))^T gz, (x sin(a))^T gz: one product as tall as the weight gradient's, where
            # the gradient of the (U, 2F) features would be a (U, H) x (H, 2F) product and two more passes
            ab = (feat[:, : 2 * nf] * col[:, None]).t() @ gz  # (2F, H) = [A; B]
            w_c, w_s = w1[d, :nf], w1[d, nf:2 * nf]
            grads["freqs"].append((w_s * ab[:nf] - w_c * ab[nf:]).sum(-1) * (2 * math.pi))
        ctx.saved = None
        g_b2 = g.sum(0).expand(len(grads["w2"]), hdim).contiguous()
        stack = {k: torch.stack(v) for k, v in grads.items()}
        return None, stack["freqs"], stack["w1"], stack["b1"], g_lnw, g_lnb, stack["w2"], g_b2, None, None, None


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


def knn_grouped(query_xy: torch.Tensor, group: torch.Tensor, key_xy: torch.Tensor, radius_m: float, k: int,
                key_valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`knn_within` for a flat list of queries, each searching the keys of its own group:
    query_xy [Q, 2], group [Q] (long, ascending: e.g. the scene of each valid (agent, step) row),
    key_xy [G, M, 2], key_valid [G, M] -> (index [Q, K] into the M keys of the query's group, mask
    [Q, K]). The queries are packed per group before the search, so padded query slots cost nothing."""
    g = key_xy.shape[0]
    counts = torch.bincount(group, minlength=g)
    q_max = int(counts.max()) if group.numel() else 0
    slot = torch.arange(group.numel(), device=group.device) - (torch.cumsum(counts, 0) - counts)[group]  # rank in its group
    packed = query_xy.new_zeros(g, q_max, 2)
    packed[group, slot] = query_xy
    packed_valid = torch.zeros(g, q_max, dtype=torch.bool, device=group.device)
    packed_valid[group, slot] = True
    idx, mask = knn_within(packed, key_xy, radius_m, k, packed_valid, key_valid)  # (G, Qmax, K)
    return idx[group, slot], mask[group, slot]


def valid_rows(valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The rows of the valid entries of ``valid`` [...] (flattened) and, for every entry, its place
    among them (-1 where invalid): (rows [V], compact [numel])."""
    valid_flat = valid.reshape(-1)
    rows = valid_flat.nonzero().squeeze(1)
    compact = torch.full(valid_flat.shape, -1, dtype=torch.long, device=valid.device)
    compact[rows] = torch.arange(rows.numel(), device=valid.device)
    return rows, compact


def trim_neighbours(index: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Neighbour lists index, mask [Q, K] (nearest first, as :func:`knn_within` gives them) cut to
    the largest number of real neighbours of any query -> [Q, K'], K' <= K."""
    k = int(mask.sum(-1).max()) if mask.numel() else 0
    return index[:, :k], mask[:, :k]


# The attention over gathered neighbours, as two functions with hand-written backwards: autograd's
# backward of the same expressions materialises several broadcast [Q, K, h, dh] products and copies;
# these re-gather the key / value rows (cheaper than keeping them) and write each product once.
def _autocast_state(t: torch.Tensor) -> dict:
    """The autocast settings in force for ``t``'s device (a forward's, for its hand-written backward)."""
    dev = t.device.type
    return dict(device_type=dev, enabled=torch.is_autocast_enabled(dev), dtype=torch.get_autocast_dtype(dev))


class _NeighbourSoftmax(torch.autograd.Function):
    """Attention weights of each query over its K neighbours: q [Q, h, dh] against the gathered key rows
    k_rows[index] ([M, h * dh]; index [Q, K]) plus the RPE scores q_r [Q, h, d] . r [Q, K, d], scaled by
    1 / sqrt(dh), softmax over the neighbours in ``mask`` [Q, K] -> [Q, h, K] (0 where masked, and
    on every neighbour of a query that has none)."""

    @staticmethod
    def forward(ctx, q, q_r, k_rows, r, index, mask):
        nq, kk = index.shape
        h, dh = q.shape[1:]
        k = k_rows.index_select(0, index.reshape(-1)).view(nq, kk, h, dh)
        # per-head dot products of a head dim of 8-16 run faster as a product and a sum than as Q tiny GEMMs
        scores = ((q[:, None] * k).sum(-1).transpose(1, 2) + torch.bmm(q_r, r.transpose(1, 2))) / math.sqrt(dh)
        m = mask[:, None, :]
        scores = scores.masked_fill_(~m, torch.finfo(scores.dtype).min)
        attn = torch.softmax(scores, dim=-1).mul_(m)
        ctx.save_for_backward(q, q_r, k_rows, r, index, attn)
        ctx.amp = _autocast_state(q)
        return attn

    @staticmethod
    def backward(ctx, g):
        with torch.autocast(**ctx.amp):
            return _NeighbourSoftmax._backward(ctx, g)

    @staticmethod
    def _backward(ctx, g):
        q, q_r, k_rows, r, index, attn = ctx.saved_tensors
        nq, kk = index.shape
        h, dh = q.shape[1:]
        gs = attn * (g - (attn * g).sum(-1, keepdim=True)) / math.sqrt(dh)  # (Q, h, K): through the softmax
        gs_t = gs.transpose(1, 2).contiguous()  # (Q, K, h)
        k = k_rows.index_select(0, index.reshape(-1)).view(nq, kk, h, dh)
        g_q = (gs_t[..., None] * k).sum(1)  # (Q, h, dh)
        g_k = (gs_t[..., None] * q[:, None]).view(-1, h * dh)  # (Q * K, inner)
        g_k_rows = g_k.new_zeros(k_rows.shape).index_add_(0, index.reshape(-1), g_k)
        return g_q, torch.bmm(gs, r), g_k_rows, torch.bmm(gs_t, q_r), None, None


class _NeighbourSum(torch.autograd.Function):
    """The attention-weighted sums of the gathered value rows v_rows[index] and of the RPE r [Q, K, d]:
    attn [Q, h, K] -> ([Q, h, dh], [Q, h, d])."""

    @staticmethod
    def forward(ctx, attn, v_rows, r, index):
        nq, kk = index.shape
        h = attn.shape[1]
        v = v_rows.index_select(0, index.reshape(-1)).view(nq, kk, h, -1)
        ctx.save_for_backward(attn, v_rows, r, index)
        ctx.amp = _autocast_state(attn)
        return (attn.transpose(1, 2)[..., None] * v).sum(1), torch.bmm(attn, r)

    @staticmethod
    def backward(ctx, g_v, g_r):
        with torch.autocast(**ctx.amp):
            return _NeighbourSum._backward(ctx, g_v, g_r)

    @staticmethod
    def _backward(ctx, g_v, g_r):
        attn, v_rows, r, index = ctx.saved_tensors
        nq, kk = index.shape
        h = attn.shape[1]
        v = v_rows.index_select(0, index.reshape(-1)).view(nq, kk, h, -1)
        g_v, g_r = g_v.contiguous(), g_r.contiguous()
        g_attn = (g_v[:, None] * v).sum(-1).transpose(1, 2) + torch.bmm(g_r, r.transpose(1, 2))  # (Q, h, K)
        attn_t = attn.transpose(1, 2).contiguous()  # (Q, K, h)
        g_vals = (attn_t[..., None] * g_v[:, None]).view(nq * kk, -1)  # (Q * K, inner)
        g_v_rows = g_vals.new_zeros(v_rows.shape).index_add_(0, index.reshape(-1), g_vals)
        return g_attn, g_v_rows, torch.bmm(attn_t, g_r), None


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
        attn = _NeighbourSoftmax.apply(q, q_r, k_rows, r, index, mask)  # (Q, h, K); 0 on padded neighbours
        attn = self.attn_drop(attn)
        agg, r_agg = _NeighbourSum.apply(attn, v_rows, r, index)  # (Q, h, dh), (Q, h, d) attention-weighted RPE
        agg = (agg + torch.einsum("qhc,hec->qhe", r_agg, w_vr)
               + self.to_v_r.bias.view(h, dh) * attn.sum(-1, keepdim=True)).reshape(nq, h * dh)  # (Q, inner)
        g = torch.sigmoid(self.to_g(torch.cat([agg, q_in], -1)))
        agg = agg + g * (self.to_s(q_in) - agg)
        x = x_q + self.out_drop(self.to_out(agg))
        return x + self.ff_drop(self.ff(self.norm_ff(x)))
