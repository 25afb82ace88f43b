"""Road kinds across domains: SUMO maps carry WOMD's painted road lines, and a SUMO-trained model
sees real maps only through the road kinds SUMO produces (``SmartConfig.road_types = "sumo"``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from smart_marl.model.batch import RoadSettings, road_type_ids, scene_road
from smart_marl.model.smart import ModelConfigError, get_config
from smart_marl.scenario import LaneType, MapFeatureType, RoadEdgeType, RoadLineType
from smart_marl.tokens.road import RoadVocabulary

F = MapFeatureType


def test_sumo_road_types_map_unseen_subtypes_to_trained_ones_and_leave_out_bumps_and_driveways():
    ftype = np.array([F.LANE, F.LANE, F.LANE, F.ROAD_LINE, F.ROAD_LINE, F.ROAD_LINE, F.ROAD_EDGE, F.ROAD_EDGE, F.CROSSWALK,
                      F.SPEED_BUMP, F.DRIVEWAY, F.STOP_SIGN])
    sub = np.array([LaneType.FREEWAY, LaneType.SURFACE_STREET, LaneType.BIKE_LANE, RoadLineType.UNKNOWN,
                    RoadLineType.PASSING_DOUBLE_YELLOW, RoadLineType.SOLID_SINGLE_YELLOW, RoadEdgeType.MEDIAN, RoadEdgeType.BOUNDARY,
                    0, 0, 0, 0])
    ids, keep = road_type_ids(ftype, sub, "all")
    assert keep.all() and list(ids) == list(ftype * 9 + sub)
    ids, keep = road_type_ids(ftype, sub, "sumo")
    assert list(keep) == [True] * 9 + [False, False, True]
    assert list(ids[keep]) == [2, 2, 3, 9 + 1, 9 + 7, 9 + 6, 18 + 1, 18 + 1, 36, 27]
    with pytest.raises(ValueError, match="road_types"):
        road_type_ids(ftype, sub, "nosuch")
    with pytest.raises(ModelConfigError, match="road_types"):
        get_config("smart-1m", road_types="nosuch")


def test_sumo_road_view_of_a_real_scene_drops_its_driveways_and_keeps_successor_pairs_consistent(shared_data):
    from smart_marl.readers import read_scenarios

    scene = next(read_scenarios(shared_data / "womd_tfrecord" / "motion_data_one_scenario.tfrecord"))
    rv = RoadVocabulary(points=np.zeros((1, 11, 2), np.float32), tolerance_m=0.0, requested_size=1)
    full, sumo = scene_road(scene, rv, RoadSettings("all")), scene_road(scene, rv, RoadSettings("sumo"))
    dropped = np.isin(full.type_id // 9, [F.SPEED_BUMP, F.DRIVEWAY])
    assert dropped.any() and len(sumo.token) == len(full.token) - dropped.sum()
    np.testing.assert_array_equal(sumo.pose, full.pose[~dropped])
    assert not np.isin(sumo.type_id, [1, 18, 20]).any()  # no freeway lane, no unknown or median edge
    assert len(sumo.pairs) > 0 and sumo.pairs.max() < len(sumo.token)


def test_sumo_maps_have_painted_lines_between_lanes_and_a_yellow_centre_line(tmp_path):
    pytest.importorskip("sumolib")
    from smart_marl.sources.sumo_net import build_network, network_map, random_network_spec

    spec = dataclasses.replace(random_network_spec(np.random.default_rng(1)), kind="grid", lanes=2, random_lanenumber=False,
                               bikelanes=False, sidewalks=False, crossings=False, rotation_rad=0.3,
                               params={"x-number": 2, "y-number": 2, "x-length": 150, "y-length": 150, "attach-length": 0})
    nmap = network_map(build_network(spec, tmp_path / "net.net.xml"), spec.rotation_rad)
    kinds = nmap.road_line_subtypes
    assert (kinds == RoadLineType.BROKEN_SINGLE_WHITE).sum() > 0 and (kinds == RoadLineType.SOLID_DOUBLE_YELLOW).sum() > 0
    # a broken white line runs midway between two lanes of one road: half a lane width from each centre
    lane_xy = [nmap.lane_points[a:b, :2] for a, b in zip(nmap.lane_offsets[:-1], nmap.lane_offsets[1:])]
    k = int(np.flatnonzero(kinds == RoadLineType.BROKEN_SINGLE_WHITE)[0])
    line = nmap.road_line_points[nmap.road_line_offsets[k]:nmap.road_line_offsets[k + 1], :2]
    mid = line[len(line) // 2]
    d = sorted(np.min(np.linalg.norm(xy - mid, axis=1)) for xy in lane_xy)
    assert d[0] == pytest.approx(nmap.lane_widths_m[0] / 2, abs=0.15) and d[1] == pytest.approx(d[0], abs=0.15)
    # cropped into a scene's map as ROAD_LINE features
    road_map, _ = nmap.crop(mid[None], 80.0, np.array([*mid, 0.0]))
    assert len(road_map.indices_of(MapFeatureType.ROAD_LINE)) > 0
