"""GPUDrive / Nocturne JSON and Argoverse 2 readers, against the real scenes in ../shared/data.

Expected numbers are computed here from the raw JSON / parquet where that is cheap, or were read off
the files by inspection (noted where so)."""

from __future__ import annotations

import collections
import json
import math
import shutil
import sys

import numpy as np
import pytest

from smart_marl.errors import ScenarioReadError
from smart_marl.readers import detect_format, read_scenarios
from smart_marl.readers import av2 as av2_reader
from smart_marl.readers import gpudrive_json
from smart_marl.scenario import TYPICAL_BOX_M, AgentType, LaneType, LinkType, MapFeatureType, RoadEdgeType, SignalState

GPUDRIVE_FILE = "gpudrive_json/tfrecord-00000-of-01000_222.json"
NOCTURNE_FILE = "nocturne_json/intersection_scenario.json"
AV2_ID = "0a1e6f0a-1817-4a98-b02e-db8c9327d151"
AV2_FILE = f"av2/scenario_{AV2_ID}.parquet"
AV2_MAP = f"av2/log_map_archive_{AV2_ID}.json"

_TYPE_NAMES = {"vehicle": AgentType.VEHICLE, "pedestrian": AgentType.PEDESTRIAN, "cyclist": AgentType.CYCLIST}
_ROAD_TYPES = {"lane": MapFeatureType.LANE, "road_line": MapFeatureType.ROAD_LINE, "road_edge": MapFeatureType.ROAD_EDGE,
               "stop_sign": MapFeatureType.STOP_SIGN, "crosswalk": MapFeatureType.CROSSWALK,
               "speed_bump": MapFeatureType.SPEED_BUMP, "driveway": MapFeatureType.DRIVEWAY}


def _read_one(path):
    scenes = list(read_scenarios(path))
    assert len(scenes) == 1
    return scenes[0]


def _raw(path):
    with open(path) as f:
        return json.load(f)


def _counts_by_type(raw):
    objects = collections.Counter(_TYPE_NAMES.get(o["type"], AgentType.OTHER) for o in raw["objects"])
    roads = collections.Counter(_ROAD_TYPES[r["type"]] for r in raw["roads"])
    return objects, roads


def _assert_matches_raw_json(scene, raw):
    """Track and map counts, validity and source positions agree with the raw JSON."""
    objects, roads = _counts_by_type(raw)
    assert collections.Counter(AgentType(int(t)) for t in scene.tracks.types) == objects
    assert collections.Counter(MapFeatureType(int(t)) for t in scene.road_map.types) == roads
    assert scene.num_frames == len(raw["objects"][0]["valid"])
    valid = np.array([o["valid"] for o in raw["objects"]])
    np.testing.assert_array_equal(scene.tracks.valid, valid)
    xy = np.array([[(p["x"], p["y"]) for p in o["position"]] for o in raw["objects"]])
    back = scene.frame.to_source(scene.tracks.position)[..., :2]
    np.testing.assert_allclose(back[valid], xy[valid], atol=2e-3)
    pts = np.array([(p["x"], p["y"]) for r in raw["roads"] for p in r["geometry"]])
    np.testing.assert_allclose(scene.frame.to_source(scene.road_map.points)[:, :2], pts, atol=2e-3)
    lengths = [len(r["geometry"]) for r in raw["roads"]]
    np.testing.assert_array_equal(np.diff(scene.road_map.point_offsets), lengths)


# --------------------------------------------------------------------------------------- GPUDrive
def test_gpudrive_file_reads_ids_roles_and_map_from_metadata(shared_data):
    path = shared_data / GPUDRIVE_FILE
    raw = _raw(path)
    scene = _read_one(path)
    assert detect_format(path) == "gpudrive_json"
    assert scene.source == "gpudrive"
    assert scene.scenario_id == raw["scenario_id"] == "1c365f15b70ebdbf"
    assert scene.num_frames == 91 and scene.current_frame == 10
    summary = scene.summary()
    assert summary["tracks_per_type"] == {"vehicle": 23, "pedestrian": 2, "cyclist": 0, "other": 0}
    assert summary["lanes"] == 39 and summary["road_edges"] == 18 and summary["road_lines"] == 8
    assert summary["traffic_light_frames"] == 0 and raw["tl_states"] == {}
    _assert_matches_raw_json(scene, raw)
    # ids, roles and map subtypes come from the file
    np.testing.assert_array_equal(scene.tracks.ids, [o["id"] for o in raw["objects"]])
    np.testing.assert_array_equal(scene.road_map.ids, [r["id"] for r in raw["roads"]])
    meta = raw["metadata"]
    assert scene.sdc_index == meta["sdc_track_index"] == 24
    assert scene.predict_indices.tolist() == [t["track_index"] for t in meta["tracks_to_predict"]] == [7, 24]
    assert scene.objects_of_interest.tolist() == meta["objects_of_interest"] == [1847, 1415]
    # the local frame is the SDC's position at the current frame, and its box is the file's
    sdc_pos = raw["objects"][24]["position"][10]
    assert (scene.frame.x, scene.frame.y, scene.frame.z) == (sdc_pos["x"], sdc_pos["y"], sdc_pos["z"])
    np.testing.assert_allclose(scene.tracks.size[24, 10], [raw["objects"][24][k] for k in ("length", "width", "height")],
                               rtol=1e-6)
    expected_subtypes = [r["map_element_id"] - {"lane": 0, "road_line": 5, "road_edge": 14}[r["type"]]
                         if r["type"] in ("lane", "road_line", "road_edge") else 0 for r in raw["roads"]]
    np.testing.assert_array_equal(scene.road_map.subtypes, expected_subtypes)
    assert len(scene.road_map.links) == 0  # the JSON has no lane topology
    assert scene.metadata["heading_unit_in_source"] == "radians"
    np.testing.assert_allclose(scene.tracks.heading[24, 10], raw["objects"][24]["heading"][10], atol=1e-6)


def test_nocturne_file_reads_with_degrees_no_ids_and_default_heights(shared_data):
    path = shared_data / NOCTURNE_FILE
    raw = _raw(path)
    scene = _read_one(path)
    assert scene.source == "nocturne"
    assert raw["name"] == "tfrecord-00222-of-01000_260.json"
    assert scene.scenario_id == "tfrecord-00222-of-01000_260"
    assert scene.num_frames == 91 and scene.current_frame == 10
    summary = scene.summary()
    assert summary["tracks_per_type"] == {"vehicle": 90, "pedestrian": 33, "cyclist": 1, "other": 0}
    assert summary["lanes"] == 74 and summary["crosswalks"] == 6 and summary["road_edges"] == 24
    assert summary["traffic_light_frames"] == 0
    _assert_matches_raw_json(scene, raw)
    assert scene.sdc_index == -1 and len(scene.predict_indices) == 0
    np.testing.assert_array_equal(scene.tracks.ids, np.arange(124))
    np.testing.assert_array_equal(scene.road_map.ids, np.arange(124))
    assert not scene.road_map.subtypes.any()  # no map_element_id: UNDEFINED / UNKNOWN
    assert float(np.abs(scene.tracks.position[..., 2]).max()) == 0.0  # 2-D file
    assert scene.metadata["heading_unit_in_source"] == "degrees"
    o = raw["objects"][0]
    f = next(i for i, v in enumerate(o["valid"]) if v)
    expected = math.remainder(math.radians(o["heading"][f]), 2 * math.pi)
    assert abs(math.remainder(float(scene.tracks.heading[0, f]) - expected, 2 * math.pi)) < 1e-5
    heights = {AgentType(int(t)): float(h) for t, h in zip(scene.tracks.types, scene.tracks.size[:, 0, 2])}
    assert heights == {t: pytest.approx(TYPICAL_BOX_M[t][2]) for t in heights}


def test_every_json_scene_reads_and_headings_follow_the_direction_of_motion(shared_data):
    """Headings (radians or degrees in the source) point where moving agents go, in every file."""
    seen = []
    for folder in ("gpudrive_json", "nocturne_json"):
        for scene in read_scenarios(shared_data / folder):
            seen.append(scene.scenario_id)
            tr = scene.tracks
            speed = np.linalg.norm(tr.velocity, axis=-1)
            moving = tr.valid & (speed > 3.0)
            course = np.arctan2(tr.velocity[..., 1], tr.velocity[..., 0])
            err = np.abs((tr.heading - course + np.pi) % (2 * np.pi) - np.pi)[moving]
            assert moving.sum() > 50 and float(np.median(err)) < 0.05, scene.scenario_id
            assert float(np.abs(tr.heading).max()) <= math.pi + 1e-6
    assert len(seen) == 14 and len(set(seen)) == 14


def test_json_flavour_is_decided_from_structure(shared_data):
    sources = {p.name: _read_one(p).source for p in sorted((shared_data / "gpudrive_json").glob("*.json"))}
    with_gpudrive_fields = {p.name for p in (shared_data / "gpudrive_json").glob("*.json")
                            if {"scenario_id", "metadata"} & set(_raw(p))}
    assert {n for n, s in sources.items() if s == "gpudrive"} == with_gpudrive_fields
    assert len(with_gpudrive_fields) == 6  # by inspection: the other 5 are in the original Nocturne layout
    assert {_read_one(p).source for p in (shared_data / "nocturne_json").glob("*.json")} == {"nocturne"}


def test_json_traffic_light_states_map_per_lane_and_frame(shared_data, tmp_path):
    raw = _raw(shared_data / GPUDRIVE_FILE)
    lane = next(r for r in raw["roads"] if r["type"] == "lane")
    raw["tl_states"] = {str(lane["id"]): {"state": ["go", "caution", "stop"], "x": [4400.0] * 3, "y": [700.0] * 3,
                                          "z": [-123.0] * 3, "time_index": [0, 1, 5]},
                        "99999": {"state": ["arrow_stop"], "x": [4401.0], "y": [701.0], "z": [-123.0], "time_index": [90]}}
    path = tmp_path / "tl.json"
    path.write_text(json.dumps(raw))
    tl = _read_one(path).traffic_lights
    assert tl.lane_ids.tolist() == [lane["id"], 99999]
    assert tl.states[[0, 1, 5], 0].tolist() == [SignalState.GO, SignalState.CAUTION, SignalState.STOP]
    assert tl.present[:, 0].sum() == 3 and tl.present[:, 1].sum() == 1 and tl.states[90, 1] == SignalState.ARROW_STOP
    assert tl.frames_with_signals() == 4
    scene = _read_one(path)
    np.testing.assert_allclose(scene.frame.to_source(tl.stop_points)[0], [4400.0, 700.0, -123.0], atol=1e-3)


# ------------------------------------------------------------------------------------ bad JSON
def _write(tmp_path, raw, name="bad.json"):
    path = tmp_path / name
    path.write_text(json.dumps(raw))
    return path


def test_json_object_missing_a_field_names_file_record_and_field(shared_data, tmp_path):
    raw = _raw(shared_data / NOCTURNE_FILE)
    del raw["objects"][3]["position"]
    path = _write(tmp_path, raw)
    with pytest.raises(ScenarioReadError) as info:
        _read_one(path)
    assert info.value.path == str(path) and info.value.record == "objects[3]" and "'position'" in info.value.problem


def test_json_point_missing_a_coordinate_names_the_point(shared_data, tmp_path):
    raw = _raw(shared_data / GPUDRIVE_FILE)
    del raw["roads"][5]["geometry"][2]["y"]
    with pytest.raises(ScenarioReadError) as info:
        _read_one(_write(tmp_path, raw))
    assert info.value.record == "roads[5].geometry[2]" and "'y'" in info.value.problem


def test_invalid_json_reports_line_and_column(shared_data, tmp_path):
    text = (shared_data / NOCTURNE_FILE).read_text()
    path = tmp_path / "broken.json"
    path.write_text(text[:5000] + "\n  ]]oops" + text[5000:])
    with pytest.raises(ScenarioReadError) as info:
        _read_one(path)
    assert info.value.path == str(path) and "line 2 column" in info.value.problem


def test_json_nan_on_a_valid_frame_is_an_error_naming_the_object(shared_data, tmp_path):
    raw = _raw(shared_data / NOCTURNE_FILE)
    o = raw["objects"][7]
    f = next(i for i, v in enumerate(o["valid"]) if v)
    o["position"][f]["x"] = float("nan")  # json.dumps writes NaN, which json.load accepts
    with pytest.raises(ScenarioReadError) as info:
        _read_one(_write(tmp_path, raw))
    assert info.value.record == "objects[7]" and f"valid frame {f}" in info.value.problem
    # NaN on an invalid frame is fine: values there are arbitrary
    raw = _raw(shared_data / NOCTURNE_FILE)
    o = raw["objects"][7]
    f = next(i for i, v in enumerate(o["valid"]) if not v)
    o["position"][f]["x"] = float("nan")
    assert _read_one(_write(tmp_path, raw, "ok.json")).num_tracks == 124


def test_json_empty_boxes_get_their_types_default_and_are_listed(shared_data, tmp_path):
    raw = _raw(shared_data / NOCTURNE_FILE)
    kinds = {o["type"]: i for i, o in enumerate(raw["objects"]) if any(o["valid"])}  # one object of each type
    for i in kinds.values():
        raw["objects"][i]["length"], raw["objects"][i]["width"] = 0.0, 0.0
    raw["objects"][kinds["vehicle"]]["width"] = 1.9  # one side empty is enough
    scene = _read_one(_write(tmp_path, raw))
    for name, i in kinds.items():
        t = AgentType[name.upper()]
        np.testing.assert_allclose(scene.tracks.size[i, :, :2], np.broadcast_to(TYPICAL_BOX_M[t][:2], (scene.num_frames, 2)))
    assert scene.metadata["default_box_ids"] == sorted(kinds.values())  # ids are the indices in this file
    # the shared files: every object with a valid frame has a box
    for path in sorted((shared_data / "nocturne_json").glob("*.json")) + sorted((shared_data / "gpudrive_json").glob("*.json")):
        sc = _read_one(path)
        assert (sc.tracks.size[sc.tracks.valid][:, :2] > 0).all(), path.name


def test_json_unknown_road_type_and_bad_sdc_index_are_errors(shared_data, tmp_path):
    raw = _raw(shared_data / GPUDRIVE_FILE)
    raw["roads"][2]["type"] = "tram_track"
    with pytest.raises(ScenarioReadError, match="tram_track") as info:
        _read_one(_write(tmp_path, raw))
    assert info.value.record == "roads[2]"
    raw = _raw(shared_data / GPUDRIVE_FILE)
    raw["metadata"]["sdc_track_index"] = 25
    with pytest.raises(ScenarioReadError, match="sdc_track_index 25"):
        _read_one(_write(tmp_path, raw, "sdc.json"))


def test_json_scenes_agree_with_scenarionet_copies_of_the_same_scene(shared_data):
    """Some GPUDrive scenes are WOMD training scenes; where ScenarioNet holds the same scene, the
    tracks must agree."""
    try:
        from smart_marl.readers import scenarionet  # noqa: F401
    except ImportError:
        pytest.skip("the ScenarioNet reader is not in the repository yet")
    json_ids = {_raw(p).get("scenario_id") for p in (shared_data / "gpudrive_json").glob("*.json")}
    pairs = [p for p in (shared_data / "scenarionet" / "waymo").glob("*.pkl") if p.stem.rsplit("_", 1)[-1] in json_ids]
    if not pairs:
        pytest.skip("no scene of gpudrive_json/ is also in scenarionet/waymo/ (ids and positions compared by hand)")
    for pkl in pairs:
        net = _read_one(pkl)
        js = next(s for s in read_scenarios(shared_data / "gpudrive_json") if s.scenario_id == net.scenario_id)
        common, ij, inet = np.intersect1d(js.tracks.ids, net.tracks.ids, return_indices=True)
        assert len(common) == js.num_tracks
        a = js.frame.to_source(js.tracks.position[ij])
        b = net.frame.to_source(net.tracks.position[inet])
        valid = js.tracks.valid[ij]
        np.testing.assert_array_equal(valid, net.tracks.valid[inet])
        np.testing.assert_allclose(a[valid][:, :2], b[valid][:, :2], atol=1e-2)


# -------------------------------------------------------------------------------------------- AV2
@pytest.fixture(scope="module")
def av2_scene(shared_data):
    pytest.importorskip("pyarrow")
    return _read_one(shared_data / AV2_FILE)


def test_av2_tracks_match_the_parquet(shared_data, av2_scene):
    pq = pytest.importorskip("pyarrow.parquet")
    table = pq.read_table(shared_data / AV2_FILE).to_pydict()
    scene = av2_scene
    assert detect_format(shared_data / AV2_FILE) == "av2"
    assert scene.source == "av2" and scene.scenario_id == AV2_ID
    assert scene.num_frames == 110 and scene.current_frame == 49
    np.testing.assert_allclose(np.diff(scene.timestamps_s), 0.1)
    assert scene.timestamps_s[-1] == pytest.approx(10.9)
    track_type = dict(zip(table["track_id"], table["object_type"]))
    assert len(track_type) == scene.num_tracks == 58
    expected = collections.Counter(av2_reader.AGENT_TYPES.get(t, AgentType.OTHER) for t in track_type.values())
    assert collections.Counter(AgentType(int(t)) for t in scene.tracks.types) == expected
    assert scene.summary()["tracks_per_type"] == {"vehicle": 32, "pedestrian": 12, "cyclist": 0, "other": 14}
    assert scene.tracks.valid.sum() == len(table["track_id"]) == 2434
    id_map = scene.metadata["track_id_map"]
    assert set(id_map) == set(track_type) and id_map["138951"] == 138951
    # one row checked end to end
    row = 1000
    i = int(np.flatnonzero(scene.tracks.ids == id_map[table["track_id"][row]])[0])
    t = table["timestep"][row]
    src = scene.frame.to_source(scene.tracks.position[i, t])
    assert src[:2] == pytest.approx([table["position_x"][row], table["position_y"][row]], abs=2e-3)
    assert scene.tracks.velocity[i, t].tolist() == pytest.approx([table["velocity_x"][row], table["velocity_y"][row]], abs=1e-5)
    # roles: AV is the SDC, the focal track then the scored ones are to be predicted
    assert scene.sdc_index == int(np.flatnonzero(scene.tracks.ids == id_map["AV"])[0])
    assert scene.tracks.valid[scene.sdc_index].all()
    focal = table["focal_track_id"][0]
    scored = sorted({tid for tid, c in zip(table["track_id"], table["object_category"]) if c == 2})
    assert scene.tracks.ids[scene.predict_indices].tolist() == [id_map[focal]] + [id_map[s] for s in scored]
    assert scene.objects_of_interest.tolist() == [id_map[focal]] == [138951]
    assert scene.metadata["city"] == "austin"
    assert scene.traffic_lights.lane_ids.size == 0 and scene.traffic_lights.num_frames == 110
    vehicle_box = scene.tracks.size[scene.sdc_index, 49]
    assert vehicle_box.tolist() == pytest.approx(TYPICAL_BOX_M[AgentType.VEHICLE])


def test_av2_map_matches_the_archive(shared_data, av2_scene):
    raw = _raw(shared_data / AV2_MAP)
    map_path = shared_data / AV2_MAP
    assert not gpudrive_json.sniff(str(map_path), map_path.read_bytes()[:4096])  # a companion, not a scene
    rm = av2_scene.road_map
    lanes = raw["lane_segments"]
    summary = av2_scene.summary()
    assert summary["lanes"] == len(lanes) == 71
    assert summary["lanes_with_successors"] == sum(bool(l["successors"]) for l in lanes.values()) == 70
    assert summary["lanes_with_predecessors"] == sum(bool(l["predecessors"]) for l in lanes.values()) == 70
    left = rm.links[rm.link_types == LinkType.LEFT_NEIGHBOR]
    assert len(left) == sum(l["left_neighbor_id"] is not None for l in lanes.values()) == 35
    assert summary["crosswalks"] == len(raw["pedestrian_crossings"]) == 6
    assert summary["road_edges"] == len(raw["drivable_areas"]) == 2
    assert summary["traffic_light_frames"] == 0
    lane_idx = rm.indices_of(MapFeatureType.LANE)
    by_id = dict(zip(rm.ids[lane_idx].tolist(), lane_idx.tolist()))
    bikes = {int(k) for k, l in lanes.items() if l["lane_type"] == "BIKE"}
    assert {i for i in by_id if rm.subtypes[by_id[i]] == LaneType.BIKE_LANE} == bikes and len(bikes) == 37
    assert {i for i in by_id if rm.interpolating[by_id[i]]} == {int(k) for k, l in lanes.items() if l["is_intersection"]}
    # road edges are closed outlines; crosswalks are 4-corner polygons
    for i in rm.indices_of(MapFeatureType.ROAD_EDGE):
        pts = rm.feature_points(i)
        assert rm.subtypes[i] == RoadEdgeType.BOUNDARY and np.array_equal(pts[0], pts[-1])
    assert all(len(rm.feature_points(i)) == 4 for i in rm.indices_of(MapFeatureType.CROSSWALK))
    # painted boundaries: one road line per distinct geometry, typed
    painted = sum((l["left_lane_mark_type"] != "NONE") + (l["right_lane_mark_type"] != "NONE") for l in lanes.values())
    assert painted == 50 and summary["road_lines"] == 37  # 13 boundaries shared by two lanes (by inspection)
    line_types = collections.Counter(int(t) for t in rm.subtypes[rm.indices_of(MapFeatureType.ROAD_LINE)])
    assert set(line_types) <= {int(v) for v in av2_reader.ROAD_LINE_TYPES.values()}


def test_av2_centerlines_follow_the_archive_centerlines(shared_data, av2_scene):
    """The centerlines built from the boundaries pass within a few cm of the archive's own."""
    raw = _raw(shared_data / AV2_MAP)
    rm = av2_scene.road_map
    index = {int(i): k for k, i in enumerate(rm.ids)}
    worst = 0.0
    for key, lane in raw["lane_segments"].items():
        ours = av2_scene.frame.to_source(rm.feature_points(index[int(key)]))[:, :2]
        given = np.array([(p["x"], p["y"]) for p in lane["centerline"]])
        a, b = ours[:-1], ours[1:]
        ab = b - a
        t = np.clip(((given[:, None] - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
        dist = np.linalg.norm(given[:, None] - (a + t[..., None] * ab), axis=-1).min(axis=1)
        worst = max(worst, float(dist.max()))
        spacing = np.linalg.norm(np.diff(ours, axis=0), axis=1)
        assert spacing.max() <= av2_reader.CENTERLINE_SPACING_M + 1e-3
    assert worst < 0.1


def test_av2_missing_map_names_the_expected_map_path(shared_data, tmp_path):
    pytest.importorskip("pyarrow")
    path = tmp_path / f"scenario_{AV2_ID}.parquet"
    shutil.copy(shared_data / AV2_FILE, path)
    with pytest.raises(ScenarioReadError) as info:
        _read_one(path)
    assert info.value.path == str(path)
    assert str(tmp_path / f"log_map_archive_{AV2_ID}.json") in info.value.problem


def test_av2_bad_parquet_is_an_error_naming_column_or_row(shared_data, tmp_path):
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    table = pq.read_table(shared_data / AV2_FILE)
    shutil.copy(shared_data / AV2_MAP, tmp_path / f"log_map_archive_{AV2_ID}.json")
    path = tmp_path / f"scenario_{AV2_ID}.parquet"
    pq.write_table(table.drop_columns(["heading"]), path)
    with pytest.raises(ScenarioReadError, match="missing column.*heading"):
        _read_one(path)
    x = table.column("position_x").to_numpy().copy()
    x[17] = np.nan
    pq.write_table(table.set_column(table.schema.get_field_index("position_x"), "position_x", pa.array(x)), path)
    with pytest.raises(ScenarioReadError) as info:
        _read_one(path)
    assert info.value.record == "row 17" and "position_x" in info.value.problem


def test_av2_without_pyarrow_asks_for_the_extra(shared_data, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    with pytest.raises(ImportError, match=r"smart-marl\[av2\]"):
        next(av2_reader.read(shared_data / AV2_FILE))


def test_every_shared_json_and_av2_scene_reads_through_read_scenarios(shared_data):
    pytest.importorskip("pyarrow")
    counts = {folder: sum(1 for _ in read_scenarios(shared_data / folder))
              for folder in ("gpudrive_json", "nocturne_json", "av2")}
    assert counts == {"gpudrive_json": 11, "nocturne_json": 3, "av2": 1}


def test_json_and_av2_scenes_survive_the_flat_array_round_trip(shared_data):
    """What the scene cache stores (arrays plus JSON-able scalars) rebuilds the same scenes."""
    pytest.importorskip("pyarrow")
    from smart_marl.scenario import Scenario

    for path in (shared_data / GPUDRIVE_FILE, shared_data / NOCTURNE_FILE, shared_data / AV2_FILE):
        scene = _read_one(path)
        arrays, meta = scene.to_arrays()
        again = Scenario.from_arrays(arrays, json.loads(json.dumps(meta)))
        assert again.equals(scene, ignore=()), path.name
        assert all(a.flags.c_contiguous for a in arrays.values()), path.name
