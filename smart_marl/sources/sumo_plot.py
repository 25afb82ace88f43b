"""A quick bird's-eye picture of one scene (any source), to check that generated scenes look like
traffic. Stage: a look at a Scenario; the project's real renderer is :mod:`smart_marl.render`.

Draws lanes (bike lanes green), road edges, crosswalks, stop signs, the signal of each controlled
lane at the chosen frame, and every agent valid there as its box (self-driving car red, vehicles
blue, cyclists green, pedestrians orange) with its past path.
"""

from __future__ import annotations

import os

import numpy as np

from ..scenario import AgentType, LaneType, MapFeatureType, Scenario, SignalState

_AGENT_COLOURS = {AgentType.VEHICLE: "#1f5fbf", AgentType.PEDESTRIAN: "#e07b00", AgentType.CYCLIST: "#2a9d3a",
                  AgentType.OTHER: "#777777"}
_SIGNAL_COLOURS = {SignalState.GO: "#22b14c", SignalState.ARROW_GO: "#22b14c", SignalState.CAUTION: "#f2c400",
                   SignalState.ARROW_CAUTION: "#f2c400", SignalState.FLASHING_CAUTION: "#f2c400",
                   SignalState.STOP: "#d62020", SignalState.ARROW_STOP: "#d62020", SignalState.FLASHING_STOP: "#d62020"}


def box_corners(xy: np.ndarray, heading: np.ndarray, length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """[N, 4, 2] corners of oriented boxes."""
    c, s = np.cos(heading), np.sin(heading)
    dx = np.array([0.5, 0.5, -0.5, -0.5])[None] * length[:, None]
    dy = np.array([0.5, -0.5, -0.5, 0.5])[None] * width[:, None]
    return np.stack([xy[:, :1] + c[:, None] * dx - s[:, None] * dy, xy[:, 1:2] + s[:, None] * dx + c[:, None] * dy], -1)


def plot_scene(scenario: Scenario, path: str | os.PathLike, frame: int | None = None, view_m: float = 70.0,
               size_in: float = 6.0, dpi: int = 110) -> None:
    """Write a PNG of ``scenario`` at ``frame`` (the current frame by default), ``view_m`` around the SDC."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection, PolyCollection

    f = scenario.current_frame if frame is None else frame
    rm, tr = scenario.road_map, scenario.tracks
    fig, ax = plt.subplots(figsize=(size_in, size_in), dpi=dpi)
    ax.set_facecolor("#f4f4f0")

    def polylines(kind, subtype=None):
        idx = rm.indices_of(kind)
        if subtype is not None:
            idx = idx[rm.subtypes[idx] == subtype]
        return [rm.feature_points(i)[:, :2] for i in idx]

    crosswalks = polylines(MapFeatureType.CROSSWALK)
    ax.add_collection(PolyCollection(crosswalks, facecolors="#d9d9d9", edgecolors="#9a9a9a", hatch="////", lw=0.5))
    ax.add_collection(LineCollection(polylines(MapFeatureType.LANE, LaneType.SURFACE_STREET), colors="#b8b8b8", lw=0.7))
    ax.add_collection(LineCollection(polylines(MapFeatureType.LANE, LaneType.BIKE_LANE), colors="#7cc48a", lw=0.7))
    ax.add_collection(LineCollection(polylines(MapFeatureType.ROAD_EDGE), colors="#222222", lw=1.2))
    stops = rm.indices_of(MapFeatureType.STOP_SIGN)
    if len(stops):
        pts = np.array([rm.feature_points(i)[0, :2] for i in stops])
        ax.scatter(pts[:, 0], pts[:, 1], marker="8", s=28, c="#b00000", zorder=3)
    tl = scenario.traffic_lights
    if len(tl.lane_ids):
        on = tl.present[f]
        colours = [_SIGNAL_COLOURS.get(SignalState(int(s)), "#888888") for s in tl.states[f][on]]
        ax.scatter(tl.stop_points[on, 0], tl.stop_points[on, 1], s=9, c=colours, zorder=3, linewidths=0)

    ok = tr.valid[:, f]
    past = slice(max(0, f - 10), f + 1)
    for i in np.flatnonzero(ok):
        v = tr.valid[i, past]
        ax.plot(tr.position[i, past, 0][v], tr.position[i, past, 1][v], color=_AGENT_COLOURS[AgentType(int(tr.types[i]))],
                lw=0.8, alpha=0.5)
    corners = box_corners(tr.position[ok, f, :2], tr.heading[ok, f], tr.size[ok, f, 0], tr.size[ok, f, 1])
    colours = ["#d62020" if i == scenario.sdc_index else _AGENT_COLOURS[AgentType(int(tr.types[i]))] for i in np.flatnonzero(ok)]
    ax.add_collection(PolyCollection(corners, facecolors=colours, edgecolors="black", lw=0.4, zorder=4))
    cx, cy = (tr.position[scenario.sdc_index, f, :2] if scenario.sdc_index >= 0 and ok[scenario.sdc_index] else (0.0, 0.0))
    ax.set_xlim(cx - view_m, cx + view_m)
    ax.set_ylim(cy - view_m, cy + view_m)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    counts = {t.name.lower(): int(((tr.types == t) & ok).sum()) for t in (AgentType.VEHICLE, AgentType.CYCLIST, AgentType.PEDESTRIAN)}
    kind = scenario.metadata.get("network", {}).get("kind", "")
    ax.set_title(f"{scenario.scenario_id} ({kind}) t={scenario.timestamps_s[f]:.1f}s  "
                 + ", ".join(f"{v} {k}" for k, v in counts.items()), fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
