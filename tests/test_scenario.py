"""The Scenario model: validation at construction, cheap slicing, transforms that keep the source frame."""

from __future__ import annotations

import numpy as np
import pytest

from smart_marl import AgentType, LinkType, MapFeatureType, Scenario, ScenarioValidationError, Tracks
from smart_marl.scenario import RoadMap, TrafficLights
from smart_marl.synthetic import synthetic_scenario


def _track_arrays(n=3, t=11):
    return dict(ids=np.arange(n), types=np.zeros(n, np.int8), position=np.zeros((n, t, 3)), heading=np.zeros((n, t)),
                velocity=np.zeros((n, t, 2)), size=np.ones((n, t, 3)), valid=np.ones((n, t), bool))


def test_nan_position_on_a_valid_frame_is_rejected_with_track_and_frame():
    arrays = _track_arrays()
    arrays["position"][1, 4, 0] = np.nan
    with pytest.raises(ScenarioValidationError, match=r"position .*track 1 \(id 1\) frame 4"):
        Tracks(**arrays)


def test_nan_on_an_invalid_frame_is_allowed():
    arrays = _track_arrays()
    arrays["position"][1, 4] = np.nan
    arrays["valid"][1, 4] = False
    assert Tracks(**arrays).num_tracks == 3


@pytest.mark.parametrize("field,value,match", [
    ("heading", np.zeros((3, 10)), "heading has shape"),
    ("ids", np.arange(2), "ids has shape"),
    ("ids", np.array([1, 1, 2]), "not unique"),
    ("valid", np.ones((3, 11)), "boolean mask"),
    ("types", np.array([0, 1, 9]), "outside AgentType"),
])
def test_inconsistent_track_arrays_are_rejected(field, value, match):
    arrays = _track_arrays()
    arrays[field] = value
    with pytest.raises(ScenarioValidationError, match=match):
        Tracks(**arrays)


def test_scenario_rejects_mismatched_frames_and_indices():
    s = synthetic_scenario()
    kwargs = dict(scenario_id="x", source="test", tracks=s.tracks, road_map=s.road_map, traffic_lights=s.traffic_lights)
    with pytest.raises(ScenarioValidationError, match="timestamps_s has shape"):
        Scenario(timestamps_s=np.zeros(90), current_frame=10, **kwargs)
    with pytest.raises(ScenarioValidationError, match="current_frame 91"):
        Scenario(timestamps_s=s.timestamps_s, current_frame=91, **kwargs)
    with pytest.raises(ScenarioValidationError, match="sdc_index"):
        Scenario(timestamps_s=s.timestamps_s, current_frame=10, sdc_index=s.num_tracks, **kwargs)
    with pytest.raises(ScenarioValidationError, match="TrafficLights has 5 frames"):
        Scenario(timestamps_s=s.timestamps_s, current_frame=10,
                 **{**kwargs, "traffic_lights": TrafficLights.empty(5)})


def test_road_map_offsets_must_cover_the_points():
    m = synthetic_scenario().road_map
    with pytest.raises(ScenarioValidationError, match="point_offsets"):
        RoadMap(**{**{k: getattr(m, k) for k in m.__dataclass_fields__}, "point_offsets": m.point_offsets[:-1]})


def test_arrays_are_read_only():
    s = synthetic_scenario()
    with pytest.raises(ValueError):
        s.tracks.position[0, 0, 0] = 1.0


def test_window_shares_memory_and_keeps_the_current_time():
    s = synthetic_scenario()
    w = s.window(5, 50)
    assert w.num_frames == 45 and w.current_frame == 5
    assert np.shares_memory(w.tracks.position, s.tracks.position)
    assert w.timestamps_s[w.current_frame] == s.timestamps_s[s.current_frame]
    np.testing.assert_array_equal(w.traffic_lights.states, s.traffic_lights.states[5:50])
    with pytest.raises(ScenarioValidationError, match="outside the window"):
        s.window(20, 40)
    assert s.window(20, 40, current_frame=0).current_frame == 0


def test_select_tracks_remaps_sdc_and_tracks_to_predict():
    s = synthetic_scenario()  # sdc 0, predict [1, 2]
    sub = s.select_tracks([2, 0, 5])
    assert sub.tracks.ids.tolist() == [3, 1, 6]
    assert sub.sdc_index == 1
    assert sub.predict_indices.tolist() == [0]
    no_sdc = s.select_tracks(s.tracks.types == AgentType.PEDESTRIAN)
    assert no_sdc.sdc_index == -1 and len(no_sdc.predict_indices) == 0


def test_to_frame_keeps_source_coordinates_and_rotates_everything():
    s = synthetic_scenario()
    c = s.centered_on(3)  # origin and heading of track 3 at the current frame
    np.testing.assert_allclose(c.tracks.position[3, c.current_frame, :2], 0.0, atol=1e-5)
    assert abs(c.tracks.heading[3, c.current_frame]) < 1e-6
    turned = c.to_frame(1.0, -2.0, 0.7)
    valid = s.tracks.valid
    for scene in (c, turned):
        src = scene.frame.to_source(scene.tracks.position.astype(np.float64))
        np.testing.assert_allclose(src[valid], s.frame.to_source(s.tracks.position.astype(np.float64))[valid], atol=2e-4)
        np.testing.assert_allclose(scene.frame.to_source(scene.road_map.points),
                                   s.frame.to_source(s.road_map.points), atol=2e-4)
    # headings and velocities turn with the frame: velocity direction stays equal to heading for the cars
    cars = s.tracks.types == AgentType.VEHICLE
    h = turned.tracks.heading[cars][valid[cars]]
    v = turned.tracks.velocity[cars][valid[cars]]
    np.testing.assert_allclose(np.arctan2(v[:, 1], v[:, 0]), h, atol=1e-5)
    np.testing.assert_allclose(turned.frame.heading_to_source(turned.tracks.heading[0, 10]), 0.0, atol=1e-6)


def test_flat_arrays_round_trip_exactly():
    s = synthetic_scenario(seed=3)
    arrays, meta = s.to_arrays()
    back = Scenario.from_arrays(arrays, meta)
    assert back.equals(s, ignore=())
    assert s.differences(s.to_frame(1.0, 0.0)) == ["frame", "tracks.position", "road_map.points",
                                                   "traffic_lights.stop_points"]


def test_summary_counts_lanes_with_links():
    s = synthetic_scenario()
    summary = s.summary()
    lanes = s.road_map.indices_of(MapFeatureType.LANE)
    assert summary["lanes"] == len(lanes) == 6
    succ = s.road_map.link_indices(LinkType.SUCCESSOR)
    assert summary["lanes_with_successors"] == len(np.unique(succ[:, 0])) == 3
    assert summary["traffic_light_frames"] == 91
    assert summary["tracks_per_type"] == {"vehicle": 6, "pedestrian": 2, "cyclist": 0, "other": 0}


def test_link_indices_drop_links_to_features_outside_the_map():
    m = RoadMap.from_features(
        [dict(id=10, type=MapFeatureType.LANE, points=[[0, 0], [1, 0]]),
         dict(id=11, type=MapFeatureType.LANE, points=[[1, 0], [2, 0]])],
        [(10, 11, LinkType.SUCCESSOR), (11, 99, LinkType.SUCCESSOR)])
    assert m.link_indices(LinkType.SUCCESSOR).tolist() == [[0, 1]]
