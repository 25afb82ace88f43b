"""Pickle readers: the restricted unpickler, ScenarioNet / MetaDrive scenes and SMART preprocessed
pickles. Facts are pinned from the real files in ../shared/data (counted independently from the raw
dicts where the test can do it in a few lines)."""

from __future__ import annotations

import io
import os
import pickle
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import smart_marl
from smart_marl import AgentType, LaneType, LinkType, MapFeatureType, ScenarioReadError, SignalState
from smart_marl.readers import scenarionet, smart_pkl
from smart_marl.readers.safe_pickle import SCENARIONET_GLOBALS, load_restricted, smart_pickle_globals

WOMD_SN = "scenarionet/waymo/sd_training.tfrecord-00000-of-01000_2a1e44d405a6833f.pkl"
WOMD_SN_V12 = "scenarionet/waymo/sd_waymo_v1.2_eb4b91b10ca94ff2.pkl"
NUSC_SN = "scenarionet/nuscenes/sd_nuscenes_v1.0-mini_scene-0061.pkl"
SMART = "smart_pkl/1d71990efc3c6c0e.pkl"


def _raw(path: Path) -> dict:
    return load_restricted(path, SCENARIONET_GLOBALS)


def _read_one(path) -> smart_marl.Scenario:
    scenes = list(smart_marl.read_scenarios(path))
    assert len(scenes) == 1
    return scenes[0]


def _head(path) -> bytes:
    with open(path, "rb") as f:
        return f.read(4096)


# ------------------------------------------------------------------------- restricted unpickler
class _Evil:
    """Unpickling this would run a shell command that creates ``marker``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_forbidden_global_is_refused_before_anything_runs(tmp_path):
    marker = tmp_path / "pwned"
    bad = tmp_path / "evil.pkl"
    # Shaped like a ScenarioNet scene, so the ScenarioNet reader claims it and must refuse it.
    bad.write_bytes(pickle.dumps({"id": "x", "version": "v1.2", "tracks": _Evil(marker), "metadata": {}}, protocol=4))
    assert smart_marl.detect_format(bad) == "scenarionet"
    with pytest.raises(ScenarioReadError) as err:
        list(smart_marl.read_scenarios(bad))
    system = f"{os.system.__module__}.system"  # posix.system on Linux
    assert err.value.path == str(bad)
    assert f"pickle tries to import {system}, which is not allowed" in str(err.value)
    assert not marker.exists()
    with pytest.raises(ScenarioReadError, match=system.replace(".", r"\.")):
        list(smart_pkl.read(bad))
    assert not marker.exists()


def test_restricted_loader_round_trips_numpy_containers_and_torch_tensors():
    import torch

    value = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "s": np.float64(2.5), "set": {1, 2},
             "dd": __import__("collections").defaultdict(int, {"k": 3})}
    back = load_restricted(io.BytesIO(pickle.dumps(value, protocol=4)), SCENARIONET_GLOBALS, path="mem.pkl")
    assert np.array_equal(back["a"], value["a"]) and back["a"].dtype == np.float32
    assert back["s"] == 2.5 and back["set"] == {1, 2} and back["dd"]["k"] == 3
    tensors = {"t": torch.arange(5, dtype=torch.int64), "m": torch.ones(2, 2, dtype=torch.bool)}
    back = load_restricted(io.BytesIO(pickle.dumps(tensors)), smart_pickle_globals(), path="mem.pkl")
    assert torch.equal(back["t"], tensors["t"]) and torch.equal(back["m"], tensors["m"])
    with pytest.raises(ScenarioReadError, match=r"mem\.pkl: pickle tries to import torch\._utils\._rebuild_tensor_v2"):
        load_restricted(io.BytesIO(pickle.dumps(tensors)), SCENARIONET_GLOBALS, path="mem.pkl")


def test_truncated_pickle_is_a_read_error_naming_the_file(tmp_path, shared_data):
    cut = tmp_path / "cut.pkl"
    cut.write_bytes((shared_data / WOMD_SN).read_bytes()[:5000])
    with pytest.raises(ScenarioReadError, match=r"cut\.pkl: not a valid pickle"):
        list(scenarionet.read(cut))


# ------------------------------------------------------------------------------ format sniffing
def test_each_pickle_reader_claims_only_its_own_files(shared_data):
    sn_files = sorted((shared_data / "scenarionet").rglob("*.pkl"))
    smart_files = sorted((shared_data / "smart_pkl").glob("*.pkl"))
    token_files = sorted((shared_data / "smart_tokens").glob("*.pkl"))
    assert len(sn_files) == 7 and len(smart_files) == 2
    for f in sn_files:
        assert scenarionet.sniff(str(f), _head(f)) and not smart_pkl.sniff(str(f), _head(f)), f
        assert smart_marl.detect_format(f) == "scenarionet"
    for f in smart_files:
        assert smart_pkl.sniff(str(f), _head(f)) and not scenarionet.sniff(str(f), _head(f)), f
        assert smart_marl.detect_format(f) == "smart_pkl"
    for f in token_files:  # vocabularies are pickles too, but not scenes
        assert not scenarionet.sniff(str(f), _head(f)) and not smart_pkl.sniff(str(f), _head(f)), f


@pytest.mark.parametrize("name", ["scenarionet", "smart_pkl"])
def test_every_shared_pickle_reads_through_read_scenarios(shared_data, name):
    files = sorted((shared_data / name).rglob("*.pkl"))
    scenes = list(smart_marl.read_scenarios(shared_data / name))
    assert len(scenes) == len(files)
    for path, scene in zip(files, scenes):
        assert scene.scenario_id in path.name or path.name.endswith(scene.scenario_id + ".pkl")
        assert scene.metadata["path"] == str(path)
        assert scene.tracks.valid[scene.sdc_index, scene.current_frame]


# --------------------------------------------------------------------------- ScenarioNet facts
def test_scenarionet_womd_scene_facts(shared_data):
    path = shared_data / WOMD_SN
    scene = _read_one(path)
    raw = _raw(path)
    lanes = [f for f in raw["map_features"].values() if f["type"].startswith("LANE")]
    s = scene.summary()
    assert (scene.scenario_id, scene.source, s["frames"], scene.current_frame) == ("2a1e44d405a6833f", "scenarionet/waymo", 91, 10)
    assert s["tracks_per_type"] == {"vehicle": 184, "pedestrian": 25, "cyclist": 2, "other": 0}
    assert s["sdc_id"] == 1629 and scene.sdc_index == 210
    assert s["tracks_to_predict"] == len(raw["metadata"]["tracks_to_predict"]) == 7
    assert sorted(scene.objects_of_interest.tolist()) == [333, 490]
    assert s["lanes"] == len(lanes) == 182
    assert s["lanes_with_successors"] == sum(bool(f["exit_lanes"]) for f in lanes) == 163
    assert s["lanes_with_predecessors"] == sum(bool(f["entry_lanes"]) for f in lanes) == 155
    rm = scene.road_map
    assert int((rm.link_types == LinkType.SUCCESSOR).sum()) == sum(len(f["exit_lanes"]) for f in lanes) == 200
    assert int((rm.link_types == LinkType.LEFT_NEIGHBOR).sum()) == 241
    assert int((rm.link_types == LinkType.STOP_SIGN_LANE).sum()) == 9
    assert (s["road_lines"], s["road_edges"], s["crosswalks"]) == (66, 51, 16)
    assert Counter(rm.subtypes[rm.types == MapFeatureType.ROAD_EDGE].tolist()) == {1: 33, 2: 18}  # boundary, median
    assert len(rm.points) == 24889
    tl = scene.traffic_lights
    assert sorted(tl.lane_ids.tolist()) == [226, 227, 272, 316, 317, 321, 354, 355]
    assert s["traffic_light_frames"] == 91 and bool(tl.present.all())
    assert int((tl.states == SignalState.STOP).sum()) == 564 and int((tl.states == SignalState.UNKNOWN).sum()) == 164
    # The local frame maps back onto the file's coordinates.
    key = "490"
    i = int(np.flatnonzero(scene.tracks.ids == 490)[0])
    state = raw["tracks"][key]["state"]
    v = state["valid"]
    np.testing.assert_allclose(scene.frame.to_source(scene.tracks.position[i])[v], state["position"][v], atol=2e-3)
    np.testing.assert_allclose(scene.tracks.heading[i][v], state["heading"][v], atol=1e-6)
    np.testing.assert_allclose(scene.timestamps_s, raw["metadata"]["ts"], atol=1e-6)


def test_scenarionet_format_1_2_scene_reads(shared_data):
    scene = _read_one(shared_data / WOMD_SN_V12)
    s = scene.summary()
    assert scene.metadata["version"] == "v1.2"
    assert (scene.scenario_id, s["frames"], scene.current_frame, s["tracks"]) == ("eb4b91b10ca94ff2", 199, 0, 45)
    assert s["sdc_id"] == 51 and sorted(scene.objects_of_interest.tolist()) == [11, 17]
    rm = scene.road_map
    lanes = rm.types == MapFeatureType.LANE
    assert Counter(rm.subtypes[lanes].tolist()) == {LaneType.SURFACE_STREET: 83, LaneType.FREEWAY: 24}
    tl = scene.traffic_lights
    assert len(tl.lane_ids) == 14 and int((~tl.present).sum()) == 1295  # None: not reported on that frame
    present = tl.present
    assert Counter(tl.states[present].tolist()) == {SignalState.GO: 780, SignalState.STOP: 414,
                                                    SignalState.UNKNOWN: 237, SignalState.ARROW_STOP: 60}


def test_scenarionet_nuscenes_scene_keeps_all_frames_and_original_ids(shared_data):
    scene = _read_one(shared_data / NUSC_SN)
    s = scene.summary()
    assert (scene.scenario_id, scene.source, s["frames"]) == ("scene-0061", "scenarionet/nuscenes", 191)
    assert scene.timestamps_s[-1] == pytest.approx(19.0)
    assert s["tracks_per_type"] == {"vehicle": 24, "pedestrian": 60, "cyclist": 6, "other": 136}  # cones, barriers
    id_map = scene.metadata["track_id_map"]
    assert id_map[str(scene.sdc_id)] == "ego" and len(id_map) == 226
    assert scene.tracks.valid[scene.sdc_index].sum() == 191
    assert (s["lanes"], s["road_lines"], s["lanes_with_successors"], s["traffic_light_lanes"]) == (460, 126, 0, 0)
    rm = scene.road_map
    assert int(np.isclose(rm.speed_limit_mph, 100 / 1.609344).sum()) == 247  # 100 km/h lanes
    assert len(scene.metadata["map_feature_id_map"]) == 586
    assert scene.frame.x == pytest.approx(408.20055834) and scene.frame.y == pytest.approx(1172.41952021)


# --------------------------------------------------------------------------- ScenarioNet errors
def _write(tmp_path: Path, data: dict, name="scene.pkl") -> Path:
    out = tmp_path / name
    out.write_bytes(pickle.dumps(data, protocol=4))
    return out


def test_scenarionet_missing_field_names_file_and_field(tmp_path, shared_data):
    raw = _raw(shared_data / WOMD_SN)
    no_tracks = dict(raw)
    del no_tracks["tracks"]
    bad = _write(tmp_path, no_tracks, "no_tracks.pkl")
    with pytest.raises(ScenarioReadError, match=r"no_tracks\.pkl, record scene: missing field 'tracks'"):
        list(scenarionet.read(bad))
    raw = _raw(shared_data / WOMD_SN)
    del raw["tracks"]["490"]["state"]["position"]
    bad = _write(tmp_path, raw, "no_position.pkl")
    with pytest.raises(ScenarioReadError) as err:
        list(scenarionet.read(bad))
    assert err.value.path == str(bad) and err.value.record == "tracks/490/state"
    assert err.value.problem == "missing field 'position'"


def test_scenarionet_nan_on_a_valid_frame_names_file_track_and_problem(tmp_path, shared_data):
    raw = _raw(shared_data / WOMD_SN)
    state = raw["tracks"]["490"]["state"]
    frame = int(np.flatnonzero(state["valid"])[3])
    state["position"][frame, 0] = np.nan
    bad = _write(tmp_path, raw)
    with pytest.raises(ScenarioReadError) as err:
        list(scenarionet.read(bad))
    assert err.value.path == str(bad) and err.value.record == "tracks/490"
    assert "track 490: position is NaN or infinite on 1 valid frame(s)" in err.value.problem
    assert f"first on frame {frame}" in err.value.problem


def test_scenarionet_unknown_light_state_is_an_error_not_a_drop(tmp_path, shared_data):
    raw = _raw(shared_data / WOMD_SN)
    raw["dynamic_map_states"]["226"]["state"]["object_state"][5] = "LANE_STATE_PURPLE"
    with pytest.raises(ScenarioReadError, match="unknown traffic light state 'LANE_STATE_PURPLE'"):
        list(scenarionet.read(_write(tmp_path, raw)))


# ------------------------------------------------------------------------------------ SMART facts
def test_smart_pickle_scene_facts(shared_data):
    import torch  # noqa: F401  (the file holds torch tensors)

    path = shared_data / SMART
    scene = _read_one(path)
    raw = load_restricted(path, smart_pickle_globals())
    s = scene.summary()
    assert (scene.scenario_id, scene.source, s["frames"], scene.current_frame) == ("1d71990efc3c6c0e", "smart_pkl", 91, 10)
    assert s["tracks_per_type"] == {"vehicle": 15, "pedestrian": 3, "cyclist": 0, "other": 0}
    assert s["sdc_id"] == 2703 and scene.sdc_index == 17 and s["tracks_to_predict"] == 2
    # Map counts from the point types of each polygon (16 centerline, 12 edge, 15 crosswalk).
    polygon_of_point = raw[("map_point", "to", "map_polygon")]["edge_index"][1].numpy()
    point_type = raw["map_point"]["type"].numpy()
    first_type = point_type[np.searchsorted(polygon_of_point, np.arange(raw["map_polygon"]["num_nodes"]))]
    assert (s["lanes"], s["road_edges"], s["crosswalks"], s["road_lines"]) == (76, 46, 13, 26)
    assert [int((first_type == t).sum()) for t in (16, 12, 15)] == [76, 46, 13]
    edge_type = raw[("map_polygon", "to", "map_polygon")]["type"].numpy()
    edge_index = raw[("map_polygon", "to", "map_polygon")]["edge_index"].numpy()
    assert s["lanes_with_successors"] == len(np.unique(edge_index[1][edge_type == 2])) == 67
    # Every polygon gets its dropped end point back: one more point per polygon than stored.
    assert len(scene.road_map.points) == raw["map_point"]["num_nodes"] + 161 == 9799
    crosswalks = scene.road_map.indices_of(MapFeatureType.CROSSWALK)
    assert set(np.diff(scene.road_map.point_offsets)[crosswalks].tolist()) == {4}
    # Traffic lights: light_type 0 (STOP) on 3 lanes, held over all frames.
    tl = scene.traffic_lights
    assert len(tl.lane_ids) == 3 and bool((tl.states == SignalState.STOP).all()) and bool(tl.present.all())
    assert scene.metadata["traffic_light_state_held_constant"] is True
    # Validity: SMART's vector mask on the future frames, the recorded frames everywhere else.
    vector_valid = raw["agent"]["valid_mask"].numpy()
    assert np.array_equal(scene.tracks.valid[:, 11:], vector_valid[:, 11:])
    assert bool(np.all(scene.tracks.valid[vector_valid])) and int(scene.tracks.valid[:, 0].sum()) == 18
    assert scene.tracks.types[scene.sdc_index] == AgentType.VEHICLE
    # Positions map back to the stored WOMD coordinates.
    pos = raw["agent"]["position"].numpy()
    v = scene.tracks.valid
    np.testing.assert_allclose(scene.frame.to_source(scene.tracks.position)[v], pos[v], atol=2e-3)


def test_smart_lane_topology_direction_matches_womd_semantics(shared_data):
    """SMART stores a PRED edge (entry lane -> lane); ours is (lane -> entry lane): each successor link
    (a -> b) must come with the predecessor link (b -> a) when both lanes are in the map."""
    scene = _read_one(shared_data / SMART)
    rm = scene.road_map
    succ = {tuple(x) for x in rm.links[rm.link_types == LinkType.SUCCESSOR].tolist()}
    pred = {tuple(x) for x in rm.links[rm.link_types == LinkType.PREDECESSOR].tolist()}
    assert len(succ) == len(pred) == 86
    assert {(b, a) for a, b in succ} == pred
    # Successor lanes start near where their predecessor ends.
    ends, starts = [], []
    for a, b in succ:
        ends.append(rm.feature_points(a)[-1, :2])
        starts.append(rm.feature_points(b)[0, :2])
    gap = np.linalg.norm(np.array(ends) - np.array(starts), axis=1)
    assert float(np.median(gap)) < 0.1


def test_smart_pickle_forbidden_global_is_refused(tmp_path):
    marker = tmp_path / "pwned"
    bad = tmp_path / "fake_smart.pkl"
    import torch

    bad.write_bytes(pickle.dumps({"scenario_id": "x", "agent": {"av_index": 0, "valid_mask": torch.zeros(1)},
                                  "map_polygon": _Evil(marker)}))
    assert smart_marl.detect_format(bad) == "smart_pkl"
    with pytest.raises(ScenarioReadError, match="which is not allowed"):
        list(smart_marl.read_scenarios(bad))
    assert not marker.exists()


def test_no_scene_is_shared_between_pickle_formats(shared_data):
    """The cross-format track comparison needs a scene in two formats; pin that the shared data has
    none (ScenarioNet WOMD ids vs SMART ids vs WOMD TFRecord ids), so a new overlap gets a test."""
    sn = {s.scenario_id for s in smart_marl.read_scenarios(shared_data / "scenarionet" / "waymo")}
    sm = {s.scenario_id for s in smart_marl.read_scenarios(shared_data / "smart_pkl")}
    womd = {"637f20cafde22ff8", "ee519cf571686d19"}
    assert sn == {"2a1e44d405a6833f", "8a346109094cd5aa", "c403d5992cab9e0", "eb4b91b10ca94ff2"}
    assert sm == {"1d71990efc3c6c0e", "2a716fad0956ffcf"}
    assert not (sn & sm) and not (sn & womd) and not (sm & womd)
