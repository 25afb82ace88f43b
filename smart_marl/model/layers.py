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

from ..geometry_torch import squared_length
from ..scenario import wrap_angle
from .precision import bucket_rows, pad_rows, pads_rows


def relative_pose_features(query_pose: torch.Tensor, key_pose: torch.Tensor) -> torch.Tensor:
    """RPE inputs of keys seen from queries: (distance_m, bearing of the key in the query frame,
    heading difference key - query), broadcast over leading dims.

    query_pose [..., 3] (x, y, heading), key_pose [..., 3] -> [..., 3].
    """
    d = key_pose[..., :2] - query_pose[..., :2]
    dist = torch.sqrt(squared_length(d) + 1e-12)
    bearing = wrap_angle(torch.atan2(d[..., 1], d[..., 0]) - query_pose[..., 2])
    dheading = wrap_angle(key_pose[..., 2] - query_pose[..., 2])
    return torch.stack([dist, bearing, dheading], -1)


EMBED_BLOCK_ROWS = 8192
"""Rows that CPU inference (no autograd) embeds at once: more rows go in nearly equal blocks of at most this
many (4 MB of cos/sin features each), which stay in the cache, where embedding every pair of a large batch at
once spent more time waiting on memory (and on the allocator's fresh pages) than computing. A row's result
does not depend on the block it is in: matrix products of a few hundred rows or more give each row alike."""


class FourierEmbedding(nn.Module):
    """Continuous features [..., D] -> [..., hidden]: per input dimension, learned frequencies
    (cos, sin and the raw value) through its own 2-layer MLP; summed over dimensions (plus any
    categorical embeddings), then LayerNorm, ReLU, Linear. (SMART's/QCNet's FourierEmbedding.)

    CPU inference embeds many rows in blocks (:data:`EMBED_BLOCK_ROWS`). Two ways to skip work that cannot
    change a result, both exact:

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
        cat = None if categorical is None else categorical.reshape(-1, self.hidden_dim)
        rows = None
        if valid is not None:
            rows = valid.reshape(-1).nonzero().squeeze(1)  # (M',) the rows to embed
            x = x[rows]
            cat = None if cat is None else cat[rows]
        inference = not torch.is_grad_enabled() and x.device.type == "cpu" and not torch.is_autocast_enabled("cpu")
        parts = -(-x.shape[0] // EMBED_BLOCK_ROWS) if inference else 1
        if parts <= 1:
            h = self._embed(x, cat, repeated_dims)
            if rows is not None:
                h = h.new_zeros(valid.numel(), self.hidden_dim).index_copy(0, rows, h)
            return h.reshape(*lead, self.hidden_dim)
        h = x.new_zeros(x.shape[0] if rows is None else valid.numel(), self.hidden_dim, dtype=self.out[-1].weight.dtype)
        ends = [x.shape[0] * i // parts for i in range(parts + 1)]  # nearly equal blocks
        for lo, hi in zip(ends[:-1], ends[1:]):
            part = self._embed(x[lo:hi], None if cat is None else cat[lo:hi], repeated_dims)
            if rows is None:
                h[lo:hi] = part
            else:
                h.index_copy_(0, rows[lo:hi], part)
        return h.reshape(*lead, self.hidden_dim)

    def _embed(self, x: torch.Tensor, categorical: torch.Tensor | None, repeated_dims: tuple[int, ...]) -> torch.Tensor:
        """The embeddings [M, hidden] of rows x [M, D] (categorical [M, hidden] or None)."""
        m = x.shape[0]
        if pads_rows(self.w1) and not x.requires_grad:  # rows padded to a known shape (bucket_rows)
            x, categorical = pad_rows(x, bucket_rows(m)), None if categorical is None else pad_rows(categorical, bucket_rows(m))
            return self._embed_rows(x, categorical, repeated_dims)[:m]
        return self._embed_rows(x, categorical, repeated_dims)

    def _embed_rows(self, x: torch.Tensor, categorical: torch.Tensor | None, repeated_dims: tuple[int, ...]) -> torch.Tensor:
        if x.requires_grad or torch.is_autocast_enabled(x.device.type):
            h = self._trunk_autograd(x, repeated_dims)
        else:  # the usual case: geometry carries no gradient; hand-written backward, fewer passes over memory
            h = _FourierTrunk.apply(x, self.freqs, self.w1, self.b1, self.ln1.weight, self.ln1.bias, self.w2, self.b2,
                                    self.ln1.eps, tuple(repeated_dims), torch.is_grad_enabled())
        if categorical is not None:
            h = h + categorical
        return self.out(h)

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
            if inverse is not None and pads_rows(w1):  # the distinct values padded too (bucket_rows)
                col = pad_rows(col, bucket_rows(col.shape[0]))
            feat = x.new_empty(col.shape[0], 2 * nf + 1)  # (U, 2F+1) = [cos, sin, x]
            ang = torch.mul(col[:, None], freqs[d]).mul_(2 * math.pi)  # (U, F)
            torch.cos(ang, out=feat[:, :nf])
            torch.sin(ang, out=feat[:, nf:2 * nf])
            feat[:, 2 * nf] = col
            # the phases and their cos/sin in float32 (x's), the products at the weights' precision (.precision)
            feat = feat.to(w1.dtype)  # kept at the weights' precision for the backward too
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
            ab = ((feat[:, : 2 * nf] * col[:, None]).to(gz.dtype).t() @ gz).float()  # (2F, H) = [A; B], x float32
            w_c, w_s = w1[d, :nf], w1[d, nf:2 * nf]
            grads["freqs"].append((w_s.float() * ab[:nf] - w_c.float() * ab[nf:]).sum(-1) * (2 * math.pi))
        ctx.saved = None
        g_b2 = g.sum(0).expand(len(grads["w2"]), hdim).contiguous()
        stack = {k: torch.stack(v) for k, v in grads.items()}
        return None, stack["freqs"], stack["w1"], stack["b1"], g_lnw, g_lnb, stack["w2"], g_b2, None, None, None


class MLP(nn.Sequential):
    """Linear -> (LayerNorm, ReLU, Linear) x (layers - 1), run at its weights' precision: an input in another
    float format (geometry in float32 into a bfloat16 model, :mod:`.precision`) is cast once on the way in."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w = self[0].weight
        x = x.to(w.dtype)
        if not pads_rows(w) or x.numel() == 0:
            return super().forward(x)
        flat = x.reshape(-1, x.shape[-1])  # rows padded to a known shape (bucket_rows)
        out = super().forward(pad_rows(flat, bucket_rows(flat.shape[0])))[: flat.shape[0]]
        return out.reshape(*x.shape[:-1], out.shape[-1])


def mlp(in_dim: int, hidden_dim: int, out_dim: int, layers: int = 2) -> MLP:
    """Linear -> (LayerNorm, ReLU, Linear) x (layers - 1)."""
    mods: list[nn.Module] = [nn.Linear(in_dim, hidden_dim if layers > 1 else out_dim)]
    for i in range(1, layers):
        mods += [nn.LayerNorm(hidden_dim), nn.ReLU(inplace=True), nn.Linear(hidden_dim, hidden_dim if i < layers - 1 else out_dim)]
    return MLP(*mods)


# ------------------------------------------------------------------------------ neighbourhoods
KNN_BLOCK_PAIRS = 1 << 20
"""(query, key) pairs whose distances one block of the CPU neighbour search holds (4 MB of float32): the
search runs over blocks of groups, each cut to its last valid query and key, so that its intermediates stay
in the cache and off the allocator's fresh pages, and a batch's padding (the largest scene's agents and road
pieces) is not searched by every group. Each group is searched alone either way: the result is the same."""


def knn_within(query_xy: torch.Tensor, key_xy: torch.Tensor, radius_m: float, k: int,
               query_valid: torch.Tensor, key_valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` nearest valid keys within ``radius_m`` of each query, batched.

    query_xy [G, Q, 2], key_xy [G, M, 2], query_valid [G, Q], key_valid [G, M]
    -> (index [G, Q, K] into the M keys of the same group, mask [G, Q, K]); K = min(k, M).
    Padded slots point at key 0 and are masked. On the CPU, in blocks of groups (:data:`KNN_BLOCK_PAIRS`).
    """
    g, q, m = query_xy.shape[0], query_xy.shape[1], key_xy.shape[1]
    kk = min(int(k), m)
    if kk == 0 or g * q == 0 or query_xy.device.type != "cpu":
        return _knn_block(query_xy, key_xy, radius_m, kk, query_valid, key_valid)
    index = torch.zeros((g, q, kk), dtype=torch.long)
    mask = torch.zeros((g, q, kk), dtype=torch.bool)
    q_end, m_end = _extent(query_valid), _extent(key_valid)  # (G,) each group's last valid query / key + 1
    per_block = max(1, KNN_BLOCK_PAIRS // max(int(q_end.max()) * int(m_end.max()), 1))
    for g0 in range(0, g, per_block):
        blk = slice(g0, g0 + per_block)
        qb, mb = int(q_end[blk].max()), int(m_end[blk].max())
        rows = max(1, KNN_BLOCK_PAIRS // max(len(q_end[blk]) * mb, 1))  # queries per block (one large group: a part of them)
        for q0 in range(0, qb if mb else 0, rows):
            part = slice(q0, min(q0 + rows, qb))
            idx, ok = _knn_block(query_xy[blk, part], key_xy[blk, :mb], radius_m, kk, query_valid[blk, part], key_valid[blk, :mb])
            index[blk, part, : idx.shape[-1]], mask[blk, part, : idx.shape[-1]] = idx, ok
    return index, mask


def _extent(valid: torch.Tensor) -> torch.Tensor:
    """[G, M] bool -> [G] long: one past the last true entry of each row (0 for a row with none)."""
    place = torch.arange(1, valid.shape[1] + 1, device=valid.device)
    return (valid * place).amax(1) if valid.shape[1] else valid.new_zeros(valid.shape[0], dtype=torch.long)


def _knn_block(query_xy: torch.Tensor, key_xy: torch.Tensor, radius_m: float, k: int,
               query_valid: torch.Tensor, key_valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`knn_within` of one block of groups, all at once; K = min(k, M)."""
    g, q, m = query_xy.shape[0], query_xy.shape[1], key_xy.shape[1]
    kk = min(int(k), m)
    if kk == 0:
        return query_xy.new_zeros((g, q, 0), dtype=torch.long), torch.zeros((g, q, 0), dtype=torch.bool, device=query_xy.device)
    # squared distances pair by pair (not the |a|^2 + |b|^2 - 2ab expansion, whose rounding depends on the
    # tensors' sizes and would let a batch's padding change which near-tied neighbours are picked): a scene's
    # neighbourhoods, and so its rollouts, do not depend on the scenes it is batched with. Plain elementwise
    # work: as fast as torch.cdist's exact mode on a CPU, tens of times faster on a GPU
    q, key = query_xy.float(), key_xy.float()
    dx = q[..., 0, None] - key[:, None, :, 0]
    dy = q[..., 1, None] - key[:, None, :, 1]
    dist2 = dx.mul_(dx).add_(dy.mul_(dy))  # (G, Q, M)
    ok = (dist2 <= float(radius_m) ** 2).logical_and_(query_valid[:, :, None]).logical_and_(key_valid[:, None, :])
    dist2 = dist2.masked_fill_(~ok, float("inf"))
    d_sel, idx = smallest_k(dist2, kk, free_inf_ties=True)  # (G, Q, K)
    mask = torch.isfinite(d_sel)
    return idx.masked_fill(~mask, 0), mask


def smallest_k(values: torch.Tensor, k: int, free_inf_ties: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(values, indices) [..., k] of the ``k`` smallest entries of each row of ``values`` [..., M],
    smallest first and, among equal values, lowest index first (entries tied at the k-th value are
    taken lowest index first): the result is that of a stable sort, so it does not depend on how many
    entries follow them (``torch.topk`` alone may break such
    ties differently for a row padded to another length, e.g. a scene batched with larger ones).
    Only rows whose (k+1)-th smallest value equals their k-th are re-chosen. ``free_inf_ties``: entries
    of +inf are padding whose place the caller ignores (a row with fewer than ``k`` finite entries then
    keeps topk's pick of infinite ones: its finite entries are the same)."""
    m = values.shape[-1]
    if k >= m:
        return torch.sort(values, dim=-1, stable=True)
    vals, idx = torch.topk(values, k + 1, dim=-1, largest=False)
    ambiguous = vals[..., k] == vals[..., k - 1]  # a tie across the boundary: topk's pick is arbitrary
    if free_inf_ties:
        ambiguous &= torch.isfinite(vals[..., k])
    vals, idx = vals[..., :k], idx[..., :k]
    by_index = idx.sort(dim=-1).indices  # ties inside the k in index order too: the result is a function of the row
    vals, idx = vals.gather(-1, by_index), idx.gather(-1, by_index)
    by_value = torch.sort(vals, dim=-1, stable=True).indices
    vals, idx = vals.gather(-1, by_value), idx.gather(-1, by_value)
    if bool(ambiguous.any()):
        rows = ambiguous.nonzero(as_tuple=True)
        v = values[rows]  # (A, M)
        thr = vals[rows][:, -1:]
        below, tied = v < thr, v == thr
        take = below | (tied & (tied.cumsum(-1) <= k - below.sum(-1, keepdim=True)))  # k true per row
        chosen = take.nonzero()[:, -1].view(-1, k)  # increasing index
        chosen_vals = v.gather(-1, chosen)
        order = torch.sort(chosen_vals, dim=-1, stable=True).indices
        vals, idx = vals.clone(), idx.clone()
        vals[rows], idx[rows] = chosen_vals.gather(-1, order), chosen.gather(-1, order)
    return vals, idx


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


NORM_EPS = 1e-5  # the eps of every LayerNorm that attention inputs go through (nn.LayerNorm's default)


def normalise(t: torch.Tensor) -> torch.Tensor:
    """LayerNorm over the last dim without a scale and shift: [..., d] -> [..., d]. What the attentions'
    key-side inputs go through once, shared by every layer that reads them (each
    :class:`NeighbourAttention` folds its own LayerNorms' scales and shifts into its weights)."""
    return F.layer_norm(t, t.shape[-1:], eps=NORM_EPS)


def neighbour_keys(rows: torch.Tensor, index: torch.Tensor, rpe: torch.Tensor) -> torch.Tensor:
    """The key-side input of an attention, per (query, neighbour) pair: the neighbour's normalised row
    and the pair's normalised RPE side by side. rows [M, d] (through :func:`normalise`), index [Q, K]
    (rows of ``rows``), rpe [Q, K, d] (through :func:`normalise`) -> [Q, K, 2d]."""
    gathered = rows.index_select(0, index.reshape(-1)).view(*index.shape, rows.shape[-1])  # (Q, K, d)
    return torch.cat([gathered, rpe.to(gathered.dtype)], -1)


def _autocast_state(t: torch.Tensor) -> dict:
    """The autocast settings in force for ``t``'s device (a forward's, for its hand-written backward)."""
    dev = t.device.type
    return dict(device_type=dev, enabled=torch.is_autocast_enabled(dev), dtype=torch.get_autocast_dtype(dev))


def dropout_mask(like: torch.Tensor, p: float) -> torch.Tensor:
    """A dropout mask for ``like``: 0 with probability ``p``, else 1 / (1 - p), as ``nn.Dropout`` draws it.
    On the CPU each mask entry compares 32 random bits (two per 64-bit draw: half the generator's work
    of uniform or Bernoulli draws, which dominates there) with p * 2^32; elsewhere a uniform draw."""
    if like.device.type != "cpu":
        return (torch.rand_like(like, dtype=torch.float32) >= p).to(like.dtype).mul_(1.0 / (1.0 - p))
    n = like.numel()
    bits = torch.randint(-(2**63), 2**63 - 1, ((n + 1) // 2,), dtype=torch.int64).view(torch.int32)[:n]
    threshold = int(round(p * 2**32)) - 2**31  # P(bits < threshold) = p (to 2^-32)
    return (bits >= threshold).view(like.shape).to(like.dtype).mul_(1.0 / (1.0 - p))


class FastDropout(nn.Dropout):
    """``nn.Dropout`` with its mask from :func:`dropout_mask` (the same distribution, fewer cycles)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or self.p == 0.0:
            return x
        return _MaskMul.apply(x, dropout_mask(x, self.p))


class _MaskMul(torch.autograd.Function):
    """x * mask with only the mask kept for the backward."""

    @staticmethod
    def forward(ctx, x, mask):
        ctx.save_for_backward(mask)
        return x * mask

    @staticmethod
    def backward(ctx, g):
        (mask,) = ctx.saved_tensors
        return g * mask, None


class _Headwise(torch.autograd.Function):
    """Per-head linear maps: x [Q, h, i], w [h, i, o] -> [Q, h, o] (y[:, j] = x[:, j] @ w[j]). As
    ``einsum("qhi,hio->qho")``, with the weight gradient always formed as the product whose output has
    the short side first (a (i x Q) (Q x o) product with i >> o runs at a tenth of the speed here)."""

    @staticmethod
    def forward(ctx, x, w):
        ctx.save_for_backward(x, w)
        ctx.amp = _autocast_state(x)
        return torch.bmm(x.transpose(0, 1), w).transpose(0, 1)  # (Q, h, o), head-major in memory

    @staticmethod
    def backward(ctx, g):
        with torch.autocast(**ctx.amp):
            return _Headwise._backward(ctx, g)

    @staticmethod
    def _backward(ctx, g):
        x, w = ctx.saved_tensors
        xt, gt = x.transpose(0, 1), g.transpose(0, 1)  # (h, Q, i), (h, Q, o)
        g_x = torch.bmm(gt, w.transpose(1, 2)).transpose(0, 1) if ctx.needs_input_grad[0] else None
        if w.shape[1] <= w.shape[2]:
            g_w = torch.bmm(xt.transpose(1, 2), gt)  # (h, i, o)
        else:
            g_w = torch.bmm(gt.transpose(1, 2), xt).transpose(1, 2)  # (h, o, i) -> (h, i, o)
        return g_x, g_w


class _NeighbourAttention(torch.autograd.Function):
    """The attention of each query over its neighbours, on the key-side inputs themselves (the key and
    value maps live in per-query weights, see :meth:`NeighbourAttention.forward`).

    ``apply(mask [Q, K], drop_p, a_1, keys_1, a_2, keys_2, ...)``: the key-side inputs in parts keys_i
    [Q, K, C_i] (gathered rows, RPE: whatever is at hand, without copying them side by side) with their
    per-query, per-head weights a_i [Q, h, C_i] (scaled by 1 / sqrt(head dim)); drop_p: attention
    dropout (0: none).

        scores = sum_i a_i . keys_i per head, masked softmax over K -> attn [Q, h, K], dropped out -> attn_d
        -> (attn_d @ keys_i [Q, h, C_i] for each part, attn_d summed over K [Q, h])

    Every product is a batched matrix product over queries that reads one part once; in the backward,
    the two weighings of each part (by the scores' gradient against a_i, by attn_d against the output's
    gradient) are stacked into one product.
    """

    @staticmethod
    def forward(ctx, mask, drop_p, *pairs):
        a, keys = pairs[0::2], pairs[1::2]
        scores = torch.bmm(a[0], keys[0].transpose(1, 2))  # (Q, h, K)
        for a_i, k_i in zip(a[1:], keys[1:]):
            scores = torch.baddbmm(scores, a_i, k_i.transpose(1, 2))
        m = mask[:, None, :]
        scores = scores.masked_fill_(~m, torch.finfo(scores.dtype).min)
        attn = torch.softmax(scores, dim=-1).mul_(m)
        keep = dropout_mask(attn, drop_p) if drop_p > 0 else None
        attn_d = attn if keep is None else attn * keep
        ctx.save_for_backward(attn, keep, *pairs)
        ctx.amp = _autocast_state(a[0])
        return (*(torch.bmm(attn_d, k_i) for k_i in keys), attn_d.sum(-1))

    @staticmethod
    def backward(ctx, *grads):
        with torch.autocast(**ctx.amp):
            return _NeighbourAttention._backward(ctx, *grads)

    @staticmethod
    def _backward(ctx, *grads):
        attn, keep, *pairs = ctx.saved_tensors
        a, keys = pairs[0::2], pairs[1::2]
        g_out, g_sum = grads[:-1], grads[-1]
        g_attn = g_sum[..., None].expand_as(attn).clone() if g_sum is not None else torch.zeros_like(attn)
        for g_i, k_i in zip(g_out, keys):
            g_attn = torch.baddbmm(g_attn, g_i, k_i.transpose(1, 2))  # (Q, h, K)
        attn_d = attn
        if keep is not None:
            g_attn = g_attn.mul_(keep)
            attn_d = attn * keep
        gs = attn * (g_attn - (attn * g_attn).sum(-1, keepdim=True))  # (Q, h, K): through the softmax
        w = torch.cat([gs, attn_d.to(gs.dtype)], 1).transpose(1, 2)  # (Q, K, 2h)
        out = [None, None]
        for a_i, k_i, g_i in zip(a, keys, g_out):
            out.append(torch.bmm(gs, k_i))  # the gradient of a_i
            out.append(torch.bmm(w, torch.cat([a_i, g_i.to(a_i.dtype)], 1)))  # of keys_i (Q, K, C_i)
        return tuple(out)


# ---------------------------------------------------------------------------------- attention
class NeighbourAttention(nn.Module):
    """Pre-norm multi-head attention of each query over its gathered neighbours, with RPE added to
    keys and values, a gated residual (SMART/QCNet ``AttentionLayer``) and a feed-forward block.

    ``forward(x_q [Q, d], keys, mask [Q, K], source=None)``: ``keys`` is either a pair (index [Q, K], rpe
    [Q, K, d]) for self-attention among rows of one table (index points into ``source`` [M, d], by default
    x_q itself; a caller that needs only some rows' outputs passes those rows as x_q), or the key-side inputs
    [Q, K, 2d] of :func:`neighbour_keys` (source rows and RPE through :func:`normalise`, e.g. the road
    encodings and map RPE that every map attention shares, or a KV cache's rows). ``rpe`` always
    comes through :func:`normalise`. ``bipartite`` queries and keys come from different sets (map ->
    agent) and get their own norms.

    Computed as SMART's layer: keys to_k(LN_src(x_j)) + to_k_r(LN_rpe(r_ij)), values to_v(LN_src(x_j)) +
    to_v_r(LN_rpe(r_ij)). Every linear map and every LayerNorm's scale and shift is moved off the
    (query, key) pairs: q . W (g * n + b) = ((W^T q) * g) . n + q . W b and sum_j a_j W (g * n_j + b) =
    (W diag(g)) sum_j a_j n_j + W b sum_j a_j. So the pairs carry only the normalised inputs, shared by
    every layer that reads them, and the per-query constant q . W b of the scores is left out (the
    softmax does not change with it).
    """

    def __init__(self, hidden_dim: int, num_heads: int, head_dim: int, dropout: float, bipartite: bool) -> None:
        super().__init__()
        inner = num_heads * head_dim
        self.num_heads, self.head_dim, self.bipartite = num_heads, head_dim, bipartite
        self.norm_q = nn.LayerNorm(hidden_dim, eps=NORM_EPS)
        self.norm_src = nn.LayerNorm(hidden_dim, eps=NORM_EPS) if bipartite else None  # self-attention: keys share norm_q
        self.norm_rpe = nn.LayerNorm(hidden_dim, eps=NORM_EPS)
        self.to_q = nn.Linear(hidden_dim, inner)
        self.to_k = nn.Linear(hidden_dim, inner, bias=False)
        self.to_v = nn.Linear(hidden_dim, inner)
        self.to_k_r = nn.Linear(hidden_dim, inner, bias=False)
        self.to_v_r = nn.Linear(hidden_dim, inner)
        self.to_s = nn.Linear(hidden_dim, inner)
        self.to_g = nn.Linear(inner + hidden_dim, inner)
        self.to_out = nn.Linear(inner, hidden_dim)
        self.attn_drop = nn.Dropout(dropout)  # its p: the attention dropout, drawn inside the attention
        self.out_drop = FastDropout(dropout)
        self.norm_ff = nn.LayerNorm(hidden_dim)
        self.ff = nn.Sequential(nn.Linear(hidden_dim, 4 * hidden_dim), nn.ReLU(inplace=True), FastDropout(dropout),
                                nn.Linear(4 * hidden_dim, hidden_dim))
        self.ff_drop = FastDropout(dropout)

    def forward(self, x_q: torch.Tensor, keys: torch.Tensor | tuple[torch.Tensor, torch.Tensor],
                mask: torch.Tensor, source: torch.Tensor | None = None) -> torch.Tensor:
        q = x_q.shape[0]
        if not pads_rows(self.to_q.weight) or bucket_rows(q) == q:
            return self._attend(x_q, keys, mask, source)
        # queries padded to a known shape (bucket_rows) by rows that attend to nothing (their index 0 is in range)
        pad = lambda t: pad_rows(t, bucket_rows(q))  # noqa: E731
        keys = tuple(pad(k) for k in keys) if isinstance(keys, tuple) else pad(keys)
        return self._attend(pad(x_q), keys, pad(mask), source)[:q]

    def _attend(self, x_q: torch.Tensor, keys: torch.Tensor | tuple[torch.Tensor, torch.Tensor],
                mask: torch.Tensor, source: torch.Tensor | None) -> torch.Tensor:
        n_q = normalise(x_q)  # (Q, d)
        q_in = torch.addcmul(self.norm_q.bias, n_q, self.norm_q.weight)  # norm_q(x_q)
        h, dh = self.num_heads, self.head_dim
        d = q_in.shape[-1]
        norm_src = self.norm_src or self.norm_q
        g_src, b_src, g_rpe, b_rpe = norm_src.weight, norm_src.bias, self.norm_rpe.weight, self.norm_rpe.bias
        q = self.to_q(q_in).view(-1, h, dh) * (1.0 / math.sqrt(dh))  # (Q, h, dh)
        w_k = torch.cat([self.to_k.weight * g_src, self.to_k_r.weight * g_rpe], 1).view(h, dh, 2 * d)
        a = _Headwise.apply(q, w_k)  # (Q, h, 2d): the key maps moved onto the query
        drop_p = self.attn_drop.p if self.training else 0.0
        if isinstance(keys, tuple):  # the source table's rows, gathered, and the RPE: two parts
            index, rpe = keys
            n_src = n_q if source is None else normalise(source)
            rows = n_src.index_select(0, index.reshape(-1)).view(*index.shape, d)  # (Q, K, d)
            o_src, o_rpe, attn_sum = _NeighbourAttention.apply(mask, drop_p, a[..., :d], rows, a[..., d:], rpe)
            out = torch.cat([o_src, o_rpe], -1)  # (Q, h, 2d)
        else:
            out, attn_sum = _NeighbourAttention.apply(mask, drop_p, a, keys)  # (Q, h, 2d), (Q, h)
        w_v = torch.cat([self.to_v.weight * g_src, self.to_v_r.weight * g_rpe], 1).view(h, dh, 2 * d)
        bias = self.to_v.bias + self.to_v.weight @ b_src + self.to_v_r.bias + self.to_v_r.weight @ b_rpe  # (inner,)
        agg = _Headwise.apply(out, w_v.transpose(1, 2)) + bias.view(h, dh) * attn_sum[..., None]  # the value maps
        agg = agg.reshape(-1, h * dh)  # (Q, inner)
        g = torch.sigmoid(self.to_g(torch.cat([agg, q_in], -1)))
        agg = agg + g * (self.to_s(q_in) - agg)
        x = x_q + self.out_drop(self.to_out(agg))
        return x + self.ff_drop(self.ff(self.norm_ff(x)))
