"""The one neighbour search (smart_marl.model.layers.knn_within) picks the same neighbours for a scene
whatever it is batched with: ties are broken by index, as a stable sort breaks them, and distances
are computed exactly (not by the |a|^2 + |b|^2 - 2ab expansion, whose rounding depends on sizes)."""

from __future__ import annotations

import torch

from smart_marl.model.layers import knn_within, smallest_k


def test_smallest_k_is_a_stable_sort_prefix_and_padding_does_not_change_it():
    gen = torch.Generator().manual_seed(0)
    for _ in range(300):
        m = int(torch.randint(3, 40, (), generator=gen))
        k = int(torch.randint(1, m + 2, (), generator=gen))
        x = torch.randint(0, 6, (4, m), generator=gen).float()  # many ties
        x[0, ::3] = float("inf")
        want_v, want_i = torch.sort(x, dim=-1, stable=True)
        v, i = smallest_k(x, k)
        assert torch.equal(v, want_v[:, :k]) and torch.equal(i, want_i[:, :k])
        padded = torch.cat([x, torch.full((4, 7), float("inf"))], -1)
        assert torch.equal(smallest_k(padded, min(k, m))[1], want_i[:, : min(k, m)])


def test_a_scene_has_the_same_neighbours_alone_and_batched_with_a_larger_one():
    gen = torch.Generator().manual_seed(1)
    grid = torch.stack(torch.meshgrid(torch.arange(12.0), torch.arange(12.0), indexing="ij"), -1).reshape(-1, 2) * 2.5  # equal gaps
    small = grid[:100] + 1000.0  # far from the origin, where float32 rounding bites
    big = torch.rand(700, 2, generator=gen) * 60 + 1000.0
    alone = knn_within(small[None], small[None], 10.0, 16, torch.ones(1, 100, dtype=torch.bool), torch.ones(1, 100, dtype=torch.bool))
    keys = torch.zeros(2, 700, 2)
    keys[0, :100], keys[1] = small, big
    valid = torch.zeros(2, 700, dtype=torch.bool)
    valid[0, :100], valid[1] = True, True
    batched = knn_within(keys[:, :100], keys, 10.0, 16, valid[:, :100], valid)
    assert torch.equal(alone[0][0], batched[0][0]) and torch.equal(alone[1][0], batched[1][0])
    assert alone[1].sum(-1).min() >= 8  # the grid gives every point many equidistant neighbours


def test_the_cpu_search_in_small_blocks_finds_what_one_search_of_the_whole_batch_finds(monkeypatch):
    """knn_within on the CPU runs in blocks of groups (and of queries), each cut to its groups' last valid
    query and key (KNN_BLOCK_PAIRS): any block size gives what one search of the padded batch gives."""
    from smart_marl.model import layers

    gen = torch.Generator().manual_seed(2)
    g, q, m = 7, 50, 90
    qxy = torch.randint(0, 12, (g, q, 2), generator=gen).float() * 2.5 + 1000.0  # a grid: many equal distances
    kxy = torch.randint(0, 12, (g, m, 2), generator=gen).float() * 2.5 + 1000.0
    qv = torch.arange(q)[None] < torch.randint(0, q + 1, (g, 1), generator=gen)  # groups of different extents,
    kv = (torch.arange(m)[None] < torch.randint(0, m + 1, (g, 1), generator=gen)) & (torch.rand(g, m, generator=gen) < 0.8)
    qv[0], kv[1] = False, False  # one group without queries, one without keys
    want = layers._knn_block(qxy, kxy, 9.0, 12, qv, kv)
    for pairs in (1, 200, 3000, 1 << 20):  # one query of one group at a time ... the whole batch at once
        monkeypatch.setattr(layers, "KNN_BLOCK_PAIRS", pairs)
        idx, mask = knn_within(qxy, kxy, 9.0, 12, qv, kv)
        assert torch.equal(mask, want[1]) and torch.equal(idx, want[0]), pairs
    assert want[1].sum() > 100 and not want[1][0].any()


def test_free_inf_ties_keeps_every_finite_pick_of_the_stable_sort():
    gen = torch.Generator().manual_seed(3)
    x = torch.randint(0, 4, (200, 30), generator=gen).float()
    x[torch.rand(200, 30, generator=gen) < 0.7] = float("inf")  # most rows have fewer than k finite entries
    want_v, want_i = torch.sort(x, dim=-1, stable=True)
    v, i = smallest_k(x, 8, free_inf_ties=True)
    finite = torch.isfinite(want_v[:, :8])
    assert torch.equal(v, want_v[:, :8]) and torch.equal(i[finite], want_i[:, :8][finite])
