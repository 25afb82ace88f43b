"""Rollout stage, collision-aware sampling: the tokens an agent may not draw because they would put
its box into another agent's box.

What comes in: every slot's current pose and where its last token started ``[G, N, 3]`` (local
frame), box sizes, which slots are present, which rows sample, their logits ``[M, V]`` and every
type's token poses. What goes out: ``bool [M, V]``, true on the tokens to exclude from sampling.

The rule, per sampling agent ``i`` (a vehicle, pedestrian or cyclist whose token is drawn, not
forced): a token is excluded when, on any of the token's five 10 Hz frames (drawn as the rollout
draws them, :mod:`~smart_marl.rollout.frames`), the agent's box overlaps the box of one of its
``NEIGHBOURS`` nearest present agents ``j`` on the same frame, ``j`` moving at constant velocity
(its last token's displacement repeated, heading held), or, where ``j``'s token of this step is
forced (a policy's controlled agent, a scripted what-if agent), on the frames that token really
takes it to (``known_frames``); a ``j`` whose token comes later (a controlled agent acting with the step, drawn
ahead of) also standing where it is (:func:`standing_test`, given by the caller as a second test). Pairs whose boxes
overlap already at the
current poses are left alone: pedestrians walking in a group, or boxes that overlap in the log,
keep doing what the model says. Tokens are checked most likely first until ``k`` are free, so excluding them and then
sampling the top ``k`` is the same as top-k sampling from the distribution with every colliding token
removed, with one bound: an agent that has found some but fewer than ``k`` free tokens among its
``SEARCH_DEPTH`` most likely draws from those (the search goes on only for an agent with none free there).
An agent whose every token collides is not restricted.

Boxes are exact oriented rectangles (separating axes); the realism metrics' rounded corners make
their boxes a little smaller, so a token excluded here may not have collided there. Agents of type
OTHER (moved at constant velocity outside the model) are not checked against.

Why: the prior was trained on SUMO traffic, where pedestrians and vehicles rarely meet, and in
closed loop on real scenes it walks pedestrians into cars and lets followers close in on a slower
leader. On the 7 held-out real scenes (docs/model_card.md) this rule raises the collision
likelihood of WOSAC's metrics from 0.887 to 0.98 without retraining. It changes what is drawn, not
the model: the logits, the log-probabilities a step reports and the KL reference of fine-tuning
stay the model's own.
"""

from __future__ import annotations

from typing import Callable

import torch

from ..geometry_torch import RoadEdgeTensors, bound_length, boxes_off_road, boxes_overlap, loose
from ..tokens import FRAMES_PER_TOKEN
from .frames import compose_torch, token_frames
from .sampling import any_rows

NEIGHBOURS = 16
"""How many nearest agents (by distance to where they will be) each sampling agent is checked against."""

SORTED_DEPTH = 64
"""How many of each row's most likely tokens are ranked up front when the search may go through the whole
vocabulary (``top_k <= 0``; the rest only for the rare row that gets that deep)."""

SEARCH_DEPTH = 128
"""How far down its most likely tokens a top-k row with some free token is searched. At 32 real scenes
(the batched env, 1,200 sampling rows a step) about 10 rows a step had fewer than 6 free tokens among their
first 128, most of them one to five, and the search went on through up to the whole vocabulary to fill their
6 with tokens the model all but rules out: 30% of its time. Those rows now draw from the free tokens they
have; the 3 rows a step with none free among the first 128 are searched on as before (realism on the 7 real
scenes, 4 seeds: the same, 0.7279 both ways)."""

CHUNK_GROWTH = 4
"""How many times more tokens each round of the search checks than the round before. A round costs
about a millisecond whatever its size (some forty tensor operations) on top of about a microsecond a
token; the rows that go on past the first round are few, so fewer, larger rounds cost less: at 32
real scenes a step's search fell from 8 rounds to 5 and from about 34 to 29 ms going from 2 to 4.
Checking more tokens than needed changes nothing drawn: the extra ones rank below the ``want``-th
token that passed, and sampling takes the top ``k`` of what is left (where a logit ties with that
token's, a blocked twin that smaller rounds left unchecked is now excluded too)."""


def boxes_overlap_near(a_xy: torch.Tensor, a_heading: torch.Tensor, a_half: torch.Tensor, b_xy: torch.Tensor,
                       b_heading: torch.Tensor, b_half: torch.Tensor, where: torch.Tensor | None = None,
                       apart: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`boxes_overlap` (same arguments, broadcast) on the pairs ``where`` says (all by default,
    false elsewhere), with the exact test run only where the centres are closer than the two half
    diagonals together (elsewhere the boxes cannot overlap). ``apart``: the centres' distance
    ``(b_xy - a_xy).norm(dim=-1)`` where the caller has it already."""
    if apart is None:
        apart = (b_xy - a_xy).norm(dim=-1)
    close = apart < a_half.norm(dim=-1) + b_half.norm(dim=-1)  # radii on the unbroadcast inputs
    if where is not None:
        close = close & where
    shape = close.shape
    a_xy, b_xy = a_xy.expand(shape + (2,)), b_xy.expand(shape + (2,))
    a_heading, b_heading = a_heading.expand(shape), b_heading.expand(shape)
    a_half, b_half = a_half.expand(shape + (2,)), b_half.expand(shape + (2,))
    at = close.nonzero(as_tuple=True)
    out = torch.zeros(shape, dtype=torch.bool, device=a_xy.device)
    out[at] = boxes_overlap(a_xy[at], a_heading[at], a_half[at], b_xy[at], b_heading[at], b_half[at])
    return out


def frames_collide(frames: torch.Tensor, own_xy: torch.Tensor, own_half: torch.Tensor, other_xy: torch.Tensor,
                   other_cos: torch.Tensor, other_sin: torch.Tensor, other_half: torch.Tensor, other_gap: torch.Tensor,
                   other_ok: torch.Tensor) -> torch.Tensor:
    """bool [R, c]: does a box of half size ``own_half`` [R, 2] on frames ``frames`` [R, c, F, 3] (c
    candidate paths per row, e.g. tokens, that start at ``own_xy`` [R, 2]) overlap, on the same frame,
    one of ``K`` others: centres ``other_xy`` [R, K, F, 2], the cosine and sine of their headings
    ``other_cos`` / ``other_sin`` [R, K, F or 1], half sizes ``other_half`` [R, K, 2], where
    ``other_ok`` [R, K]. The same as :func:`boxes_overlap_near` on every (path, frame, other), run
    only on the (path, other) pairs that can come close: ``other_gap`` [R, K] is a lower bound of the
    other's distance to ``own_xy`` on every frame (its distance now less how far it travels), and a
    path that stays within ``e`` of ``own_xy`` cannot reach an other whose gap is ``e`` plus the two
    half diagonals or more. The pairs' operands are gathered as whole rows of flattened views (one
    index each, not an index per dimension): the same values, a fraction of the indexing time."""
    r, c, f = frames.shape[:3]
    k, fo = other_xy.shape[1], other_cos.shape[2]
    own_r, other_r = bound_length(own_half), bound_length(other_half)  # [R], [R, K] half diagonals
    extent = bound_length(frames[..., :2] - own_xy[:, None, None]).amax(-1)  # [R, c] farthest the path gets
    reach = extent[..., None] + (own_r[:, None] + other_r)[:, None]  # [R, c, K]
    can = other_ok[:, None] & (other_gap[:, None] < loose(reach))  # margin for rounding: only more pairs
    pi, pc, pk = can.nonzero(as_tuple=True)  # [P] the (row, path, other) pairs to test on every frame
    path, other = pi * c + pc, pi * k + pk  # the pairs' rows of frames [R * c, F, 3] and of the others [R * K, ...]
    own_frames = frames.reshape(r * c, f, 3).index_select(0, path)  # [P, F, 3]
    d = other_xy.reshape(r * k, f, 2).index_select(0, other) - own_frames[..., :2]  # [P, F, 2]
    # the exact test where the centres are closer than the two half diagonals (:func:`boxes_overlap_near`)
    close = bound_length(d) < loose(own_r.index_select(0, pi) + other_r.reshape(-1).index_select(0, other))[:, None]  # [P, F]
    p, fr = close.nonzero(as_tuple=True)  # [Q] the (pair, frame) to test exactly
    q = p * f + fr  # flat
    heading = own_frames.reshape(-1, 3).index_select(0, q)[:, 2]
    row, at = pi.index_select(0, p), other.index_select(0, p)
    slot = at * fo + fr.clamp(max=fo - 1)  # the other's heading on that frame (or its one heading)
    hit = _overlap_sat(d.reshape(-1, 2).index_select(0, q), heading.cos(), heading.sin(), own_half.index_select(0, row),
                       other_cos.reshape(-1).index_select(0, slot), other_sin.reshape(-1).index_select(0, slot),
                       other_half.reshape(-1, 2).index_select(0, at))
    out = torch.zeros(r * c, dtype=torch.bool, device=frames.device)
    out[path.index_select(0, p)[hit]] = True
    return out.view(r, c)


def _overlap_sat(d: torch.Tensor, ca: torch.Tensor, sa: torch.Tensor, a_half: torch.Tensor, cb: torch.Tensor, sb: torch.Tensor,
                 b_half: torch.Tensor) -> torch.Tensor:
    """:func:`~smart_marl.geometry_torch.boxes_overlap_rotated`, bit for bit, with fewer operations: of
    the eight direction products its four axes read, two are a box's own and the others are, up to sign
    and the order of commutative terms (exact in floating point), ``ca * cb + sa * sb`` and
    ``sa * cb - ca * sb``; each is computed once. A box's own products on its own axes are
    ``ca * ca + sa * sa`` (exactly so: ``ca * ca - (-sa) * sa`` is the same sum) and ``sa * ca - ca * sa``,
    which is exactly 0 (one product subtracted from itself), so its term drops out (half sizes are
    finite)."""
    a0, a1, b0, b1 = a_half[..., 0], a_half[..., 1], b_half[..., 0], b_half[..., 1]
    p1 = (ca * cb + sa * sb).abs()
    p2 = (sa * cb - ca * sb).abs()
    nsa, nsb = -sa, -sb
    unit_a, unit_b = ca * ca + sa * sa, cb * cb + sb * sb  # each box's own axis, projected on itself
    own_a1, own_a2 = a0 * unit_a, a1 * unit_a  # axes (ca, sa) and (-sa, ca)
    own_b3, own_b4 = b0 * unit_b, b1 * unit_b  # axes (cb, sb) and (-sb, cb)
    dx, dy = d[..., 0], d[..., 1]
    hit = (dx * ca + dy * sa).abs() < own_a1 + (b0 * p1 + b1 * p2)
    hit &= (dx * nsa + dy * ca).abs() < own_a2 + (b0 * p2 + b1 * p1)
    hit &= (dx * cb + dy * sb).abs() < (a0 * p1 + a1 * p2) + own_b3
    hit &= (dx * nsb + dy * cb).abs() < (a0 * p2 + a1 * p1) + own_b4
    return hit


def constant_velocity_pose(pose: torch.Tensor, previous_pose: torch.Tensor) -> torch.Tensor:
    """[..., 3] where each agent will be one token later if it repeats its last token's displacement
    (heading held); an agent with no previous pose (NaN) stays where it is."""
    prev = torch.where(torch.isnan(previous_pose), pose, previous_pose)
    return torch.cat([2 * pose[..., :2] - prev[..., :2], pose[..., 2:]], -1)


def off_road_test(edges: RoadEdgeTensors, scene: torch.Tensor, pose: torch.Tensor, token_ends: torch.Tensor, size: torch.Tensor,
                  z: torch.Tensor, applies: torch.Tensor) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """An ``also`` of :func:`excluded_tokens` for its M rows, in scenes ``scene`` [M] (ascending) of ``edges``, at
    ``pose`` [M, 3], their type's token ends ``token_ends`` [M, V, 3] in their own frame, boxes ``size`` [M, 3]
    at height ``z`` [M]: ``test(r [R], tokens [R, c]) -> bool [R, c]``, a token that ends with a bottom corner of
    the row's box beyond a road edge (:func:`~smart_marl.geometry_torch.boxes_off_road`, the offroad event's test),
    for the rows where ``applies`` [M] (the shield's vehicles, the vehicles on the road now)."""
    def test(r: torch.Tensor, tok: torch.Tensor) -> torch.Tensor:
        end = compose_torch(pose[r][:, None], token_ends[r].gather(1, tok[..., None].expand(-1, -1, 3)))  # [R, c, 3]
        return applies[r][:, None] & boxes_off_road(edges, scene[r], end[..., :2], end[..., 2], size[r], z[r])
    return test


def standing_test(own_pose: torch.Tensor, own_half: torch.Tensor, other_pose: torch.Tensor, other_half: torch.Tensor,
                  ok: torch.Tensor) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """For M rows at ``own_pose`` [M, 3] with half sizes ``own_half`` [M, 2], each with K others standing at
    ``other_pose`` [M, K, 3] with half sizes ``other_half`` [M, K, 2] where ``ok`` [M, K]: ``test(r [R], frames
    [R, c, F, 3]) -> bool [R, c]``, a path of row ``r`` whose box overlaps one of those others, standing where it is,
    on any frame (exact rectangles). A pair overlapping already is left alone, as in the main rule. What the others do
    at the step is not known (a controlled agent, whose token comes with the policy's): with the main rule's
    constant-velocity check, a path is kept clear of them both ways, whether they drive on or stop."""
    ok = ok & ~boxes_overlap(own_pose[:, None, :2], own_pose[:, None, 2], own_half[:, None], other_pose[..., :2],
                             other_pose[..., 2], other_half)

    def test(r: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        hit = boxes_overlap(frames[:, :, None, :, :2], frames[:, :, None, :, 2], own_half[r][:, None, None, None],
                            other_pose[r][:, None, :, None, :2], other_pose[r][:, None, :, None, 2],
                            other_half[r][:, None, :, None])  # [R, c, K, F]
        return (hit.any(-1) & ok[r][:, None]).any(-1)
    return test


def excluded_tokens(logits: torch.Tensor, rows: torch.Tensor, pose: torch.Tensor, previous_pose: torch.Tensor,
                    size: torch.Tensor, present: torch.Tensor, agent_type: torch.Tensor, token_poses: torch.Tensor,
                    top_k: int, interpolation: str = "spline", known_frames: torch.Tensor | None = None,
                    known: torch.Tensor | None = None,
                    also: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
                    top: tuple[torch.Tensor, torch.Tensor] | None = None,
                    vocab_sizes: torch.Tensor | None = None, depth: int | None = SEARCH_DEPTH) -> torch.Tensor:
    """bool [M, V]: the tokens that sampling rows ``rows`` [M] (flat indices into the G x N slots)
    must not draw (module docstring).

    ``logits`` [M, V] of those rows (``-inf`` beyond a type's vocabulary), ``pose`` /
    ``previous_pose`` [G, N, 3], ``size`` [G, N, >= 2] length and width, ``present`` [G, N] the slots
    that are on the road this step (they block others), ``agent_type`` [G, N], ``token_poses``
    [types, V, 6, 3] every token's poses in its start frame, ``top_k`` the sampler's k (<= 0: the
    whole vocabulary is checked), ``interpolation`` how the token's frames are drawn
    (:func:`~smart_marl.rollout.frames.token_frames`). ``known_frames`` [G, N, 5, 3] and ``known`` [G, N]: the
    slots whose frames of this step are known before the draw (their token is forced: a policy's or a
    script's), checked against where they will really be instead of at constant velocity. ``also``: a
    second test ``also(rows [R], tokens [R, c]) -> bool [R, c]`` (rows: indices into ``rows``) whose
    tokens are excluded too, in the same search (every row is checked; the shield of :mod:`envs._shield`
    adds leaving the road). ``top``: ``torch.topk(logits, top_k + 1)`` where the caller has it (the
    engine ranks once for this and for the sampler). ``vocab_sizes`` [types]: each type's vocabulary
    size, where the caller knows that ``logits`` are finite on it (a model's next-token logits:
    :meth:`~smart_marl.model.SMART.next_token_logits`); the finite tokens are counted otherwise. ``depth``:
    with ``top_k > 0``, how far down a row's most likely tokens the search goes while it has found a free one
    (at least ``top_k``; None: the whole vocabulary): a row with some but fewer than ``top_k`` free among them
    has every other token excluded, a row with none is searched on."""
    n = pose.shape[1]
    m, v = logits.shape
    out = torch.zeros(m, v, dtype=torch.bool, device=logits.device)
    if m == 0 or (n < 2 and also is None):
        return out
    half = size[..., :2].to(pose.dtype) / 2
    ahead = constant_velocity_pose(pose, previous_pose)
    travel = bound_length((ahead - pose)[..., :2])  # [G, N] how far each agent gets from its pose during the step
    if known is not None:
        known_frames = known_frames.to(pose.dtype)
        ahead = torch.where(known[..., None], known_frames[:, :, -1], ahead)
        travel = torch.where(known, bound_length(known_frames[..., :2] - pose[:, :, None, :2]).amax(-1), travel)
    # 1. the rows that need checking: those whose first tokens (the top k) can reach another agent; the
    # others draw their top k whatever is excluded further down, so nothing of theirs is
    gi, si = rows // n, rows % n
    head, tied = _top_set(logits, v if top_k is None or top_k <= 0 else min(int(top_k), v), top)  # [M, k] each row's first tokens
    first = head.clone()
    if bool(tied.any()):  # topk's own pick where a tie crosses the k-th token
        first[tied] = torch.topk(logits[tied], head.shape[1], dim=-1).indices
    reach = token_reach(token_poses)[agent_type[gi, si][:, None], first].amax(-1)  # [M] farthest a first token goes
    radius = bound_length(half)  # [G, N] half diagonals
    own_xy, own_r = pose[gi, si, :2], radius[gi, si]
    # the rows' groups gathered whole with index_select (indexing a strided view such as pose[..., :2] with a
    # tensor is some 30x slower on the CPU)
    apart = bound_length(pose[..., :2].contiguous().index_select(0, gi) - own_xy[:, None])  # [M, N] how far apart they are now
    gap = apart - travel.index_select(0, gi)  # [M, N] nearest they come
    there, other_r = present.index_select(0, gi), radius.index_select(0, gi)  # [M, N]
    maybe = there & (gap < loose(reach[:, None] + own_r[:, None] + other_r))
    maybe[torch.arange(m, device=rows.device), si] = False
    sub = (any_rows(maybe) | (also is not None)).nonzero().squeeze(1)
    if not len(sub):
        return out
    logits, rows, gi, si, head, tied, apart, gap, there, other_r, own_r = (
        t.index_select(0, sub) for t in (logits, rows, gi, si, head, tied, apart, gap, there, other_r, own_r))
    m = len(sub)
    # 2. each such row's NEIGHBOURS nearest present others, not overlapping it now (the exact box test
    # where the centres are closer than the two half diagonals, as :func:`boxes_overlap_near`)
    own_pose, own_before, own_half, own_type = pose[gi, si], previous_pose[gi, si], half[gi, si], agent_type[gi, si]
    dist = (ahead[..., :2].contiguous().index_select(0, gi) - own_pose[:, None, :2]).norm(dim=-1)  # [M, N]
    cr, cj = (there & (apart < loose(own_r[:, None] + other_r))).nonzero(as_tuple=True)
    blocked_now = torch.zeros_like(there)
    if len(cr):
        cg = gi[cr]
        blocked_now[cr, cj] = boxes_overlap(own_pose[cr, :2], own_pose[cr, 2], own_half[cr], pose[cg, cj, :2], pose[cg, cj, 2],
                                            half[cg, cj])
    usable = there & ~blocked_now
    usable[torch.arange(m, device=rows.device), si] = False
    near_d, near = torch.topk(dist.masked_fill(~usable, float("inf")), min(NEIGHBOURS, n - 1), dim=-1, largest=False)
    near_ok = torch.isfinite(near_d)  # [M, K]
    # the neighbours on the token's 5 frames, at constant velocity with the heading held (forced ones on
    # their own frames): [M, K, 5, 2] and the cosines and sines of their headings [M, K, 1 or 5]
    slot = (gi[:, None] * n + near).reshape(-1)

    def at_near(t: torch.Tensor) -> torch.Tensor:
        """[M, K, ...] the neighbours' entries of ``t`` [G, N, ...] (one flat index: a fast gather)."""
        return t.reshape(-1, *t.shape[2:]).index_select(0, slot).view(*near.shape, *t.shape[2:])

    other_xy, other_cos, other_sin, other_half = (at_near(t) for t in (*_slot_frames(pose, ahead, known, known_frames), half))
    other_gap = gap.gather(1, near)  # [M, K] how near each neighbour can come during the step (the bound of ``collides``)
    collides = _collision_test(token_poses, interpolation, (own_type, own_pose, own_before, own_half),
                               (other_xy, other_cos, other_sin, other_half, other_gap, near_ok), also, sub)
    # [M] tokens of the row's type (isfinite as two comparisons: 3x faster on the CPU)
    finite = (vocab_sizes.to(own_type.device).index_select(0, own_type) if vocab_sizes is not None
              else ((logits > float("-inf")) & (logits < float("inf"))).sum(-1))
    want = finite if top_k is None or top_k <= 0 else finite.clamp(max=int(top_k))
    todo = near_ok.any(-1) | (also is not None)
    limit = None if depth is None or top_k is None or top_k <= 0 else max(int(depth), int(top_k))
    out[sub] = _exclude_in_order(logits, finite, want, todo, collides, (head, tied), limit)
    return out


def _collision_test(token_poses: torch.Tensor, interpolation: str, own: tuple[torch.Tensor, ...], others: tuple[torch.Tensor, ...],
                    also: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None,
                    sub: torch.Tensor) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """The ``test`` of :func:`_exclude_in_order` for :func:`excluded_tokens`' rows: ``own`` = their type, pose, the
    pose their last token started at and half size [M, ...]; ``others`` = their neighbours' centres on the step's
    frames, the cosines and sines of their headings, half sizes, gaps and validity [M, K, ...]
    (:func:`frames_collide`); ``also`` the second test, called with the rows' indices ``sub`` [M] in the caller's."""
    types, v_max = token_poses.shape[:2]
    flat_poses = token_poses.reshape(types * v_max, *token_poses.shape[2:])
    own_type, own_pose, own_before, own_half = own

    def collides(r: torch.Tensor, tok: torch.Tensor) -> torch.Tensor:
        """[R, c]: does token ``tok`` [R, c] of rows ``r`` [R] overlap a neighbour on any of its frames."""
        at = lambda t: t.index_select(0, r)  # noqa: E731  the rows' entries (index_select: a fast gather)
        local = flat_poses.index_select(0, (at(own_type)[:, None] * v_max + tok).reshape(-1)).view(*tok.shape, *flat_poses.shape[1:])
        # the row's pose broadcast, not expanded: what depends on it alone is computed once a row
        pose_r = at(own_pose)
        frames = token_frames(local, pose_r[:, None], at(own_before)[:, None], interpolation)  # [R, c, 5, 3]
        hit = frames_collide(frames, pose_r[:, :2], at(own_half), *(at(t) for t in others))
        return hit if also is None else hit | also(sub[r], tok)
    return collides


def _slot_frames(pose: torch.Tensor, ahead: torch.Tensor, known: torch.Tensor | None,
                 known_frames: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every slot's centres on the step's 5 frames [G, N, 5, 2] and the cosine and sine of its heading
    [G, N, 1 or 5]: from ``pose`` to ``ahead`` [G, N, 3] at constant velocity, the heading held, or where
    ``known`` [G, N], the frames ``known_frames`` [G, N, 5, 3] (built per slot, fewer than the rows'
    neighbours, then gathered once)."""
    s = torch.arange(1, FRAMES_PER_TOKEN + 1, dtype=pose.dtype, device=pose.device) / FRAMES_PER_TOKEN
    xy = pose[:, :, None, :2] + s[:, None] * (ahead - pose)[:, :, None, :2]
    cos, sin = pose[..., 2].cos()[..., None], pose[..., 2].sin()[..., None]
    if known is not None:
        xy = torch.where(known[..., None, None], known_frames[..., :2], xy)
        cos = torch.where(known[..., None], known_frames[..., 2].cos(), cos)
        sin = torch.where(known[..., None], known_frames[..., 2].sin(), sin)
    return xy, cos, sin


def token_reach(token_poses: torch.Tensor) -> torch.Tensor:
    """[types, V] how far from its start any of a token's 10 Hz frames can be (m), with either
    interpolation: the contour's own poses, or the spline's, which stays within 1.42 times the end's
    distance (its start tangent is capped at ``frames.MAX_LEAD`` times the chord: 4/27 * 2.8 + 1); 1.5
    times it here."""
    xy = token_poses[..., 1:, :2].norm(dim=-1)  # [types, V, 5]
    return torch.maximum(xy.amax(-1), 1.5 * xy[..., -1])


def _top_set(logits: torch.Tensor, k: int, top: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """([M, k] long, [M] bool): each row's ``k`` most likely tokens of ``logits`` [M, V], read off the
    top ``k + 1`` (``top``: ``torch.topk(logits, k + 1)`` where the caller has it), and the rows where
    the k-th is not strictly more likely than the next (a tie, or k = V). On the other rows these are,
    as a set, what any ranking's first ``k`` are (``torch.topk`` with any k >= ``k``, a sort): no tie
    can swap a token in or out."""
    m, v = logits.shape
    if k >= v:
        return torch.topk(logits, v, dim=-1).indices, torch.ones(m, dtype=torch.bool, device=logits.device)
    vals, idx = torch.topk(logits, k + 1, dim=-1) if top is None else top
    return idx[:, :k], ~(vals[:, k - 1] > vals[:, k])


def _exclude_in_order(logits: torch.Tensor, finite: torch.Tensor, want: torch.Tensor, todo: torch.Tensor,
                      test: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                      head: tuple[torch.Tensor, torch.Tensor] | None = None, limit: int | None = None) -> torch.Tensor:
    """bool [M, V]: tokens ``test(rows [R], tokens [R, c]) -> bool [R, c]`` rejects, checked most
    likely first (by ``logits`` [M, V], ``torch.topk``'s ranking of the first ``SORTED_DEPTH``, or of the
    first ``limit``) in chunks (``want`` tokens, then :data:`CHUNK_GROWTH` times as many each round) until
    ``want`` [M] have passed or the row's ``finite`` [M] tokens are exhausted; rows not in ``todo`` [M] are
    not checked, and a row whose every token is rejected is left alone (nothing excluded; read off the
    count of passed tokens, not a sum over [M, V]). ``limit``: a row with fewer than ``want`` but some
    passed among its first ``limit`` stops there, every token past them excluded (a row with none goes
    on). ``head``: the :func:`_top_set` of ``logits`` if known; where it is not tied and has the first chunk's
    size, the first chunk is read off it, and only the rows that go on are ranked further (most rows stop there)."""
    m, v = logits.shape
    excluded = torch.zeros(m, v, dtype=torch.bool, device=logits.device)
    passed = torch.zeros(m, dtype=torch.long, device=logits.device)
    checked, todo = todo, todo.clone()
    start, chunk = 0, max(int(want.max()) if m else 1, 1)
    lim = v if limit is None else min(int(limit), v)
    depth = min(SORTED_DEPTH, v) if limit is None else lim  # ranked up front
    if head is None or head[0].shape[1] != chunk or chunk >= depth:
        head = _top_set(logits, chunk) if chunk < depth else None
    if head is None:
        order, ranked = torch.topk(logits, depth, dim=-1).indices, torch.ones(m, dtype=torch.bool, device=logits.device)
    else:  # [M, D] most likely first: the first chunk of every row, the rest of the tied ones
        order, ranked = torch.zeros(m, depth, dtype=torch.long, device=logits.device), head[1].clone()
        order[:, :chunk] = head[0]
        if bool(ranked.any()):
            order[ranked] = torch.topk(logits[ranked], depth, dim=-1).indices
    while todo.any() and start < v:
        r = todo.nonzero().squeeze(1)
        if 0 < start < lim < v and start + chunk * (1 + CHUNK_GROWTH) > lim:
            chunk = lim - start  # the last round takes the rest of the limit (no round of a few tokens after it)
        if start + chunk > order.shape[1] and order.shape[1] < v:
            # deeper than ranked so far: rank everything and check these rows again from the top
            # (the full ranking may order tied logits differently)
            order = torch.empty(m, v, dtype=torch.long, device=logits.device)  # rows done by now are not read again
            order[r] = torch.sort(logits[r], dim=-1, descending=True, stable=True).indices
            excluded[r], passed[r], start = False, 0, 0
            ranked[:] = True
            if lim < v:  # past the limit (rows with nothing free in it, a few): the whole vocabulary in one round
                chunk = v
        elif start > 0 and not bool(ranked[r].all()):  # past the first chunk: topk's ranking (its first chunk is the same set)
            late = r[~ranked[r]]
            order[late] = torch.topk(logits[late], depth, dim=-1).indices
            ranked[late] = True
        tok = order[r, start:start + chunk]  # [R, c]
        in_vocab = torch.arange(start, start + tok.shape[1], device=tok.device)[None] < finite[r, None]
        hit = test(r, tok) & in_vocab
        excluded[r[:, None], tok] = hit
        passed[r] += (in_vocab & ~hit).sum(-1)
        start += tok.shape[1]
        chunk *= CHUNK_GROWTH
        todo[r] = (passed[r] < want[r]) & (start < finite[r])
        if start == lim < v:  # at the limit: a row with some passed draws from those alone, one with none goes on
            short = r[todo[r] & (passed[r] > 0)]
            if len(short):
                first = order[short, :lim]
                excluded[short] = torch.ones(len(short), v, dtype=torch.bool, device=logits.device).scatter_(
                    1, first, excluded[short].gather(1, first))
                todo[short] = False
    alone = (checked & (passed == 0)).nonzero().squeeze(1)  # every token of the row rejected (or none to check)
    if len(alone):
        excluded.index_fill_(0, alone, False)
    return excluded
