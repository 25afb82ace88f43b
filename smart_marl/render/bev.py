"""The bird's-eye-view renderer: a scene's static map drawn once, agents drawn per frame.

Stage: rendering, at the end of the data flow. :class:`BevRenderer` reads a
:class:`~smart_marl.scenario.Scenario` (its map, traffic-light stop points and self-driving car)
and per-frame agent states given as plain arrays, and hands back RGB images
(``np.ndarray [H, W, 3] uint8``); nothing here changes a scene.

The static map (lane centrelines, bike lanes, painted lines by colour and dash, road edges,
crosswalks, speed bumps, driveways, stop signs) is rasterised once per tile; each frame copies its
window and draws only what moves over it: agents as oriented boxes with a pointed front, fading
recent trajectories, traffic-light dots at the stop points and a text overlay. About 40-60
frames/s at 600x600 px for a WOMD scene of 83 agents and 199 lanes on a shared 2-core CPU.

matplotlib (Agg canvas, never pyplot, never a window) is imported when a renderer is built.
Coordinates are the scene's local frame in metres; image rows grow downwards, so world +y is up.
"""

from __future__ import annotations

import numpy as np

from ..config_files import check_value, number
from ..errors import UsageError
from ..scenario import AgentType, LaneType, MapFeatureType, RoadLineType, Scenario, SignalState
from .style import (
    AGENT_COLORS, AGENT_EDGE_COLOR, BACKGROUND, BIKE_LANE_COLOR, BROKEN_LINES, CROSSWALK_FACE, CROSSWALK_HATCH,
    DOUBLE_LINES, DRIVEWAY_COLOR, EGO_COLOR, LANE_COLOR, MIN_AGENT_PX, ROAD_EDGE_COLOR, SPEED_BUMP_COLOR,
    STOP_SIGN_COLOR, TEXT_SIZE_PT, UNKNOWN_LINE_COLOR, WHITE_LINE_COLOR, WHITE_LINES, YELLOW_LINE_COLOR,
    light_color_table, rgba,
)


def box_outlines(positions: np.ndarray, headings: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """[N, 5, 2] outlines of oriented boxes (a rectangle whose front edge has a small nose, so the
    heading reads at a glance): ``positions`` [N, 2] centres, ``headings`` [N] radians,
    ``sizes`` [N, 2] (length, width) in metres."""
    half_l = sizes[:, 0:1] / 2
    half_w = sizes[:, 1:2] / 2
    nose = np.minimum(half_w, half_l * 0.5) * 0.6  # how far the front corners are cut back
    # local (along, across) coordinates of: rear-right, front-right (cut), nose, front-left (cut), rear-left
    along = np.concatenate([-half_l, half_l - nose, half_l, half_l - nose, -half_l], axis=1)
    across = np.concatenate([-half_w, -half_w, np.zeros_like(half_w), half_w, half_w], axis=1)
    c, s = np.cos(headings)[:, None], np.sin(headings)[:, None]
    x = positions[:, 0:1] + c * along - s * across
    y = positions[:, 1:2] + s * along + c * across
    return np.stack([x, y], axis=-1)


def _polylines(road_map, index: np.ndarray) -> list[np.ndarray]:
    offsets = road_map.point_offsets
    return [np.asarray(road_map.points[offsets[i]:offsets[i + 1], :2], np.float64) for i in index]


def _offset_polyline(points: np.ndarray, offset_m: float) -> np.ndarray:
    """A polyline shifted sideways by ``offset_m`` (left positive), for double painted lines."""
    if len(points) < 2:
        return points
    d = np.gradient(points, axis=0)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = d / np.where(norm > 1e-9, norm, 1.0)
    return points + offset_m * np.stack([-d[:, 1], d[:, 0]], axis=1)

MIN_VIEW_RADIUS_M = 1.0
"""The narrowest view (metres from the centre to an edge). Line widths, dashes and markers scale with
the zoom (pixels per metre): at a radius of 1e-10 m a road edge is a line millions of kilometres wide
in points that matplotlib's Agg stroker never finishes, and at 1e-300 m the zoom overflows. 1 m (a
view 2 m across, narrower than a car) keeps every frame finite and fast."""


class BevRenderer:
    """Renders frames of one scene seen from above.

    ``center`` picks the view: ``"sdc"`` follows the ego agent (the scene's self-driving car, or
    ``ego_index`` given to :meth:`render`) frame by frame; ``"agents"`` is a fixed view on the
    middle of every logged valid agent position of the scene; ``(x, y)`` is a fixed view on that
    local point. The view is a square of side ``2 * view_radius_m`` rendered at ``size_px`` pixels
    (``view_radius_m`` a finite number >= :data:`MIN_VIEW_RADIUS_M`, else a :class:`UsageError`).

    How it stays fast: the static map is rasterised once per *tile* (a square of 1.5 view widths on
    a global pixel grid, kept in a small cache) by a second, off-screen figure; a frame copies its
    window out of the tile (the view is snapped to whole pixels, at most half a pixel off) and
    draws only the moving artists over it. Because tiles and the snapping depend only on the view
    centre, the same input always gives the same image, whatever was rendered before.
    """

    TILE_CACHE_SIZE = 4

    def __init__(self, scenario: Scenario, size_px: int = 600, view_radius_m: float = 60.0,
                 center: str | tuple[float, float] = "sdc", dpi: float = 100.0,
                 show_lane_centerlines: bool = True):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.scenario = scenario
        self.size_px = int(size_px)
        self.view_radius_m = float(check_value("view_radius_m", view_radius_m, number(MIN_VIEW_RADIUS_M),
                                               UsageError, "BevRenderer"))
        self.dpi = float(dpi)
        if isinstance(center, str):
            if center not in ("sdc", "agents"):
                raise ValueError(f"center must be 'sdc', 'agents' or an (x, y) pair, got {center!r}")
            self.center = center
        else:
            x, y = (float(v) for v in center)
            self.center = (x, y)
        self._fixed_center = self._initial_center()
        self._last_center = self._fixed_center

        self._px_per_m = self.size_px / (2 * self.view_radius_m)
        self._tile_step_px = max(self.size_px // 2, 1)
        self._tile_px = self.size_px + self._tile_step_px

        def new_figure(size_px: int):
            # A Figure with an Agg canvas, not pyplot: no global state, no window.
            fig = Figure(figsize=(size_px / self.dpi, size_px / self.dpi), dpi=self.dpi)
            canvas = FigureCanvasAgg(fig)
            fig.patch.set_facecolor(BACKGROUND)
            ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
            ax.set_axis_off()
            ax.set_aspect("auto")  # square axes and square limits: 1 m is the same on both axes
            ax.set_autoscale_on(False)
            return fig, canvas, ax

        # the static layer: an off-screen figure one tile wide
        self._tile_figure, self._tile_canvas, self._tile_ax = new_figure(self._tile_px)
        self._draw_static_map(self._tile_ax, show_lane_centerlines)
        self._tiles: dict[tuple[int, int], np.ndarray] = {}  # (kx, ky) -> [tile, tile, 4] uint8, LRU order
        # the moving layer: drawn over a copy of the tile's window
        self.figure, self.canvas, self.ax = new_figure(self.size_px)
        self.ax.patch.set_visible(False)
        self._make_dynamic_artists()
        self._font = None  # FreeType font of the text overlay, loaded on first use

    # ------------------------------------------------------------------------------ the view
    def _initial_center(self) -> tuple[float, float]:
        sc = self.scenario
        if isinstance(self.center, tuple):
            return self.center
        tr = sc.tracks
        if self.center == "sdc" and sc.sdc_index >= 0 and tr.valid[sc.sdc_index].any():
            f = sc.current_frame if tr.valid[sc.sdc_index, sc.current_frame] else int(np.argmax(tr.valid[sc.sdc_index]))
            return tuple(float(v) for v in tr.position[sc.sdc_index, f, :2])
        if tr.valid.any():
            xy = tr.position[..., :2][tr.valid].astype(np.float64)
            return tuple(float(v) for v in (xy.min(axis=0) + xy.max(axis=0)) / 2)
        pts = sc.road_map.points
        if len(pts):
            return tuple(float(v) for v in (pts[:, :2].min(axis=0) + pts[:, :2].max(axis=0)) / 2)
        return (0.0, 0.0)

    def _wanted_center(self, positions, valid, ego_index) -> tuple[float, float]:
        if self.center != "sdc":
            return self._fixed_center
        ego = self.scenario.sdc_index if ego_index is None else ego_index
        if positions is not None and 0 <= ego < len(positions) and (valid is None or valid[ego]):
            return float(positions[ego, 0]), float(positions[ego, 1])
        return self._last_center

    def _view_edges_px(self, center: tuple[float, float]) -> tuple[int, int]:
        """(left, bottom) edges of the view on the global pixel grid (pixel ``i`` spans
        ``[i, i + 1) / px_per_m`` metres)."""
        half = self.size_px / 2
        return (int(np.floor(center[0] * self._px_per_m - half + 0.5)),
                int(np.floor(center[1] * self._px_per_m - half + 0.5)))

    def snap_center(self, center: tuple[float, float]) -> tuple[float, float]:
        """The centre of the image actually rendered for a wanted centre (within half a pixel)."""
        left, bottom = self._view_edges_px(center)
        half = self.size_px / 2
        return (left + half) / self._px_per_m, (bottom + half) / self._px_per_m

    def view_center(self, positions: np.ndarray | None = None, valid: np.ndarray | None = None,
                    ego_index: int | None = None) -> tuple[float, float]:
        """The local point at the image centre for a frame with these agent states (for
        :meth:`world_to_pixel`): the ego's position when following it, else the fixed centre,
        snapped to the pixel grid."""
        return self.snap_center(self._wanted_center(positions, valid, ego_index))

    def world_to_pixel(self, xy: np.ndarray, center: tuple[float, float]) -> np.ndarray:
        """Local points [..., 2] (m) -> (row, col) pixel coordinates [..., 2] (float) in an image
        rendered with the view centred on ``center``."""
        xy = np.asarray(xy, np.float64)
        col = (xy[..., 0] - center[0]) * self._px_per_m + self.size_px / 2
        row = (center[1] - xy[..., 1]) * self._px_per_m + self.size_px / 2
        return np.stack([row, col], axis=-1)

    # ------------------------------------------------------------------------ the static map
    def _draw_static_map(self, ax, show_lane_centerlines: bool) -> None:
        from matplotlib.collections import LineCollection, PolyCollection

        rm = self.scenario.road_map
        lw = max(self._px_per_m / 5.0, 0.5)  # line widths scale a little with the zoom (points)

        def add_lines(index, color, width, z, style="solid"):
            if len(index):
                ax.add_collection(LineCollection(_polylines(rm, index), colors=color, linewidths=width,
                                                 linestyles=style, zorder=z, capstyle="butt"))

        def add_polygons(index, face, z, hatch=None, edge=None):
            if len(index):
                polys = [p for p in _polylines(rm, index) if len(p) >= 3]
                if polys:
                    ax.add_collection(PolyCollection(polys, facecolors=face, edgecolors=edge or face,
                                                     hatch=hatch, linewidths=0.6, zorder=z))

        types, sub = rm.types, rm.subtypes
        add_polygons(np.flatnonzero(types == MapFeatureType.DRIVEWAY), DRIVEWAY_COLOR, 1)
        add_polygons(np.flatnonzero(types == MapFeatureType.CROSSWALK), CROSSWALK_FACE, 2, hatch="////",
                     edge=CROSSWALK_HATCH)
        add_polygons(np.flatnonzero(types == MapFeatureType.SPEED_BUMP), SPEED_BUMP_COLOR, 2, hatch="xx",
                     edge="#a85a1c")
        lanes = types == MapFeatureType.LANE
        bike = lanes & (sub == LaneType.BIKE_LANE)
        if show_lane_centerlines:
            add_lines(np.flatnonzero(lanes & ~bike), LANE_COLOR, 0.6 * lw, 3)
        add_lines(np.flatnonzero(bike), BIKE_LANE_COLOR, 1.0 * lw, 3, style=(0, (2, 2)))

        lines = np.flatnonzero(types == MapFeatureType.ROAD_LINE)
        white = np.isin(sub[lines], list(WHITE_LINES))
        yellow = np.isin(sub[lines], [t for t in RoadLineType if t not in WHITE_LINES and t != RoadLineType.UNKNOWN])
        broken = np.isin(sub[lines], list(BROKEN_LINES))
        double = np.isin(sub[lines], list(DOUBLE_LINES))
        for color, kind in ((WHITE_LINE_COLOR, white), (YELLOW_LINE_COLOR, yellow), (UNKNOWN_LINE_COLOR, ~(white | yellow))):
            for dashed in (False, True):
                sel = lines[kind & (broken == dashed)]
                if not len(sel):
                    continue
                polys, is_double = _polylines(rm, sel), double[kind & (broken == dashed)]
                paths = [p for p, d in zip(polys, is_double) if not d]
                for p, d in zip(polys, is_double):
                    if d:
                        paths += [_offset_polyline(p, 0.12), _offset_polyline(p, -0.12)]
                ax.add_collection(LineCollection(paths, colors=color, linewidths=0.9 * lw, zorder=4,
                                                 linestyles=(0, (4, 4)) if dashed else "solid", capstyle="butt"))
        add_lines(np.flatnonzero(types == MapFeatureType.ROAD_EDGE), ROAD_EDGE_COLOR, 1.6 * lw, 5)

        stops = np.flatnonzero(types == MapFeatureType.STOP_SIGN)
        if len(stops):
            xy = rm.points[rm.point_offsets[stops], :2]
            side_pt = max(2.2 * self._px_per_m, 9.0) * 72 / self.dpi  # ~2.2 m across, at least 9 px
            ax.scatter(xy[:, 0], xy[:, 1], s=side_pt ** 2, marker="8", c=STOP_SIGN_COLOR, edgecolors="white",
                       linewidths=1.2, zorder=6)
            ax.scatter(xy[:, 0], xy[:, 1], s=(side_pt * 0.35) ** 2, marker="s", c="white", linewidths=0, zorder=6)

    # ---------------------------------------------------------------------- moving artists
    def _make_dynamic_artists(self) -> None:
        from matplotlib.collections import LineCollection, PathCollection, PolyCollection

        ax = self.ax
        dot_pt = max(1.4 * self._px_per_m * 72 / self.dpi, 3.0)  # light dot diameter: ~1.4 m
        self._lights = ax.scatter(np.zeros(0), np.zeros(0), s=dot_pt ** 2, edgecolors="#111111",
                                  linewidths=0.6, zorder=7)
        assert isinstance(self._lights, PathCollection)
        self._trails = LineCollection([], linewidths=max(0.3 * self._px_per_m, 1.0), zorder=8, capstyle="round")
        self._boxes = PolyCollection([], edgecolors=AGENT_EDGE_COLOR, linewidths=0.7, zorder=9)
        for artist in (self._trails, self._boxes):
            ax.add_collection(artist)
        self._dynamic = (self._lights, self._trails, self._boxes)
        self._light_table = light_color_table()
        colors = np.zeros((2, len(AgentType), 4))
        for t in AgentType:
            colors[0, t], colors[1, t] = rgba(AGENT_COLORS[t][1]), rgba(AGENT_COLORS[t][0])
        self._agent_table = colors  # [controlled?, type] -> RGBA
        self._ego_rgba = rgba(EGO_COLOR)

    def agent_colors(self, types: np.ndarray, controlled: np.ndarray, ego_index: int | None = None) -> np.ndarray:
        """[N, 4] RGBA fill of each agent: by type, strong when controlled, the ego colour for ego."""
        types = np.clip(np.asarray(types, np.int64), 0, len(AgentType) - 1)
        out = self._agent_table[np.asarray(controlled, bool).astype(np.int64), types].copy()
        if ego_index is not None and 0 <= ego_index < len(out):
            out[ego_index] = self._ego_rgba
        return out

    # ------------------------------------------------------------------------------ render
    def render(self, positions: np.ndarray, headings: np.ndarray, sizes: np.ndarray, valid: np.ndarray,
               types: np.ndarray, controlled: np.ndarray | None = None, *, ego_index: int | None = None,
               trajectories: np.ndarray | None = None, trajectories_valid: np.ndarray | None = None,
               light_states: np.ndarray | None = None, light_present: np.ndarray | None = None,
               text: str | None = None, center: tuple[float, float] | None = None) -> np.ndarray:
        """One frame as ``[H, W, 3] uint8``.

        Args:
            positions: [N, 2] (or [N, 3]) box centres, local frame (m).
            headings: [N] radians. sizes: [N, 2] (or [N, 3]) length, width (m).
            valid: [N] bool, agents drawn. types: [N] AgentType codes.
            controlled: [N] bool, agents a policy controls (strong colours); None: none.
            ego_index: the agent drawn in the ego colour and followed by ``center="sdc"``;
                None: the scene's self-driving car when the arrays are the scene's tracks
                (N equal to its track count), else no ego. -1: no ego.
            trajectories: [N, K, 2] recent positions, oldest first, drawn as fading lines;
                ``trajectories_valid`` [N, K] masks them.
            light_states: [L] SignalState codes of the scene's traffic-light lanes (the order of
                ``scenario.traffic_lights.lane_ids``); ``light_present`` [L] hides absent ones.
            text: an overlay in the top-left corner (e.g. step and time).
            center: overrides the view centre (m) for this frame.
        """
        positions = np.asarray(positions, np.float64)[:, :2]
        n = len(positions)
        headings = np.asarray(headings, np.float64).reshape(n)
        sizes = np.asarray(sizes, np.float64)[:, :2].reshape(n, 2)
        valid = np.asarray(valid, bool).reshape(n)
        types = np.asarray(types).reshape(n)
        controlled = np.zeros(n, bool) if controlled is None else np.asarray(controlled, bool).reshape(n)
        if ego_index is None:
            ego_index = self.scenario.sdc_index if n == self.scenario.num_tracks else -1
        wanted = center if center is not None else self._wanted_center(positions, valid, ego_index)
        self._last_center = wanted

        colors = self.agent_colors(types, controlled, ego_index)
        # draw the ego last so that it is never covered by an overlapping box
        order = np.flatnonzero(valid)
        if 0 <= ego_index < n and valid[ego_index]:
            order = np.concatenate([order[order != ego_index], [ego_index]])
        # boxes are drawn at least MIN_AGENT_PX pixels across so that pedestrians stay visible
        drawn_sizes = np.maximum(sizes[order], MIN_AGENT_PX / self._px_per_m)
        self._boxes.set_verts(box_outlines(positions[order], headings[order], drawn_sizes))
        self._boxes.set_facecolors(colors[order])

        if trajectories is not None and np.shape(trajectories)[1] >= 2:
            traj = np.asarray(trajectories, np.float64)[:, :, :2]
            k = traj.shape[1]
            tv = np.ones(traj.shape[:2], bool) if trajectories_valid is None else np.asarray(trajectories_valid, bool)
            seg = np.stack([traj[:, :-1], traj[:, 1:]], axis=2)  # [N, K-1, 2, 2]
            seg = np.concatenate([seg, np.full((n, k - 1, 1, 2), np.nan)], axis=2)  # NaN row: a pen lift
            seg_ok = tv[:, :-1] & tv[:, 1:] & valid[:, None]  # [N, K-1]
            alphas = np.linspace(0.1, 0.9, k - 1)  # oldest segment faintest
            # one NaN-separated polyline per (colour, age): a few paths instead of one per segment
            palette, colour_of_agent = np.unique(colors, axis=0, return_inverse=True)
            paths, path_rgba = [], []
            for c in range(len(palette)):
                for a in range(k - 1):
                    sel = seg_ok[:, a] & (colour_of_agent.reshape(-1) == c)
                    if sel.any():
                        paths.append(seg[sel, a].reshape(-1, 2))
                        path_rgba.append((*palette[c, :3], alphas[a]))
            self._trails.set_segments(paths)
            self._trails.set_colors(path_rgba if path_rgba else "none")
        else:
            self._trails.set_segments([])

        tl = self.scenario.traffic_lights
        if light_states is not None and len(tl.lane_ids):
            states = np.clip(np.asarray(light_states, np.int64).reshape(-1), 0, len(SignalState) - 1)
            shown = np.ones(len(states), bool) if light_present is None else np.asarray(light_present, bool).reshape(-1)
            self._lights.set_offsets(np.asarray(tl.stop_points[shown, :2], np.float64))
            self._lights.set_facecolors(self._light_table[states[shown]])
        else:
            self._lights.set_offsets(np.zeros((0, 2)))

        image = self._draw(*self._view_edges_px(wanted))
        if text:
            self._overlay_text(image, text)
        return image

    def _tile(self, kx: int, ky: int) -> np.ndarray:
        """The static map rasterised over global pixels [k * step, k * step + tile) on each axis."""
        key = (kx, ky)
        if key in self._tiles:
            self._tiles[key] = self._tiles.pop(key)  # most recently used last
            return self._tiles[key]
        step, size = self._tile_step_px, self._tile_px
        self._tile_ax.set_xlim(kx * step / self._px_per_m, (kx * step + size) / self._px_per_m)
        self._tile_ax.set_ylim(ky * step / self._px_per_m, (ky * step + size) / self._px_per_m)
        self._tile_canvas.draw()
        tile = np.array(self._tile_canvas.buffer_rgba())  # a copy: the canvas is reused
        self._tiles[key] = tile
        while len(self._tiles) > self.TILE_CACHE_SIZE:
            self._tiles.pop(next(iter(self._tiles)))
        return tile

    def _draw(self, left: int, bottom: int) -> np.ndarray:
        """The static layer's window with the moving artists drawn over it, [H, W, 3] uint8."""
        size, step = self.size_px, self._tile_step_px
        kx, ky = left // step, bottom // step
        tile = self._tile(kx, ky)
        col0 = left - kx * step
        row0 = (ky * step + self._tile_px) - (bottom + size)  # image rows grow downwards
        renderer = self.canvas.get_renderer()
        buffer = np.asarray(renderer.buffer_rgba())
        buffer[...] = tile[row0:row0 + size, col0:col0 + size]
        self.ax.set_xlim(left / self._px_per_m, (left + size) / self._px_per_m)
        self.ax.set_ylim(bottom / self._px_per_m, (bottom + size) / self._px_per_m)
        for artist in self._dynamic:
            self.ax.draw_artist(artist)
        return np.ascontiguousarray(buffer[..., :3])

    def _overlay_text(self, image: np.ndarray, text: str) -> None:
        """Write ``text`` (dark, on a light box) into the top-left corner of ``image`` in place.

        The string is rasterised with FreeType directly (matplotlib's Text artist costs ~20 ms a
        frame, this ~3 ms) and composited in numpy."""
        if self._font is None:
            from matplotlib.font_manager import FontProperties, findfont
            from matplotlib.ft2font import FT2Font

            self._font = FT2Font(findfont(FontProperties(family="monospace")))
        font = self._font
        font.clear()
        font.set_size(TEXT_SIZE_PT * float(np.clip(self.size_px / 600.0, 0.7, 1.5)), self.dpi)
        font.set_text(text, 0.0)
        font.draw_glyphs_to_bitmap(antialiased=True)
        ink = np.asarray(font.get_image(), np.float64) / 255.0  # [h, w] coverage
        pad, margin = 4, 5
        h, w = image.shape[:2]
        ink = ink[: max(h - 2 * (pad + margin), 0), : max(w - 2 * (pad + margin), 0)]
        top, left = margin, margin
        rows, cols = slice(top, top + ink.shape[0] + 2 * pad), slice(left, left + ink.shape[1] + 2 * pad)
        box = image[rows, cols].astype(np.float64)
        box += 0.8 * (255.0 - box)  # a white box at 80 %
        box[pad: pad + ink.shape[0], pad: pad + ink.shape[1]] *= 1.0 - ink[..., None]  # black glyphs
        image[rows, cols] = np.round(box).astype(np.uint8)

    # ------------------------------------------------------------------- logged-state helper
    def render_logged(self, frame_index: int, history_frames: int = 10, controlled: np.ndarray | None = None,
                      text: str | None = "auto") -> np.ndarray:
        """The scene's logged state at ``frame_index``: every valid track, the last
        ``history_frames`` frames as trails, that frame's traffic lights. ``controlled`` defaults
        to the tracks to predict; ``text="auto"`` writes the frame number and time."""
        sc = self.scenario
        tr = sc.tracks
        f = int(frame_index)
        if not 0 <= f < sc.num_frames:
            raise IndexError(f"frame {f} outside [0, {sc.num_frames}) of scenario {sc.scenario_id}")
        if controlled is None:
            controlled = np.zeros(sc.num_tracks, bool)
            controlled[sc.predict_indices] = True
        start = max(0, f - history_frames)
        trajectories = tr.position[:, start:f + 1, :2] if history_frames > 0 else None
        tv = tr.valid[:, start:f + 1] if history_frames > 0 else None
        if text == "auto":
            t_s = sc.timestamps_s[f] - sc.timestamps_s[0]
            text = f"{sc.scenario_id}  frame {f:3d}  t={t_s:4.1f} s"
        tl = sc.traffic_lights
        return self.render(tr.position[:, f, :2], tr.heading[:, f], tr.size[:, f, :2], tr.valid[:, f], tr.types,
                           controlled, trajectories=trajectories, trajectories_valid=tv,
                           light_states=tl.states[f] if len(tl.lane_ids) else None,
                           light_present=tl.present[f] if len(tl.lane_ids) else None, text=text)

    def close(self) -> None:
        """Release the figure (it is not registered with pyplot, so this only drops references)."""
        self.figure.clear()
        self._tile_figure.clear()
        self._tiles.clear()


def render_scenario_frame(scenario: Scenario, frame_index: int | None = None, *, history_frames: int = 10,
                          controlled: np.ndarray | None = None, text: str | None = "auto", **renderer_kw) -> np.ndarray:
    """The logged state of ``scenario`` at ``frame_index`` (its current frame by default) as an RGB
    image ``[H, W, 3] uint8``. ``renderer_kw`` go to :class:`BevRenderer` (size_px, view_radius_m,
    center, dpi)."""
    renderer = BevRenderer(scenario, **renderer_kw)
    frame = scenario.current_frame if frame_index is None else frame_index
    return renderer.render_logged(frame, history_frames=history_frames, controlled=controlled, text=text)
