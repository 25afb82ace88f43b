"""Colours and sizes of the bird's-eye view (one place to restyle every image).

Stage: rendering, at the end of the data flow; constants only, plus the conversions that the
renderer and the tests share (a colour as the exact ``uint8`` RGB it has in a rendered image).
"""

from __future__ import annotations

import numpy as np

from ..scenario import AgentType, RoadLineType, SignalState

BACKGROUND = "#d9d9d9"
LANE_COLOR = "#9a9a9a"
BIKE_LANE_COLOR = "#3f9e6e"
ROAD_EDGE_COLOR = "#262626"
WHITE_LINE_COLOR = "#ffffff"
YELLOW_LINE_COLOR = "#f0b400"
UNKNOWN_LINE_COLOR = "#bdbdbd"
CROSSWALK_FACE = "#ececec"
CROSSWALK_HATCH = "#8c8c8c"
SPEED_BUMP_COLOR = "#e08a3c"
DRIVEWAY_COLOR = "#c8c8c8"
STOP_SIGN_COLOR = "#b71c1c"

EGO_COLOR = "#d81b60"
"""The self-driving car (or the agent the view follows)."""
# per AgentType: (controlled fill, background fill)
AGENT_COLORS = {
    AgentType.VEHICLE: ("#1565c0", "#90a9c9"),
    AgentType.PEDESTRIAN: ("#ef6c00", "#f0c08a"),
    AgentType.CYCLIST: ("#2e7d32", "#9ccc9f"),
    AgentType.OTHER: ("#6a1b9a", "#bfa6cc"),
}
AGENT_EDGE_COLOR = "#1a1a1a"
TEXT_SIZE_PT = 11.0
MIN_AGENT_PX = 4.0
"""Smallest drawn box side in pixels (a 0.5 m pedestrian is 2.5 px at the default zoom)."""

LIGHT_RED, LIGHT_YELLOW, LIGHT_GREEN, LIGHT_UNKNOWN = "#e53935", "#fdd835", "#43a047", "#7f7f7f"
LIGHT_COLOR_OF_STATE = {
    SignalState.UNKNOWN: LIGHT_UNKNOWN,
    SignalState.ARROW_STOP: LIGHT_RED,
    SignalState.STOP: LIGHT_RED,
    SignalState.FLASHING_STOP: LIGHT_RED,
    SignalState.ARROW_CAUTION: LIGHT_YELLOW,
    SignalState.CAUTION: LIGHT_YELLOW,
    SignalState.FLASHING_CAUTION: LIGHT_YELLOW,
    SignalState.ARROW_GO: LIGHT_GREEN,
    SignalState.GO: LIGHT_GREEN,
}

WHITE_LINES = {RoadLineType.BROKEN_SINGLE_WHITE, RoadLineType.SOLID_SINGLE_WHITE, RoadLineType.SOLID_DOUBLE_WHITE}
BROKEN_LINES = {RoadLineType.BROKEN_SINGLE_WHITE, RoadLineType.BROKEN_SINGLE_YELLOW, RoadLineType.BROKEN_DOUBLE_YELLOW}
DOUBLE_LINES = {RoadLineType.SOLID_DOUBLE_WHITE, RoadLineType.BROKEN_DOUBLE_YELLOW, RoadLineType.SOLID_DOUBLE_YELLOW,
                 RoadLineType.PASSING_DOUBLE_YELLOW}


def rgba(color: str, alpha: float = 1.0) -> np.ndarray:
    from matplotlib.colors import to_rgba

    r, g, b, _ = to_rgba(color)
    return np.array([r, g, b, alpha])


def color_uint8(color: str) -> np.ndarray:
    """A matplotlib colour as the ``uint8 [3]`` RGB it has in a rendered image."""
    return np.round(rgba(color)[:3] * 255).astype(np.uint8)


def light_color_table() -> np.ndarray:
    """[9, 4] RGBA of each SignalState code."""
    return np.stack([rgba(LIGHT_COLOR_OF_STATE[SignalState(s)]) for s in range(len(SignalState))])
