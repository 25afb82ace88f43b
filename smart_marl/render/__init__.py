"""Bird's-eye-view images of scenes and recordings of episodes.

Stage: rendering, at the end of the data flow (used by the demo, the PettingZoo env's ``render()``
and the what-if tool). It reads a Scenario plus per-frame agent states as arrays and hands back
RGB images ``[H, W, 3] uint8``, GIFs and MP4s; it never changes a scene.

* :class:`BevRenderer` (``bev``): the static map drawn once, agents, trails, lights and a text
  overlay drawn per frame; :func:`render_scenario_frame` for a scene's logged state at a frame.
* :class:`EpisodeRecorder` and :func:`render_log_replay` (``record``): frames -> GIF / MP4.
* ``style``: every colour and size.

matplotlib, imageio and imageio-ffmpeg (the ``render`` extra) are imported only when used.
"""

from .bev import MIN_VIEW_RADIUS_M, BevRenderer, box_outlines, render_scenario_frame
from .record import FRAME_FPS, TOKEN_STEP_FPS, EpisodeRecorder, render_log_replay
from .style import (
    AGENT_COLORS, BACKGROUND, EGO_COLOR, LIGHT_GREEN, LIGHT_RED, LIGHT_UNKNOWN, LIGHT_YELLOW, ROAD_EDGE_COLOR,
    color_uint8,
)

__all__ = [
    "BevRenderer", "MIN_VIEW_RADIUS_M", "box_outlines", "render_scenario_frame", "FRAME_FPS", "TOKEN_STEP_FPS", "EpisodeRecorder",
    "render_log_replay", "AGENT_COLORS", "BACKGROUND", "EGO_COLOR", "LIGHT_GREEN", "LIGHT_RED", "LIGHT_UNKNOWN",
    "LIGHT_YELLOW", "ROAD_EDGE_COLOR", "color_uint8",
]
