"""Bird's-eye-view renderer and episode recorder: images of real and synthetic scenes, pixel
colours checked against the view transform, determinism, locality of changes, GIF/MP4 round trips."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("matplotlib", reason="the render extra (matplotlib) is not installed")
pytest.importorskip("imageio", reason="the render extra (imageio) is not installed")

from smart_marl import AgentType, MapFeatureType, RoadMap, SignalState, TrafficLights  # noqa: E402
from smart_marl.render import (  # noqa: E402
    AGENT_COLORS, EGO_COLOR, LIGHT_GREEN, LIGHT_RED, ROAD_EDGE_COLOR, BevRenderer, EpisodeRecorder, color_uint8,
    render_log_replay, render_scenario_frame,
)
from smart_marl.synthetic import synthetic_scenario  # noqa: E402

SIZE_PX = 300  # small images keep the tests fast; the view transform is the same at any size


@pytest.fixture(scope="module")
def scene(sample_scenes):
    """A scene with a map, lights and traffic: the sample scene sumo-7-000000-02 (44 tracks, 155
    signalised lanes, 7 vehicles within 35 m of the SDC)."""
    return sample_scenes[2]


def _pixel(image: np.ndarray, renderer: BevRenderer, xy, center) -> np.ndarray:
    row, col = renderer.world_to_pixel(np.asarray(xy, np.float64), center)
    return image[int(np.floor(row)), int(np.floor(col))]


def _count_color(image: np.ndarray, color: str) -> int:
    return int(np.all(image == color_uint8(color), axis=-1).sum())


def _logged(scenario, f):
    tr = scenario.tracks
    return dict(positions=tr.position[:, f, :2], headings=tr.heading[:, f], sizes=tr.size[:, f, :2],
                valid=tr.valid[:, f], types=tr.types)


def test_a_frame_is_an_rgb_image_with_the_ego_colour_at_the_sdc(scene):
    renderer = BevRenderer(scene, size_px=SIZE_PX, view_radius_m=40.0, center="sdc")
    f = scene.current_frame
    image = renderer.render_logged(f)
    assert image.shape == (SIZE_PX, SIZE_PX, 3) and image.dtype == np.uint8
    assert len(np.unique(image.reshape(-1, 3), axis=0)) >= 8  # map, lines, agents, lights, text: not blank
    sdc_xy = scene.tracks.position[scene.sdc_index, f, :2]
    center = renderer.view_center(scene.tracks.position[:, f, :2], scene.tracks.valid[:, f])
    np.testing.assert_allclose(center, sdc_xy)
    np.testing.assert_allclose(renderer.world_to_pixel(sdc_xy, center), [SIZE_PX / 2, SIZE_PX / 2])
    assert np.array_equal(_pixel(image, renderer, sdc_xy, center), color_uint8(EGO_COLOR))
    # a controlled (to-predict) agent other than the SDC, inside the view and not under the title's box
    # (the top-left 40 rows x 3/4 of the width, see test_text_overlay_is_confined_to_the_top_left_corner),
    # has the controlled colour
    def under_title(xy):
        row, col = renderer.world_to_pixel(np.asarray(xy, np.float64), center)
        return row < 40 and col < SIZE_PX * 0.75

    shown = [i for i in scene.predict_indices if i != scene.sdc_index and scene.tracks.valid[i, f]
             and np.abs(scene.tracks.position[i, f, :2] - sdc_xy).max() < 35 and not under_title(scene.tracks.position[i, f, :2])]
    assert len(shown) == 6
    for i in shown:
        want = AGENT_COLORS[AgentType(int(scene.tracks.types[i]))][0]
        assert np.array_equal(_pixel(image, renderer, scene.tracks.position[i, f, :2], center), color_uint8(want))


def test_background_vehicles_have_their_type_colour(scene):
    renderer = BevRenderer(scene, size_px=SIZE_PX, view_radius_m=40.0, center="sdc")
    f = scene.current_frame
    state = _logged(scene, f)
    image = renderer.render(**state, controlled=None, ego_index=-1, center=(0.0, 0.0))
    vehicles = np.flatnonzero(state["valid"] & (scene.tracks.types == AgentType.VEHICLE)
                              & (np.abs(state["positions"]).max(axis=1) < 35))
    assert len(vehicles) >= 5
    colour = color_uint8(AGENT_COLORS[AgentType.VEHICLE][1])
    hits = [np.array_equal(_pixel(image, renderer, state["positions"][i], (0.0, 0.0)), colour) for i in vehicles]
    assert np.mean(hits) >= 0.8  # all but those covered by a neighbour's box or a light


def test_rendering_is_deterministic_and_independent_of_earlier_frames(scene):
    a = BevRenderer(scene, size_px=SIZE_PX, center="agents")
    first = a.render_logged(20)
    a.render_logged(60)  # the cached background is reused; nothing of frame 60 may stay behind
    again = a.render_logged(20)
    fresh = BevRenderer(scene, size_px=SIZE_PX, center="agents").render_logged(20)
    assert np.array_equal(first, again) and np.array_equal(first, fresh)
    b = BevRenderer(scene, size_px=SIZE_PX, center="sdc")
    assert np.array_equal(b.render_logged(15), BevRenderer(scene, size_px=SIZE_PX, center="sdc").render_logged(15))


def test_moving_one_agent_changes_the_image_only_near_it(scene):
    renderer = BevRenderer(scene, size_px=SIZE_PX, view_radius_m=40.0, center=(0.0, 0.0))
    f = scene.current_frame
    state = _logged(scene, f)
    pos = state["positions"].astype(np.float64)
    far = np.flatnonzero(state["valid"] & (np.linalg.norm(pos, axis=1) > 15) & (np.abs(pos).max(axis=1) < 35))  # in the 40 m view
    j = int(far[0])
    before = renderer.render(**state)
    moved = dict(state, positions=pos.copy())
    moved["positions"][j] += (3.0, 2.0)
    after = renderer.render(**moved)
    changed = np.argwhere(np.any(before != after, axis=-1))
    assert len(changed) > 20
    reach_px = (np.linalg.norm(state["sizes"][j]) / 2) * renderer._px_per_m + 3  # half diagonal + antialiasing
    centres = renderer.world_to_pixel(np.stack([pos[j], moved["positions"][j]]), (0.0, 0.0))  # [2, (row, col)]
    dist = np.linalg.norm(changed[:, None, :] + 0.5 - centres[None], axis=-1).min(axis=1)
    assert dist.max() <= reach_px


def test_traffic_lights_are_dots_in_their_state_colour_at_the_stop_points(scene):
    tl = scene.traffic_lights
    center = tuple(float(v) for v in tl.stop_points[:, :2].mean(axis=0))
    renderer = BevRenderer(scene, size_px=SIZE_PX, view_radius_m=50.0, center=center)
    n = scene.num_tracks
    nobody = dict(positions=np.zeros((n, 2)), headings=np.zeros(n), sizes=np.ones((n, 2)), valid=np.zeros(n, bool),
                  types=scene.tracks.types)
    in_view = tl.stop_points[np.abs(tl.stop_points[:, :2] - center).max(axis=1) < 45, :2]  # a SUMO network reaches further
    assert len(in_view) >= 3
    for state, colour in ((SignalState.STOP, LIGHT_RED), (SignalState.GO, LIGHT_GREEN)):
        image = renderer.render(**nobody, light_states=np.full(len(tl.lane_ids), state))
        for xy in in_view:
            assert np.array_equal(_pixel(image, renderer, xy, center), color_uint8(colour))
    hidden = renderer.render(**nobody, light_states=np.full(len(tl.lane_ids), SignalState.GO),
                             light_present=np.zeros(len(tl.lane_ids), bool))
    assert _count_color(hidden, LIGHT_GREEN) == 0
    # the logged frame: the three lanes in front of the SDC show red at frame 10
    logged = renderer.render_logged(scene.current_frame, history_frames=0)
    red = tl.states[scene.current_frame] == SignalState.STOP
    assert red.sum() >= 3 and _count_color(logged, LIGHT_RED) > 0


def _without(scenario, feature_type):
    rm = scenario.road_map
    keep = np.flatnonzero(rm.types != feature_type)
    features = [dict(id=rm.ids[i], type=rm.types[i], subtype=rm.subtypes[i], points=rm.feature_points(i)) for i in keep]
    return dataclasses.replace(scenario, road_map=RoadMap.from_features(features))


def test_synthetic_scene_renders_with_edges_lights_and_ego():
    scenario = synthetic_scenario(0)
    renderer = BevRenderer(scenario, size_px=SIZE_PX, view_radius_m=30.0)
    image = renderer.render_logged(scenario.current_frame)
    assert len(np.unique(image.reshape(-1, 3), axis=0)) >= 6
    sdc_xy = scenario.tracks.position[scenario.sdc_index, scenario.current_frame, :2]
    assert np.array_equal(_pixel(image, renderer, sdc_xy, tuple(sdc_xy)), color_uint8(EGO_COLOR))
    assert _count_color(image, ROAD_EDGE_COLOR) > 100


def test_scenes_without_road_edges_or_traffic_lights_render():
    scenario = synthetic_scenario(1)
    f = scenario.current_frame
    no_edges = _without(scenario, MapFeatureType.ROAD_EDGE)
    image = render_scenario_frame(no_edges, f, size_px=SIZE_PX, view_radius_m=30.0)
    assert image.shape == (SIZE_PX, SIZE_PX, 3) and _count_color(image, ROAD_EDGE_COLOR) == 0
    no_lights = dataclasses.replace(scenario, traffic_lights=TrafficLights.empty(scenario.num_frames))
    renderer = BevRenderer(no_lights, size_px=SIZE_PX, view_radius_m=60.0, center=(0.0, 0.0))
    without = renderer.render_logged(f)
    with_lights = render_scenario_frame(scenario, f, size_px=SIZE_PX, view_radius_m=60.0, center=(0.0, 0.0))
    changed = np.argwhere(np.any(with_lights != without, axis=-1))
    assert len(changed) > 10  # the lights are the only difference, and they are drawn only at the stop points
    stops = renderer.world_to_pixel(scenario.traffic_lights.stop_points[:, :2], (0.0, 0.0))
    dist = np.linalg.norm(changed[:, None, :] + 0.5 - stops[None], axis=-1).min(axis=1)
    assert dist.max() <= 1.0 * renderer._px_per_m + 3  # a 1.4 m dot plus antialiasing
    empty_map = dataclasses.replace(no_lights, road_map=RoadMap.empty())
    assert render_scenario_frame(empty_map, f, size_px=SIZE_PX).shape == (SIZE_PX, SIZE_PX, 3)


def _distinct_frames(n: int, size=(64, 80)) -> list[np.ndarray]:
    frames = []
    for k in range(n):
        frame = np.full((*size, 3), 30, np.uint8)
        frame[:, 8 * k: 8 * k + 8] = (250, 40, 40)
        frames.append(frame)
    return frames


def test_gif_round_trip_keeps_frame_count_size_and_duration(tmp_path):
    import imageio.v3 as iio

    recorder = EpisodeRecorder(tmp_path / "out" / "episode.gif", fps=2)
    recorder.extend(_distinct_frames(7))
    path = recorder.write()
    frames = iio.imread(path, index=None)
    assert frames.shape[:3] == (7, 64, 80)
    assert iio.immeta(path, index=0)["duration"] == 500  # ms per frame at 2 fps


def test_mp4_round_trip_keeps_frame_count_and_pads_odd_sizes(tmp_path):
    import imageio.v2 as iio2

    recorder = EpisodeRecorder(tmp_path / "episode.mp4", fps=10)
    recorder.extend(_distinct_frames(9, size=(63, 81)))
    path = recorder.write()
    frames = iio2.mimread(path, format="FFMPEG", memtest=False)
    assert len(frames) == 9 and frames[0].shape == (64, 82, 3)
    assert abs(int(frames[4][30, 36, 0]) - 250) < 40 and int(frames[4][30, 10, 0]) < 80  # the red band moved


def test_recorder_rejects_unknown_extensions_and_bad_frames(tmp_path):
    with pytest.raises(ValueError, match=r"unknown extension '\.avi'.*\.gif, \.mp4"):
        EpisodeRecorder(tmp_path / "x.avi")
    recorder = EpisodeRecorder(tmp_path / "x.gif")
    with pytest.raises(ValueError, match="uint8"):
        recorder.add(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError, match="no frames"):
        recorder.write()


def test_log_replay_writes_one_image_per_selected_frame(tmp_path):
    import imageio.v3 as iio

    scenario = synthetic_scenario(2, num_frames=21)
    path = render_log_replay(scenario, tmp_path / "replay.gif", fps=5, every=4, size_px=120)
    frames = iio.imread(path, index=None)
    assert frames.shape[:3] == (len(range(0, 21, 4)), 120, 120)


def test_map_and_agents_stay_aligned_while_the_view_follows_the_sdc_across_tiles():
    scenario = synthetic_scenario(3)
    tr, rm = scenario.tracks, scenario.road_map
    edge = rm.feature_points(int(rm.indices_of(MapFeatureType.ROAD_EDGE)[0]))
    edge_y = float(edge[0, 1])
    renderer = BevRenderer(scenario, size_px=SIZE_PX, view_radius_m=12.0, center="sdc")
    ego = scenario.sdc_index
    frames = range(0, scenario.num_frames, 6)
    images = {}
    for f in frames:
        images[f] = image = renderer.render_logged(f, history_frames=0, text=None)
        center = renderer.view_center(tr.position[:, f, :2], tr.valid[:, f])
        ego_xy = tr.position[ego, f, :2]
        assert np.abs(np.subtract(center, ego_xy)).max() <= 0.5 / renderer._px_per_m  # snapped to half a pixel
        assert np.array_equal(_pixel(image, renderer, ego_xy, center), color_uint8(EGO_COLOR))
        for dx in (-8.0, 3.0, 9.0):  # the road edge's pixels are where the view transform puts them
            assert np.array_equal(_pixel(image, renderer, (ego_xy[0] + dx, edge_y), center), color_uint8(ROAD_EDGE_COLOR))
    travelled_m = tr.position[ego, frames[-1], 0] - tr.position[ego, 0, 0]
    assert travelled_m > 2 * 12.0  # the view crossed several tiles
    again = BevRenderer(scenario, size_px=SIZE_PX, view_radius_m=12.0, center="sdc")
    for f in (frames[-1], frames[0]):  # a fresh renderer, visiting the tiles in another order
        assert np.array_equal(again.render_logged(f, history_frames=0, text=None), images[f])


def test_text_overlay_is_confined_to_the_top_left_corner(scene):
    renderer = BevRenderer(scene, size_px=SIZE_PX, center="agents")
    plain = renderer.render_logged(10, text=None)
    titled = renderer.render_logged(10, text="step 3  t=1.5 s")
    changed = np.argwhere(np.any(plain != titled, axis=-1))
    assert len(changed) > 50
    assert changed[:, 0].max() < 40 and changed[:, 1].max() < SIZE_PX * 0.75
    assert titled[changed[:, 0], changed[:, 1]].min() < 60  # dark glyphs on a light box


def test_renderer_rejects_an_unknown_view_centre():
    with pytest.raises(ValueError, match="center must be 'sdc', 'agents' or an \\(x, y\\) pair"):
        BevRenderer(synthetic_scenario(0), center="middle")


def _distance_to_segments(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """[P] distance of pixel points [P, 2] to a polyline [K, 2] (both (row, col))."""
    a, b = polyline[:-1][None], polyline[1:][None]  # [1, K-1, 2]
    ab = b - a
    t = np.clip(((points[:, None] - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-9), 0, 1)
    return np.linalg.norm(points[:, None] - (a + t[..., None] * ab), axis=-1).min(axis=1)


def test_trails_follow_each_agents_own_path_and_never_join_agents():
    scenario = synthetic_scenario(0)
    renderer = BevRenderer(scenario, size_px=SIZE_PX, view_radius_m=20.0, center=(0.0, 0.0))
    n = 3
    positions = np.array([[-10.0, -8.0], [10.0, 8.0], [0.0, 15.0]])
    k = np.linspace(-1.0, 0.0, 8)[None, :, None]
    trajectories = positions[:, None, :] + k * np.array([[12.0, 0.0], [0.0, -14.0], [6.0, 0.0]])[:, None, :]
    valid_traj = np.ones((n, 8), bool)
    valid_traj[2, 3] = False  # a gap: the segments on both sides of it are not drawn
    state = dict(positions=positions, headings=np.zeros(n), sizes=np.full((n, 2), 1.0), valid=np.ones(n, bool),
                 types=np.zeros(n, np.int8), controlled=np.array([True, False, True]), ego_index=-1)
    plain = renderer.render(**state)
    trails = renderer.render(**state, trajectories=trajectories, trajectories_valid=valid_traj)
    changed = np.argwhere(np.any(plain != trails, axis=-1)).astype(np.float64) + 0.5
    assert len(changed) > 30
    pix = [renderer.world_to_pixel(trajectories[i], (0.0, 0.0)) for i in range(n)]
    pieces = [pix[0], pix[1], pix[2][:3], pix[2][4:]]
    dist = np.min([_distance_to_segments(changed, p) for p in pieces], axis=0)
    assert dist.max() <= 4.0  # within the line's half width and antialiasing of some agent's own path
    # nothing is drawn across the gap of agent 2 (between its samples 2 and 4)
    gap_mid = renderer.world_to_pixel(trajectories[2, 3], (0.0, 0.0))
    assert np.linalg.norm(changed - gap_mid, axis=1).min() > 2.0
