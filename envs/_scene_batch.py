"""Environment stage, per-scene constants of a batch: ``B`` scenes' :class:`~envs._scene.SceneStatic`
as padded tensors with a leading scene dimension, what every batched step reads (Waymax's batched
state, GPUDrive's worlds).

What comes in: one :class:`~envs._scene.SceneStatic` per row. What goes out: a :class:`SceneBatch`
whose tensors are padded to budgets (tracks ``N``, frames ``T``, route points ``R``, road points
``P``, lights ``L``, road-edge segments ``S``) with masks that say what is real. :meth:`SceneBatch.write`
puts new scenes in some rows (a refill); budgets grow when a new scene needs more and never shrink,
so a long run settles on the largest scene it has seen. Padding is never real: padded tracks are
not ``track_valid`` (and never present), padded road points, lights and segments are not valid.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Sequence

import numpy as np
import torch

from smart_marl.geometry_torch import RoadEdgeTensors, rows_rewritten
from smart_marl.padding import grow, put_rows

from ._scene import SceneStatic

# every tensor field: (fill of padding, {dimension: budget name})
_LAYOUT = {
    "track_valid": (False, {1: "N"}), "types": (-1, {1: "N"}), "is_motion": (False, {1: "N"}), "controllable": (False, {1: "N"}),
    "box_size": (0.0, {1: "N"}), "z": (0.0, {1: "N"}), "cv_velocity": (0.0, {1: "N"}),
    "log_pose": (0.0, {1: "N", 2: "T"}), "log_valid": (False, {1: "N", 2: "T"}),
    "route_xy": (0.0, {1: "N", 2: "R"}), "route_valid": (False, {1: "N", 2: "R"}), "route_arc_m": (0.0, {1: "N", 2: "R"}),
    "route_length_m": (0.0, {1: "N"}), "goal_xy": (0.0, {1: "N"}),
    "current_frame": (0, {}), "num_frames": (0, {}),
    "road_xy": (0.0, {1: "P"}), "road_type": (0, {1: "P"}), "road_valid": (False, {1: "P"}),
    "light_xy": (0.0, {1: "L"}), "light_valid": (False, {1: "L"}), "light_state": (0, {1: "T", 2: "L"}),
    "light_present": (False, {1: "T", 2: "L"}),
}


@dataclass
class SceneBatch:
    """Padded per-scene constants of ``B`` scenes (module docstring); float tensors in ``dtype``."""

    track_valid: torch.Tensor  # [B, N] bool, a real track
    types: torch.Tensor  # [B, N] long AgentType (-1 on padding)
    is_motion: torch.Tensor  # [B, N] bool, vehicle / pedestrian / cyclist
    controllable: torch.Tensor  # [B, N] bool, a motion type valid at the current frame
    box_size: torch.Tensor  # [B, N, 3] length, width, height
    z: torch.Tensor  # [B, N] z at the last valid frame at or before the current one
    cv_velocity: torch.Tensor  # [B, N, 2] logged velocity at the current frame
    log_pose: torch.Tensor  # [B, N, T, 3] logged x, y, heading (local frame)
    log_valid: torch.Tensor  # [B, N, T] bool
    route_xy: torch.Tensor  # [B, N, R, 2] logged positions from the current frame on
    route_valid: torch.Tensor  # [B, N, R] bool
    route_arc_m: torch.Tensor  # [B, N, R] arc length along the valid route points
    route_length_m: torch.Tensor  # [B, N]
    goal_xy: torch.Tensor  # [B, N, 2] last valid logged position
    current_frame: torch.Tensor  # [B] long
    num_frames: torch.Tensor  # [B] long
    road_xy: torch.Tensor  # [B, P, 2] road points for observations (~2 m apart)
    road_type: torch.Tensor  # [B, P] long MapFeatureType
    road_valid: torch.Tensor  # [B, P] bool
    light_xy: torch.Tensor  # [B, L, 2] stop points of the signalised lanes
    light_valid: torch.Tensor  # [B, L] bool
    light_state: torch.Tensor  # [B, T, L] long SignalState per frame
    light_present: torch.Tensor  # [B, T, L] bool
    edges: RoadEdgeTensors  # [B, S] road-edge segments (offroad)
    statics: list  # [B] SceneStatic (names, the Scenario)

    @property
    def num_scenes(self) -> int:
        return int(self.track_valid.shape[0])

    @property
    def num_tracks(self) -> int:
        return int(self.track_valid.shape[1])

    @classmethod
    def build(cls, statics: Sequence[SceneStatic], dtype=torch.float32, device="cpu") -> "SceneBatch":
        """A batch of ``statics``, one row each, padded to the largest."""
        arrays = [_arrays(st) for st in statics]
        budgets = {}
        for a in arrays:
            for name, (_, dims) in _LAYOUT.items():
                for d, budget in dims.items():
                    budgets[budget] = max(budgets.get(budget, 1), a[name].shape[d - 1])
        tensors = {}
        for name, (fill, dims) in _LAYOUT.items():
            rows = []
            for a in arrays:
                t = torch.from_numpy(np.array(a[name]))  # a copy: scenes hold read-only arrays
                t = t.to(dtype) if t.is_floating_point() else t
                rows.append(grow(t[None], {d: budgets[b] for d, b in dims.items()}, fill))
            tensors[name] = torch.cat(rows).to(device)
        edges = RoadEdgeTensors.from_segments([st.road_edges for st in statics], dtype=dtype, device=device)
        return cls(**tensors, edges=edges, statics=list(statics))

    def write(self, rows: Sequence[int], statics: Sequence[SceneStatic]) -> None:
        """Put ``statics`` in rows ``rows`` (in order); budgets grow as needed."""
        if not len(rows):
            return
        dtype, device = self.box_size.dtype, self.box_size.device
        new = SceneBatch.build(statics, dtype, device)
        index = torch.as_tensor(list(rows), dtype=torch.long, device=device)
        with rows_rewritten(self, index):  # the road's search blocks: the new rows' alone
            for name, (fill, dims) in _LAYOUT.items():
                mine, theirs = getattr(self, name), getattr(new, name)
                mine = grow(mine, {d: theirs.shape[d] for d in dims}, fill)
                put_rows(mine, index, theirs, fill)
                setattr(self, name, mine)
        size = max(self.edges.num_segments, new.edges.num_segments)
        with rows_rewritten(self.edges, index):
            for f in fields(RoadEdgeTensors):
                fill = RoadEdgeTensors.FILL[f.name]
                mine = grow(getattr(self.edges, f.name), {1: size}, fill)
                put_rows(mine, index, getattr(new.edges, f.name), fill)
                setattr(self.edges, f.name, mine)
        for b, st in zip(rows, statics):
            self.statics[b] = st


def gather_tracks(values: torch.Tensor, tracks: torch.Tensor) -> torch.Tensor:
    """``values`` [B, N, ...] at ``tracks`` [B, C] (indices into N; -1 reads track 0) -> [B, C, ...]."""
    idx = tracks.clamp(min=0)
    return values.gather(1, idx.reshape(*idx.shape, *([1] * (values.dim() - 2))).expand(*idx.shape, *values.shape[2:]))


def _arrays(st: SceneStatic) -> dict[str, np.ndarray]:
    """One scene's arrays in :data:`_LAYOUT`'s shapes (without the leading scene dimension)."""
    sc = st.scenario
    tr, cf, tl = sc.tracks, sc.current_frame, sc.traffic_lights
    n = st.num_tracks
    log_pose = np.concatenate([tr.position[:, :, :2], tr.heading[:, :, None]], -1)
    lights = len(tl.lane_ids)
    states = np.zeros((tr.num_frames, lights), np.int64)
    present = np.zeros((tr.num_frames, lights), bool)
    k = min(tl.num_frames, tr.num_frames)
    states[:k], present[:k] = tl.states[:k], tl.present[:k]
    if k < tr.num_frames and k:  # lights logged on fewer frames: the last logged state holds
        states[k:], present[k:] = tl.states[k - 1], tl.present[k - 1]
    return {
        "track_valid": np.ones(n, bool), "types": st.types, "is_motion": st.is_motion, "controllable": st.controllable,
        "box_size": st.box_size, "z": st.z, "cv_velocity": tr.velocity[:, cf].astype(np.float64),
        "log_pose": log_pose, "log_valid": tr.valid,
        "route_xy": st.route_xy, "route_valid": st.route_valid, "route_arc_m": st.route_arc_m,
        "route_length_m": st.route_length_m, "goal_xy": st.goal_xy,
        "current_frame": np.asarray(cf, np.int64), "num_frames": np.asarray(tr.num_frames, np.int64),
        "road_xy": st.road_xy, "road_type": st.road_type, "road_valid": np.ones(len(st.road_xy), bool),
        "light_xy": st.light_xy, "light_valid": np.ones(len(st.light_xy), bool), "light_state": states, "light_present": present,
    }


__all__ = ["SceneBatch", "gather_tracks"]
