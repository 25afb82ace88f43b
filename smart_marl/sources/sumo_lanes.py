"""SUMO road networks, the lane geometry their maps are made of: source coordinates quantised
(:func:`quantize`), polylines densified, SUMO's frame rotated, a lane's shape, the painted lines
beside lanes (:func:`road_lines`) and lanes cut into WOMD-length pieces (:func:`split_lanes`).
Re-exported by :mod:`.sumo_net`, whose docstring says what becomes what.
"""

from __future__ import annotations

import math

import numpy as np

from ..scenario import LaneType, LinkType, RoadLineType


QUANTUM = 2.0 ** -16
"""Source coordinates are multiples of this (m) so that local float32 <-> source float64 is exact."""

LANE_POINT_SPACING_M = 1.0
"""Lane centre lines and road edges get a point at least every metre (WOMD's are ~0.5 m apart)."""


def quantize(values: np.ndarray) -> np.ndarray:
    """Round source coordinates to multiples of :data:`QUANTUM` (float64)."""
    return np.round(np.asarray(values, np.float64) / QUANTUM) * QUANTUM


def densify(points: np.ndarray, max_spacing_m: float) -> np.ndarray:
    """A polyline [n, D] with points added on its segments so that none is longer than ``max_spacing_m``
    (its own vertices are kept)."""
    seg = np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1)
    pieces = np.maximum(np.ceil(seg / max_spacing_m).astype(np.int64), 1)
    start = np.repeat(np.arange(len(seg)), pieces)
    frac = (np.arange(pieces.sum()) - np.repeat(np.cumsum(pieces) - pieces, pieces)) / np.repeat(pieces, pieces)
    out = points[start] + frac[:, None] * (points[start + 1] - points[start])
    return np.concatenate([out, points[-1:]])


def rotation_matrix(rotation_rad: float) -> np.ndarray:
    c, s = math.cos(rotation_rad), math.sin(rotation_rad)
    return np.array([[c, -s], [s, c]])


def lane_shape(lane) -> np.ndarray:
    """A sumolib lane's shape points [n, 3] (x, y, z; z = 0 where the network has none), SUMO's frame."""
    pts = np.asarray(lane.getShape3D() if hasattr(lane, "getShape3D") else lane.getShape(), np.float64)
    if pts.shape[1] == 2:
        pts = np.concatenate([pts, np.zeros((len(pts), 1))], axis=1)
    return pts


def road_lines(net, lanes: list, subtypes: list[int], rotation: np.ndarray) -> tuple[list[np.ndarray], list[int]]:
    """The painted lines of the network's roads (see the module docstring): polylines [n, 3] (source
    frame, quantised, a point at least every metre) and their RoadLineType."""
    import shapely

    kept = {lane.getID(): k for k, lane in enumerate(lanes)}
    points: list[np.ndarray] = []
    kinds: list[int] = []

    def add(lane, side: float, kind: RoadLineType) -> None:
        shape = np.asarray(lane.getShape(), np.float64)[:, :2]
        if len(shape) < 2 or np.ptp(shape, axis=0).max() < 1e-3:
            return
        line = shapely.offset_curve(shapely.LineString(shape), side * lane.getWidth() / 2, join_style="mitre", mitre_limit=2.0)
        for part in getattr(line, "geoms", [line]):
            if part.is_empty or part.length < 0.5:
                continue
            xy = quantize(densify(np.asarray(part.coords)[:, :2], LANE_POINT_SPACING_M) @ rotation.T)
            points.append(np.concatenate([xy, np.zeros((len(xy), 1))], axis=1))
            kinds.append(int(kind))

    for edge in net.getEdges():  # normal edges only: no painted line crosses a junction
        road = [lane for lane in edge.getLanes() if lane.getID() in kept]
        if not road:
            continue
        bike = [subtypes[kept[lane.getID()]] == LaneType.BIKE_LANE for lane in road]
        for i in range(len(road) - 1):
            add(road[i], 1.0, RoadLineType.SOLID_SINGLE_WHITE if bike[i] or bike[i + 1] else RoadLineType.BROKEN_SINGLE_WHITE)
        opposite = [e for e in edge.getToNode().getOutgoing() if e.getToNode() == edge.getFromNode()]
        if not opposite:
            add(road[-1], 1.0, RoadLineType.SOLID_SINGLE_YELLOW)
        elif edge.getID() < opposite[0].getID():  # one centre line per two-way road
            add(road[-1], 1.0, RoadLineType.SOLID_DOUBLE_YELLOW)
    return points, kinds


def split_lanes(shapes: list[np.ndarray], lane_ids: np.ndarray, edge_of: list[str | None], lane_links: np.ndarray,
                max_piece_m: float):
    """Cut the lanes of normal edges into pieces of at most ``max_piece_m`` (all lanes of an edge into
    the same number of pieces, at the same fractions of their length, so that neighbours stay side by
    side), as WOMD cuts its lanes: a lane's pieces follow each other by SUCCESSOR/PREDECESSOR links
    (each piece ends on the point where the next starts), piece i of a lane neighbours piece i of its
    neighbour, a lane's successors follow its last piece. The first piece keeps the lane's id; the
    others get new ids after the largest. Internal (junction) lanes (``edge_of`` None) are not cut.

    Returns (shapes, ids [P], parent lane index of each piece [P], links [E', 3], last piece id of each
    original lane id)."""
    lengths = [float(np.linalg.norm(np.diff(s[:, :2], axis=0), axis=1).sum()) for s in shapes]
    count: dict[str, int] = {}
    for k, edge in enumerate(edge_of):
        if edge is not None:
            count[edge] = max(count.get(edge, 1), int(math.ceil(lengths[k] / max_piece_m - 1e-9)))
    next_id = int(lane_ids.max(initial=0)) + 1
    out_shapes, out_ids, parent = [], [], []
    pieces: dict[int, list[int]] = {}
    for k, shape in enumerate(shapes):
        n = count.get(edge_of[k], 1) if edge_of[k] is not None else 1
        if n > 1:
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(shape[:, :2], axis=0), axis=1))])
            cuts = np.searchsorted(arc, arc[-1] * np.arange(1, n) / n)
            cuts = np.unique(np.clip(cuts, 1, len(shape) - 2))
            bounds = [0, *cuts.tolist(), len(shape) - 1]
        else:
            bounds = [0, len(shape) - 1]
        ids = []
        for i in range(len(bounds) - 1):
            ids.append(int(lane_ids[k]) if i == 0 else next_id)
            next_id += i > 0
            out_shapes.append(shape[bounds[i]:bounds[i + 1] + 1])
            parent.append(k)
        out_ids += ids
        pieces[int(lane_ids[k])] = ids
    links = []
    for a, b, kind in lane_links.tolist():
        pa, pb = pieces[a], pieces[b]
        if kind == LinkType.SUCCESSOR:
            links.append((pa[-1], pb[0], kind))
        elif kind == LinkType.PREDECESSOR:
            links.append((pa[0], pb[-1], kind))
        else:  # neighbours: piece by piece
            links += [(x, y, kind) for x, y in zip(pa, pb)]
    for ids in pieces.values():
        links += [(x, y, LinkType.SUCCESSOR) for x, y in zip(ids[:-1], ids[1:])]
        links += [(y, x, LinkType.PREDECESSOR) for x, y in zip(ids[:-1], ids[1:])]
    last_piece = {lane: ids[-1] for lane, ids in pieces.items()}
    return (out_shapes, np.asarray(out_ids, np.int64), np.asarray(parent, np.int64),
            np.asarray(links, np.int64).reshape(-1, 3), last_piece)
