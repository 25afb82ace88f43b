"""The training-speed rewrites of the model's two hottest layers compute what the straightforward
implementations computed: the same loss and the same gradients on the package's sample scenes, within
float tolerance.

The reference forwards below are the project's previous implementations, kept verbatim (one batched
einsum over the Fourier dimensions, every row embedded, padded neighbour pairs included; relative
positional embeddings projected per (query, key) pair; RoadNet over every padded piece).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from smart_marl.model import layers, losses, motionnet, roadnet
from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors
from smart_marl.model.losses import NextTokenLoss
from smart_marl.model.smart import SMART, get_config
from smart_marl.tokens.road import RoadVocabulary, road_pieces


def reference_fourier_forward(self, x, categorical=None, valid=None, repeated_dims=()):
    lead = x.shape[:-1]
    x = x.reshape(-1, self.input_dim)  # (M, D)
    ang = x[..., None] * self.freqs * (2 * math.pi)  # (M, D, F)
    feat = torch.cat([ang.cos(), ang.sin(), x[..., None]], -1)  # (M, D, 2F+1)
    h = torch.einsum("mdf,dfh->mdh", feat, self.w1) + self.b1  # (M, D, H)
    h = F.relu(self.ln1(h))
    h = torch.einsum("mdh,dhk->mdk", h, self.w2) + self.b2  # (M, D, H)
    h = h.sum(1)  # (M, H)
    if categorical is not None:
        h = h + categorical.reshape(-1, self.hidden_dim)
    return self.out(h).reshape(*lead, self.hidden_dim)


def reference_attention_forward(self, x_q, keys, mask):
    q_in = self.norm_q(x_q)
    if keys[0] == "raw":  # the map attention: raw road encodings, the neighbours' rows, raw RPE
        _, src, index, rpe = keys
        k_rows, v_rows = self.project_source(src)
    else:  # self-attention among the queries' own rows
        index, rpe = keys
        k_rows, v_rows = self.project_source(x_q)
    r = self.norm_rpe(rpe)
    nq, kk = index.shape
    h, dh = self.num_heads, self.head_dim
    q = self.to_q(q_in).view(nq, h, dh)
    k = (k_rows[index] + self.to_k_r(r)).view(nq, kk, h, dh)
    v = (v_rows[index] + self.to_v_r(r)).view(nq, kk, h, dh)
    scores = torch.einsum("qhd,qkhd->qhk", q, k) / math.sqrt(dh)
    m = mask[:, None, :]
    scores = scores.masked_fill(~m, torch.finfo(scores.dtype).min)
    attn = torch.softmax(scores, dim=-1) * m
    attn = self.attn_drop(attn)
    agg = torch.einsum("qhk,qkhd->qhd", attn, v).reshape(nq, h * dh)
    g = torch.sigmoid(self.to_g(torch.cat([agg, q_in], -1)))
    agg = agg + g * (self.to_s(q_in) - agg)
    x = x_q + self.out_drop(self.to_out(agg))
    return x + self.ff_drop(self.ff(self.norm_ff(x)))


def reference_project_source(self, src):
    s = (self.norm_src or self.norm_q)(src)
    return self.to_k(s), self.to_v(s)


def reference_road_forward(self, points, pose, road_type, light, valid, masked=None, needed=None):  # every piece
    b, r = valid.shape
    x = self.piece_mlp(points.flatten(-2))
    if masked is not None:
        x = torch.where(masked[..., None], self.mask_emb.to(x.dtype).expand_as(x), x)
    x = x + self.type_emb(road_type) + self.light_emb(light)
    idx, nmask = layers.knn_within(pose[..., :2], pose[..., :2], self.cfg.road_radius_m, self.cfg.road_neighbours, valid, valid)
    key_pose = torch.gather(pose, 1, idx.reshape(b, -1, 1).expand(-1, -1, 3)).view(b, r, -1, 3)
    rpe = self.rpe(layers.relative_pose_features(pose[:, :, None, :], key_pose))
    flat_idx = (idx + torch.arange(b, device=idx.device)[:, None, None] * r).view(b * r, -1)
    x = x.reshape(b * r, -1)
    nmask, rpe = nmask.view(b * r, -1), rpe.view(b * r, nmask.shape[-1], -1)
    for layer in self.layers:
        x = layer(x, (flat_idx, rpe), nmask)
    return x.view(b, r, -1)


def _loss_and_grads(model: SMART, batch) -> tuple[dict[str, float], dict[str, torch.Tensor]]:
    model.zero_grad(set_to_none=True)
    out = NextTokenLoss(model, label_smoothing=0.1)(batch)
    out["loss"].backward()
    return ({k: float(v.detach()) for k, v in out.items()},
            {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})


@pytest.fixture(scope="module")
def two_scenes(sample_scenes):
    """Sample scenes sumo-7-000000-02 and -00 (44 and 22 tracks, so that a batch of them pads agents and road pieces)."""
    return [sample_scenes[2], sample_scenes[0]]


def _scene_items(scenes, vocab, steps: slice, road_keep_radius_m: float = 40.0) -> tuple[list[dict], dict]:
    """Training items of the scenes over the token ``steps``, and the config fields that fit them
    (vocabulary sizes)."""
    pieces = np.concatenate([road_pieces(sc.road_map).local for sc in scenes])
    rv = RoadVocabulary(points=pieces[np.random.default_rng(0).choice(len(pieces), 64)], tolerance_m=0.0, requested_size=64)
    items = []
    for i, scene in enumerate(scenes):
        arrays = scene_tensors(scene, vocab, scene_road(scene, rv), noise_topk=5, rng=i, road_keep_radius_m=road_keep_radius_m)
        for k in ("agent_tokens", "agent_valid", "agent_start_pose", "agent_pose", "target_tokens", "target_valid"):
            arrays[k] = arrays[k][:, steps]
        items.append(arrays)
    return items, dict(motion_vocab_sizes=tuple(vocab[t].size for t in range(3)), road_vocab_size=64, dropout=0.0)


@pytest.mark.parametrize("size", ["smart-1m", "smart-7m"])
def test_fast_layers_give_the_reference_loss_and_gradients_on_sample_scenes(two_scenes, sample_vocab, size, one_torch_thread,
                                                                            monkeypatch):
    # the first 6 token steps keep the test fast
    items, fields = _scene_items(two_scenes, sample_vocab, slice(4, 10))
    cfg = get_config(size, **fields, num_agent_blocks=1 if size == "smart-7m" else 2)
    batch = collate_scenes(items)
    assert not batch.road_valid.all() and not batch.agent_valid.all()  # padding that the fast paths skip
    torch.manual_seed(0)
    model = SMART(cfg, [sample_vocab[t].contour for t in range(3)]).train()  # dropout 0: deterministic
    fast_losses, fast_grads = _loss_and_grads(model, batch)
    monkeypatch.setattr(layers.FourierEmbedding, "forward", reference_fourier_forward)
    monkeypatch.setattr(layers.NeighbourAttention, "forward", reference_attention_forward)
    monkeypatch.setattr(roadnet.RoadNet, "forward", reference_road_forward)
    # each reference layer normalises its own inputs and projects keys and values per pair
    monkeypatch.setattr(layers.NeighbourAttention, "project_source", reference_project_source, raising=False)
    monkeypatch.setattr(motionnet, "normalise", lambda t: t)
    monkeypatch.setattr(motionnet, "neighbour_keys", lambda rows, index, rpe: ("raw", rows, index, rpe))
    ref_losses, ref_grads = _loss_and_grads(model, batch)

    assert batch.target_valid.sum() > 200 and ref_losses["road_tokens"] > 20  # a real workload, not an empty one
    for k in ("loss", "motion_loss", "road_loss"):
        assert fast_losses[k] == pytest.approx(ref_losses[k], rel=1e-5, abs=1e-6), k
    assert set(fast_grads) == set(ref_grads)
    for name, g in ref_grads.items():
        scale = float(g.abs().max()) + 1e-12
        assert float((fast_grads[name] - g).abs().max()) <= 1e-4 * scale + 1e-8, name


def test_rows_after_the_last_target_are_skipped_without_changing_the_loss(two_scenes, sample_vocab, one_torch_thread,
                                                                          monkeypatch):
    # the last 5 token steps of both scenes: the final step has no next token, so no target; the
    # second scene's targets are all dropped, so none of its rows can reach the loss
    items, fields = _scene_items(two_scenes, sample_vocab, slice(-5, None))
    cfg = get_config("smart-1m", **fields)
    items[1]["target_valid"][:] = False
    batch = collate_scenes(items)
    needed = losses.rows_reaching_targets(batch)
    assert not batch.target_valid[:, :, -1].any() and batch.agent_valid[0, :, -1].any()
    assert not needed[:, :, -1].any() and not needed[1].any()  # the final step and the target-less scene are skipped
    assert torch.equal(needed[0, :, :-1], batch.agent_valid[0, :, :-1])  # every other row is kept
    torch.manual_seed(0)
    model = SMART(cfg, [sample_vocab[t].contour for t in range(3)]).train()
    skipped_losses, skipped_grads = _loss_and_grads(model, batch)
    monkeypatch.setattr(losses, "rows_reaching_targets", lambda b: b.agent_valid)  # every valid row
    all_losses, all_grads = _loss_and_grads(model, batch)
    assert all_losses["vehicle_tokens"] > 50  # a real workload
    for k in ("loss", "motion_loss", "road_loss"):
        assert skipped_losses[k] == pytest.approx(all_losses[k], rel=1e-6, abs=1e-7), k
    for name, g in all_grads.items():
        assert _close(skipped_grads[name], g), name


def _close(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal within float32 rounding, relative to the tensor's largest entry."""
    return float((a - b).abs().max()) <= 1e-5 * float(b.abs().max()) + 1e-7


def test_road_pieces_that_nothing_reads_are_skipped_without_changing_the_loss(two_scenes, sample_vocab, one_torch_thread,
                                                                            monkeypatch):
    # three road layers, so that each layer's pieces are the next layer's plus their neighbours
    items, fields = _scene_items(two_scenes, sample_vocab, slice(4, 8), road_keep_radius_m=60.0)
    cfg = get_config("smart-1m", **fields, num_road_layers=3)
    batch = collate_scenes(items)
    torch.manual_seed(0)
    model = SMART(cfg, [sample_vocab[t].contour for t in range(3)]).train()
    layer_queries = []
    road_forward, layer_forward = roadnet.RoadNet.forward, layers.NeighbourAttention.forward

    def spy(self, x_q, keys, mask, source=None):
        if isinstance(self, layers.NeighbourAttention) and self in list(model.road_net.layers):
            layer_queries.append(x_q.shape[0])
        return layer_forward(self, x_q, keys, mask, source)

    monkeypatch.setattr(layers.NeighbourAttention, "forward", spy)
    skipped_losses, skipped_grads = _loss_and_grads(model, batch)
    computed = list(layer_queries)
    layer_queries.clear()
    monkeypatch.setattr(roadnet.RoadNet, "forward", lambda self, *a, needed=None, **k: road_forward(self, *a, **k))
    all_losses, all_grads = _loss_and_grads(model, batch)
    valid = int(batch.road_valid.sum())
    assert layer_queries == [valid] * 3  # the reference computes every piece in every layer
    assert computed[2] < computed[1] <= computed[0] < valid  # each layer computes fewer pieces than the one before
    assert all_losses["road_tokens"] > 20 and all_losses["vehicle_tokens"] > 50  # a real workload
    for k in ("loss", "motion_loss", "road_loss"):
        assert skipped_losses[k] == pytest.approx(all_losses[k], rel=1e-6, abs=1e-7), k
    assert set(skipped_grads) == set(all_grads)
    for name, g in all_grads.items():
        assert _close(skipped_grads[name], g), name


def _fourier_grads(emb, x, **kwargs):
    emb.zero_grad(set_to_none=True)
    out = emb(x, **kwargs)
    weights = torch.linspace(-1.0, 1.0, out.numel()).view_as(out)  # a loss that weighs every output differently
    (out * weights).sum().backward()
    return out.detach(), {n: p.grad.clone() for n, p in emb.named_parameters()}


def test_fourier_embedding_skips_padded_rows_and_embeds_each_repeated_value_once_with_the_same_gradients(monkeypatch):
    torch.manual_seed(0)
    emb = layers.FourierEmbedding(3, 16, 8)
    g = torch.Generator().manual_seed(1)
    x = torch.stack([torch.randint(0, 5, (40, 6), generator=g).float(),  # 5 distinct values: embedded once each
                     torch.randn(40, 6, generator=g) * 3,  # all distinct: embedded per row
                     torch.randint(0, 3, (40, 6), generator=g).float() * 0.5], -1)  # (40, 6, 3)
    valid = torch.rand(40, 6, generator=g) < 0.7
    ref_out, ref_grads = _fourier_grads(emb, x, valid=None)
    calls = []  # what each dimension was embedded from

    def recording_distinct(col, repeated):
        calls.append(real_distinct(col, repeated))
        return calls[-1]

    real_distinct = layers._distinct
    monkeypatch.setattr(layers, "_distinct", recording_distinct)
    fast_out, fast_grads = _fourier_grads(emb, x, valid=valid, repeated_dims=(0, 1, 2))
    # dims 0 and 2 were embedded per distinct value, dim 1 (no repeats) per row, and only the valid rows
    assert [c[0].numel() for c in calls] == [5, int(valid.sum()), 3] and calls[1][1] is None
    assert torch.allclose(fast_out[valid], ref_out[valid], atol=1e-6) and (fast_out[~valid] == 0).all()
    # the reference's gradients with its padded rows' outputs weighed by 0, as attention weighs padded pairs
    emb.zero_grad(set_to_none=True)
    out = emb(x)
    (out * torch.linspace(-1.0, 1.0, out.numel()).view_as(out) * valid[..., None]).sum().backward()
    for name, p in emb.named_parameters():
        assert _close(fast_grads[name], p.grad), name


def test_fourier_embedding_fast_trunk_matches_autograd_on_inputs_that_need_a_gradient():
    torch.manual_seed(0)
    emb = layers.FourierEmbedding(2, 16, 8)
    x = torch.randn(50, 2)
    fast_out, fast_grads = _fourier_grads(emb, x)  # geometry: no gradient, the hand-written backward
    slow_out, slow_grads = _fourier_grads(emb, x.clone().requires_grad_())  # autograd's path
    assert torch.allclose(fast_out, slow_out, atol=1e-6)
    for name in slow_grads:
        assert _close(fast_grads[name], slow_grads[name]), name


@pytest.mark.parametrize("bipartite", [False, True])
def test_neighbour_attention_folds_its_layer_norms_exactly(bipartite):
    # in float64, so that any difference is the algebra and not rounding: the fast layer (normalised inputs on
    # the pairs, every LayerNorm's scale and shift folded into per-query weights, the scores' per-query
    # constant left out) against SMART's layer written out, with LayerNorms far from their initial (1, 0)
    torch.manual_seed(0)
    att = layers.NeighbourAttention(32, 4, 8, 0.0, bipartite=bipartite).double()
    with torch.no_grad():
        for norm in (att.norm_q, att.norm_src, att.norm_rpe, att.norm_ff):
            if norm is not None:
                norm.weight.normal_(1.0, 0.5)
                norm.bias.normal_(0.0, 0.5)
    x = torch.randn(30, 32, dtype=torch.float64, requires_grad=True)
    src = torch.randn(45, 32, dtype=torch.float64, requires_grad=True) if bipartite else x
    index = torch.randint(0, src.shape[0], (30, 6))
    mask = torch.rand(30, 6) < 0.8
    mask[3] = False  # a query without neighbours
    rpe = torch.randn(30, 6, 32, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(30, 32, dtype=torch.float64)

    def run(forward, keys):
        for t in (x, src, rpe):
            t.grad = None
        att.zero_grad(set_to_none=True)
        out = forward(att, x, keys, mask)
        (out * weights).sum().backward()
        inputs = (x, src, rpe) if bipartite else (x, rpe)
        return out.detach(), [t.grad.clone() for t in inputs], {n: p.grad.clone() for n, p in att.named_parameters()}

    if bipartite:
        fast_keys = layers.neighbour_keys(layers.normalise(src), index, layers.normalise(rpe))
    else:
        fast_keys = (index, layers.normalise(rpe))
    fast = run(layers.NeighbourAttention.forward, fast_keys)
    ref_keys = ("raw", src, index, rpe) if bipartite else (index, rpe)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(layers.NeighbourAttention, "project_source", reference_project_source, raising=False)
        ref = run(reference_attention_forward, ref_keys)
    torch.testing.assert_close(fast[0], ref[0], rtol=1e-10, atol=1e-10)
    for g_fast, g_ref in zip(fast[1], ref[1]):
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-9, atol=1e-10)
    assert fast[2].keys() == ref[2].keys()
    for name in ref[2]:
        torch.testing.assert_close(fast[2][name], ref[2][name], rtol=1e-9, atol=1e-10, msg=name)


def test_neighbour_attention_runs_under_bf16_autocast_and_stays_near_float32():
    torch.manual_seed(0)
    att = layers.NeighbourAttention(32, 4, 8, 0.0, bipartite=False)
    x = torch.randn(30, 32, requires_grad=True)
    index, mask = torch.randint(0, 30, (30, 6)), torch.rand(30, 6) < 0.8
    rpe = layers.normalise(torch.randn(30, 6, 32))
    ref = att(x, (index, rpe), mask)
    ref.sum().backward()
    ref_grad, x.grad = x.grad.clone(), None
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = att(x, (index, rpe), mask)
    out.float().sum().backward()  # the hand-written backward runs under the forward's autocast
    assert torch.allclose(out.float(), ref, atol=0.1) and torch.allclose(x.grad, ref_grad, atol=0.15)


def test_knn_grouped_finds_what_knn_within_finds_on_the_padded_layout():
    g = torch.Generator().manual_seed(0)
    keys = torch.rand(3, 20, 2, generator=g) * 50
    key_valid = torch.rand(3, 20, generator=g) < 0.8
    queries = torch.rand(3, 9, 2, generator=g) * 50
    query_valid = torch.rand(3, 9, generator=g) < 0.6
    idx, mask = layers.knn_within(queries, keys, 20.0, 5, query_valid, key_valid)  # (3, 9, 5)
    group, slot = query_valid.nonzero(as_tuple=True)
    g_idx, g_mask = layers.knn_grouped(queries[group, slot], group, keys, 20.0, 5, key_valid)
    assert torch.equal(g_mask, mask[group, slot]) and torch.equal(g_idx[g_mask], idx[group, slot][g_mask])


def test_dropout_masks_drop_p_of_the_entries_and_keep_the_mean():
    torch.manual_seed(0)
    x = torch.ones(999, 1001)  # an odd count: the last 64-bit draw gives one entry
    for p in (0.1, 0.5):
        mask = layers.dropout_mask(x, p)
        dropped = float((mask == 0).float().mean())
        assert abs(dropped - p) < 0.003, (p, dropped)  # 1e6 entries: the standard error is under 0.0005
        assert torch.allclose(mask[mask != 0], torch.tensor(1.0 / (1.0 - p)))
        assert abs(float(mask.mean()) - 1.0) < 0.006
    # neighbouring entries come from the two halves of one draw: they must not be correlated
    mask = layers.dropout_mask(x, 0.5).flatten()[:-1].view(-1, 2) > 0  # entries 2i and 2i + 1 share a draw
    both = float((mask[:, 0] & mask[:, 1]).float().mean())
    assert abs(both - 0.25) < 0.003
    drop = layers.FastDropout(0.3)
    y = torch.randn(50, 40, requires_grad=True)
    out = drop(y)
    out.sum().backward()
    assert torch.equal(y.grad, (out.detach() != 0).float() / 0.7 * (y.detach() != 0))  # the gradient is the mask
    assert drop.eval()(y) is y


def test_fourier_embedding_of_many_rows_in_blocks_equals_one_pass(monkeypatch):
    """CPU inference embeds more than EMBED_BLOCK_ROWS rows in blocks; each row's result is the one pass's
    (valid rows, categorical embeddings and repeated values included), padded rows zero."""
    torch.manual_seed(0)
    emb = layers.FourierEmbedding(3, 16, 8)
    g = torch.Generator().manual_seed(2)
    x = torch.stack([torch.randint(0, 5, (300, 6), generator=g).float(), torch.randn(300, 6, generator=g) * 3,
                     torch.randn(300, 6, generator=g)], -1)  # (300, 6, 3)
    valid = torch.rand(300, 6, generator=g) < 0.7
    cat = torch.randn(300, 6, 16, generator=g)
    with torch.no_grad():
        want = emb(x, categorical=cat, valid=valid, repeated_dims=(0,))
        want_all = emb(x, categorical=cat)
        for rows in (7, 64, 1000):
            monkeypatch.setattr(layers, "EMBED_BLOCK_ROWS", rows)
            got = emb(x, categorical=cat, valid=valid, repeated_dims=(0,))
            assert torch.allclose(got, want, atol=1e-6) and (got[~valid] == 0).all(), rows
            assert torch.allclose(emb(x, categorical=cat), want_all, atol=1e-6), rows
