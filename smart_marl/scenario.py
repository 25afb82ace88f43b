"""The canonical scene: the first stage of the data flow, which every reader produces.

A :class:`Scenario` is plain numpy arrays, validated once when it is built:

* ``tracks``: every agent's boxes at 10 Hz (:class:`Tracks`, arrays shaped ``[N, T, ...]``);
* ``road_map``: typed polylines and polygons with lane topology (:class:`RoadMap`, defined in
  :mod:`smart_marl.road_map` and re-exported here; ragged arrays
  in CSR form: all points concatenated plus offsets);
* ``traffic_lights``: per-lane signal states per frame (:class:`TrafficLights`);
* the self-driving car's index, the tracks to predict, the current frame, the source's scenario
  id, the source's name and the frame (:class:`SceneFrame`) that maps the scene's local
  coordinates back to the source's.

Coordinates are metres in a local frame near the scene's centre (float32 stays exact); the
:class:`SceneFrame` keeps the shift and rotation in float64 so outputs can be written back in the
source frame. Scenarios are immutable: slicing (:meth:`Scenario.window`,
:meth:`Scenario.select_tracks`) and transforms (:meth:`Scenario.to_frame`) return new Scenarios
that share whatever arrays they did not change.

Everything downstream (scene cache, tokenizers, environment, metrics, what-if tools) takes a
Scenario and never needs to know which file format it came from.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, Iterable, Mapping

import numpy as np

from .errors import ScenarioValidationError
from .road_map import (  # noqa: F401  (re-exported: the scene's map types live beside the scene)
    MAX_SPEED_LIMIT_MPH, POLYGON_FEATURES, LaneType, LinkType, MapFeatureType, RoadEdgeType, RoadLineType, RoadMap,
)
from .values import (  # noqa: F401  (as_floats, as_integers, as_mask: re-exported, their home is smart_marl.values)
    _arrays_equal, _check, _coerce, _replace, _trusted, as_floats, as_int, as_integers, as_mask,
)

DT_S = 0.1
"""Seconds between two frames (10 Hz)."""
CURRENT_FRAME = 10
"""The current frame of a WOMD-style scene (91 frames at 10 Hz: 1 s of history up to it, 8 s to simulate
after it). The one definition: the readers whose format does not store it default to it, the SUMO and
synthetic scenes use it, and WOSAC scores from it (:data:`smart_marl.metrics.config.CURRENT_STEP`)."""


class AgentType(IntEnum):
    """Agent types. The first three each have a motion-token vocabulary; OTHER is context only."""

    VEHICLE = 0
    PEDESTRIAN = 1
    CYCLIST = 2
    OTHER = 3


TYPICAL_BOX_M = {
    AgentType.VEHICLE: (4.6, 2.1, 1.6),
    AgentType.PEDESTRIAN: (0.9, 0.8, 1.8),
    AgentType.CYCLIST: (1.8, 0.8, 1.7),
    AgentType.OTHER: (1.0, 1.0, 1.0),
}
"""(length, width, height) in metres of an agent whose source gives no box (AV2 tracks, empty Nocturne boxes,
agents a what-if script adds): per type, the medians of the shared real WOMD scenes' boxes, rounded (1,214
vehicles 4.62 x 2.06, 160 pedestrians 0.86 x 0.83, 14 cyclists 1.84 x 0.84; heights typical of WOMD's)."""


class SignalState(IntEnum):
    """Traffic-signal state of a lane (WOMD codes)."""

    UNKNOWN = 0
    ARROW_STOP = 1
    ARROW_CAUTION = 2
    ARROW_GO = 3
    STOP = 4
    CAUTION = 5
    GO = 6
    FLASHING_STOP = 7
    FLASHING_CAUTION = 8


def wrap_angle(angle):
    """Radians wrapped to [-pi, pi): the one angle wrap of the project, for numpy arrays, scalars
    and torch tensors alike (``%`` is ``torch.remainder`` on tensors)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi



@dataclass(frozen=True)
class SceneFrame:
    """Where the scene's local frame sits in the source's coordinates.

    A local point ``p`` is ``R(heading) @ p[:2] + (x, y)`` and ``p[2] + z`` in the source frame;
    local headings are source headings minus ``heading``.
    """

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    heading: float = 0.0

    def __post_init__(self) -> None:
        for name in ("x", "y", "z", "heading"):
            value = getattr(self, name)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(value):
                raise ScenarioValidationError(f"SceneFrame.{name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))

    def to_source(self, xyz: np.ndarray) -> np.ndarray:
        """Local points [..., 2 or 3] -> source points, float64."""
        xyz = np.asarray(xyz, dtype=np.float64)
        c, s = math.cos(self.heading), math.sin(self.heading)
        out = xyz.copy()
        out[..., 0] = c * xyz[..., 0] - s * xyz[..., 1] + self.x
        out[..., 1] = s * xyz[..., 0] + c * xyz[..., 1] + self.y
        if xyz.shape[-1] > 2:
            out[..., 2] = xyz[..., 2] + self.z
        return out

    def from_source(self, xyz: np.ndarray) -> np.ndarray:
        """Source points [..., 2 or 3] -> local points, float64."""
        xyz = np.asarray(xyz, dtype=np.float64)
        c, s = math.cos(self.heading), math.sin(self.heading)
        dx, dy = xyz[..., 0] - self.x, xyz[..., 1] - self.y
        out = xyz.copy()
        out[..., 0] = c * dx + s * dy
        out[..., 1] = -s * dx + c * dy
        if xyz.shape[-1] > 2:
            out[..., 2] = xyz[..., 2] - self.z
        return out

    def heading_to_source(self, heading: np.ndarray) -> np.ndarray:
        return wrap_angle(np.asarray(heading, dtype=np.float64) + self.heading)

    def compose(self, x: float, y: float, heading: float) -> "SceneFrame":
        """The frame whose origin is local point (x, y) of this frame, rotated by ``heading``."""
        sx, sy = self.to_source(np.array([x, y]))
        return SceneFrame(float(sx), float(sy), self.z, float(wrap_angle(np.float64(self.heading + heading))))


@dataclass(frozen=True, eq=False)
class Tracks:
    """Agent boxes at 10 Hz. ``N`` tracks, ``T`` frames. Values on invalid frames are arbitrary."""

    ids: np.ndarray  # [N] int64, the source's track ids, unique
    types: np.ndarray  # [N] int8, AgentType
    position: np.ndarray  # [N, T, 3] float32, box centre x, y, z (m, local frame)
    heading: np.ndarray  # [N, T] float32, radians, counter-clockwise from +x
    velocity: np.ndarray  # [N, T, 2] float32, m/s (local frame)
    size: np.ndarray  # [N, T, 3] float32, length, width, height (m)
    valid: np.ndarray  # [N, T] bool

    def __post_init__(self) -> None:
        _coerce(self, "ids", np.int64, 1)
        _coerce(self, "types", np.int8, 1)
        _coerce(self, "position", np.float32, 3)
        _coerce(self, "heading", np.float32, 2)
        _coerce(self, "velocity", np.float32, 3)
        _coerce(self, "size", np.float32, 3)
        if np.asarray(self.valid).dtype != np.bool_:
            raise ScenarioValidationError(
                f"Tracks.valid must be a boolean mask, got dtype {np.asarray(self.valid).dtype}"
            )
        _coerce(self, "valid", np.bool_, 2)
        n, t = self.valid.shape
        _check(self.ids.shape == (n,), f"Tracks.ids has shape {self.ids.shape}, valid has {n} tracks")
        _check(self.types.shape == (n,), f"Tracks.types has shape {self.types.shape}, valid has {n} tracks")
        for name, shape in (("position", (n, t, 3)), ("heading", (n, t)), ("velocity", (n, t, 2)), ("size", (n, t, 3))):
            got = getattr(self, name).shape
            _check(got == shape, f"Tracks.{name} has shape {got}, expected {shape} (from valid [{n}, {t}])")
        _check(len(np.unique(self.ids)) == n, "Tracks.ids are not unique")
        _check(bool(np.all((self.types >= 0) & (self.types <= AgentType.OTHER))), "Tracks.types outside AgentType")
        for name in ("position", "heading", "velocity", "size"):
            values = getattr(self, name)
            finite = np.isfinite(values)
            if finite.all():  # the common case: one reduction
                continue
            if finite.ndim == 3:
                finite = finite.all(axis=-1)
            bad = self.valid & ~finite
            if bad.any():
                i, f = np.argwhere(bad)[0]
                raise ScenarioValidationError(
                    f"Tracks.{name} is not finite on {int(bad.sum())} valid frame(s), "
                    f"first at track {int(i)} (id {int(self.ids[i])}) frame {int(f)}"
                )
        negative = self.valid & (self.size < 0).any(axis=-1) if (self.size < 0).any() else None
        if negative is not None and negative.any():
            i, f = np.argwhere(negative)[0]
            raise ScenarioValidationError(
                f"Tracks.size is negative on {int(negative.sum())} valid frame(s), first at track {int(i)} "
                f"(id {int(self.ids[i])}) frame {int(f)}: {self.size[i, f].tolist()}"
            )

    @property
    def num_tracks(self) -> int:
        return self.valid.shape[0]

    @property
    def num_frames(self) -> int:
        return self.valid.shape[1]

    def box_size(self) -> np.ndarray:
        """[N, 3] length, width, height of each agent: the median over its valid frames."""
        size = np.where(self.valid[..., None], self.size, np.nan)
        with np.errstate(all="ignore"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                out = np.nanmedian(size, axis=1)
        return np.nan_to_num(out, nan=0.0).astype(np.float32)

    def z_at(self, frame: int) -> np.ndarray:
        """[N] float64, each track's z at its last valid frame at or before ``frame`` (its first frame's
        when it has none): the height its box is carried at in simulation."""
        seen = self.valid[:, : frame + 1]
        last = np.where(seen.any(1), frame - np.argmax(seen[:, ::-1], axis=1), 0)
        return self.position[np.arange(len(self.ids)), last, 2].astype(np.float64)

    def names(self) -> list[str]:
        """``"vehicle_1234"``-style names: type and track id."""
        return [f"{AgentType(int(t)).name.lower()}_{int(i)}" for t, i in zip(self.types, self.ids)]

    def _take(self, index) -> "Tracks":
        return _trusted(
            Tracks,
            ids=self.ids[index],
            types=self.types[index],
            position=self.position[index],
            heading=self.heading[index],
            velocity=self.velocity[index],
            size=self.size[index],
            valid=self.valid[index],
        )

    def _window(self, start: int, stop: int) -> "Tracks":
        s = slice(start, stop)
        return _replace(
            self,
            position=self.position[:, s],
            heading=self.heading[:, s],
            velocity=self.velocity[:, s],
            size=self.size[:, s],
            valid=self.valid[:, s],
        )


@dataclass(frozen=True, eq=False)
class TrafficLights:
    """Signal states of ``L`` controlled lanes over ``T`` frames."""

    lane_ids: np.ndarray  # [L] int64, map feature ids of the controlled lanes
    states: np.ndarray  # [T, L] int8, SignalState (meaningful where present)
    present: np.ndarray  # [T, L] bool, the source reported this lane's signal on this frame
    stop_points: np.ndarray  # [L, 3] float32, stop point of each lane (local frame)

    def __post_init__(self) -> None:
        _coerce(self, "lane_ids", np.int64, 1)
        _coerce(self, "states", np.int8, 2)
        _coerce(self, "present", np.bool_, 2)
        _coerce(self, "stop_points", np.float32, 2)
        num_lanes = self.lane_ids.shape[0]
        _check(self.states.shape[1] == num_lanes, f"TrafficLights.states has shape {self.states.shape}, expected [T, {num_lanes}]")
        _check(self.present.shape == self.states.shape, "TrafficLights.present and states disagree in shape")
        _check(self.stop_points.shape == (num_lanes, 3), f"TrafficLights.stop_points has shape {self.stop_points.shape}, expected ({num_lanes}, 3)")
        _check(len(np.unique(self.lane_ids)) == num_lanes, "TrafficLights.lane_ids are not unique")
        _check(bool(np.all((self.states >= 0) & (self.states <= SignalState.FLASHING_CAUTION))), "TrafficLights.states outside SignalState")
        _check(bool(np.isfinite(self.stop_points).all()), "TrafficLights.stop_points are not all finite")

    @classmethod
    def empty(cls, num_frames: int) -> "TrafficLights":
        return cls(np.zeros(0, np.int64), np.zeros((num_frames, 0), np.int8), np.zeros((num_frames, 0), bool), np.zeros((0, 3), np.float32))

    @property
    def num_frames(self) -> int:
        return self.states.shape[0]

    def frames_with_signals(self) -> int:
        return int(self.present.any(axis=1).sum())


@dataclass(frozen=True, eq=False)
class Scenario:
    """One driving scene. See the module docstring; build it with keyword arguments."""

    scenario_id: str
    source: str  # the source's name: "womd", "scenarionet/waymo", "gpudrive", "av2", "sumo"...
    timestamps_s: np.ndarray  # [T] float64
    current_frame: int
    tracks: Tracks
    road_map: RoadMap
    traffic_lights: TrafficLights
    sdc_index: int = -1  # index into tracks, -1 when the source has no self-driving car
    predict_indices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [K] track indices
    predict_difficulty: np.ndarray | None = None  # [K] int8 (WOMD difficulty), zeros when absent
    objects_of_interest: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [M] track ids
    frame: SceneFrame = SceneFrame()
    metadata: Mapping[str, Any] = field(default_factory=dict)  # JSON-able extras (city, source path...)

    def __post_init__(self) -> None:
        _check(isinstance(self.scenario_id, str) and self.scenario_id != "", "Scenario.scenario_id must be a non-empty string")
        _check(isinstance(self.source, str) and self.source != "", "Scenario.source must be a non-empty string")
        _check(isinstance(self.tracks, Tracks), "Scenario.tracks must be a Tracks")
        _check(isinstance(self.road_map, RoadMap), "Scenario.road_map must be a RoadMap")
        _check(isinstance(self.traffic_lights, TrafficLights), "Scenario.traffic_lights must be a TrafficLights")
        _check(isinstance(self.frame, SceneFrame), "Scenario.frame must be a SceneFrame")
        _coerce(self, "timestamps_s", np.float64, 1)
        _coerce(self, "predict_indices", np.int64, 1)
        if self.predict_difficulty is None:
            object.__setattr__(self, "predict_difficulty", np.zeros(len(self.predict_indices), np.int8))
        _coerce(self, "predict_difficulty", np.int8, 1)
        _coerce(self, "objects_of_interest", np.int64, 1)
        object.__setattr__(self, "current_frame", as_int(self.current_frame, "Scenario.current_frame"))
        object.__setattr__(self, "sdc_index", as_int(self.sdc_index, "Scenario.sdc_index"))
        _check(isinstance(self.metadata, Mapping), f"Scenario.metadata must be a mapping, got {type(self.metadata).__name__}")
        object.__setattr__(self, "metadata", dict(self.metadata))
        n, t = self.tracks.num_tracks, self.tracks.num_frames
        _check(self.timestamps_s.shape == (t,), f"Scenario.timestamps_s has shape {self.timestamps_s.shape}, tracks have {t} frames")
        _check(bool(np.isfinite(self.timestamps_s).all()), "Scenario.timestamps_s are not all finite")
        _check(self.traffic_lights.num_frames == t, f"TrafficLights has {self.traffic_lights.num_frames} frames, tracks have {t}")
        _check(0 <= self.current_frame < t, f"Scenario.current_frame {self.current_frame} outside [0, {t})")
        _check(-1 <= self.sdc_index < n, f"Scenario.sdc_index {self.sdc_index} outside [-1, {n})")
        _check(bool(np.all((self.predict_indices >= 0) & (self.predict_indices < n))), f"Scenario.predict_indices outside [0, {n})")
        _check(len(np.unique(self.predict_indices)) == len(self.predict_indices), "Scenario.predict_indices are not unique")
        _check(self.predict_difficulty.shape == self.predict_indices.shape, "Scenario.predict_difficulty and predict_indices disagree in length")

    # ----------------------------------------------------------------------------- properties
    @property
    def num_tracks(self) -> int:
        return self.tracks.num_tracks

    @property
    def num_frames(self) -> int:
        return self.tracks.num_frames

    @property
    def sdc_id(self) -> int | None:
        return None if self.sdc_index < 0 else int(self.tracks.ids[self.sdc_index])

    def summary(self) -> dict[str, Any]:
        """Counts that describe the scene (what ``smart-marl info`` prints)."""
        rm = self.road_map
        lanes = rm.indices_of(MapFeatureType.LANE)
        lane_ids = rm.ids[lanes]

        def lanes_with(link: LinkType) -> int:
            return int(np.isin(lane_ids, rm.links[rm.link_types == link][:, 0]).sum())

        types, counts = np.unique(self.tracks.types, return_counts=True)
        per_type = {t.name.lower(): 0 for t in AgentType}
        per_type.update({AgentType(int(k)).name.lower(): int(c) for k, c in zip(types, counts)})
        return {
            "source": self.source,
            "scenario_id": self.scenario_id,
            "frames": self.num_frames,
            "current_frame": self.current_frame,
            "tracks": self.num_tracks,
            "tracks_per_type": per_type,
            "sdc_id": self.sdc_id,
            "tracks_to_predict": int(len(self.predict_indices)),
            "lanes": int(len(lanes)),
            "lanes_with_successors": lanes_with(LinkType.SUCCESSOR),
            "lanes_with_predecessors": lanes_with(LinkType.PREDECESSOR),
            "road_lines": int((rm.types == MapFeatureType.ROAD_LINE).sum()),
            "road_edges": int((rm.types == MapFeatureType.ROAD_EDGE).sum()),
            "crosswalks": int((rm.types == MapFeatureType.CROSSWALK).sum()),
            "traffic_light_lanes": int(len(self.traffic_lights.lane_ids)),
            "traffic_light_frames": self.traffic_lights.frames_with_signals(),
        }

    # ------------------------------------------------------------------------ slicing, transforms
    def window(self, start: int, stop: int, current_frame: int | None = None) -> "Scenario":
        """The frames [start, stop), sharing memory with this scene.

        The current frame keeps its absolute time (``current_frame - start``) unless a new one
        (relative to ``start``) is given; it must fall inside the window.
        """
        t = self.num_frames
        start, stop, _ = slice(start, stop).indices(t)
        _check(stop > start, f"window [{start}, {stop}) is empty")
        current = self.current_frame - start if current_frame is None else int(current_frame)
        _check(0 <= current < stop - start, f"current frame {current} falls outside the window [{start}, {stop}); pass current_frame=")
        tl = self.traffic_lights
        return _replace(
            self,
            timestamps_s=self.timestamps_s[start:stop],
            current_frame=current,
            tracks=self.tracks._window(start, stop),
            traffic_lights=_replace(tl, states=tl.states[start:stop], present=tl.present[start:stop]),
        )

    def select_tracks(self, selection) -> "Scenario":
        """A subset of the tracks (a boolean mask or indices, in the given order).

        The self-driving car index becomes -1 when it is dropped; tracks to predict that are
        dropped are removed; objects of interest keep only ids still present.
        """
        index = np.asarray(selection)
        if index.dtype == np.bool_:
            _check(index.shape == (self.num_tracks,), f"track mask has shape {index.shape}, expected ({self.num_tracks},)")
            index = np.flatnonzero(index)
        index = index.astype(np.int64).reshape(-1)
        _check(bool(np.all((index >= 0) & (index < self.num_tracks))), f"track indices outside [0, {self.num_tracks})")
        _check(len(np.unique(index)) == len(index), "track indices are not unique")
        new_of_old = np.full(self.num_tracks, -1, np.int64)
        new_of_old[index] = np.arange(len(index))
        keep_pred = new_of_old[self.predict_indices] >= 0
        tracks = self.tracks._take(index)
        return _replace(
            self,
            tracks=tracks,
            sdc_index=int(new_of_old[self.sdc_index]) if self.sdc_index >= 0 else -1,
            predict_indices=new_of_old[self.predict_indices][keep_pred],
            predict_difficulty=self.predict_difficulty[keep_pred],
            objects_of_interest=self.objects_of_interest[np.isin(self.objects_of_interest, tracks.ids)],
        )

    def to_frame(self, x: float, y: float, heading: float = 0.0) -> "Scenario":
        """The same scene expressed in the frame whose origin is local point (x, y) and whose +x
        axis points along ``heading`` (radians, local frame). ``frame`` is updated so that
        :meth:`SceneFrame.to_source` still gives source coordinates."""
        c, s = math.cos(heading), math.sin(heading)
        rot = np.array([[c, s], [-s, c]])  # source -> new, applied to row vectors as p @ rot.T

        def move(points: np.ndarray) -> np.ndarray:
            p = points.astype(np.float64)
            out = np.empty_like(p)
            xy = p[..., :2] - (x, y)
            out[..., :2] = xy @ rot.T
            if p.shape[-1] > 2:
                out[..., 2:] = p[..., 2:]
            return out.astype(np.float32)

        tr = self.tracks
        tracks = _replace(
            tr,
            position=move(tr.position),
            heading=wrap_angle(tr.heading.astype(np.float64) - heading).astype(np.float32),
            velocity=(tr.velocity.astype(np.float64) @ rot.T).astype(np.float32),
        )
        tl = self.traffic_lights
        return _replace(
            self,
            tracks=tracks,
            road_map=self.road_map._transform(move),
            traffic_lights=_replace(tl, stop_points=move(tl.stop_points)),
            frame=self.frame.compose(x, y, heading),
        )

    def centered_on(self, track_index: int, frame_index: int | None = None, rotate: bool = True) -> "Scenario":
        """The scene in the frame of one agent's pose (at the current frame by default)."""
        f = self.current_frame if frame_index is None else frame_index
        _check(bool(self.tracks.valid[track_index, f]), f"track {track_index} is not valid on frame {f}")
        px, py = (float(v) for v in self.tracks.position[track_index, f, :2])
        h = float(self.tracks.heading[track_index, f]) if rotate else 0.0
        return self.to_frame(px, py, h)

    # --------------------------------------------------------------------------- comparison
    def differences(self, other: "Scenario") -> list[str]:
        """The names of the fields that differ (exact comparison, NaN equal to NaN)."""
        diffs = []
        for a_obj, b_obj, prefix in ((self, other, ""), (self.tracks, other.tracks, "tracks."),
                                     (self.road_map, other.road_map, "road_map."),
                                     (self.traffic_lights, other.traffic_lights, "traffic_lights.")):
            for f in dataclasses.fields(a_obj):
                a, b = getattr(a_obj, f.name), getattr(b_obj, f.name)
                if isinstance(a, (Tracks, RoadMap, TrafficLights)):
                    continue
                if isinstance(a, np.ndarray):
                    same = isinstance(b, np.ndarray) and _arrays_equal(a, b)
                else:
                    same = a == b
                if not same:
                    diffs.append(prefix + f.name)
        return diffs

    def equals(self, other: "Scenario", ignore: Iterable[str] = ("metadata",)) -> bool:
        """Exact equality of every field but those in ``ignore``."""
        return not [d for d in self.differences(other) if d not in set(ignore)]

    # ------------------------------------------------------------------ flat arrays (scene cache)
    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Flatten into named arrays plus JSON-able scalars; :meth:`from_arrays` inverts it."""
        arrays: dict[str, np.ndarray] = {"timestamps_s": self.timestamps_s, "predict_indices": self.predict_indices,
                                         "predict_difficulty": self.predict_difficulty,
                                         "objects_of_interest": self.objects_of_interest}
        for prefix, obj in (("tracks", self.tracks), ("road_map", self.road_map), ("traffic_lights", self.traffic_lights)):
            for f in dataclasses.fields(obj):
                arrays[f"{prefix}.{f.name}"] = getattr(obj, f.name)
        meta = {
            "scenario_id": self.scenario_id,
            "source": self.source,
            "current_frame": self.current_frame,
            "sdc_index": self.sdc_index,
            "frame": dataclasses.asdict(self.frame),
            "metadata": self.metadata,
        }
        return arrays, meta

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any], validate: bool = True) -> "Scenario":
        """Inverse of :meth:`to_arrays`. ``validate=False`` trusts the arrays (only for arrays this
        process made itself); with ``validate`` every missing, extra or ill-typed entry raises
        :class:`ScenarioValidationError`."""
        if not validate:
            parts, kwargs = cls._split_arrays(arrays, meta)
            kwargs["current_frame"] = int(kwargs["current_frame"])
            kwargs["sdc_index"] = int(kwargs["sdc_index"])
            kwargs["metadata"] = dict(kwargs["metadata"])
            return _trusted(cls, tracks=_trusted(Tracks, **parts["tracks"]), road_map=_trusted(RoadMap, **parts["road_map"]),
                            traffic_lights=_trusted(TrafficLights, **parts["traffic_lights"]), **kwargs)
        try:
            _check(isinstance(meta, Mapping) and isinstance(meta.get("frame"), Mapping), "the scene's meta and frame must be mappings")
            parts, kwargs = cls._split_arrays(arrays, meta)
            return cls(tracks=Tracks(**parts["tracks"]), road_map=RoadMap(**parts["road_map"]),
                       traffic_lights=TrafficLights(**parts["traffic_lights"]), **kwargs)
        except (KeyError, TypeError) as exc:  # a missing or unknown entry
            raise ScenarioValidationError(f"the arrays and meta do not make a Scenario: {type(exc).__name__}: {exc}") from None

    @staticmethod
    def _split_arrays(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]):
        parts: dict[str, dict[str, np.ndarray]] = {"tracks": {}, "road_map": {}, "traffic_lights": {}}
        top = {}
        for key, value in arrays.items():
            prefix, _, name = key.partition(".")
            if name:
                parts[prefix][name] = value
            else:
                top[key] = value
        kwargs = dict(
            scenario_id=meta["scenario_id"], source=meta["source"], current_frame=meta["current_frame"],
            sdc_index=meta["sdc_index"], frame=SceneFrame(**meta["frame"]), metadata=meta.get("metadata", {}),
            **top,
        )
        return parts, kwargs
