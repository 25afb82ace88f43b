"""Planar geometry of agent boxes and road edges, shared by the metrics and the environment.

Stage: a utility under the last stages of the data flow (environment, metrics); pure, vectorised
numpy functions of arrays, no Scenario or model needed. The one copy of: oriented-box corners,
signed distance between oriented boxes (plain and with rounded corners, as the sim-agents
metrics define it), box overlap (collision), which agents of a scene collide over some frames
(:func:`colliding`) and an agent's smallest distance to the others (:func:`min_box_distance`),
signed distance of points to road-edge polylines (positive = off road), offroad, and time to
collision with the object in front.

Conventions: metres and radians, heading counter-clockwise from +x; a box is a centre ``(x, y)``,
a ``length`` along the heading and a ``width`` across it. Leading dimensions ``...`` broadcast.
Everything is computed in float64, except :func:`box_corners_float32` and
:func:`rounded_box_core_float32`, which reproduce the official float32 rounding of box corners (it
decides histogram bins at source-frame magnitudes; see :mod:`smart_marl.metrics.inputs`).

The formulas follow the Waymo Open Sim Agents Challenge metrics (``waymo-open-dataset`` 1.6.x,
``box_utils``, ``geometry_utils``, ``interaction_features``, ``map_metric_features``); the
quirks that change numbers are kept and named where they occur (see docs/wosac_metrics.md).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

EXTREMELY_LARGE_DISTANCE_M = 1e10
"""Stand-in distance for invalid pairs (the official constant)."""
CORNER_ROUNDING_FACTOR = 0.7
"""Boxes shrink by ``min(length, width) * 0.7 / 2`` per side and get rounded corners of that radius."""
MAX_HEADING_DIFF_RAD = np.radians(75.0)
MAX_HEADING_DIFF_FOR_SMALL_OVERLAP_RAD = np.radians(10.0)
SMALL_OVERLAP_THRESHOLD_M = 0.5
MAXIMUM_TIME_TO_COLLISION_S = 5.0
Z_STRETCH = 3.0
"""Road-edge matching: z differences count three times, so edges of another level are not chosen."""
CYCLIC_POLYLINE_TOLERANCE_M2 = 1.0
"""A polyline whose ends are closer than 1 m (squared distance < 1 m^2) is closed."""


def _f64(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


# ------------------------------------------------------------------------------------ boxes
def box_corners(x, y, length, width, heading) -> np.ndarray:
    """Corners [..., 4, 2] of oriented boxes, counter-clockwise: front-left, rear-left, rear-right,
    front-right (the order of the official ``get_upright_3d_box_corners``)."""
    x, y, length, width, heading = map(_f64, (x, y, length, width, heading))
    c, s = np.cos(heading), np.sin(heading)
    l2, w2 = length * 0.5, width * 0.5
    sign_l = np.array([1.0, -1.0, -1.0, 1.0])
    sign_w = np.array([1.0, 1.0, -1.0, -1.0])
    dl = l2[..., None] * sign_l  # [..., 4]
    dw = w2[..., None] * sign_w
    cx = x[..., None] + c[..., None] * dl - s[..., None] * dw
    cy = y[..., None] + s[..., None] * dl + c[..., None] * dw
    return np.stack([cx, cy], axis=-1)


def box_corners_float32(x, y, length, width, heading, z=None, height=None) -> np.ndarray:
    """:func:`box_corners` computed the way the official float32 code does (offsets rotated in
    float32, then added to float32 centres), returned as float64 [..., 4, 2] (or [..., 4, 3] with
    the bottom z when ``z`` and ``height`` are given). With centres in the source frame (thousands
    of metres) the float32 rounding is ~1e-4 m, which decides the bin of values that sit on a
    histogram edge, so parity with the official numbers needs the same rounding."""
    f = np.float32
    x, y, length, width, heading = (np.asarray(a, dtype=f) for a in (x, y, length, width, heading))
    c, s = np.cos(heading), np.sin(heading)
    l2, w2 = length * f(0.5), width * f(0.5)
    sign_l = np.array([1.0, -1.0, -1.0, 1.0], dtype=f)
    sign_w = np.array([1.0, 1.0, -1.0, -1.0], dtype=f)
    dl = l2[..., None] * sign_l
    dw = w2[..., None] * sign_w
    off_x = c[..., None] * dl + (-s)[..., None] * dw
    off_y = s[..., None] * dl + c[..., None] * dw
    cx = x[..., None] + off_x
    cy = y[..., None] + off_y
    parts = [cx, cy]
    if z is not None:
        h2 = np.asarray(height, dtype=f) * f(0.5)
        cz = np.asarray(z, dtype=f) + (-h2)
        parts.append(np.broadcast_to(cz[..., None], cx.shape))
    return np.stack(parts, axis=-1).astype(np.float64)


def rounded_box_core_float32(length, width, rounding: float = CORNER_ROUNDING_FACTOR):
    """(shrink, core length, core width) in float32 as the official code computes them."""
    f = np.float32
    length, width = np.asarray(length, f), np.asarray(width, f)
    shrink = np.minimum(length, width) * f(rounding) / f(2.0)
    return shrink.astype(np.float64), (length - f(2.0) * shrink).astype(np.float64), (width - f(2.0) * shrink).astype(np.float64)


def _cross(ax, ay, bx, by):
    return ax * by - ay * bx


def _downmost_edge(corners: np.ndarray):
    """Index of the lowest corner (first on ties) and the unit direction of the edge leaving it."""
    start = np.argmin(corners[..., 1], axis=-1)
    a = np.take_along_axis(corners, start[..., None, None], axis=-2)[..., 0, :]
    b = np.take_along_axis(corners, ((start + 1) % 4)[..., None, None], axis=-2)[..., 0, :]
    d = b - a
    with np.errstate(invalid="ignore", divide="ignore"):
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return start, d


_ORDER_1 = np.array([0, 0, 1, 1, 2, 2, 3, 3])
_ORDER_2 = np.array([0, 1, 1, 2, 2, 3, 3, 0])


def minkowski_sum_of_boxes(corners_a: np.ndarray, corners_b: np.ndarray) -> np.ndarray:
    """Minkowski sum [..., 8, 2] of two counter-clockwise boxes [..., 4, 2] (edges interleaved, as
    two rectangles' edges alternate in angle)."""
    start_a, dir_a = _downmost_edge(corners_a)
    start_b, dir_b = _downmost_edge(corners_b)
    cond = (_cross(dir_a[..., 0], dir_a[..., 1], dir_b[..., 0], dir_b[..., 1]) >= 0.0)[..., None]
    order_a = (np.where(cond, _ORDER_2, _ORDER_1) + start_a[..., None]) % 4
    order_b = (np.where(cond, _ORDER_1, _ORDER_2) + start_b[..., None]) % 4
    pa = np.take_along_axis(corners_a, order_a[..., None], axis=-2)
    pb = np.take_along_axis(corners_b, order_b[..., None], axis=-2)
    return pa + pb


def signed_distance_point_to_convex_polygon(point: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Signed distance [...] from points [..., 2] to counter-clockwise convex polygons [..., V, 2]:
    negative inside (the official rule: nearest edge whose projection falls on it, or vertex)."""
    nxt = np.roll(polygon, -1, axis=-2)
    edge = nxt - polygon
    edge_len = np.linalg.norm(edge, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        tangent = edge / edge_len[..., None]
        normal = np.stack([-tangent[..., 1], tangent[..., 0]], axis=-1)  # inward for counter-clockwise
        to_query = point[..., None, :] - polygon
        vertex_dist = np.linalg.norm(to_query, axis=-1)
        perp = np.sum(-normal * to_query, axis=-1)  # <= 0 inside
        inside = np.all(perp <= 0, axis=-1)
        along = np.sum(tangent * to_query, axis=-1) / edge_len
    on_edge = (along >= 0.0) & (along <= 1.0)
    edge_dist = np.where(on_edge, np.abs(perp), np.inf)
    dist = np.minimum(edge_dist.min(axis=-1), vertex_dist.min(axis=-1))
    return np.where(inside, -dist, dist)


def box_signed_distance(corners_a: np.ndarray, corners_b: np.ndarray) -> np.ndarray:
    """Signed distance [...] between oriented boxes given by their corners [..., 4, 2]: the gap when
    apart, minus the penetration depth when they overlap (Minkowski difference to the origin)."""
    msum = minkowski_sum_of_boxes(corners_a, -corners_b)
    return signed_distance_point_to_convex_polygon(np.zeros(msum.shape[:-2] + (2,)), msum)


def rounded_box_shrink(length, width, rounding: float = CORNER_ROUNDING_FACTOR) -> np.ndarray:
    """How much each side of a box moves in to become the core of its rounded-corner box."""
    return np.minimum(_f64(length), _f64(width)) * rounding / 2.0


def rounded_box_signed_distance(x_a, y_a, length_a, width_a, heading_a, x_b, y_b, length_b, width_b, heading_b,
                                rounding: float = CORNER_ROUNDING_FACTOR) -> np.ndarray:
    """Signed distance [...] between boxes with rounded corners (the sim-agents "distance to nearest
    object" geometry): the boxes shrink by ``s = min(l, w) * rounding / 2`` per side, the signed
    distance of the shrunk boxes minus ``s_a + s_b``."""
    s_a = rounded_box_shrink(length_a, width_a, rounding)
    s_b = rounded_box_shrink(length_b, width_b, rounding)
    ca = box_corners(x_a, y_a, _f64(length_a) - 2 * s_a, _f64(width_a) - 2 * s_a, heading_a)
    cb = box_corners(x_b, y_b, _f64(length_b) - 2 * s_b, _f64(width_b) - 2 * s_b, heading_b)
    return box_signed_distance(ca, cb) - s_a - s_b


def boxes_overlap(*args, rounding: float = CORNER_ROUNDING_FACTOR) -> np.ndarray:
    """Collision test [...] between rounded boxes: signed distance < 0 (arguments as
    :func:`rounded_box_signed_distance`)."""
    return rounded_box_signed_distance(*args, rounding=rounding) < 0.0


def box_distance_bounds(dist_centres, length_a, width_a, length_b, width_b):
    """Lower and upper bounds of the (rounded or plain) box signed distance from the centre
    distance: circumscribed discs give the lower bound, inscribed discs the upper bound."""
    la, wa, lb, wb = map(_f64, (length_a, width_a, length_b, width_b))
    circ = 0.5 * np.hypot(la, wa) + 0.5 * np.hypot(lb, wb)
    insc = 0.5 * np.minimum(la, wa) + 0.5 * np.minimum(lb, wb)
    return dist_centres - circ, dist_centres - insc


def bearing_deg(dx: float, dy: float, heading: float) -> float:
    """The angle (degrees, 0-180) between a heading and the direction (dx, dy) to another point: 0 dead
    ahead, 180 straight behind (who ran into whom: the one that has the other ahead)."""
    c, s = math.cos(heading), math.sin(heading)
    return abs(math.degrees(math.atan2(-dx * s + dy * c, dx * c + dy * s)))


def overlapping_pairs(poses: np.ndarray, present: np.ndarray, length: np.ndarray, width: np.ndarray,
                      query: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Every (query agent, other agent, frame) whose rounded boxes overlap (:func:`boxes_overlap`, query
    first) where both are present: index arrays ``(*leading, q, a, f)``, ``q`` into ``query`` (default:
    every agent), ``a`` an agent index, ``f`` a frame. poses [..., A, F, 3], present [..., A, F] bool,
    length / width [A]. Only the pairs whose centre distance allows an overlap
    (:func:`box_distance_bounds`) are tested box against box."""
    poses, present = _f64(poses), np.asarray(present, bool)
    length, width = _f64(length), _f64(width)
    a = poses.shape[-3]
    q = np.arange(a) if query is None else np.asarray(query, np.int64)
    if len(q) == 0 or a == 0:
        return tuple(np.zeros(0, np.int64) for _ in range(poses.ndim - 1))
    mine = poses[..., q, :, :]  # [..., Q, F, 3]
    dist = np.linalg.norm(mine[..., :, None, :, :2] - poses[..., None, :, :, :2], axis=-1)  # [..., Q, A, F]
    lo, _ = box_distance_bounds(dist, length[q, None, None], width[q, None, None], length[None, :, None], width[None, :, None])
    other = q[:, None, None] != np.arange(a)[None, :, None]  # [Q, A, 1]
    cand = (lo < 0) & other & present[..., q, None, :] & present[..., None, :, :]
    *lead, qi, ai, fi = np.nonzero(cand)
    pa, pb = mine[(*lead, qi, fi)], poses[(*lead, ai, fi)]  # [M, 3]
    hit = boxes_overlap(pa[:, 0], pa[:, 1], length[q[qi]], width[q[qi]], pa[:, 2], pb[:, 0], pb[:, 1], length[ai], width[ai], pb[:, 2])
    return (*[i[hit] for i in lead], qi[hit], ai[hit], fi[hit])


def first_overlaps(poses: np.ndarray, present: np.ndarray, length: np.ndarray, width: np.ndarray,
                   query: np.ndarray | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """Each query agent's first collision: (first frame [Q], -1 for none; the agents its box overlaps on that
    frame, ascending, one array per query agent) from :func:`overlapping_pairs`. poses [A, F, 3], present
    [A, F] bool, length / width [A]; query [Q] agent indices (default: every agent)."""
    nq = poses.shape[-3] if query is None else len(query)
    q, a, f = overlapping_pairs(poses, present, length, width, query)
    first = np.full(nq, -1, np.int64)
    partners = [np.zeros(0, np.int64) for _ in range(nq)]
    for i in np.unique(q):
        mine = q == i
        first[i] = f[mine].min()
        partners[i] = np.unique(a[mine & (f == first[i])])
    return first, partners


def colliding(poses: np.ndarray, present: np.ndarray, length: np.ndarray, width: np.ndarray,
              query: np.ndarray | None = None) -> np.ndarray:
    """Which agents collide: [..., Q] bool, true when agent ``query[q]``'s rounded box overlaps
    another agent's on some frame where both are present (:func:`overlapping_pairs`).

    poses [..., A, F, 3] (x, y, heading of A agents over F frames), present [..., A, F] bool,
    length / width [A]; query [Q] agent indices (default: every agent).
    """
    a = np.shape(poses)[-3]
    nq = a if query is None else len(query)
    out = np.zeros(np.shape(poses)[:-3] + (nq,), bool)
    *lead, qi, _ai, _fi = overlapping_pairs(poses, present, length, width, query)
    out[(*lead, qi)] = True
    return out


def min_box_distance(poses: np.ndarray, present: np.ndarray, length: np.ndarray, width: np.ndarray, index: int,
                     near_m: float = 30.0) -> np.ndarray:
    """[...] the smallest rounded-box signed distance (m, negative = overlap) between agent ``index``
    and any other agent over the frames where both are present (NaN when there is none). Pairs
    farther apart than ``near_m`` (centre distance) count with their centre distance, an upper bound.

    poses [..., A, F, 3], present [..., A, F] bool, length / width [A].
    """
    poses, present = _f64(poses), np.asarray(present, bool)
    length, width = _f64(length), _f64(width)
    me = poses[..., index, :, :]  # [..., F, 3]
    both = present[..., index, None, :] & present  # [..., A, F]
    both[..., index, :] = False
    centre = np.linalg.norm(poses[..., :2] - me[..., None, :, :2], axis=-1)  # [..., A, F]
    near = np.where(both, centre, np.inf) < near_m  # box distance only for the near pairs
    d = np.where(both, centre, np.nan)
    *lead, ai, fi = np.nonzero(near)
    if len(ai):
        pa, pb = me[(*lead, fi)], poses[(*lead, ai, fi)]
        d[(*lead, ai, fi)] = rounded_box_signed_distance(pa[:, 0], pa[:, 1], length[index], width[index], pa[:, 2],
                                                        pb[:, 0], pb[:, 1], length[ai], width[ai], pb[:, 2])
    flat = d.reshape(d.shape[:-2] + (-1,))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: never present together
        return np.nanmin(flat, axis=-1)


# ------------------------------------------------------------------------------ road edges
@dataclass(frozen=True)
class RoadEdgeSegments:
    """Road-edge polylines flattened into segments with the neighbour facts the sign rule needs.

    ``start``/``end`` [S, 3]; ``prior``/``next_`` [S] index of the neighbouring segment the sign rule
    may consult (``has_prior``/``has_next`` [S] whether it may), ``convex_prior``/``convex_next`` [S]
    whether the polyline turns left at that joint. Polylines are counter-clockwise: the road is on
    their left (port) side.
    """

    start: np.ndarray
    end: np.ndarray
    prior: np.ndarray
    next_: np.ndarray
    has_prior: np.ndarray
    has_next: np.ndarray
    convex_prior: np.ndarray
    convex_next: np.ndarray

    @property
    def num_segments(self) -> int:
        return int(self.start.shape[0])

    @classmethod
    def from_polylines(cls, polylines: list[np.ndarray]) -> "RoadEdgeSegments":
        """Polylines: a list of [n_i, 3] point arrays (polylines with < 2 points are skipped).

        Official quirk kept: the official code pads polylines to the longest one, so the closing
        joint of a closed (cyclic) polyline is only used for polylines of that maximal length."""
        polylines = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in polylines]
        polylines = [p for p in polylines if len(p) >= 2]
        if not polylines:
            z3, zi, zb = np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, bool)
            return cls(z3, z3, zi, zi, zb, zb, zb, zb)
        max_len = max(len(p) for p in polylines)
        starts, ends, prior, nxt, has_p, has_n, conv_p, conv_n = [], [], [], [], [], [], [], []
        offset = 0
        for p in polylines:
            k = len(p) - 1  # segments
            seg = p[1:] - p[:-1]
            cyclic = bool(np.sum((p[0] - p[-1]) ** 2) < CYCLIC_POLYLINE_TOLERANCE_M2) and len(p) == max_len
            idx = np.arange(k)
            pr = idx - 1
            nx = idx + 1
            hp = np.ones(k, bool)
            hn = np.ones(k, bool)
            if cyclic:
                pr[0], nx[-1] = k - 1, 0
            else:
                pr[0], nx[-1] = 0, k - 1  # the segment itself: max/min of n with itself is n
            # joint convexity: cross(previous segment, this segment) > 0
            prev_seg = seg[pr]
            next_seg = seg[nx]
            cp = _cross(prev_seg[:, 0], prev_seg[:, 1], seg[:, 0], seg[:, 1]) > 0.0
            cn = _cross(seg[:, 0], seg[:, 1], next_seg[:, 0], next_seg[:, 1]) > 0.0
            starts.append(p[:-1])
            ends.append(p[1:])
            prior.append(pr + offset)
            nxt.append(nx + offset)
            has_p.append(hp)
            has_n.append(hn)
            conv_p.append(cp)
            conv_n.append(cn)
            offset += k
        cat = np.concatenate
        return cls(cat(starts), cat(ends), cat(prior), cat(nxt), cat(has_p), cat(has_n), cat(conv_p), cat(conv_n))


def _segment_terms(q: np.ndarray, start: np.ndarray, end: np.ndarray, z_stretch: float):
    """Per (query, segment) pair: 3D stretched distance, 2D distance, rel_t, raw side sign n."""
    sp = q - start
    se = end - start
    denom = se[..., 0] ** 2 + se[..., 1] ** 2
    num = sp[..., 0] * se[..., 0] + sp[..., 1] * se[..., 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        rel_t = np.where(denom > 0, num / np.where(denom > 0, denom, 1.0), 0.0)  # divide_no_nan
    n = np.sign(_cross(sp[..., 0], sp[..., 1], se[..., 0], se[..., 1]))
    tc = np.clip(rel_t, 0.0, 1.0)[..., None]
    d = sp - se * tc
    d3 = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + (z_stretch * d[..., 2]) ** 2)
    d2 = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
    return d3, d2, rel_t, n


def _side_sign(q, seg: RoadEdgeSegments, idx: np.ndarray) -> np.ndarray:
    """Sign of the chosen segment ``idx`` [N] for queries q [N, 3] (the official neighbour rule)."""
    _, _, rel_t, n = _segment_terms(q, seg.start[idx], seg.end[idx], 1.0)
    pi, ni = seg.prior[idx], seg.next_[idx]
    _, _, _, n_prior = _segment_terms(q, seg.start[pi], seg.end[pi], 1.0)
    _, _, _, n_next = _segment_terms(q, seg.start[ni], seg.end[ni], 1.0)
    before = np.where(seg.convex_prior[idx], np.maximum(n, n_prior), np.minimum(n, n_prior))
    after = np.where(seg.convex_next[idx], np.maximum(n, n_next), np.minimum(n, n_next))
    return np.where((rel_t < 0.0) & seg.has_prior[idx], before,
                    np.where((rel_t > 1.0) & seg.has_next[idx], after, n))


def signed_distance_to_road_edges(points_xyz: np.ndarray, segments: RoadEdgeSegments,
                                  z_stretch: float = Z_STRETCH, cell_m: float = 2.0) -> np.ndarray:
    """Signed 2D distance [...] of points [..., 3] to the road-edge polylines: positive = off road
    (right of a counter-clockwise edge), negative = on road.

    The segment is the nearest by 3D distance with z stretched ``z_stretch`` times (the official
    rule, so edges of an overpass are not chosen); the distance returned is the 2D distance to it.
    Exact nearest-segment search with pruning: points are bucketed in ``cell_m`` cells; each cell
    keeps the segments that can be nearest to any of its points (bounds from the cell's nearest
    vertex), and each point is compared with its cell's candidates only.
    """
    pts = _f64(points_xyz)
    shape = pts.shape[:-1]
    q = pts.reshape(-1, 3)
    if segments.num_segments == 0:
        raise ValueError("no road-edge polylines: the distance to the road edge is undefined")
    if q.shape[0] == 0:
        return np.zeros(shape)
    nearest = nearest_segment_indices(q, segments.start, segments.end, z_stretch, cell_m)
    _, d2, _, _ = _segment_terms(q, segments.start[nearest], segments.end[nearest], z_stretch)
    sign = _side_sign(q, segments, nearest)
    return (sign * d2).reshape(shape)


def box_distance_to_road_edge(x, y, z, length, width, height, heading, segments: RoadEdgeSegments,
                              float32_corners: bool = True) -> np.ndarray:
    """Signed distance [...] of boxes to the road edge: the largest over the 4 bottom corners
    (positive = some part of the box is off road)."""
    if float32_corners:
        pts = box_corners_float32(x, y, length, width, heading, z=z, height=height)
    else:
        c = box_corners(x, y, length, width, heading)
        zb = np.broadcast_to((_f64(z) - _f64(height) / 2.0)[..., None, None], c.shape[:-1] + (1,))
        pts = np.concatenate([c, zb], axis=-1)
    return signed_distance_to_road_edges(pts, segments).max(axis=-1)


def is_offroad(x, y, z, length, width, height, heading, segments: RoadEdgeSegments) -> np.ndarray:
    """Offroad test [...]: the box's distance to the road edge is > 0."""
    return box_distance_to_road_edge(x, y, z, length, width, height, heading, segments) > 0.0


def nearest_segment_indices(q: np.ndarray, start: np.ndarray, end: np.ndarray, z_stretch: float = 1.0,
                            cell_m: float = 2.0) -> np.ndarray:
    """Index [N] of the segment nearest (3D, z stretched) to each point q [N, 3]; first on ties.

    Exact: per cell of points, every segment whose lower bound (distance to its midpoint minus its
    half length) does not exceed the cell's upper bound (distance from the cell's reference point to
    the nearest segment end point, plus twice the cell's radius) is a candidate."""
    stretch = np.array([1.0, 1.0, z_stretch])
    qs = q * stretch
    ss, es = start * stretch, end * stretch
    mid = 0.5 * (ss + es)
    half = 0.5 * np.linalg.norm(es - ss, axis=-1)
    cells = np.floor(q[:, :2] / cell_m).astype(np.int64)
    key = cells[:, 0] * 2_000_003 + cells[:, 1]
    uniq, inv = np.unique(key, return_inverse=True)
    inv = inv.reshape(-1)
    num_cells = len(uniq)
    lo = np.full((num_cells, 3), np.inf)
    hi = np.full((num_cells, 3), -np.inf)
    np.minimum.at(lo, inv, qs)
    np.maximum.at(hi, inv, qs)
    ref = 0.5 * (lo + hi)
    radius = 0.5 * np.linalg.norm(hi - lo, axis=-1)
    verts = np.concatenate([ss, es], axis=0)
    out = np.empty(len(q), np.int64)
    cols = tuple(np.ascontiguousarray(a) for a in (*start.T, *(end - start).T))
    order = np.argsort(inv, kind="stable")
    verts = np.unique(verts, axis=0)
    bounds = np.searchsorted(inv[order], np.arange(num_cells + 1))
    chunk = max(1, int(2_000_000 // max(len(ss), 1)))
    for c0 in range(0, num_cells, chunk):
        c1 = min(num_cells, c0 + chunk)
        r = ref[c0:c1]
        ub = pairwise_distance(r, verts).min(axis=1) + 2 * radius[c0:c1]
        lb = pairwise_distance(r, mid) - half[None]
        cand_mask = lb <= ub[:, None] + 1e-9
        counts = cand_mask.sum(axis=1)
        # cells in groups of similar candidate counts, so that one crowded cell does not pad all
        by_count = np.argsort(counts, kind="stable")
        group_bounds = group_by_count(counts[by_count])
        for g0, g1 in zip(group_bounds[:-1], group_bounds[1:]):
            cells_g = by_count[g0:g1]
            kmax = int(counts[cells_g].max())
            # candidate segment indices per cell, in increasing index (first on ties, like argmin)
            cand = np.argsort(~cand_mask[cells_g], axis=1, kind="stable")[:, :kmax]
            cand_valid = np.arange(kmax)[None] < counts[cells_g][:, None]
            local_of_cell = np.full(c1 - c0, -1)
            local_of_cell[cells_g] = np.arange(len(cells_g))
            qi = np.concatenate([order[bounds[c0 + c]:bounds[c0 + c + 1]] for c in cells_g]) if len(cells_g) < 64 else \
                order[bounds[c0]:bounds[c1]][np.isin(inv[order[bounds[c0]:bounds[c1]]] - c0, cells_g)]
            cell_of_q = local_of_cell[inv[qi] - c0]
            cq = cand[cell_of_q]  # [n, kmax]
            vq = cand_valid[cell_of_q]
            d3 = _segment_distance3(q[qi][:, None, :], cols, cq, z_stretch)
            d3 = np.where(vq, d3, np.inf)
            out[qi] = cq[np.arange(len(qi)), np.argmin(d3, axis=1)]
    return out


def pairwise_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distances [n, m] between points a [n, d] and b [m, d] (per component: exact at
    source-frame magnitudes, unlike the |a|^2 + |b|^2 - 2ab expansion)."""
    acc = None
    for k in range(a.shape[1]):
        d = a[:, k, None] - b[None, :, k]
        d *= d
        acc = d if acc is None else acc.__iadd__(d)
    return np.sqrt(acc, out=acc)


def group_by_count(sorted_counts: np.ndarray) -> list[int]:
    """Split points of ascending candidate counts into groups whose counts are within 1.5x."""
    bounds = [0]
    n = len(sorted_counts)
    while bounds[-1] < n:
        lo = max(int(sorted_counts[bounds[-1]]), 1)
        nxt = int(np.searchsorted(sorted_counts, lo * 1.5, side="right"))
        bounds.append(max(nxt, bounds[-1] + 1))
    return bounds


def _segment_distance3(q, cols, idx, z_stretch):
    """Only the stretched 3D point-segment distance (the search's inner loop), per component:
    ``cols`` = (sx, sy, sz, ex, ey, ez) segment starts and start-to-end vectors [S], ``idx`` the
    candidate segments [n, k] of the points q [n, 1, 3]."""
    qx, qy, qz = q[..., 0], q[..., 1], q[..., 2]
    sx, sy, sz, ex, ey, ez = (c[idx] for c in cols)
    px, py, pz = qx - sx, qy - sy, qz - sz
    denom = ex * ex + ey * ey
    num = px * ex + py * ey
    with np.errstate(invalid="ignore", divide="ignore"):
        t = num / denom
    t = np.where(denom > 0, np.clip(t, 0.0, 1.0), 0.0)
    dx, dy, dz = px - ex * t, py - ey * t, (pz - ez * t) * z_stretch
    return np.sqrt(dx * dx + dy * dy + dz * dz)


# ------------------------------------------------------------------------ time to collision
def time_to_collision(ego_x, ego_y, ego_length, ego_width, ego_heading, ego_speed,
                      other_x, other_y, other_length, other_width, other_heading, other_speed,
                      other_valid) -> np.ndarray:
    """Time to collision [..., E] (s) of each ego box with the box it follows, at constant speeds.

    Ego arrays are [..., E], other arrays [..., A] (the egos are usually among the others; an ego
    never follows itself). An other box is followed when it is valid, ahead (longitudinal gap > 0),
    the raw, unwrapped |heading difference| <= 75 degrees (official quirk: no wrapping), their
    lateral overlap < 0, and either the overlap < -0.5 m or the heading difference <= 10 degrees.
    Of those, the nearest ahead; TTC = gap / (ego speed - its speed) when that is > 0, capped at 5 s;
    otherwise (nothing followed, NaN speeds) 5 s.
    """
    ex, ey, el, ew, eh, es = (_f64(a)[..., :, None] for a in (ego_x, ego_y, ego_length, ego_width, ego_heading, ego_speed))
    ox, oy, ol, ow, oh, osp = (_f64(a)[..., None, :] for a in (other_x, other_y, other_length, other_width, other_heading, other_speed))
    ov = np.asarray(other_valid, bool)[..., None, :]
    yaw_diff = np.abs(oh - eh)
    c, s = np.abs(np.cos(yaw_diff)), np.abs(np.sin(yaw_diff))
    long_off = ol / 2 * c + ow / 2 * s
    lat_off = ol / 2 * s + ow / 2 * c
    dx, dy = ox - ex, oy - ey
    ce, se = np.cos(-eh), np.sin(-eh)
    rel_x = ce * dx - se * dy
    rel_y = se * dx + ce * dy
    long_dist = rel_x - el / 2 - long_off
    lat_overlap = np.abs(rel_y) - ew / 2 - lat_off
    following = ((long_dist > 0.0) & (yaw_diff <= MAX_HEADING_DIFF_RAD) & (lat_overlap < 0.0)
                 & ((lat_overlap < -SMALL_OVERLAP_THRESHOLD_M) | (yaw_diff <= MAX_HEADING_DIFF_FOR_SMALL_OVERLAP_RAD)))
    mask = ov & following
    masked = np.where(mask, long_dist, np.inf)
    idx = np.argmin(masked, axis=-1)
    gap = np.take_along_axis(masked, idx[..., None], axis=-1)[..., 0]
    ahead_speed = np.take_along_axis(np.broadcast_to(osp, masked.shape), idx[..., None], axis=-1)[..., 0]
    rel_speed = es[..., 0] - ahead_speed
    with np.errstate(invalid="ignore", divide="ignore"):
        ttc = np.where((rel_speed > 0.0) & np.isfinite(gap),
                       np.minimum(gap / np.where(rel_speed > 0, rel_speed, 1.0), MAXIMUM_TIME_TO_COLLISION_S),
                       MAXIMUM_TIME_TO_COLLISION_S)
    return ttc


def frame_steps(values: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame change of tracks ``values`` [A, T, D] with ``valid`` [A, T]: the central difference
    (half the change over two frames) where both neighbouring frames are valid, the one-sided one where
    one is, 0 where none is. Returns (steps [A, T, D] per frame, has_neighbour [A, T]); divide by the
    frame time for a rate."""
    valid = np.asarray(valid, bool)
    prev_ok = np.zeros_like(valid)
    prev_ok[:, 1:] = valid[:, 1:] & valid[:, :-1]
    next_ok = np.zeros_like(valid)
    next_ok[:, :-1] = valid[:, :-1] & valid[:, 1:]
    fwd = np.zeros_like(values)
    fwd[:, :-1] = values[:, 1:] - values[:, :-1]
    bwd = np.zeros_like(values)
    bwd[:, 1:] = values[:, 1:] - values[:, :-1]
    steps = np.where((prev_ok & next_ok)[..., None], 0.5 * (fwd + bwd),
                     np.where(next_ok[..., None], fwd, np.where(prev_ok[..., None], bwd, 0.0)))
    return steps, prev_ok | next_ok
