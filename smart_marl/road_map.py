"""The scene's vector map (:class:`RoadMap`): typed polylines and polygons in CSR form, with lane
topology, and the WOMD codes of its feature types, subtypes and links.

Re-exported by :mod:`smart_marl.scenario`, where a :class:`~smart_marl.scenario.Scenario` holds
one as ``road_map``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Iterable, Mapping

import numpy as np

from .values import _check, _coerce, _replace


class MapFeatureType(IntEnum):
    """Kinds of map feature (WOMD's ``MapFeature`` oneof)."""

    LANE = 0  # centerline polyline
    ROAD_LINE = 1  # painted line polyline
    ROAD_EDGE = 2  # boundary of the drivable area, polyline
    STOP_SIGN = 3  # a single point
    CROSSWALK = 4  # polygon
    SPEED_BUMP = 5  # polygon
    DRIVEWAY = 6  # polygon


POLYGON_FEATURES = frozenset({MapFeatureType.CROSSWALK, MapFeatureType.SPEED_BUMP, MapFeatureType.DRIVEWAY})


class LaneType(IntEnum):
    """Subtype of a LANE feature (WOMD codes)."""

    UNDEFINED = 0
    FREEWAY = 1
    SURFACE_STREET = 2
    BIKE_LANE = 3


class RoadLineType(IntEnum):
    """Subtype of a ROAD_LINE feature (WOMD codes)."""

    UNKNOWN = 0
    BROKEN_SINGLE_WHITE = 1
    SOLID_SINGLE_WHITE = 2
    SOLID_DOUBLE_WHITE = 3
    BROKEN_SINGLE_YELLOW = 4
    BROKEN_DOUBLE_YELLOW = 5
    SOLID_SINGLE_YELLOW = 6
    SOLID_DOUBLE_YELLOW = 7
    PASSING_DOUBLE_YELLOW = 8


class RoadEdgeType(IntEnum):
    """Subtype of a ROAD_EDGE feature (WOMD codes)."""

    UNKNOWN = 0
    BOUNDARY = 1
    MEDIAN = 2


class LinkType(IntEnum):
    """Kinds of directed link between two map features (``RoadMap.links``: from -> to)."""

    SUCCESSOR = 0  # a lane's exit lane (WOMD exit_lanes)
    PREDECESSOR = 1  # a lane's entry lane (WOMD entry_lanes)
    LEFT_NEIGHBOR = 2
    RIGHT_NEIGHBOR = 3
    STOP_SIGN_LANE = 4  # a stop sign controls this lane


MAX_SPEED_LIMIT_MPH = 500.0
"""The largest speed limit a lane may carry (mph; no road posts more than 100)."""


@dataclass(frozen=True, eq=False)
class RoadMap:
    """The vector map: ``F`` typed features whose points are concatenated (CSR form).

    Feature ``i`` has points ``points[point_offsets[i]:point_offsets[i + 1]]``: a polyline for
    lanes, road lines and road edges, a polygon outline for crosswalks, speed bumps and driveways,
    one point for a stop sign. ``links`` are directed (from id, to id) pairs with a
    :class:`LinkType`; they refer to feature ids, which may be absent from the map (a source that
    was cropped), see :meth:`link_indices`.
    """

    ids: np.ndarray  # [F] int64, unique
    types: np.ndarray  # [F] int8, MapFeatureType
    subtypes: np.ndarray  # [F] int8, LaneType / RoadLineType / RoadEdgeType, 0 otherwise
    speed_limit_mph: np.ndarray  # [F] float32, lanes only (0 when unknown), the source's unit
    interpolating: np.ndarray  # [F] bool, lanes only
    points: np.ndarray  # [P, 3] float32, x, y, z (m, local frame)
    point_offsets: np.ndarray  # [F + 1] int64
    links: np.ndarray  # [E, 2] int64, (from feature id, to feature id)
    link_types: np.ndarray  # [E] int8, LinkType

    def __post_init__(self) -> None:
        _coerce(self, "ids", np.int64, 1)
        _coerce(self, "types", np.int8, 1)
        _coerce(self, "subtypes", np.int8, 1)
        _coerce(self, "speed_limit_mph", np.float32, 1)
        _coerce(self, "interpolating", np.bool_, 1)
        _coerce(self, "points", np.float32, 2)
        _coerce(self, "point_offsets", np.int64, 1)
        links = np.asarray(self.links, dtype=np.int64)
        object.__setattr__(self, "links", links.reshape(-1, 2) if links.size == 0 else links)
        _coerce(self, "links", np.int64, 2)
        _coerce(self, "link_types", np.int8, 1)
        f = self.ids.shape[0]
        for name in ("types", "subtypes", "speed_limit_mph", "interpolating"):
            got = getattr(self, name).shape
            _check(got == (f,), f"RoadMap.{name} has shape {got}, expected ({f},)")
        _check(self.points.shape[1:] == (3,), f"RoadMap.points has shape {self.points.shape}, expected [P, 3]")
        _check(self.point_offsets.shape == (f + 1,), f"RoadMap.point_offsets has shape {self.point_offsets.shape}, expected ({f + 1},)")
        _check(
            self.point_offsets[0] == 0 and self.point_offsets[-1] == len(self.points),
            f"RoadMap.point_offsets must run from 0 to {len(self.points)}",
        )
        _check(bool(np.all(np.diff(self.point_offsets) >= 1)), "RoadMap: every feature needs at least one point")
        _check(bool(np.isfinite(self.points).all()), "RoadMap.points are not all finite")
        bad_speed = ~(np.isfinite(self.speed_limit_mph) & (self.speed_limit_mph >= 0) & (self.speed_limit_mph <= MAX_SPEED_LIMIT_MPH))
        _check(not bad_speed.any(), f"RoadMap.speed_limit_mph must be finite and in 0..{MAX_SPEED_LIMIT_MPH:g} mph "
               f"(0: unknown); feature {self.ids[bad_speed][:1].tolist()} has {self.speed_limit_mph[bad_speed][:1].tolist()}")
        _check(len(np.unique(self.ids)) == f, "RoadMap.ids are not unique")
        _check(bool(np.all((self.types >= 0) & (self.types <= MapFeatureType.DRIVEWAY))), "RoadMap.types outside MapFeatureType")
        _check(self.links.shape[1:] == (2,), f"RoadMap.links has shape {self.links.shape}, expected [E, 2]")
        _check(self.link_types.shape == (len(self.links),), "RoadMap.link_types and links disagree in length")
        _check(bool(np.all((self.link_types >= 0) & (self.link_types <= LinkType.STOP_SIGN_LANE))), "RoadMap.link_types outside LinkType")

    @classmethod
    def empty(cls) -> "RoadMap":
        return cls(
            ids=np.zeros(0, np.int64), types=np.zeros(0, np.int8), subtypes=np.zeros(0, np.int8),
            speed_limit_mph=np.zeros(0, np.float32), interpolating=np.zeros(0, bool),
            points=np.zeros((0, 3), np.float32), point_offsets=np.zeros(1, np.int64),
            links=np.zeros((0, 2), np.int64), link_types=np.zeros(0, np.int8),
        )

    @classmethod
    def from_features(cls, features: Iterable[Mapping[str, Any]], links: Iterable[tuple[int, int, int]] = ()) -> "RoadMap":
        """Build a map from dicts with keys ``id``, ``type``, ``points`` ([n, 2 or 3]) and the optional
        ``subtype``, ``speed_limit_mph``, ``interpolating``; ``links`` are (from id, to id, LinkType)."""
        features = list(features)
        pts = []
        for feat in features:
            p = np.asarray(feat["points"], dtype=np.float64).reshape(-1, np.shape(feat["points"])[-1] if np.ndim(feat["points"]) > 1 else 3)
            if p.shape[1] == 2:
                p = np.concatenate([p, np.zeros((len(p), 1))], axis=1)
            pts.append(p[:, :3])
        lengths = np.array([len(p) for p in pts], dtype=np.int64)
        links = list(links)
        return cls(
            ids=np.array([f["id"] for f in features], dtype=np.int64),
            types=np.array([f["type"] for f in features], dtype=np.int8),
            subtypes=np.array([f.get("subtype", 0) for f in features], dtype=np.int8),
            speed_limit_mph=np.array([f.get("speed_limit_mph", 0.0) for f in features], dtype=np.float32),
            interpolating=np.array([f.get("interpolating", False) for f in features], dtype=bool),
            points=np.concatenate(pts).astype(np.float32) if pts else np.zeros((0, 3), np.float32),
            point_offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
            links=np.array([(a, b) for a, b, _ in links], dtype=np.int64).reshape(-1, 2),
            link_types=np.array([t for _, _, t in links], dtype=np.int8),
        )

    @property
    def num_features(self) -> int:
        return self.ids.shape[0]

    def feature_points(self, index: int) -> np.ndarray:
        """The points [n, 3] of feature ``index`` (an index, not an id)."""
        return self.points[self.point_offsets[index] : self.point_offsets[index + 1]]

    def indices_of(self, feature_type: MapFeatureType) -> np.ndarray:
        return np.flatnonzero(self.types == feature_type)

    def point_feature_index(self) -> np.ndarray:
        """[P] the feature index of every point."""
        return np.repeat(np.arange(self.num_features), np.diff(self.point_offsets))

    def link_indices(self, link_type: LinkType) -> np.ndarray:
        """[E', 2] (from index, to index) of the links of one type whose both ends are in the map."""
        sel = self.links[self.link_types == link_type]
        order = np.argsort(self.ids, kind="stable")
        sorted_ids = self.ids[order]
        pos = np.searchsorted(sorted_ids, sel)
        pos = np.clip(pos, 0, max(len(sorted_ids) - 1, 0))
        found = (sorted_ids[pos] == sel).all(axis=1) if len(sorted_ids) else np.zeros(len(sel), bool)
        return order[pos[found]].reshape(-1, 2)

    def _transform(self, frame_fn) -> "RoadMap":
        return _replace(self, points=frame_fn(self.points))
