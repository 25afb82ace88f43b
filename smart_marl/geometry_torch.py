"""Planar geometry of agent boxes and road edges on torch tensors, batched over scenes: the tensor
twin of :mod:`smart_marl.geometry` for the stages that run on a device (the batched environment's
events, collision-aware sampling). Pure functions of tensors; leading dimensions broadcast; the
dtype is the inputs' (float32 on a GPU is enough in a scene's local frame, where coordinates are
within a few hundred metres).

The definitions are :mod:`smart_marl.geometry`'s, and ``tests/test_geometry_torch.py`` checks them
against it: the rounded-corner box overlap of the sim-agents metrics (:func:`rounded_boxes_overlap`,
``geometry.boxes_overlap``) and the signed distance to road edges with the official nearest-segment
and side rules (:func:`signed_distance_to_road_edges`, ``geometry.signed_distance_to_road_edges``).
Road edges of several scenes are padded to one segment count (:class:`RoadEdgeTensors`).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, fields
from typing import Callable, NamedTuple, Sequence

import torch

from .geometry import CORNER_ROUNDING_FACTOR, Z_STRETCH, RoadEdgeSegments
from .road_map import MapFeatureType

_SIGN_L = (1.0, -1.0, -1.0, 1.0)  # front-left, rear-left, rear-right, front-right (counter-clockwise)
_SIGN_W = (1.0, 1.0, -1.0, -1.0)


# ------------------------------------------------------------------------------------ boxes
def box_corners(xy: torch.Tensor, heading: torch.Tensor, length: torch.Tensor, width: torch.Tensor) -> torch.Tensor:
    """Corners [..., 4, 2] of oriented boxes (centre ``xy`` [..., 2], ``heading``, ``length``, ``width``
    [...]), counter-clockwise from the front-left, as :func:`smart_marl.geometry.box_corners`."""
    sl = torch.tensor(_SIGN_L, dtype=xy.dtype, device=xy.device)
    sw = torch.tensor(_SIGN_W, dtype=xy.dtype, device=xy.device)
    c, s = heading.cos()[..., None], heading.sin()[..., None]
    dl, dw = (length * 0.5)[..., None] * sl, (width * 0.5)[..., None] * sw  # [..., 4]
    return torch.stack([xy[..., None, 0] + c * dl - s * dw, xy[..., None, 1] + s * dl + c * dw], -1)


def boxes_overlap(a_xy: torch.Tensor, a_heading: torch.Tensor, a_half: torch.Tensor, b_xy: torch.Tensor,
                  b_heading: torch.Tensor, b_half: torch.Tensor) -> torch.Tensor:
    """bool [...]: do oriented boxes ``a`` and ``b`` overlap (separating axis theorem; touching is
    not overlapping). ``xy`` [..., 2], ``heading`` [...], ``half`` [..., 2] half length and half
    width; all broadcast."""
    return boxes_overlap_rotated(b_xy - a_xy, a_heading.cos(), a_heading.sin(), a_half, b_heading.cos(), b_heading.sin(), b_half)


def boxes_overlap_rotated(d: torch.Tensor, a_cos: torch.Tensor, a_sin: torch.Tensor, a_half: torch.Tensor, b_cos: torch.Tensor,
                          b_sin: torch.Tensor, b_half: torch.Tensor) -> torch.Tensor:
    """:func:`boxes_overlap` of boxes given by the offset ``d`` [..., 2] from ``a``'s centre to ``b``'s,
    the cosine and sine of their headings [...] and their half sizes [..., 2] (for callers that test
    one box against many: its cosine and sine computed once)."""
    ca, sa, cb, sb = a_cos, a_sin, b_cos, b_sin
    hit = None
    for ux, uy in ((ca, sa), (-sa, ca), (cb, sb), (-sb, cb)):  # the four edge normals
        ext_a = a_half[..., 0] * (ux * ca + uy * sa).abs() + a_half[..., 1] * (uy * ca - ux * sa).abs()
        ext_b = b_half[..., 0] * (ux * cb + uy * sb).abs() + b_half[..., 1] * (uy * cb - ux * sb).abs()
        sep = (d[..., 0] * ux + d[..., 1] * uy).abs() < ext_a + ext_b
        hit = sep if hit is None else hit & sep
    return hit


def bound_length(v: torch.Tensor) -> torch.Tensor:
    """[...] the length of 2D vectors ``v`` [..., 2] as ``sqrt(x * x + y * y)``: some 4x faster than
    ``v.norm(dim=-1)`` on the CPU, and not bit for bit the same (it differs by an ulp on about one
    element in twelve), so it serves bounds only, compared with a :func:`loose` limit: such a bound lets through
    at least the pairs that can meet, and an exact test decides."""
    x, y = v[..., 0], v[..., 1]
    return (x * x + y * y).sqrt()


def squared_length(v: torch.Tensor) -> torch.Tensor:
    """[...] ``x * x + y * y`` of 2D vectors ``v`` [..., 2]: bit for bit ``v.square().sum(-1)`` (a sum of two
    terms is one addition either way) and some 3x faster on the CPU, where the reduction over a last
    dimension of 2 is slow."""
    x, y = v[..., 0], v[..., 1]
    return x * x + y * y


def loose(limit: torch.Tensor) -> torch.Tensor:
    """``limit`` widened by a margin for rounding (1e-5 of it and 1 mm): a distance bound compared with
    it passes more pairs, never fewer."""
    return limit * (1 + 1e-5) + 1e-3


def _point_segment_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distance [...] from points ``p`` to segments ``a``-``b`` [..., 2]."""
    ab, ap = b - a, p - a
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    return (ap - ab * t[..., None]).norm(dim=-1)


def polygon_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distance [...] between the boundaries of convex polygons ``a`` [..., Va, 2] and ``b``
    [..., Vb, 2] that do not overlap (the smallest vertex-to-edge distance either way)."""
    a_next, b_next = a.roll(-1, -2), b.roll(-1, -2)
    ab = _point_segment_distance(a[..., :, None, :], b[..., None, :, :], b_next[..., None, :, :])  # [..., Va, Vb]
    ba = _point_segment_distance(b[..., :, None, :], a[..., None, :, :], a_next[..., None, :, :])
    return torch.minimum(ab.flatten(-2).amin(-1), ba.flatten(-2).amin(-1))


def rounded_boxes_overlap(a_xy: torch.Tensor, a_heading: torch.Tensor, a_size: torch.Tensor, b_xy: torch.Tensor,
                          b_heading: torch.Tensor, b_size: torch.Tensor, rounding: float = CORNER_ROUNDING_FACTOR) -> torch.Tensor:
    """bool [...]: the collision test of the sim-agents metrics (:func:`smart_marl.geometry.boxes_overlap`):
    boxes with rounded corners, i.e. each box shrunk by ``s = min(length, width) * rounding / 2`` per
    side and the two cores closer than ``s_a + s_b``. ``size`` [..., 2] length, width; all broadcast."""
    s_a = a_size.amin(-1) * (rounding / 2)
    s_b = b_size.amin(-1) * (rounding / 2)
    core_a, core_b = a_size / 2 - s_a[..., None], b_size / 2 - s_b[..., None]
    overlap = boxes_overlap(a_xy, a_heading, core_a, b_xy, b_heading, core_b)
    ca = box_corners(a_xy, a_heading, 2 * core_a[..., 0], 2 * core_a[..., 1])
    cb = box_corners(b_xy, b_heading, 2 * core_b[..., 0], 2 * core_b[..., 1])
    return overlap | (polygon_distance(ca, cb) < s_a + s_b)


# ------------------------------------------------------------------------------ road edges
@dataclass
class RoadEdgeTensors:
    """The road-edge segments of ``B`` scenes padded to ``S`` (:class:`smart_marl.geometry.RoadEdgeSegments`
    per scene; ``prior`` / ``next_`` index the scene's own segments; padding is not ``valid``)."""

    start: torch.Tensor  # [B, S, 3]
    end: torch.Tensor  # [B, S, 3]
    prior: torch.Tensor  # [B, S] long
    next_: torch.Tensor  # [B, S] long
    has_prior: torch.Tensor  # [B, S] bool
    has_next: torch.Tensor  # [B, S] bool
    convex_prior: torch.Tensor  # [B, S] bool
    convex_next: torch.Tensor  # [B, S] bool
    valid: torch.Tensor  # [B, S] bool

    FILL = {"start": 0.0, "end": 0.0, "prior": 0, "next_": 0, "has_prior": False, "has_next": False, "convex_prior": False,
            "convex_next": False, "valid": False}

    @classmethod
    def from_segments(cls, segments: Sequence[RoadEdgeSegments | None], dtype=torch.float32, device="cpu") -> "RoadEdgeTensors":
        """One row per scene (``None``: a scene without road edges), padded to the most segments."""
        size = max([s.num_segments for s in segments if s is not None] + [1])
        out = cls(**{f.name: torch.full((len(segments), size, 3) if f.name in ("start", "end") else (len(segments), size),
                                        cls.FILL[f.name], dtype=_dtype(f.name, dtype), device=device) for f in fields(cls)})
        for b, seg in enumerate(segments):
            if seg is None or seg.num_segments == 0:
                continue
            k = seg.num_segments
            for name in ("start", "end", "prior", "next_", "has_prior", "has_next", "convex_prior", "convex_next"):
                getattr(out, name)[b, :k] = torch.as_tensor(getattr(seg, name), dtype=_dtype(name, dtype))
            out.valid[b, :k] = True
        return out

    @property
    def num_segments(self) -> int:
        return int(self.start.shape[1])

    def blocks(self, size: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
        """(centre [B, S / size, 2], radius [B, S / size]): each run of ``size`` consecutive segments
        (a road edge's polyline goes on in the next segments) inside a circle; ``radius`` is ``-inf``
        on a block without a valid segment. Computed once and kept until a tensor of the edges is
        replaced or written to (a refill)."""
        return kept(self, "_blocks", (self.start, self.end, self.valid),
                    lambda i=slice(None): _segment_blocks(self.start[i], self.end[i], self.valid[i], size), size, by_rows=True)

    def columns(self) -> tuple[torch.Tensor, ...]:
        """The segments as seven [B, S] columns, kept as :meth:`blocks` is: the start's x, y and z, the
        direction ``end - start``'s x, y and z, and its squared 2D length (what every distance to the segment
        reads; contiguous, so the searches gather them with one index each)."""
        def compute(i=slice(None)):
            start, e = self.start[i], self.end[i] - self.start[i]
            denom = squared_length(e)
            return tuple(t.contiguous() for t in (start[..., 0], start[..., 1], start[..., 2], e[..., 0], e[..., 1], e[..., 2], denom))
        return kept(self, "_columns", (self.start, self.end), compute, by_rows=True)


def kept(owner, name: str, inputs: tuple[torch.Tensor, ...], compute, *extra, by_rows: bool = False):
    """``compute()``, kept in ``owner`` (under ``name``) until one of the tensors ``inputs`` is replaced
    or written to in place (its version counter moves) or ``extra`` changes: derived constants of
    scenes that a refill may rewrite. ``by_rows``: the values are a tuple of tensors whose row ``b``
    comes from the inputs' row ``b`` alone, and ``compute(index)`` computes rows ``index`` alone (all
    rows by default), so that :func:`rows_rewritten` keeps them through a refill of some rows."""
    cached = owner.__dict__.get(name)
    if cached is None or cached.extra != extra or len(cached.inputs) != len(inputs) or any(
            a is not b for a, b in zip(cached.inputs, inputs)) or cached.versions != _versions(inputs):
        owner.__dict__[name] = cached = _Kept(extra, tuple(inputs), _versions(inputs), compute(), compute if by_rows else None)
    return cached.values


class _Kept(NamedTuple):
    extra: tuple
    inputs: tuple  # the tensors the values come from
    versions: tuple  # their version counters when the values were computed
    values: object
    rows: Callable | None  # rows(index): the values' rows ``index`` alone


def _versions(inputs) -> tuple:
    return tuple(t._version for t in inputs)


@contextmanager
def rows_rewritten(owner, index: torch.Tensor):
    """Around a refill that writes rows ``index`` of ``owner``'s tensors in place: what :func:`kept` keeps
    in ``owner`` by rows, current before, has those rows recomputed after and stays kept (a refill of a
    few scenes then recomputes their rows, not the whole batch's). Where an input was not written in
    place (replaced by a larger one, or not touched), the value is left to :func:`kept`, which recomputes
    it whole where it must."""
    before = {name: c for name, c in owner.__dict__.items()
              if isinstance(c, _Kept) and c.rows is not None and c.versions == _versions(c.inputs)}
    yield
    for name, c in before.items():
        now = _versions(c.inputs)
        if all(v != w for v, w in zip(now, c.versions)):  # every input written in place: the same tensors, new rows
            for mine, new in zip(c.values, c.rows(index)):
                mine[index] = new
            owner.__dict__[name] = c._replace(versions=now)


def block_bounds(xy: torch.Tensor, valid: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(centre [B, nb, 2], radius [B, nb]) of each run of ``size`` consecutive items (a polyline's
    segments or points go on in the next ones) of ``B`` rows, ``nb = ceil(P / size)``: every point
    ``xy`` [B, P, E, 2] of the run's ``valid`` [B, P] items within ``radius`` of the centre of their
    bounding box (``-inf``: a run without a valid item). A segment (E = 2: its ends) lies in the
    circle with its ends; so no item of a block is nearer to a point than its distance to the centre
    less the radius."""
    b, p, e = xy.shape[:3]
    nb = -(-p // size)
    ok = valid[..., None].expand(b, p, e)
    if nb * size > p:
        xy = torch.cat([xy, xy.new_zeros(b, nb * size - p, e, 2)], 1)
        ok = torch.cat([ok, ok.new_zeros(b, nb * size - p, e)], 1)
    xy, ok = xy.reshape(b, nb, size * e, 2), ok.reshape(b, nb, size * e)
    lo = xy.masked_fill(~ok[..., None], float("inf")).amin(2)
    hi = xy.masked_fill(~ok[..., None], float("-inf")).amax(2)
    centre = torch.where(ok.any(2)[..., None], (lo + hi) / 2, torch.zeros_like(lo))  # [B, nb, 2]
    radius = (xy - centre[:, :, None]).norm(dim=-1).masked_fill(~ok, float("-inf")).amax(2)
    return centre, radius


def block_lower_bound(query: torch.Tensor, centre: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
    """[B, Q, nb] a lower bound of the 2D distance from points ``query`` [B, Q, 2] to any item of
    each block of their row (:func:`block_bounds`), less a margin for rounding; ``inf`` for an empty block.
    The radius and its margin are folded per block first (``-inf`` stays: the bound comes out ``inf``)
    and the distance is taken from its two coordinates in place: one pass over [B, Q, nb] per operation
    (the searches read it as a bound only: any lower bound gives them the same result)."""
    reach = torch.where(radius == float("-inf"), radius, radius + 1e-5 * radius.abs() + 1e-3)[:, None]  # [B, 1, nb]
    dx = query[..., 0, None] - centre[:, None, :, 0]
    dy = query[..., 1, None] - centre[:, None, :, 1]
    return dx.square_().add_(dy.square_()).sqrt_().mul_(1 - 1e-5).sub_(reach)


def _segment_blocks(start: torch.Tensor, end: torch.Tensor, valid: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:meth:`RoadEdgeTensors.blocks`."""
    return block_bounds(torch.stack([start[..., :2], end[..., :2]], 2), valid, size)


def _dtype(name: str, dtype):
    return dtype if name in ("start", "end") else torch.long if name in ("prior", "next_") else torch.bool


def _cross(ax, ay, bx, by):
    return ax * by - ay * bx


SEGMENT_BLOCK = 16
"""Segments per block of the nearest-edge search's bound (:meth:`RoadEdgeTensors.blocks`)."""


def nearest_road_edge(points: torch.Tensor, edges: RoadEdgeTensors, z_stretch: float = Z_STRETCH, candidates: int = 20,
                      max_pairs: int = 1 << 20, group: int = 1) -> torch.Tensor:
    """[B, Q] the index of the segment nearest to each point [B, Q, 3] of its scene by 3D distance with z
    stretched (the lowest index on ties), as :func:`smart_marl.geometry.nearest_segment_indices`.

    Exact with pruning: no segment of a block (:meth:`RoadEdgeTensors.blocks`, ``SEGMENT_BLOCK``
    consecutive segments) is nearer than the distance to the block's centre less its radius (the
    block's bound). Every segment of the ``candidates`` blocks of smallest bound is measured; a point
    whose nearest of them is nearer than every other block's bound is done; the others are measured
    against every segment of each block whose bound is within that distance, ``max_pairs`` (point,
    segment) pairs at a time. ``group``: the points come in runs of that many close together (a box's
    corners; Q a multiple of it), bounded together: the bound from the run's centre less the run's
    radius holds for each of its points, so the blocks are ranked and their segments gathered once a run."""
    b, q = points.shape[:2]
    centre, radius = edges.blocks(SEGMENT_BLOCK)  # [B, nb, 2], [B, nb]
    nb = centre.shape[1]
    kb = min(max(int(candidates), 1), nb)
    xy = points[..., :2].reshape(b, q // group, group, 2)
    mid = (xy.amin(2) + xy.amax(2)) / 2  # [B, Q / group, 2]
    bound = block_lower_bound(mid, centre, radius) - (xy - mid[:, :, None]).norm(dim=-1).amax(-1)[..., None]  # [B, Q / group, nb]
    lb, blk = torch.topk(bound, min(kb + 1, nb), dim=-1, largest=False)
    rest = lb[..., kb] if kb < nb else torch.full(bound.shape[:2], float("inf"), dtype=points.dtype, device=points.device)
    scene = torch.arange(b, device=points.device)[:, None].expand(b, q // group).reshape(-1)
    blk = blk[..., :kb].sort(dim=-1).values.reshape(-1, kb)  # by index: the lowest index first among equally near segments
    nearest, best = _nearest_in_blocks(points.reshape(-1, group, 3), scene, blk, edges, z_stretch)
    nearest, best = nearest.view(b, q), best.view(b, q)
    # a segment outside the candidate blocks may be as near
    unsure = (best >= rest.repeat_interleave(group, 1)) & edges.valid.any(1)[:, None]
    qb, qq = unsure.nonzero(as_tuple=True)
    if len(qb):
        need = bound[qb, qq // group] <= best[qb, qq, None]  # [U, nb] every block that may hold a segment as near
        count = need.sum(-1)
        blocks = torch.where(need, torch.arange(nb, device=points.device), nb).sort(dim=-1).values  # needed ones first, by index
        lo = 0
        while lo < nb:  # points needing about as many blocks together (a point far off the road needs many)
            hi = min(2 * max(lo, kb), nb)
            sel = ((count > lo) & (count <= hi)).nonzero().squeeze(1)
            step = max(1, max_pairs // (hi * SEGMENT_BLOCK))
            for k in range(0, len(sel), step):
                i = sel[k:k + step]
                near = _nearest_in_blocks(points[qb[i], qq[i], None], qb[i], blocks[i, :hi], edges, z_stretch)[0]
                nearest[qb[i], qq[i]] = near[:, 0]
            lo = hi
    return nearest


def _nearest_in_blocks(points: torch.Tensor, scene: torch.Tensor, blocks: torch.Tensor, edges: RoadEdgeTensors,
                       z_stretch: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(index, distance) [U, g] of the nearest segment to points [U, g, 3] of scenes ``scene`` [U] among
    the segments of blocks ``blocks`` [U, m] (ascending; ``nb`` or more: none), the lowest index on ties
    (distance ``inf`` where none is valid)."""
    s = edges.num_segments
    seg = (blocks[..., None] * SEGMENT_BLOCK + torch.arange(SEGMENT_BLOCK, device=points.device)).flatten(1)  # [U, m * block]
    inside = seg < s
    seg = torch.where(inside, seg, torch.zeros_like(seg))
    flat = (scene[:, None] * s + seg).reshape(-1)  # rows of the flattened edges (one index: a fast gather)
    # the squared 3D distance (z stretched) from each point to each segment, on the segments' columns (contiguous, not
    # strided [..., 3] views): [U, g, m * block]
    sx, sy, sz, ex, ey, ez, denom = (t.reshape(-1).index_select(0, flat).view(seg.shape[0], 1, seg.shape[1]) for t in edges.columns())
    px, py, pz = (points[..., c, None] for c in range(3))  # [U, g, 1]
    spx, spy, spz = px - sx, py - sy, pz - sz
    t = torch.where(denom > 0, (spx * ex + spy * ey) / denom.clamp_min(1e-30), torch.zeros_like(denom)).clamp(0.0, 1.0)
    dx, dy, dz = spx - ex * t, spy - ey * t, spz - ez * t
    d2 = dx ** 2 + dy ** 2 + (z_stretch * dz) ** 2
    d2 = d2.masked_fill(~(inside & edges.valid.reshape(-1).index_select(0, flat).view(seg.shape))[:, None], float("inf"))
    best = d2.argmin(-1, keepdim=True)
    return seg[:, None].expand_as(d2).gather(-1, best)[..., 0], d2.gather(-1, best)[..., 0].sqrt()


def signed_distance_to_road_edges(points: torch.Tensor, edges: RoadEdgeTensors, z_stretch: float = Z_STRETCH,
                                  max_pairs: int = 1 << 20, group: int = 1) -> torch.Tensor:
    """Signed 2D distance [B, Q] of points [B, Q, 3] to their scene's road edges, positive off the road,
    as :func:`smart_marl.geometry.signed_distance_to_road_edges`: the nearest segment by 3D distance
    with z stretched ``z_stretch`` times (the lowest index on ties, :func:`nearest_road_edge`), the 2D
    distance to it, its sign by the neighbour rule. ``max_pairs`` bounds the (point, segment) pairs
    held at once, ``group`` runs of points close together (:func:`nearest_road_edge`). A scene without
    segments gives ``-inf`` (nowhere is off its road)."""
    nearest = nearest_road_edge(points, edges, z_stretch, max_pairs=max_pairs, group=group)
    gather = lambda t: t.gather(1, nearest)  # noqa: E731  [B, S] -> [B, Q]
    gather3 = lambda t, idx=None: t.gather(1, (nearest if idx is None else idx)[..., None].expand(-1, -1, 3))  # noqa: E731

    def terms(idx: torch.Tensor | None = None):
        s0, s1 = gather3(edges.start, idx), gather3(edges.end, idx)
        sp, e = points - s0, s1 - s0
        denom = squared_length(e)
        rel_t = torch.where(denom > 0, (sp[..., 0] * e[..., 0] + sp[..., 1] * e[..., 1]) / denom.clamp_min(1e-30),
                            torch.zeros_like(denom))
        side = torch.sign(_cross(sp[..., 0], sp[..., 1], e[..., 0], e[..., 1]))
        d = sp[..., :2] - e[..., :2] * rel_t.clamp(0.0, 1.0)[..., None]
        return d.norm(dim=-1), rel_t, side

    d2, rel_t, n = terms()
    _, _, n_prior = terms(gather(edges.prior))
    _, _, n_next = terms(gather(edges.next_))
    before = torch.where(gather(edges.convex_prior), torch.maximum(n, n_prior), torch.minimum(n, n_prior))
    after = torch.where(gather(edges.convex_next), torch.maximum(n, n_next), torch.minimum(n, n_next))
    sign = torch.where((rel_t < 0.0) & gather(edges.has_prior), before, torch.where((rel_t > 1.0) & gather(edges.has_next), after, n))
    any_edge = edges.valid.any(1)[:, None]
    return torch.where(any_edge, sign * d2, torch.full_like(d2, float("-inf")))


def scene_road_edges(road_map) -> RoadEdgeSegments | None:
    """The road-edge segments of a scene's :class:`~smart_marl.road_map.RoadMap` (its ROAD_EDGE polylines, in
    the scene's frame), or None when it has none."""
    seg = RoadEdgeSegments.from_polylines([road_map.feature_points(i) for i in road_map.indices_of(MapFeatureType.ROAD_EDGE)])
    return seg if seg.num_segments else None


OFF_ROAD_BLOCK_POINTS = 1 << 15
"""Box corners :func:`boxes_off_road` measures at once."""


def boxes_off_road(edges: RoadEdgeTensors, scene: torch.Tensor, xy: torch.Tensor, heading: torch.Tensor, size: torch.Tensor,
                   z: torch.Tensor) -> torch.Tensor:
    """bool [R, c]: does a box (centre ``xy`` [R, c, 2], ``heading`` [R, c], ``size`` [R, 3] length, width,
    height, its centre's height ``z`` [R]; row ``i`` in scene ``scene[i]`` of ``edges``, ``scene`` ascending)
    have a bottom corner off the road (signed distance to the road edges > 0: the offroad event's test)?
    The rows are packed scene by scene; when they are in most of the scenes, the batch's edges are searched
    (their blocks are kept from call to call), else only those of the scenes they are in."""
    r, c = xy.shape[:2]
    step = max(1, OFF_ROAD_BLOCK_POINTS // (4 * c))
    if r > step:  # in blocks of rows: the edge search's intermediates grow with the points searched at once
        return torch.cat([boxes_off_road(edges, scene[i:i + step], xy[i:i + step], heading[i:i + step], size[i:i + step],
                                         z[i:i + step]) for i in range(0, r, step)])
    corners = box_corners_bottom(xy, heading, size[:, None].expand(-1, c, -1), z[:, None].expand(-1, c))  # [R, c, 4, 3]
    used, where = torch.unique_consecutive(scene, return_inverse=True)
    counts = torch.bincount(where, minlength=len(used))
    rank = torch.arange(r, device=scene.device) - (counts.cumsum(0) - counts)[where]
    b = edges.valid.shape[0]
    if 2 * len(used) > b:  # most scenes: every scene's row (the others padding), the edges as they are
        where, sub = used[where], edges
    else:  # a few scenes: theirs alone (their blocks computed afresh)
        sub = RoadEdgeTensors(**{f.name: getattr(edges, f.name)[used] for f in fields(RoadEdgeTensors)})
    packed = corners.new_zeros(sub.valid.shape[0], int(counts.max()), c * 4, 3)
    packed[where, rank] = corners.reshape(r, c * 4, 3)
    dist = signed_distance_to_road_edges(packed.view(packed.shape[0], -1, 3), sub, group=4)
    return dist.view(packed.shape[0], -1, c, 4)[where, rank].amax(-1) > 0


def box_corners_bottom(xy: torch.Tensor, heading: torch.Tensor, size: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """The 4 bottom corners [..., 4, 3] of boxes (``size`` [..., 3] length, width, height; ``z`` the
    box centre's height), the points the offroad test reads (:func:`smart_marl.geometry.box_distance_to_road_edge`)."""
    xy4 = box_corners(xy, heading, size[..., 0], size[..., 1])
    zb = (z - size[..., 2] / 2)[..., None, None].expand(*xy4.shape[:-1], 1)
    return torch.cat([xy4, zb], -1)


__all__ = ["RoadEdgeTensors", "box_corners", "box_corners_bottom", "boxes_off_road", "boxes_overlap", "boxes_overlap_rotated", "nearest_road_edge", "polygon_distance",
           "rounded_boxes_overlap", "scene_road_edges", "signed_distance_to_road_edges"]
