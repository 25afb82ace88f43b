"""The pruned kernels of the environment's step give exactly what the plain computation gives: the
collision-aware sampler's pair bound (:func:`smart_marl.rollout.avoidance.frames_collide` against
:func:`~smart_marl.rollout.avoidance.boxes_overlap_near` on every pair), the collision event's pair
bound (:func:`envs._reward.collisions` against every pair on every frame) and the offroad test's nearest
road edge in segment blocks (:func:`smart_marl.geometry_torch.nearest_road_edge` against every
segment), the observation's nearest road points in blocks (:func:`envs._observation.nearest_road_points`
against every point). Each case is built so that a bound cut too tight would drop what is near, and a test each
shows that a wrong bound is noticed."""

from __future__ import annotations

import math

import pytest
import torch

from smart_marl.rollout.avoidance import boxes_overlap_near, frames_collide

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def _crowd(seed: int, r: int = 40, c: int = 12, f: int = 5, k: int = 16, spread: float = 12.0, headings: int = 5):
    """Random rows: paths of c candidates from the row's centre (straight, curved, long and short),
    and k others moving over the frames (``headings`` 1: a held heading; 5: one per frame)."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    own_xy = (u(r, 2) - 0.5) * spread
    own_half = torch.stack([0.4 + 2.2 * u(r), 0.4 + 0.8 * u(r)], -1)
    h0 = (u(r, 1, 1) - 0.5) * 2 * math.pi
    speed = 12 * u(r, c, 1) ** 2  # up to 12 m a step
    turn = (u(r, c, 1) - 0.5) * 1.5
    s = torch.arange(1, f + 1, dtype=torch.float64) / f
    heading = h0 + turn * s
    step = speed * s
    frames = torch.stack([own_xy[:, None, None, 0] + step * heading.cos(), own_xy[:, None, None, 1] + step * heading.sin(), heading], -1)
    now = own_xy[:, None] + (u(r, k, 2) - 0.5) * spread
    move = (u(r, k, 2) - 0.5) * 10
    other_xy = now[:, :, None] + s[None, None, :, None] * move[:, :, None]  # [R, K, F, 2]
    other_h = (u(r, k, headings) - 0.5) * 2 * math.pi
    other_half = torch.stack([0.4 + 2.2 * u(r, k), 0.4 + 0.8 * u(r, k)], -1)
    ok = u(r, k) < 0.85
    gap = (now - own_xy[:, None]).norm(dim=-1) - move.norm(dim=-1)
    return frames, own_xy, own_half, other_xy, other_h, other_half, gap, ok


def _plain(frames, own_half, other_xy, other_h, other_half, ok):
    """Every (row, path, frame, other) through boxes_overlap_near: [R, c]."""
    hit = boxes_overlap_near(frames[..., None, :2], frames[..., None, 2], own_half[:, None, None, None],
                             other_xy.transpose(1, 2)[:, None], other_h.transpose(1, 2)[:, None], other_half[:, None, None],
                             where=ok[:, None, None])
    return hit.flatten(2).any(-1)


@pytest.mark.parametrize("seed,spread,headings,k", [(0, 30.0, 5, 16), (1, 12.0, 1, 3), (2, 50.0, 5, 16), (3, 8.0, 1, 1)])
def test_the_pair_bound_of_the_sampler_keeps_every_colliding_pair(seed, spread, headings, k):
    frames, own_xy, own_half, other_xy, other_h, other_half, gap, ok = _crowd(seed, k=k, spread=spread, headings=headings)
    want = _plain(frames, own_half, other_xy, other_h, other_half, ok)
    got = frames_collide(frames, own_xy, own_half, other_xy, other_h.cos(), other_h.sin(), other_half, gap, ok)
    assert 0.05 < want.double().mean() < 0.95, want.double().mean()  # both outcomes are exercised
    assert torch.equal(got, want)


def test_the_pair_bound_fails_when_the_gap_is_overstated():
    """The check above would notice a bound that is too tight: with the others' travel left out of
    their gap (a wrong bound), pairs that do collide are dropped."""
    frames, own_xy, own_half, other_xy, other_h, other_half, gap, ok = _crowd(0, spread=30.0)
    want = _plain(frames, own_half, other_xy, other_h, other_half, ok)
    wrong_gap = (other_xy[:, :, 0] - own_xy[:, None]).norm(dim=-1)  # distance on the first frame, travel ignored
    got = frames_collide(frames, own_xy, own_half, other_xy, other_h.cos(), other_h.sin(), other_half, wrong_gap, ok)
    assert not torch.equal(got, want)


# ------------------------------------------------------------------ the collision event's pair bound
def _plain_collisions(ctrl_track, live, frames, present, box_size):
    """The collision event measured on every (agent, other, frame): [B, C]."""
    from envs._scene_batch import gather_tracks
    from smart_marl.geometry_torch import rounded_boxes_overlap

    n = frames.shape[1]
    mine, my_size = gather_tracks(frames, ctrl_track), gather_tracks(box_size[..., :2], ctrl_track)
    reach = box_size[..., :2].norm(dim=-1) / 2
    dist = (mine[:, :, None, :, :2] - frames[:, None, :, :, :2]).norm(dim=-1)  # [B, C, N, F]
    other = torch.arange(n)[None, None] != ctrl_track[..., None]
    cand = (dist < gather_tracks(reach, ctrl_track)[..., None, None] + reach[:, None, :, None]) & (
        other & present[:, None] & live[..., None])[..., None]
    bi, ci, ni, fi = cand.nonzero(as_tuple=True)
    pa, pb = mine[bi, ci, fi], frames[bi, ni, fi]
    hit = rounded_boxes_overlap(pa[:, :2], pa[:, 2], my_size[bi, ci], pb[:, :2], pb[:, 2], box_size[bi, ni, :2])
    out = torch.zeros(ctrl_track.shape, dtype=torch.bool)
    out[bi[hit], ci[hit]] = True
    return out


@pytest.mark.parametrize("seed,spread", [(0, 20.0), (1, 60.0), (2, 8.0)])
def test_the_collision_event_s_pair_bound_keeps_every_colliding_pair(seed, spread):
    """Boxes that move fast (up to 15 m a step, so that pairs far apart on the first frame meet later),
    turn, and pass close by; agents with NaN poses on some frames."""
    from envs._reward import collisions

    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    b, n, c, f = 6, 40, 8, 5
    start, heading = (u(b, n, 2) - 0.5) * spread, (u(b, n, 1) - 0.5) * 2 * math.pi
    speed = 15 * u(b, n, 1) ** 2
    s = torch.arange(1, f + 1) / f
    h = heading + (u(b, n, 1) - 0.5) * s
    frames = torch.stack([start[..., :1] + speed * s * h.cos(), start[..., 1:] + speed * s * h.sin(), h], -1)  # [B, N, F, 3]
    frames[0, 3, 2] = float("nan")
    box_size = torch.stack([1 + 4 * u(b, n), 0.5 + 1.5 * u(b, n), torch.ones(b, n)], -1)
    ctrl_track = torch.randint(0, n, (b, c), generator=g)
    ctrl_track[:, -1] = 3
    live, present = u(b, c) < 0.9, u(b, n) < 0.9
    want = _plain_collisions(ctrl_track, live, frames, present, box_size)
    assert 0.1 < want.float().mean() < 0.9, want.float().mean()
    assert torch.equal(collisions(ctrl_track, live, frames, present, box_size), want)


# ------------------------------------------------------------------ the nearest road edge in blocks
def _edges(seed: int, sizes=(700, 333, 0, 64), shuffle: bool = False, dtype=torch.float64):
    """Road edges of scenes with ``sizes`` segments: polylines of short segments (as the real ones),
    in order or shuffled (blocks of consecutive segments then spread over the scene), with duplicated
    segments (equally near: the lowest index wins)."""
    from smart_marl.geometry_torch import RoadEdgeTensors

    g = torch.Generator().manual_seed(seed)
    s = max(sizes)
    start, end = torch.zeros(len(sizes), s, 3, dtype=dtype), torch.zeros(len(sizes), s, 3, dtype=dtype)
    valid = torch.zeros(len(sizes), s, dtype=torch.bool)
    for b, n in enumerate(sizes):
        if not n:
            continue
        turn = torch.cumsum((torch.rand(n, generator=g, dtype=dtype) - 0.5) * 0.3, 0)
        jump = torch.rand(n, generator=g) < 0.03  # a new polyline elsewhere
        step = torch.stack([turn.cos(), turn.sin()], -1) * 0.5
        step[jump] = (torch.rand(int(jump.sum()), 2, generator=g, dtype=dtype) - 0.5) * 120
        xy = torch.cumsum(step, 0) - 30
        z = torch.rand(n, 1, generator=g, dtype=dtype) * 2
        a, e = torch.cat([xy, z], -1), torch.cat([xy + torch.stack([turn.cos(), turn.sin()], -1) * 0.5, z], -1)
        dup = torch.arange(n) % 7 == 3  # copies of an earlier segment
        a[dup], e[dup] = a[torch.arange(n)[dup] - 2], e[torch.arange(n)[dup] - 2]
        order = torch.randperm(n, generator=g) if shuffle else torch.arange(n)
        start[b, :n], end[b, :n], valid[b, :n] = a[order], e[order], True
    zeros, no = torch.zeros(len(sizes), s, dtype=torch.long), torch.zeros(len(sizes), s, dtype=torch.bool)
    return RoadEdgeTensors(start=start, end=end, prior=zeros, next_=zeros, has_prior=no, has_next=no, convex_prior=no,
                           convex_next=no, valid=valid)


def _exhaustive_nearest(points, edges, z=3.0):
    sp = points[:, :, None] - edges.start[:, None]
    e = (edges.end - edges.start)[:, None]
    t = ((sp[..., :2] * e[..., :2]).sum(-1) / (e[..., :2] ** 2).sum(-1).clamp_min(1e-30)).clamp(0, 1)
    d = sp - e * t[..., None]
    return (d[..., 0] ** 2 + d[..., 1] ** 2 + (z * d[..., 2]) ** 2).masked_fill(~edges.valid[:, None], float("inf")).argmin(-1)


def _points(seed: int, b: int, q: int = 300, spread: float = 200.0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.cat([(torch.rand(b, q, 2, generator=g, dtype=dtype) - 0.5) * spread, torch.rand(b, q, 1, generator=g, dtype=dtype) * 3],
                     -1)


@pytest.mark.parametrize("shuffle", [False, True])
@pytest.mark.parametrize("candidates", [1, 3, 12, 10**6])
def test_the_nearest_edge_search_in_segment_blocks_equals_the_exhaustive_one(shuffle, candidates):
    """Near and far points (a far one needs many blocks), blocks of ordered and of shuffled segments,
    a segment count that is not a multiple of the block, a scene without edges, equally near copies."""
    from smart_marl.geometry_torch import nearest_road_edge

    edges = _edges(0, shuffle=shuffle)
    pts = _points(1, 4)
    want = _exhaustive_nearest(pts, edges)
    has = edges.valid.any(1)
    for pairs in (1 << 20, 3000):
        got = nearest_road_edge(pts, edges, z_stretch=3.0, candidates=candidates, max_pairs=pairs)
        assert torch.equal(got[has], want[has])


def _corners(seed: int, b: int, boxes: int = 80, spread: float = 200.0):
    """[B, 4 * boxes, 3] the corners of boxes up to 12 m long, a box's 4 corners one after the other."""
    from smart_marl.geometry_torch import box_corners

    centre = _points(seed, b, boxes, spread)
    g = torch.Generator().manual_seed(seed + 1)
    u = lambda: torch.rand(b, boxes, generator=g, dtype=centre.dtype)  # noqa: E731
    heading, length, width = (u() - 0.5) * 2 * math.pi, 1 + 11 * u(), 0.5 + 2 * u()
    xy = box_corners(centre[..., :2], heading, length, width)  # [B, boxes, 4, 2]
    return torch.cat([xy, centre[..., None, 2:].expand(-1, -1, 4, 1)], -1).reshape(b, 4 * boxes, 3)


@pytest.mark.parametrize("candidates", [1, 12])
def test_the_nearest_edge_search_of_a_box_s_corners_together_equals_the_exhaustive_one(candidates):
    """The corners of a box searched as a run (``group=4``): the run's bound holds for each corner."""
    from smart_marl.geometry_torch import nearest_road_edge

    edges = _edges(0)
    pts = _corners(3, 4)
    want = _exhaustive_nearest(pts, edges)
    has = edges.valid.any(1)
    for pairs in (1 << 20, 3000):
        got = nearest_road_edge(pts, edges, z_stretch=3.0, candidates=candidates, max_pairs=pairs, group=4)
        assert torch.equal(got[has], want[has])


def test_the_segment_blocks_follow_edits_of_the_edges():
    """The blocks are kept between calls; a refill that writes new segments in place is seen."""
    from smart_marl.geometry_torch import nearest_road_edge

    edges, other = _edges(0), _edges(7)
    pts = _points(2, 4)
    nearest_road_edge(pts, edges, z_stretch=3.0)
    edges.start[0], edges.end[0] = other.start[0], other.end[0]  # in place, as SceneBatch.write does
    assert torch.equal(nearest_road_edge(pts, edges, z_stretch=3.0)[0], _exhaustive_nearest(pts, edges)[0])


def test_the_nearest_edge_search_fails_with_a_block_bound_that_is_too_tight(monkeypatch):
    """The checks above would notice a wrong bound: blocks whose radius is halved miss nearer segments."""
    import smart_marl.geometry_torch as gt

    edges = _edges(0)
    pts = _points(1, 4)
    want = _exhaustive_nearest(pts, edges)
    plain = gt._segment_blocks
    monkeypatch.setattr(gt, "_segment_blocks", lambda *a: (plain(*a)[0], plain(*a)[1] / 2))
    got = gt.nearest_road_edge(pts, edges, z_stretch=3.0, candidates=1)
    assert not torch.equal(got[edges.valid.any(1)], want[edges.valid.any(1)])


# ----------------------------------------------------------- the nearest road points of an observation
class _Roads:
    """The two fields of a SceneBatch that :func:`envs._observation.nearest_road_points` reads."""

    def __init__(self, road_xy, road_valid):
        self.road_xy, self.road_valid = road_xy, road_valid


def _roads(seed: int, sizes=(3000, 1200, 40, 0), shuffle: bool = False):
    """Road points ~2 m apart along polylines (many side by side, as lanes are), equally near copies."""
    g = torch.Generator().manual_seed(seed)
    p = max(sizes)
    xy, valid = torch.zeros(len(sizes), p, 2), torch.zeros(len(sizes), p, dtype=torch.bool)
    for b, n in enumerate(sizes):
        if not n:
            continue
        turn = torch.cumsum((torch.rand(n, generator=g) - 0.5) * 0.2, 0)
        step = torch.stack([turn.cos(), turn.sin()], -1) * 2.0
        jump = torch.rand(n, generator=g) < 0.05
        step[jump] = (torch.rand(int(jump.sum()), 2, generator=g) - 0.5) * 80
        pts = torch.cumsum(step, 0) - 40
        dup = torch.arange(n) % 5 == 4
        pts[dup] = pts[torch.arange(n)[dup] - 3]
        order = torch.randperm(n, generator=g) if shuffle else torch.arange(n)
        xy[b, :n], valid[b, :n] = pts[order], True
    return _Roads(xy, valid)


@pytest.mark.parametrize("shuffle", [False, True])
@pytest.mark.parametrize("candidates", [1, 48])
def test_the_nearest_road_points_in_blocks_equal_the_plain_search(shuffle, candidates, monkeypatch):
    """Points on and far off the map, ordered and shuffled road points, a map smaller than the
    candidates, a scene without road points (all invalid), ties between copies."""
    import envs._observation as ob

    monkeypatch.setattr(ob, "ROAD_CANDIDATES", candidates)
    roads = _roads(0, shuffle=shuffle)
    g = torch.Generator().manual_seed(1)
    xy = (torch.rand(4, 30, 2, generator=g) - 0.5) * torch.tensor([150.0, 150.0])
    xy[:, :5] = roads.road_xy[:, :5] + 0.5  # right beside road points
    for k in (32, 3):
        d2 = (roads.road_xy[:, None] - xy[:, :, None]).square().sum(-1).masked_fill(~roads.road_valid[:, None], float("inf"))
        want = ob._nearest(d2, k)
        got = ob.nearest_road_points(roads, xy, k)
        assert torch.equal(got[1], want[1]) and torch.equal(got[0], want[0]), k


def test_the_nearest_road_points_fail_with_a_block_bound_that_is_too_tight(monkeypatch):
    import envs._observation as ob

    roads = _roads(0)
    xy = (torch.rand(4, 30, 2, generator=torch.Generator().manual_seed(1)) - 0.5) * 150
    d2 = (roads.road_xy[:, None] - xy[:, :, None]).square().sum(-1).masked_fill(~roads.road_valid[:, None], float("inf"))
    want = ob._nearest(d2, 32)
    plain = ob.block_bounds
    monkeypatch.setattr(ob, "block_bounds", lambda *a: (plain(*a)[0], plain(*a)[1] / 3))
    monkeypatch.setattr(ob, "ROAD_CANDIDATES", 1)
    assert not torch.equal(ob.nearest_road_points(roads, xy, 32)[0], want[0])


# --------------------------------------------------------------- the sampler's ranking, read off the top k + 1
@pytest.mark.parametrize("levels", [4, 50, 100000])
def test_the_first_chunk_read_off_the_top_set_excludes_what_topk_s_ranking_excludes(levels):
    """Logits with many ties (few levels) and without; tokens rejected by a fixed rule; some rows
    go deep (most of their tokens rejected). The reference ranks every row with topk up front."""
    from smart_marl.rollout.avoidance import _exclude_in_order, _top_set

    g = torch.Generator().manual_seed(levels)
    m, v, k = 300, 200, 6
    logits = torch.randint(0, levels, (m, v), generator=g).float()
    logits[:20, 150:] = float("-inf")  # a smaller vocabulary
    logits[20:25, 3:] = float("-inf")  # fewer tokens than k
    finite = torch.isfinite(logits).sum(-1)
    want = finite.clamp(max=k)
    blocked = torch.rand(m, v, generator=g) < torch.linspace(0.05, 0.995, m)[:, None]  # deeper rows further down
    test = lambda r, tok: blocked[r[:, None], tok]  # noqa: E731
    todo = torch.rand(m, generator=g) < 0.9
    head, tied = _top_set(logits, k)
    assert tied[20:25].all() and (tied[25:].sum() > 10 or levels > 1000)  # ties across the k-th token are exercised
    want_out = _exclude_in_order(logits, finite, want, todo, test, (head, torch.ones_like(tied)))  # topk for every row
    assert torch.equal(_exclude_in_order(logits, finite, want, todo, test, (head, tied)), want_out)
    assert torch.equal(_exclude_in_order(logits, finite, want, todo, test), want_out)
    if levels == 4:  # the test notices a first chunk read off a tied top set
        assert not torch.equal(_exclude_in_order(logits, finite, want, todo, test, (head, torch.zeros_like(tied))), want_out)


def _chunked_search(logits, finite, want, todo, blocked, chunk, depth, growth):
    """The sampler's search row by row, as it was written first: topk's ranking of the first ``depth``
    tokens in chunks (``chunk``, then ``growth`` times as many each round); past it, every token ranked by a
    stable sort and checked again from the top; a row whose every token is blocked left alone."""
    m, v = logits.shape
    ranked, full = torch.topk(logits, depth, dim=-1).indices, torch.sort(logits, dim=-1, descending=True, stable=True).indices
    out = torch.zeros(m, v, dtype=torch.bool)
    for i in todo.nonzero().squeeze(1).tolist():
        order, start, c, passed, marks = ranked[i], 0, chunk, 0, {}
        while True:
            if start + c > len(order) and len(order) < v:
                order, start, passed, marks = full[i], 0, 0, {}
            for j, t in enumerate(order[start:start + c].tolist()):
                if start + j < finite[i]:
                    marks[t] = bool(blocked[i, t])
                    passed += not marks[t]
            start, c = start + c, growth * c
            if passed >= want[i] or start >= finite[i] or start >= v:
                break
        for t, hit in marks.items():
            out[i, t] = hit and passed > 0
    return out


@pytest.mark.parametrize("levels", [4, 100000])
def test_the_samplers_search_excludes_what_a_row_by_row_search_excludes(levels):
    """Rows that stop in every round, rows that go past the first ranking (most of their tokens
    blocked, some on a small vocabulary) and rows whose every token is blocked (left alone: the
    search reads that off its count of passed tokens)."""
    from smart_marl.rollout.avoidance import CHUNK_GROWTH, SORTED_DEPTH, _exclude_in_order

    g = torch.Generator().manual_seed(levels)
    m, v, k = 200, 300, 6
    logits = torch.randint(0, levels, (m, v), generator=g).float()
    logits[:30, 100:] = float("-inf")  # a smaller vocabulary
    finite = torch.isfinite(logits).sum(-1)
    want = finite.clamp(max=k)
    blocked = torch.rand(m, v, generator=g) < torch.linspace(0.3, 1.0, m)[:, None] ** 0.25  # deeper rows further down
    blocked[-10:] = True  # boxed in: every token blocked
    test = lambda r, tok: blocked[r[:, None], tok]  # noqa: E731
    todo = torch.rand(m, generator=g) < 0.9
    got = _exclude_in_order(logits, finite, want, todo, test)
    assert torch.equal(got, _chunked_search(logits, finite, want, todo, blocked, k, SORTED_DEPTH, CHUNK_GROWTH))
    assert (got.sum(-1) > SORTED_DEPTH).sum() > 20 and not got[-10:].any()  # deep rows, boxed-in rows left alone


@pytest.mark.parametrize("limit", [10, 40, 128])
def test_a_search_with_a_depth_leaves_the_top_k_of_the_free_tokens_among_each_row_s_first(limit):
    """What a top-k draw sees after the search with a depth (``limit``): the ``k`` most likely free tokens
    among a row's first ``limit``; where fewer are free there, those alone; where none is, the ``k`` most
    likely free tokens of the whole vocabulary, and where none is free at all, the row's own top k (left
    alone). Rows on a small vocabulary (some smaller than the depth), rows boxed in, rows not checked."""
    from smart_marl.rollout.avoidance import _exclude_in_order

    g = torch.Generator().manual_seed(limit)
    m, v, k = 300, 300, 6
    logits = torch.randn(m, v, generator=g)
    logits[:30, 20:] = float("-inf")  # a smaller vocabulary
    finite = torch.isfinite(logits).sum(-1)
    want = finite.clamp(max=k)
    blocked = torch.rand(m, v, generator=g) < torch.linspace(0.05, 1.0, m)[:, None] ** 0.2  # deeper rows further down
    blocked[-10:] = True  # boxed in
    todo = torch.rand(m, generator=g) < 0.9
    got = _exclude_in_order(logits, finite, want, todo, lambda r, tok: blocked[r[:, None], tok], limit=limit)
    kept = torch.topk(logits.masked_fill(got, float("-inf")), k, dim=-1)
    order = torch.argsort(logits, dim=-1, descending=True)
    cases = set()
    for i in range(m):
        ranked = order[i, :int(finite[i])].tolist()
        free = [t for t in ranked[:limit] if not blocked[i, t]]
        free_anywhere = [t for t in ranked if not blocked[i, t]]
        if not bool(todo[i]) or not free_anywhere:
            expect = ranked[:int(want[i])]
            cases.add("left alone" if bool(todo[i]) else "not checked")
        elif not free:
            expect = free_anywhere[:int(want[i])]
            cases.add("searched on")
        else:
            expect = free[:int(want[i])]
            cases.add("short" if len(free) < want[i] and finite[i] > limit else "k free")
        assert set(kept.indices[i, torch.isfinite(kept.values[i])].tolist()) == set(expect), i
    assert cases == {"left alone", "not checked", "short", "k free", "searched on"}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_samplers_box_test_with_shared_products_equals_the_separating_axis_test(dtype):
    """Every outcome the same, touching boxes included (the sums are reordered only where exact)."""
    from smart_marl.geometry_torch import boxes_overlap_rotated
    from smart_marl.rollout.avoidance import _overlap_sat

    g = torch.Generator().manual_seed(3)
    n = 200000
    u = lambda *s: torch.rand(*s, generator=g, dtype=dtype)  # noqa: E731
    ha, hb = (u(n) - 0.5) * 7, (u(n) - 0.5) * 7
    ha[:1000], hb[:1000] = 0.0, torch.tensor(math.pi / 2, dtype=dtype)  # axis-aligned: exact touching
    a_half, b_half = 0.3 + 2 * u(n, 2), 0.3 + 2 * u(n, 2)
    d = (u(n, 2) - 0.5) * 8
    d[:1000, 0] = a_half[:1000, 0] + b_half[:1000, 1]  # edge on edge
    args = (d, ha.cos(), ha.sin(), a_half, hb.cos(), hb.sin(), b_half)
    want = boxes_overlap_rotated(*args)
    assert 0.2 < want.double().mean() < 0.8
    assert torch.equal(_overlap_sat(*args), want)


@pytest.mark.parametrize("levels", [4, 100000])
def test_the_search_s_round_sizes_change_nothing_that_is_drawn(levels, monkeypatch):
    """Larger rounds check tokens further down than needed and exclude more of them; the top k left
    over stay those of rounds that double (the search as first written): the same values, and with
    logits that do not tie (a model's), the same tokens and so the same draws. Where a tied token
    below the k-th passed one is blocked, doubling left it unchecked and topk could take it in
    place of its unblocked twin; larger rounds exclude it."""
    from smart_marl.rollout import avoidance
    from smart_marl.rollout.sampling import sample_tokens

    g = torch.Generator().manual_seed(levels)
    m, v, k = 200, 300, 6
    logits = torch.randint(0, levels, (m, v), generator=g).float() if levels < 1000 else torch.randn(m, v, generator=g)
    logits[:30, 100:] = float("-inf")
    finite = torch.isfinite(logits).sum(-1)
    blocked = torch.rand(m, v, generator=g) < torch.linspace(0.1, 1.0, m)[:, None] ** 0.25
    test = lambda r, tok: blocked[r[:, None], tok]  # noqa: E731
    todo = torch.ones(m, dtype=torch.bool)
    masks = {}
    for growth in (2, avoidance.CHUNK_GROWTH, 8):
        monkeypatch.setattr(avoidance, "CHUNK_GROWTH", growth)
        masks[growth] = avoidance._exclude_in_order(logits, finite, finite.clamp(max=k), todo, test)
    assert not torch.equal(masks[2], masks[8])  # the larger rounds do check (and exclude) more
    draws = {growth: sample_tokens(logits, torch.Generator().manual_seed(1), k, exclude=mask)[0]
             for growth, mask in masks.items()}
    kept = {growth: torch.topk(logits.masked_fill(mask, float("-inf")), k, dim=-1) for growth, mask in masks.items()}
    for growth in masks:
        assert torch.equal(kept[growth].values, kept[2].values)
        if levels > 1000:
            assert torch.equal(kept[growth].indices, kept[2].indices) and torch.equal(draws[growth], draws[2])


@pytest.mark.parametrize("levels", [3, 100000])
def test_the_sampler_reading_a_shared_ranking_draws_what_it_draws_ranking_alone(levels):
    """The engine ranks the top k + 1 once for the collision check and the sampler. Read off it, the
    sampler draws the same tokens with the same log-probabilities, with and without exclusions; with
    few levels most rows have equal values among their top k + 1, which it ranks again (a tie that
    topk orders either way)."""
    from smart_marl.rollout.sampling import _first_k, sample_tokens

    g = torch.Generator().manual_seed(levels)
    m, v, k = 400, 120, 6
    logits = torch.randint(0, levels, (m, v), generator=g).float() if levels < 1000 else torch.randn(m, v, generator=g)
    logits[:20, 4:] = float("-inf")  # fewer tokens than k + 1
    exclude = torch.rand(m, v, generator=g) < 0.3
    exclude[torch.arange(m), logits.argmax(-1)] = False  # every row keeps a token
    top = torch.topk(logits, k + 1, dim=-1)
    for ex in (None, exclude):
        want = sample_tokens(logits, torch.Generator().manual_seed(5), k, exclude=ex)
        got = sample_tokens(logits, torch.Generator().manual_seed(5), k, exclude=ex, top=(top.values, top.indices))
        assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    vals, idx = _first_k(logits, (top.values, top.indices), k)
    ranked = torch.topk(logits, k, dim=-1)
    assert torch.equal(vals, ranked.values) and torch.equal(idx, ranked.indices)
    if levels < 1000:  # the check notices a shared ranking read without ranking the tied rows again
        assert not torch.equal(top.indices[:, :k], ranked.indices)


def test_a_refill_of_some_rows_recomputes_their_search_blocks_alone():
    """The road's search blocks (offroad's segment blocks, the observations' road-point blocks) are kept
    through a refill that writes rows in place: the refilled rows are recomputed, the values stay the same
    tensors, and they equal the blocks computed afresh. A refill that grows the padding drops them (they
    are computed whole at the next search)."""
    from envs._observation import ROAD_BLOCK, nearest_road_points
    from envs._scene import scene_static
    from envs._scene_batch import SceneBatch
    from envs._setup import load_scenes
    from smart_marl.geometry_torch import SEGMENT_BLOCK, block_bounds

    statics = [scene_static(s) for s in load_scenes("embedded")]  # 3849, 3863, 5547, 2212 road points
    batch = SceneBatch.build([statics[2], statics[0], statics[1]])
    xy = torch.zeros(3, 2, 2)

    def fresh():
        seg = block_bounds(torch.stack([batch.edges.start[..., :2], batch.edges.end[..., :2]], 2), batch.edges.valid, SEGMENT_BLOCK)
        return seg, block_bounds(batch.road_xy[:, :, None], batch.road_valid, ROAD_BLOCK)

    seg = batch.edges.blocks(SEGMENT_BLOCK)
    nearest_road_points(batch, xy, 32)
    road = batch.__dict__["_road_blocks"].values
    row_before = [t[1].clone() for t in (*seg, *road)]
    batch.write([1], [statics[3]])  # a smaller scene: written in place
    assert batch.edges.__dict__["_blocks"].values is seg and batch.__dict__["_road_blocks"].values is road  # kept, not dropped
    assert all(not torch.equal(t[1], b) for t, b in zip((*seg, *road), row_before))  # row 1 recomputed
    want_seg, want_road = fresh()
    for got, want in zip((*batch.edges.blocks(SEGMENT_BLOCK), *road), (*want_seg, *want_road)):
        assert torch.equal(got, want)
    nearest_road_points(batch, xy, 32)
    assert batch.__dict__["_road_blocks"].values is road  # still current: no whole recompute
    batch2 = SceneBatch.build([statics[3], statics[0]])
    before = batch2.edges.blocks(SEGMENT_BLOCK)
    batch2.write([0], [statics[2]])  # a larger scene: the padding grows, the kept blocks are dropped
    after = batch2.edges.blocks(SEGMENT_BLOCK)
    assert after is not before and after[0].shape[1] > before[0].shape[1]
    want = block_bounds(torch.stack([batch2.edges.start[..., :2], batch2.edges.end[..., :2]], 2), batch2.edges.valid, SEGMENT_BLOCK)
    assert all(torch.equal(a, w) for a, w in zip(after, want))


def test_any_rows_read_as_bytes_is_any():
    from smart_marl.rollout.sampling import any_rows

    g = torch.Generator().manual_seed(0)
    for shape in [(5, 0), (0, 5), (3, 7), (300, 1024), (2, 3, 4)]:
        mask = torch.rand(shape, generator=g) < 0.01
        assert torch.equal(any_rows(mask), mask.any(-1)), shape
    strided = (torch.rand(10, 40, generator=g) < 0.05)[:, ::3]
    assert torch.equal(any_rows(strided), strided.any(-1))


def test_the_sampler_s_log_probabilities_of_the_forced_rows_only_are_those_of_every_row():
    from smart_marl.rollout.sampling import sample_tokens

    g = torch.Generator().manual_seed(0)
    logits = torch.randn(300, 64, generator=g)
    logits[:40, 32:] = float("-inf")
    forced = torch.full((300,), -1, dtype=torch.long)
    forced[::7] = torch.randint(0, 32, (len(forced[::7]),), generator=g)
    for temperature in (1.0, 0.7):
        tok_all, lp_all = sample_tokens(logits, torch.Generator().manual_seed(1), 6, temperature, forced)
        tok, lp = sample_tokens(logits, torch.Generator().manual_seed(1), 6, temperature, forced, log_probs_of="forced")
        assert torch.equal(tok, tok_all)
        assert torch.equal(lp[forced >= 0], lp_all[forced >= 0]) and not lp[forced < 0].any() and lp_all[forced < 0].ne(0).all()
    assert not sample_tokens(logits, torch.Generator().manual_seed(1), 6, log_probs_of="forced")[1].any()  # nothing forced
    gen = torch.Generator().manual_seed(1)
    with pytest.raises(ValueError, match="log_probs_of"):
        sample_tokens(logits, gen, 6, log_probs_of="some")
    assert torch.equal(gen.get_state(), torch.Generator().manual_seed(1).get_state())  # the refused call drew nothing
