"""Stop signs among the model's inputs (``SmartConfig.stop_signs``): the lanes that leave a stop sign's stop
line carry the light code FLASHING_STOP, whichever convention the source links its signs by."""

from __future__ import annotations

import numpy as np
import pytest

from smart_marl.model.batch import NO_LIGHT, STOP_SIGN_LIGHT, RoadSettings, light_codes, scene_road, stop_sign_lanes
from smart_marl.model.smart import ModelConfigError, get_config
from smart_marl.scenario import (LaneType, LinkType, MapFeatureType, RoadMap, Scenario, SceneFrame, SignalState,
                                 TrafficLights, Tracks)
from smart_marl.tokens.road import RoadVocabulary

T = 91
SUMO, SUMO_STOPS = RoadSettings("sumo"), RoadSettings("sumo", stop_signs=True)


def _lane(fid: int, start, end) -> dict:
    pts = np.linspace(start, end, 11)
    return dict(id=fid, type=MapFeatureType.LANE, subtype=LaneType.SURFACE_STREET, speed_limit_mph=25.0,
                points=np.concatenate([pts, np.zeros((11, 1))], 1))


# an approach (1) ending at the stop line x = 0, the lane across the junction (2) starting there, a lane
# leaving the junction the other way (3) that starts 4.5 m from the sign but with the sign on its left, and a
# lane far away (4); the sign stands at the kerb, right of the approach, 1 m before the stop line
LANES = [_lane(1, (-40, 0), (0, 0)), _lane(2, (0, 0), (20, 0)), _lane(3, (-1, 2), (-40, 2)), _lane(4, (60, 40), (90, 40))]
SIGN = dict(id=9, type=MapFeatureType.STOP_SIGN, points=[[-1.0, -2.5, 0.0]])


def _scene(links=(), lights_on: tuple[int, ...] = ()) -> Scenario:
    n = len(lights_on)
    lights = TrafficLights(lane_ids=np.array(lights_on, np.int64), states=np.full((T, n), int(SignalState.GO), np.int8),
                           present=np.ones((T, n), bool), stop_points=np.zeros((n, 3)))
    tracks = Tracks(ids=np.array([1]), types=np.zeros(1, np.int8), position=np.zeros((1, T, 3)), heading=np.zeros((1, T)),
                    velocity=np.zeros((1, T, 2)), size=np.tile([4.6, 1.9, 1.6], (1, T, 1)), valid=np.ones((1, T), bool))
    return Scenario(scenario_id="stop", source="synthetic", timestamps_s=np.arange(T) * 0.1, current_frame=10, tracks=tracks,
                    road_map=RoadMap.from_features(LANES + [SIGN], links), traffic_lights=lights, sdc_index=0,
                    predict_indices=[], frame=SceneFrame(0.0, 0.0, 0.0, 0.0))


@pytest.mark.parametrize("links", [
    [(9, 2, LinkType.STOP_SIGN_LANE)],  # WOMD: the sign names the lane that starts at it
    [(9, 1, LinkType.STOP_SIGN_LANE), (1, 2, LinkType.SUCCESSOR)],  # the SUMO source: the approach that ends at it
    [],  # no lane topology (GPUDrive JSON): the lanes that start near it with the sign on their right
], ids=["womd", "sumo", "unlinked"])
def test_the_lane_leaving_the_stop_line_is_the_one_a_stop_sign_controls(links):
    scene = _scene(links)
    assert list(stop_sign_lanes(scene.road_map)) == [1]  # feature index of lane id 2


def test_stop_sign_lanes_carry_flashing_stop_only_when_asked_and_a_signal_wins():
    rv = RoadVocabulary(points=np.zeros((1, 11, 2), np.float32), tolerance_m=0.0, requested_size=1)
    scene = _scene([(9, 2, LinkType.STOP_SIGN_LANE)])
    plain, stops = scene_road(scene, rv, SUMO), scene_road(scene, rv, SUMO_STOPS)
    index = stops.light_index
    on = index == STOP_SIGN_LIGHT
    assert on.sum() == 4  # lane 2 is 20 m long: four pieces of 5 m
    assert (plain.light == NO_LIGHT).all()
    assert (stops.light[on] == SignalState.FLASHING_STOP).all() and (stops.light[~on] == NO_LIGHT).all()
    # the logged-lights path (rollouts with lights="log") gives the same codes at any frame
    np.testing.assert_array_equal(light_codes(scene.traffic_lights, index, 50), stops.light)
    signalled = _scene([(9, 2, LinkType.STOP_SIGN_LANE)], lights_on=(2,))
    assert (scene_road(signalled, rv, SUMO_STOPS).light[on] == SignalState.GO).all()


def test_stop_signs_is_a_flag_of_the_model_config():
    assert get_config("smart-1m").stop_signs is False and get_config("smart-1m", stop_signs=True).stop_signs is True
    with pytest.raises(ModelConfigError, match="stop_signs"):
        get_config("smart-1m", stop_signs="yes")


def test_real_womd_signs_reach_lanes_and_only_their_pieces_change(shared_data):
    from smart_marl.readers import read_scenarios

    rv = RoadVocabulary(points=np.zeros((1, 11, 2), np.float32), tolerance_m=0.0, requested_size=1)
    files = [shared_data / "womd_tfrecord" / "motion_data_one_scenario.tfrecord", shared_data / "smart_pkl" / "1d71990efc3c6c0e.pkl",
             shared_data / "gpudrive_json" / "tfrecord-00001-of-01000_307.json"]
    for scene in read_scenarios(files):  # 8 linked signs, none, 1 unlinked
        plain, stops = scene_road(scene, rv, SUMO), scene_road(scene, rv, SUMO_STOPS)
        changed = plain.light != stops.light
        signs = len(scene.road_map.indices_of(MapFeatureType.STOP_SIGN))
        assert changed.any() == (signs > 0)
        assert (stops.light[changed] == SignalState.FLASHING_STOP).all() and (plain.light[changed] == NO_LIGHT).all()
