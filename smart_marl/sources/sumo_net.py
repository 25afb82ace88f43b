"""SUMO road networks: random networks from ``netgenerate`` and their vector maps.

Stage: the map half of the SUMO source (traffic simulator -> **Scenario**). A :class:`NetworkSpec`
(drawn by :func:`random_network_spec`) says which network ``netgenerate`` builds (grid, spider or
random topology, 1-4 lanes, block lengths, perturbed node positions for varied angles, junction
control, sidewalks, crossings, bike lanes); :func:`build_network` runs it; :func:`network_map`
turns the ``.net.xml`` into a :class:`NetworkMap` (the whole network's map features in source
coordinates), which :meth:`NetworkMap.crop` cuts into the :class:`~smart_marl.scenario.RoadMap` of
one scene.

What becomes what (decided here, relied on by the tests):

* LANE: every lane (normal and internal junction lanes, so that the topology is continuous through
  junctions) that a car or a bicycle may use; ``BIKE_LANE`` for bicycle-only lanes,
  ``SURFACE_STREET`` otherwise. SUCCESSOR links follow SUMO connections (a lane -> the internal lane
  that crosses the junction -> the lane after it); PREDECESSOR links are exactly their reverse;
  LEFT/RIGHT neighbours are the adjacent lanes of the same edge with the same subtype. Speed limits
  are SUMO's lane speeds in mph.
* Sidewalks and walking areas are not in the map (they are not lanes for vehicles and WOMD has no
  such feature); pedestrians walk there as agents.
* CROSSWALK: SUMO pedestrian crossings, as the polygon of the crossing lane (its centre line
  widened to its width).
* ROAD_EDGE (BOUNDARY): the boundary of the drivable area, the union of every LANE's polygon (small
  cracks between junction lanes closed, small holes dropped), oriented so that the drivable area is
  on the left of each polyline; cut to the scene's radius.
* ROAD_LINE: the painted lines of every road (not through junctions), as WOMD maps hold them: a
  ``BROKEN_SINGLE_WHITE`` line between two lanes of one direction (``SOLID_SINGLE_WHITE`` where one
  of them is a bike lane), a ``SOLID_DOUBLE_YELLOW`` centre line between the two directions of a
  two-way road (once per pair of opposite edges) and a ``SOLID_SINGLE_YELLOW`` on the left of a
  one-way road; each is the lane's centre line offset by half its width (the right side of a road
  is its road edge).
* STOP_SIGN: one at the end of every lane whose junction link has a stop or all-way-stop rule
  (``priority_stop`` / ``allway_stop`` junctions), linked to that lane.
* Traffic lights: every signal link of SUMO controls the internal lane that crosses the junction
  (one per movement, so a left turn and a straight movement from the same lane keep their own
  signals); its stop point is the first point of that internal lane (the stop line).

Source coordinates are SUMO's metres rotated by the spec's ``rotation_rad`` about SUMO's origin and
quantised to 2**-16 m, so that float32 local coordinates convert back and forth exactly.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import subprocess
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..scenario import LaneType, LinkType, MapFeatureType, RoadEdgeType, RoadMap, SignalState, wrap_angle
from .sumo_lanes import (  # noqa: F401  (re-exported: the map's lane geometry is imported from here)
    LANE_POINT_SPACING_M, QUANTUM, densify, lane_shape, quantize, road_lines, rotation_matrix, split_lanes,
)

MPH_PER_MPS = 2.2369362920544

# Feature id spaces (a scene's features keep these ids; lanes are numbered from 1).
CROSSWALK_ID0 = 1_000_000
STOP_SIGN_ID0 = 2_000_000
ROAD_EDGE_ID0 = 3_000_000
ROAD_LINE_ID0 = 4_000_000

_VEHICLE_CLASSES = ("passenger", "truck", "bus", "delivery")

INSTALL_HINT = 'SUMO is an optional extra: pip install "smart-marl[sumo]" (eclipse-sumo, libsumo, sumolib, shapely)'


class SumoUnavailableError(ImportError):
    """The SUMO packages (eclipse-sumo, libsumo, sumolib) or shapely are not installed."""


def require_sumo():
    """``(sumo package, sumolib, libsumo)`` imported lazily, or a clear :class:`SumoUnavailableError`."""
    try:
        import sumo  # eclipse-sumo: the binaries and SUMO_HOME
        import sumolib
        os.environ.setdefault("SUMO_HOME", sumo.SUMO_HOME)
        with contextlib.redirect_stdout(io.StringIO()):  # libsumo prints a pyarrow version note on import
            import libsumo
    except ImportError as exc:
        raise SumoUnavailableError(f"{INSTALL_HINT} ({exc})") from exc
    return sumo, sumolib, libsumo


def sumo_binary(name: str) -> str:
    """The path of a SUMO binary (``netgenerate``, ``sumo``...) inside the eclipse-sumo wheel."""
    sumo, _, _ = require_sumo()
    path = Path(sumo.SUMO_HOME) / "bin" / name
    if not path.exists():
        raise SumoUnavailableError(f"{path} is missing from the eclipse-sumo package; {INSTALL_HINT}")
    return os.fspath(path)


# ------------------------------------------------------------------------------------ network specs
@dataclass(frozen=True)
class NetworkSpec:
    """What ``netgenerate`` builds. ``params`` are the topology's own options (without ``--``)."""

    kind: str  # "grid" | "spider" | "rand"
    params: dict[str, Any]
    lanes: int  # default lane number (1-4)
    random_lanenumber: bool  # draw each edge's lane number from [1, lanes]
    speed_mps: float
    junction_type: str  # netgenerate default.junctions.type
    tls_guess: bool  # on top of the junction type: put lights where traffic is heavy
    sidewalks: bool
    crossings: bool
    bikelanes: bool
    perturb_m: float  # node position perturbation (normal sigma): varied angles and block lengths
    rotation_rad: float  # rotation of the whole network in the source frame
    seed: int
    lane_width_m: float | None = None  # None: netgenerate's default (3.2 m)

    def netgenerate_args(self, out_path: str) -> list[str]:
        args = [f"--{self.kind}"]
        for key, value in self.params.items():
            if value is True:
                args.append(f"--{self.kind}.{key}")
            elif value is not False:
                args += [f"--{self.kind}.{key}", str(value)]
        args += ["--default.lanenumber", str(self.lanes), "--default.speed", f"{self.speed_mps:.3f}",
                 "--default.junctions.type", self.junction_type, "--seed", str(self.seed),
                 "--no-turnarounds", "--output-file", out_path, "--no-warnings", "--xml-validation", "never"]
        if self.random_lanenumber:
            args.append("--random-lanenumber")
        if self.lane_width_m is not None:
            args += ["--default.lanewidth", f"{self.lane_width_m:.2f}"]
        if self.tls_guess:
            args += ["--tls.guess", "--tls.guess.threshold", "70"]
        if self.sidewalks:
            args += ["--sidewalks.guess", "--sidewalks.guess.min-speed", "0", "--sidewalks.guess.max-speed", "100"]
            if self.crossings:
                args += ["--crossings.guess", "--crossings.guess.speed-threshold", "100"]
        if self.bikelanes:
            args += ["--bikelanes.guess", "--bikelanes.guess.min-speed", "0", "--bikelanes.guess.max-speed", "100"]
        if self.perturb_m > 0:
            args += ["--perturb-x", f"norm(0,{self.perturb_m:.2f})", "--perturb-y", f"norm(0,{self.perturb_m:.2f})"]
        return args

    def to_metadata(self) -> dict[str, Any]:
        """The spec as JSON-able values (the optional fields only when set, as the first generator wrote it)."""
        out = asdict(self)
        if out["lane_width_m"] is None:
            del out["lane_width_m"]
        return out


JUNCTION_TYPES = ("traffic_light", "priority", "priority_stop", "allway_stop", "right_before_left")
NETWORK_KINDS = ("grid", "spider", "rand")
SPEEDS_MPS = (8.33, 11.11, 13.89, 16.67, 19.44)


def random_network_spec(rng: np.random.Generator, pedestrians: bool = True, bicycles: bool = True,
                        length_scale: float = 1.0, kind_weights=(0.45, 0.2, 0.35),
                        junction_weights=(0.5, 0.25, 0.1, 0.07, 0.08), speed_weights=None,
                        tls_guess_probability: float = 0.4, lane_width_m: tuple[float, float] | None = None,
                        speed_levels_mps: tuple[float, ...] = SPEEDS_MPS) -> NetworkSpec:
    """A random network: topology, sizes and rules drawn from ``rng``. ``length_scale`` multiplies
    every block length (grid blocks, spider rings, random-network edge lengths); the weights are the
    probabilities of :data:`NETWORK_KINDS`, :data:`JUNCTION_TYPES` and ``speed_levels_mps`` (the
    network's default speed limit, :data:`SPEEDS_MPS` unless given; None: uniform); ``lane_width_m``:
    a range to draw the lane width from (None: netgenerate's 3.2 m, and no draw). The defaults are
    the first generator's, whose draws they repeat exactly (``SumoConfig.legacy()``)."""
    k = float(length_scale)
    kind = str(rng.choice(list(NETWORK_KINDS), p=list(kind_weights)))
    if kind == "grid":
        params = {"x-number": int(rng.integers(3, 6)), "y-number": int(rng.integers(2, 5)),
                  "x-length": round(float(rng.uniform(60 * k, 180 * k)), 1),
                  "y-length": round(float(rng.uniform(60 * k, 180 * k)), 1),
                  "attach-length": round(float(rng.uniform(40 * k, 120 * k)), 1)}
        perturb = float(rng.choice([0.0, rng.uniform(1, 8)]))
    elif kind == "spider":
        params = {"arm-number": int(rng.integers(4, 8)), "circle-number": int(rng.integers(2, 4)),
                  "space-radius": round(float(rng.uniform(60 * k, 140 * k)), 1), "omit-center": bool(rng.random() < 0.5)}
        perturb = float(rng.choice([0.0, rng.uniform(1, 5)]))
    else:
        params = {"iterations": int(rng.integers(20, 60)), "min-distance": round(float(rng.uniform(60 * k, 90 * k)), 1),
                  "max-distance": round(float(rng.uniform(120 * k, 220 * k)), 1),
                  "min-angle": round(float(rng.uniform(35, 60)), 1),
                  "bidi-probability": round(float(rng.uniform(0.8, 1.0)), 2)}
        perturb = 0.0
    lanes = int(rng.choice([1, 2, 3, 4], p=[0.25, 0.4, 0.25, 0.1]))
    junction_type = str(rng.choice(list(JUNCTION_TYPES), p=list(junction_weights)))
    spec = dict(
        kind=kind, params=params, lanes=lanes, random_lanenumber=bool(lanes > 1 and rng.random() < 0.5),
        speed_mps=round(float(rng.choice(list(speed_levels_mps), p=None if speed_weights is None else list(speed_weights))), 2),
        junction_type=junction_type,
        tls_guess=bool(junction_type != "traffic_light" and rng.random() < tls_guess_probability),
        sidewalks=bool(pedestrians), crossings=bool(pedestrians),
        bikelanes=bool(bicycles and rng.random() < 0.6), perturb_m=round(perturb, 2),
        rotation_rad=round(float(rng.uniform(-math.pi, math.pi)), 4), seed=int(rng.integers(1, 2**31 - 1)),
    )
    if lane_width_m is not None:
        spec["lane_width_m"] = round(float(rng.uniform(*lane_width_m)), 2)
    return NetworkSpec(**spec)


def build_network(spec: NetworkSpec, out_path: str | os.PathLike) -> Path:
    """Run ``netgenerate`` for ``spec``; returns the ``.net.xml`` path."""
    out_path = Path(out_path)
    cmd = [sumo_binary("netgenerate"), *spec.netgenerate_args(os.fspath(out_path))]
    result = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "SUMO_HOME": _sumo_home()})
    if result.returncode != 0 or not out_path.exists():
        raise RuntimeError(f"netgenerate failed ({result.returncode}) for {spec}: {result.stderr.strip()[-2000:]}")
    return out_path


def _direction(shape, at_end: bool) -> float:
    a, b = (shape[-2], shape[-1]) if at_end else (shape[0], shape[1])
    return math.atan2(b[1] - a[1], b[0] - a[0])


def turn_angle(from_edge, to_edge) -> float:
    """The turn (radians, counter-clockwise positive, 0: straight on) from the end of one sumolib edge
    to the start of the next, measured on their first lanes."""
    turn = _direction(to_edge.getLanes()[0].getShape(), False) - _direction(from_edge.getLanes()[0].getShape(), True)
    return wrap_angle(turn)


def _sumo_home() -> str:
    sumo, _, _ = require_sumo()
    return os.fspath(sumo.SUMO_HOME)


# ------------------------------------------------------------------------------------ network maps
@dataclass
class NetworkMap:
    """The whole network's map in source coordinates (float64), ready to be cropped per scene."""

    lane_ids: np.ndarray  # [L] int64
    lane_sumo_ids: list[str]
    lane_subtypes: np.ndarray  # [L] int8 LaneType
    lane_speed_mph: np.ndarray  # [L] float32
    lane_widths_m: np.ndarray  # [L] float64
    lane_points: np.ndarray  # [P, 3] float64
    lane_offsets: np.ndarray  # [L + 1]
    lane_links: np.ndarray  # [E, 3] int64 (from lane id, to lane id, LinkType)
    crosswalk_points: np.ndarray  # [Q, 3]
    crosswalk_offsets: np.ndarray  # [C + 1]
    stop_sign_points: np.ndarray  # [S, 3]
    stop_sign_lanes: np.ndarray  # [S] int64 lane ids
    road_edges: list[np.ndarray]  # oriented closed rings [n, 2] (drivable area on the left)
    road_line_points: np.ndarray  # [Q, 3] float64
    road_line_offsets: np.ndarray  # [M + 1]
    road_line_subtypes: np.ndarray  # [M] int8 RoadLineType
    signal_links: dict[str, np.ndarray]  # tls id -> [links] lane id of each SUMO link index (-1: none)
    signal_stop_points: dict[int, np.ndarray]  # controlled lane id -> stop point [3]
    lane_index_of_sumo: dict[str, int] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)

    def crop(self, path_xy: np.ndarray, radius_m: float, origin: np.ndarray) -> tuple[RoadMap, np.ndarray]:
        """The RoadMap of the features within ``radius_m`` of the path ``path_xy`` ([K, 2] source frame:
        the self-driving car's positions over the scene), in the local frame whose origin is ``origin``
        (source [3]); also the ids of the lanes kept."""
        import shapely

        path = np.asarray(path_xy, np.float64).reshape(-1, 2)
        features: list[dict[str, Any]] = []

        def min_d2(points: np.ndarray) -> np.ndarray:
            return (((points[:, None, :2] - path[None]) ** 2).sum(-1)).min(axis=1)

        def near(points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
            if len(offsets) <= 1:
                return np.zeros(0, bool)
            return np.minimum.reduceat(min_d2(points), offsets[:-1]) <= radius_m ** 2

        def local(points: np.ndarray) -> np.ndarray:
            return (points - origin).astype(np.float32)

        keep_lane = near(self.lane_points, self.lane_offsets)
        lane_index = np.flatnonzero(keep_lane)
        kept_ids = self.lane_ids[lane_index]
        for i in lane_index:
            features.append(dict(id=int(self.lane_ids[i]), type=MapFeatureType.LANE, subtype=int(self.lane_subtypes[i]),
                                 speed_limit_mph=float(self.lane_speed_mph[i]),
                                 points=local(self.lane_points[self.lane_offsets[i]:self.lane_offsets[i + 1]])))
        for k in np.flatnonzero(near(self.road_line_points, self.road_line_offsets)):
            features.append(dict(id=ROAD_LINE_ID0 + int(k), type=MapFeatureType.ROAD_LINE, subtype=int(self.road_line_subtypes[k]),
                                 points=local(self.road_line_points[self.road_line_offsets[k]:self.road_line_offsets[k + 1]])))
        for k in np.flatnonzero(near(self.crosswalk_points, self.crosswalk_offsets)):
            features.append(dict(id=CROSSWALK_ID0 + int(k), type=MapFeatureType.CROSSWALK,
                                 points=local(self.crosswalk_points[self.crosswalk_offsets[k]:self.crosswalk_offsets[k + 1]])))
        stop_links = []
        if len(self.stop_sign_points):
            d2 = min_d2(self.stop_sign_points)
            for k in np.flatnonzero((d2 <= radius_m ** 2) & np.isin(self.stop_sign_lanes, kept_ids)):
                fid = STOP_SIGN_ID0 + int(k)
                features.append(dict(id=fid, type=MapFeatureType.STOP_SIGN, points=local(self.stop_sign_points[k:k + 1])))
                stop_links.append((fid, int(self.stop_sign_lanes[k]), LinkType.STOP_SIGN_LANE))
        area = (shapely.LineString(path) if len(path) > 1 else shapely.Point(*path[0])).buffer(radius_m, quad_segs=16)
        edge_count = 0
        for ring in self.road_edges:
            piece = shapely.LineString(ring).intersection(area)
            for line in getattr(piece, "geoms", [piece]):
                if line.is_empty or line.geom_type != "LineString" or line.length < 0.5:  # (a point touch)
                    continue
                xy = quantize(densify(np.asarray(line.coords)[:, :2], LANE_POINT_SPACING_M))
                pts = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
                pts[:, 2] = origin[2]
                features.append(dict(id=ROAD_EDGE_ID0 + edge_count, type=MapFeatureType.ROAD_EDGE,
                                     subtype=RoadEdgeType.BOUNDARY, points=local(pts)))
                edge_count += 1
        # lane links whose both ends are kept, then the stop signs' links; ordered per feature as WOMD stores them
        links = self.lane_links[np.isin(self.lane_links[:, 0], kept_ids) & np.isin(self.lane_links[:, 1], kept_ids)]
        all_links = [tuple(int(v) for v in row) for row in links] + stop_links
        position = {f["id"]: k for k, f in enumerate(features)}
        all_links.sort(key=lambda link: (position[link[0]], link[2]))
        return RoadMap.from_features(features, all_links), kept_ids


def _vehicle_lanes(net) -> tuple[list, list[int], list]:
    """(the lanes a car or a bicycle may use, their LaneType, the pedestrian crossing lanes) of a sumolib network."""
    lanes, subtypes = [], []
    crossings = []
    for edge in net.getEdges(withInternal=True):
        function = edge.getFunction()
        if function == "crossing":
            crossings.extend(edge.getLanes())
            continue
        if function == "walkingarea":
            continue
        for lane in edge.getLanes():
            cars = any(lane.allows(c) for c in _VEHICLE_CLASSES)
            bikes = lane.allows("bicycle")
            if not cars and not bikes:
                continue  # sidewalks and other lanes that no vehicle uses
            if len(lane.getShape()) < 2:
                continue
            lanes.append(lane)
            subtypes.append(LaneType.SURFACE_STREET if cars else LaneType.BIKE_LANE)
    return lanes, subtypes, crossings


def _lane_topology(lanes: list, subtypes: list[int], index_of: dict[str, int], lane_ids: np.ndarray):
    """(links [E, 3] (from id, to id, LinkType), indices of the lanes with a stop rule, (light, link index, lane index)
    of every signal link) from SUMO's connections and the lanes side by side on an edge."""
    successors: list[list[int]] = [[] for _ in lanes]
    stop_sign_lanes, signal_rows = [], []
    for k, lane in enumerate(lanes):
        stop_rule = False
        for conn in lane.getOutgoing():
            via = conn.getViaLaneID()
            target = via if via else conn.getToLane().getID()
            j = index_of.get(target)
            if j is not None and lane_ids[j] not in successors[k]:
                successors[k].append(int(lane_ids[j]))
            stop_rule |= conn.getState() in ("s", "w")
            if conn.getTLSID() and conn.getTLLinkIndex() >= 0:
                controlled = index_of.get(via) if via else None
                if controlled is not None:
                    signal_rows.append((conn.getTLSID(), conn.getTLLinkIndex(), controlled))
        if stop_rule and lane.getEdge().getFunction() != "internal":
            stop_sign_lanes.append(k)
    predecessors: list[list[int]] = [[] for _ in lanes]
    for k, succ in enumerate(successors):
        for to in succ:
            predecessors[int(to) - 1].append(int(lane_ids[k]))
    links = []
    for k, lane in enumerate(lanes):
        links += [(lane_ids[k], to, LinkType.SUCCESSOR) for to in successors[k]]
        links += [(lane_ids[k], fr, LinkType.PREDECESSOR) for fr in predecessors[k]]
        edge_lanes = lane.getEdge().getLanes()
        i = lane.getIndex()
        for nb_index, kind in ((i + 1, LinkType.LEFT_NEIGHBOR), (i - 1, LinkType.RIGHT_NEIGHBOR)):
            if 0 <= nb_index < len(edge_lanes):
                j = index_of.get(edge_lanes[nb_index].getID())
                if j is not None and subtypes[j] == subtypes[k]:
                    links.append((lane_ids[k], lane_ids[j], kind))
    lane_links = np.array(links, np.int64).reshape(-1, 3)
    return lane_links, stop_sign_lanes, signal_rows


def _signal_tables(signal_rows: list, lane_ids: np.ndarray, shapes: list[np.ndarray]):
    """(light id -> lane id per link index, -1 where none; lane id -> stop point, the lane's first point)."""
    signal_links: dict[str, np.ndarray] = {}
    signal_stop_points: dict[int, np.ndarray] = {}
    for tls_id, link_index, k in signal_rows:
        table = signal_links.setdefault(tls_id, np.full(0, -1, np.int64))
        if link_index >= len(table):
            table = np.concatenate([table, np.full(link_index + 1 - len(table), -1, np.int64)])
        table[link_index] = lane_ids[k]
        signal_links[tls_id] = table
        signal_stop_points[int(lane_ids[k])] = shapes[k][0]
    return signal_links, signal_stop_points


def _crosswalks(crossings: list, rot: np.ndarray) -> tuple[list[np.ndarray], list[int]]:
    """The crosswalk polygons [n, 3] (crossing lanes widened to their width, counter-clockwise, quantised) and their sizes."""
    import shapely
    from shapely.geometry import polygon as shapely_polygon

    cw_pts, cw_len = [], []
    for lane in crossings:
        line = np.asarray(lane.getShape(), np.float64)[:, :2] @ rot.T
        if len(line) < 2:
            continue
        poly = shapely.LineString(line).buffer(lane.getWidth() / 2, cap_style="flat")
        ring = np.asarray(shapely_polygon.orient(poly, 1.0).exterior.coords)[:-1]
        pts = np.zeros((len(ring), 3))
        pts[:, :2] = quantize(ring)
        cw_pts.append(pts)
        cw_len.append(len(pts))
    return cw_pts, cw_len


def _road_edges(lanes: list, shapes: list[np.ndarray]) -> list[np.ndarray]:
    """The drivable area's boundary rings: the union of the lane polygons (square caps: a dead-end road reaches half a
    lane width past its lanes' ends), small cracks closed, holes under 25 m^2 dropped, drivable on the left."""
    import shapely
    from shapely.geometry import polygon as shapely_polygon

    polys = [shapely.LineString(s[:, :2]).buffer(lanes[k].getWidth() / 2, cap_style="square", quad_segs=2)
             for k, s in enumerate(shapes) if np.ptp(s[:, :2], axis=0).max() > 1e-3]
    drivable = shapely.unary_union(polys).buffer(0.75, quad_segs=2).buffer(-0.75, quad_segs=2)
    drivable = drivable.simplify(0.05)
    rings: list[np.ndarray] = []
    for poly in getattr(drivable, "geoms", [drivable]):
        if poly.is_empty or poly.geom_type != "Polygon":
            continue
        poly = shapely_polygon.orient(poly, 1.0)  # exterior counter-clockwise, holes clockwise: drivable on the left
        rings.append(np.asarray(poly.exterior.coords))
        rings += [np.asarray(h.coords) for h in poly.interiors if shapely.Polygon(h).area >= 25.0]
    return rings


def network_map(net_path: str | os.PathLike, rotation_rad: float = 0.0, max_lane_piece_m: float | None = None) -> NetworkMap:
    """Read a ``.net.xml`` into a :class:`NetworkMap` (see the module docstring for what becomes what);
    with ``max_lane_piece_m``, lanes longer than that are cut into pieces (:func:`split_lanes`)."""
    _, sumolib, _ = require_sumo()
    net = sumolib.net.readNet(os.fspath(net_path), withInternal=True)
    rot = rotation_matrix(rotation_rad)

    def shape3d(lane) -> np.ndarray:
        out = densify(lane_shape(lane), LANE_POINT_SPACING_M)
        out[:, :2] = quantize(out[:, :2] @ rot.T)
        out[:, 2] = quantize(out[:, 2])
        return out

    lanes, subtypes, crossings = _vehicle_lanes(net)
    index_of = {lane.getID(): k for k, lane in enumerate(lanes)}
    lane_ids = np.arange(1, len(lanes) + 1, dtype=np.int64)
    shapes = [shape3d(lane) for lane in lanes]
    lengths = np.array([len(s) for s in shapes], np.int64)

    lane_links, stop_sign_lanes, signal_rows = _lane_topology(lanes, subtypes, index_of, lane_ids)
    signal_links, signal_stop_points = _signal_tables(signal_rows, lane_ids, shapes)
    cw_pts, cw_len = _crosswalks(crossings, rot)
    rings = _road_edges(lanes, shapes)
    line_pts, line_types = road_lines(net, lanes, subtypes, rot)
    stop_pts = np.array([shapes[k][-1] for k in stop_sign_lanes], np.float64).reshape(-1, 3)
    stop_ids = lane_ids[np.array(stop_sign_lanes, np.int64)] if stop_sign_lanes else np.zeros(0, np.int64)
    junction_types = sorted({n.getType() for n in net.getNodes()})
    sumo_ids = [lane.getID() for lane in lanes]
    speeds = np.array([lane.getSpeed() * MPH_PER_MPS for lane in lanes], np.float32)
    widths = np.array([lane.getWidth() for lane in lanes])
    parent = np.arange(len(lanes))
    if max_lane_piece_m is not None:
        edge_of = [lane.getEdge().getID() if lane.getEdge().getFunction() != "internal" else None for lane in lanes]
        shapes, lane_ids, parent, lane_links, last_piece = split_lanes(shapes, lane_ids, edge_of, lane_links, max_lane_piece_m)
        stop_ids = np.array([last_piece[int(i)] for i in stop_ids], np.int64)
        sumo_ids = [sumo_ids[p] if k == 0 or parent[k - 1] != p else f"{sumo_ids[p]}#{k - np.flatnonzero(parent == p)[0]}"
                    for k, p in enumerate(parent)]
        lengths = np.array([len(s) for s in shapes], np.int64)
    return NetworkMap(
        lane_ids=lane_ids,
        lane_sumo_ids=sumo_ids,
        lane_subtypes=np.array(subtypes, np.int8)[parent],
        lane_speed_mph=speeds[parent],
        lane_widths_m=widths[parent],
        lane_points=np.concatenate(shapes) if shapes else np.zeros((0, 3)),
        lane_offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        lane_links=lane_links,
        crosswalk_points=np.concatenate(cw_pts) if cw_pts else np.zeros((0, 3)),
        crosswalk_offsets=np.concatenate([[0], np.cumsum(cw_len)]).astype(np.int64),
        stop_sign_points=stop_pts,
        stop_sign_lanes=stop_ids,
        road_edges=rings,
        road_line_points=np.concatenate(line_pts) if line_pts else np.zeros((0, 3)),
        road_line_offsets=np.concatenate([[0], np.cumsum([len(q) for q in line_pts])]).astype(np.int64),
        road_line_subtypes=np.array(line_types, np.int8),
        signal_links=signal_links,
        signal_stop_points=signal_stop_points,
        lane_index_of_sumo={sid: int(np.flatnonzero(parent == k)[0]) for sid, k in index_of.items()},
        stats={"lanes": len(lanes), "lane_pieces": len(shapes), "crossings": len(cw_len),
               "traffic_lights": len(signal_links), "stop_signs": len(stop_sign_lanes), "road_lines": len(line_types),
               "junction_types": junction_types,
               "edges": sum(1 for e in net.getEdges() if e.getFunction() == "")},
    )


# SUMO signal characters -> SignalState (https://sumo.dlr.de/docs/Simulation/Traffic_Lights.html#signal_state_definitions)
SIGNAL_OF_CHAR = np.zeros(256, np.int8)
for _chars, _state in (("Gg", SignalState.GO), ("yYu", SignalState.CAUTION), ("rR", SignalState.STOP),
                       ("o", SignalState.FLASHING_CAUTION), ("s", SignalState.FLASHING_STOP), ("O", SignalState.UNKNOWN)):
    for _c in _chars:
        SIGNAL_OF_CHAR[ord(_c)] = _state
