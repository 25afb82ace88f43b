"""WOMD: the project's own protobuf schema, TFRecord framing (CRC32C), the Scenario reader and
writer, and the sim-agents submission helpers. Numbers are pinned from the real test files in
../shared/data/womd_tfrecord (skipped when absent); the reader's handling of damaged input is also
checked on a record the writer made of the package's sample scene sumo-7-000000-02."""

from __future__ import annotations

import gzip
import math
import shutil
import struct

import numpy as np
import pytest

from smart_marl.errors import ScenarioReadError
from smart_marl.proto import womd as pb
from smart_marl.readers import read_scenarios, tfrecord, womd
from smart_marl.readers.submission import read_submission, write_submission
from smart_marl.scenario import LinkType, MapFeatureType
from smart_marl.synthetic import synthetic_scenario

ONE_SCENARIO = "womd_tfrecord/motion_data_one_scenario.tfrecord"
INPUT_SCENARIO = "womd_tfrecord/womd_scenario_input.tfrecord"
SUBMISSION = "womd_tfrecord/sim_agents_test_submission.binproto"


@pytest.fixture(scope="module")
def one_path(shared_data):
    return shared_data / ONE_SCENARIO


def _only_scenario(path):
    [scenario] = list(womd.read(path))
    return scenario


def _only_proto(path):
    [payload] = list(tfrecord.iter_records(path))
    return pb.Scenario.FromString(payload)


@pytest.fixture(scope="module")
def one_scenario(one_path):
    return _only_scenario(one_path)


@pytest.fixture(scope="module")
def one_proto(one_path):
    return _only_proto(one_path)


@pytest.fixture(scope="module")
def sample_path(sample_scenes, tmp_path_factory):
    """The sample scene sumo-7-000000-02 (44 tracks) as a one-record WOMD TFRecord (about 1.1 MB)."""
    path = tmp_path_factory.mktemp("womd") / "sample.tfrecord"
    womd.write_womd_tfrecord([sample_scenes[2]], path)
    return path


@pytest.fixture(scope="module")
def sample_record_scenario(sample_path):
    return _only_scenario(sample_path)


@pytest.fixture(scope="module")
def sample_proto(sample_path):
    return _only_proto(sample_path)


def _write_raw_records(path, payloads):
    with open(path, "wb") as f:
        for p in payloads:
            f.write(tfrecord.frame_record(p))


# --------------------------------------------------------------------------------------- schema
def test_schema_has_waymo_field_numbers_and_packing():
    fields = {f.name: f for f in pb.LaneCenter.DESCRIPTOR.fields}
    assert (fields["polyline"].number, fields["entry_lanes"].number, fields["exit_lanes"].number) == (8, 9, 10)
    assert pb.Scenario.DESCRIPTOR.full_name == "waymo.open_dataset.Scenario"
    assert {f.name: f.number for f in pb.ObjectState.DESCRIPTOR.fields}["valid"] == 11
    fdp = pb.build_file_descriptor()
    assert fdp.syntax == "proto2" and fdp.package == "waymo.open_dataset"
    packed = {(m.name, f.name) for m in fdp.message_type for f in m.field if f.options.packed}
    assert packed == {("LaneCenter", "entry_lanes"), ("LaneCenter", "exit_lanes")} | {
        ("SimulatedTrajectory", n) for n in ("center_x", "center_y", "center_z", "heading", "width", "length", "height", "valid")
    }
    assert pb.Track.TYPE_CYCLIST == 3 and pb.TrafficSignalLaneState.LANE_STATE_GO == 6


def test_unknown_field_3_is_skipped_and_kept_on_reserialising(shared_data):
    from google.protobuf import unknown_fields

    [payload] = list(tfrecord.iter_records(shared_data / INPUT_SCENARIO))
    message = pb.Scenario.FromString(payload)
    assert [u.field_number for u in unknown_fields.UnknownFieldSet(message)] == [3]
    assert message.scenario_id == "ee519cf571686d19"
    again = pb.Scenario.FromString(message.SerializeToString())  # upb may move the unknown field to the end
    assert [u.field_number for u in unknown_fields.UnknownFieldSet(again)] == [3]
    assert again == message and len(again.SerializeToString()) == len(payload)


# --------------------------------------------------------------------------------------- CRC32C
# RFC 3720 (iSCSI) appendix B.4 test vectors plus the classic check value.
CRC_VECTORS = [
    (b"123456789", 0xE3069283),
    (bytes(32), 0x8A9136AA),
    (b"\xff" * 32, 0x62A8AB43),
    (bytes(range(32)), 0x46DD794E),
    (bytes(range(31, -1, -1)), 0x113FDB5C),
    (b"", 0x0),
]


@pytest.mark.parametrize("data,expected", CRC_VECTORS)
def test_crc32c_known_vectors_both_implementations(data, expected):
    assert tfrecord.crc32c_numpy(data) == expected
    assert tfrecord.crc32c(data) == expected


def test_crc32c_numpy_matches_the_accelerated_one_on_long_buffers():
    if tfrecord.CRC32C_IMPLEMENTATION == "numpy":
        pytest.skip("no C-accelerated crc32c installed (pip install crc32c) to compare against")
    rng = np.random.default_rng(7)
    for n in (2047, 2048, 2049, 4096 + 13, 70_001, 1_000_003):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert tfrecord.crc32c_numpy(data) == tfrecord.crc32c(data), n


def test_crc32c_numpy_agrees_with_bytewise_definition():
    rng = np.random.default_rng(3)
    data = rng.integers(0, 256, 9_000, dtype=np.uint8).tobytes()
    bytewise = tfrecord._raw_update_py(0xFFFFFFFF, data) ^ 0xFFFFFFFF  # one table step per byte
    assert tfrecord.crc32c_numpy(data) == bytewise


def test_masked_crc_of_the_real_first_header(one_path):
    head = one_path.read_bytes()[:12]
    (length, crc) = struct.unpack("<QI", head)
    assert length == 952_947  # the whole file is one record: 952,963 bytes - 16 bytes of framing
    assert tfrecord.masked_crc32c(head[:8]) == crc


# ---------------------------------------------------------------------------------- TFRecord IO
@pytest.mark.parametrize("compress", [False, True])
def test_tfrecord_write_then_read_gives_the_payloads(tmp_path, compress):
    payloads = [b"", b"a", bytes(range(256)) * 40]
    path = tmp_path / "x.tfrecord"
    assert tfrecord.write_records(payloads, path, compress=compress) == 3
    assert (path.read_bytes()[:2] == b"\x1f\x8b") == compress
    assert list(tfrecord.iter_records(path)) == payloads


def _three_record_file(tmp_path):
    path = tmp_path / "three.tfrecord"
    _write_raw_records(path, [b"first record", b"second record", b"third record"])
    return path, path.read_bytes()


def test_truncated_record_names_file_and_record(tmp_path):
    path, data = _three_record_file(tmp_path)
    path.write_bytes(data[:-6])
    with pytest.raises(ScenarioReadError, match=r"three\.tfrecord, record 2: truncated record") as info:
        list(tfrecord.iter_records(path))
    assert info.value.record == 2
    path.write_bytes(data[: 16 + 12 + 5])  # second header truncated after 5 bytes
    with pytest.raises(ScenarioReadError, match=r"record 1: truncated record: the 12-byte header has only 5 bytes"):
        list(tfrecord.iter_records(path))


def test_flipped_length_crc_byte_is_a_length_crc_error(tmp_path):
    path, data = _three_record_file(tmp_path)
    second = 16 + len(b"first record")
    corrupt = bytearray(data)
    corrupt[second + 9] ^= 0x01
    path.write_bytes(bytes(corrupt))
    with pytest.raises(ScenarioReadError, match=r"three\.tfrecord, record 1: length CRC mismatch") as info:
        list(tfrecord.iter_records(path))
    assert info.value.record == 1 and info.value.path == str(path)


def test_flipped_payload_byte_is_a_data_crc_error(tmp_path):
    path, data = _three_record_file(tmp_path)
    second = 16 + len(b"first record")
    corrupt = bytearray(data)
    corrupt[second + 12 + 3] ^= 0x40
    path.write_bytes(bytes(corrupt))
    with pytest.raises(ScenarioReadError, match=r"three\.tfrecord, record 1: data CRC mismatch"):
        list(tfrecord.iter_records(path))


def test_flipped_payload_byte_in_a_scene_file_is_caught(tmp_path, sample_path):
    data = bytearray(sample_path.read_bytes())
    data[500_000] ^= 0x10
    path = tmp_path / "bad.tfrecord"
    path.write_bytes(bytes(data))
    with pytest.raises(ScenarioReadError, match=r"bad\.tfrecord, record 0: data CRC mismatch"):
        list(womd.read(path))


# ---------------------------------------------------------------------------- real scene facts
def test_one_scenario_counts(one_scenario):
    s = one_scenario
    summary = s.summary()
    assert s.scenario_id == "637f20cafde22ff8" and s.source == "womd"
    assert s.num_frames == 91 and s.current_frame == 10 and s.num_tracks == 83
    assert summary["tracks_per_type"] == {"vehicle": 70, "pedestrian": 10, "cyclist": 3, "other": 0}
    assert summary["lanes"] == 199
    assert summary["lanes_with_predecessors"] == 150
    assert summary["traffic_light_frames"] == 91
    assert summary["road_lines"] == 59 and summary["road_edges"] == 28 and summary["crosswalks"] == 4
    assert int((s.road_map.types == MapFeatureType.STOP_SIGN).sum()) == 8
    assert int((s.road_map.types == MapFeatureType.SPEED_BUMP).sum()) == 3
    assert s.metadata == {"path": str(womd_path(s)), "record": 0}
    np.testing.assert_allclose(np.diff(s.timestamps_s), 0.1, atol=1e-4)  # logged times jitter


def womd_path(scenario):
    return scenario.metadata["path"]


def test_one_scenario_matches_the_protobuf_values(one_scenario, one_proto):
    s, m = one_scenario, one_proto
    assert s.sdc_index == m.sdc_track_index == 82
    sdc_state = m.tracks[82].states[10]
    assert (s.frame.x, s.frame.y, s.frame.z) == (sdc_state.center_x, sdc_state.center_y, sdc_state.center_z)
    assert s.frame.heading == 0.0
    np.testing.assert_array_equal(s.tracks.position[82, 10], [0, 0, 0])
    first = m.tracks[0].states[0]
    assert s.tracks.ids[0] == m.tracks[0].id == 1580
    assert s.tracks.position[0, 0, 0] == np.float32(first.center_x - s.frame.x)
    assert s.tracks.heading[0, 0] == np.float32(first.heading)
    assert s.tracks.size[0, 0].tolist() == [np.float32(first.length), np.float32(first.width), np.float32(first.height)]
    expected_valid = np.array([[st.valid for st in t.states] for t in m.tracks])
    np.testing.assert_array_equal(s.tracks.valid, expected_valid)
    assert s.predict_indices.tolist() == [r.track_index for r in m.tracks_to_predict]
    assert s.predict_difficulty.tolist() == [r.difficulty for r in m.tracks_to_predict]


def test_one_scenario_lane_topology_and_stop_signs(one_scenario, one_proto):
    rm, m = one_scenario.road_map, one_proto
    lanes = [f for f in m.map_features if f.HasField("lane")]
    counts = {t: int((rm.link_types == t).sum()) for t in LinkType}
    assert counts[LinkType.SUCCESSOR] == sum(len(f.lane.exit_lanes) for f in lanes)
    assert counts[LinkType.PREDECESSOR] == sum(len(f.lane.entry_lanes) for f in lanes)
    assert counts[LinkType.LEFT_NEIGHBOR] == sum(len(f.lane.left_neighbors) for f in lanes)
    assert counts[LinkType.RIGHT_NEIGHBOR] == sum(len(f.lane.right_neighbors) for f in lanes)
    stop = [f for f in m.map_features if f.HasField("stop_sign")][0]
    assert stop.stop_sign.lane[:] == [213, 212, 211, 210]
    sel = (rm.link_types == LinkType.STOP_SIGN_LANE) & (rm.links[:, 0] == stop.id)
    assert rm.links[sel, 1].tolist() == [213, 212, 211, 210]
    index = int(np.flatnonzero(rm.ids == stop.id)[0])
    assert len(rm.feature_points(index)) == 1
    first_lane = lanes[0]
    i = int(np.flatnonzero(rm.ids == first_lane.id)[0])
    assert rm.subtypes[i] == first_lane.lane.type
    assert rm.speed_limit_mph[i] == np.float32(first_lane.lane.speed_limit_mph)
    assert len(rm.feature_points(i)) == len(first_lane.lane.polyline)


def test_one_scenario_traffic_lights(one_scenario, one_proto):
    tl = one_scenario.traffic_lights
    lanes = sorted({ls.lane for d in one_proto.dynamic_map_states for ls in d.lane_states})
    assert tl.lane_ids.tolist() == lanes and len(lanes) == 12
    assert tl.present.all()  # every one of the 12 lanes is reported on every one of the 91 frames
    for f in (0, 10, 90):
        got = dict(zip(tl.lane_ids.tolist(), tl.states[f].tolist()))
        assert got == {ls.lane: ls.state for ls in one_proto.dynamic_map_states[f].lane_states}
    state = one_proto.dynamic_map_states[0].lane_states[0]
    j = tl.lane_ids.tolist().index(state.lane)
    assert tl.stop_points[j, 0] == np.float32(state.stop_point.x - one_scenario.frame.x)


def test_input_scenario_with_unknown_field_reads(shared_data):
    [s] = list(womd.read(shared_data / INPUT_SCENARIO))
    assert s.scenario_id == "ee519cf571686d19"
    assert s.num_tracks == 257 and s.num_frames == 91
    assert s.summary()["tracks_per_type"]["pedestrian"] == 68
    assert s.objects_of_interest.tolist() == [625, 2694]


# ------------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("name", [ONE_SCENARIO, INPUT_SCENARIO])
@pytest.mark.parametrize("compress", [False, True])
def test_real_file_round_trip_is_exact(shared_data, tmp_path, name, compress):
    [a] = list(womd.read(shared_data / name))
    path = tmp_path / ("out.tfrecord.gz" if compress else "out.tfrecord")
    assert womd.write_womd_tfrecord([a], path, compress=compress) == 1
    [b] = list(womd.read(path))
    assert a.differences(b) == ["metadata"]
    assert b.metadata == {"path": str(path), "record": 0}


def test_synthetic_round_trip_is_exact(tmp_path):
    scenes = [synthetic_scenario(0), synthetic_scenario(1)]
    womd.write_womd_tfrecord(scenes, tmp_path / "a.tfrecord")
    first = list(womd.read(tmp_path / "a.tfrecord"))
    assert [s.scenario_id for s in first] == ["synthetic-0000", "synthetic-0001"]
    # the first read moves the scene to the SDC-centred frame; the source coordinates are kept
    for orig, got in zip(scenes, first):
        np.testing.assert_allclose(got.frame.to_source(got.tracks.position), orig.frame.to_source(orig.tracks.position), atol=1e-3)
        assert np.array_equal(got.tracks.valid, orig.tracks.valid)
        assert got.traffic_lights.states.tolist() == orig.traffic_lights.states.tolist()
        assert sorted(map(tuple, got.road_map.links.tolist())) == sorted(map(tuple, orig.road_map.links.tolist()))
    womd.write_womd_tfrecord(first, tmp_path / "b.tfrecord")
    second = list(womd.read(tmp_path / "b.tfrecord"))
    for a, b in zip(first, second):
        assert a.equals(b), a.differences(b)


def test_rotated_frame_is_written_in_source_coordinates(tmp_path):
    scene = synthetic_scenario(2)
    rotated = scene.to_frame(5.0, -3.0, 0.7)
    womd.write_womd_tfrecord([rotated], tmp_path / "r.tfrecord")
    [back] = list(womd.read(tmp_path / "r.tfrecord"))
    np.testing.assert_allclose(back.frame.to_source(back.tracks.position), scene.frame.to_source(scene.tracks.position), atol=1e-3)
    v = scene.tracks.valid
    dh = (back.tracks.heading[v].astype(np.float64) - scene.tracks.heading[v] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(dh).max() < 1e-5
    np.testing.assert_allclose(back.tracks.velocity[v], scene.tracks.velocity[v], atol=1e-4)


def test_scenario_to_proto_counts(one_scenario, one_proto):
    m = womd.scenario_to_proto(one_scenario)
    assert len(m.tracks) == 83 and len(m.map_features) == len(one_proto.map_features) == 301
    assert len(m.dynamic_map_states) == 91
    # written back from the float32 local frame: within float32 resolution of the source value
    assert abs(m.tracks[0].states[0].center_x - one_proto.tracks[0].states[0].center_x) < 1e-5
    assert m.tracks[0].states[0].heading == one_proto.tracks[0].states[0].heading


# ------------------------------------------------------------------------------------- bad input
def test_record_that_is_not_a_scenario_is_a_clear_error(tmp_path):
    path = tmp_path / "notscene.tfrecord"
    _write_raw_records(path, [b"\xff\xff\xff garbage that is no protobuf"])
    with pytest.raises(ScenarioReadError, match=r"notscene\.tfrecord, record 0: the record is not a WOMD Scenario"):
        list(womd.read(path))
    _write_raw_records(path, [pb.MapPoint(x=1.0).SerializeToString()])  # parses, but has no scenario_id
    with pytest.raises(ScenarioReadError, match=r"record 0: the record is not a WOMD Scenario protobuf \(it has no scenario_id\)"):
        list(womd.read(path))


def test_nan_position_on_a_valid_frame_names_file_record_and_problem(tmp_path, sample_proto):
    bad = pb.Scenario()
    bad.CopyFrom(sample_proto)
    assert bad.tracks[5].states[20].valid
    bad.tracks[5].states[20].center_y = math.nan
    path = tmp_path / "nan.tfrecord"
    _write_raw_records(path, [sample_proto.SerializeToString(), bad.SerializeToString()])
    reader = womd.read(path)
    assert next(reader).scenario_id == "sumo-7-000000-02"
    with pytest.raises(ScenarioReadError) as info:
        next(reader)
    assert info.value.record == 1 and info.value.path == str(path)
    message = str(info.value)
    assert "nan.tfrecord, record 1" in message and "Tracks.position is not finite" in message
    assert "track 5" in message and "frame 20" in message


def test_decode_scenario_from_bytes_checks_state_counts(sample_proto):
    bad = pb.Scenario()
    bad.CopyFrom(sample_proto)
    del bad.tracks[3].states[-1]
    with pytest.raises(ScenarioReadError, match=r"<bytes>, record 0: .*track 3 \(id \d+\) has 90 states but there are 91"):
        womd.decode_scenario(bad.SerializeToString())


# --------------------------------------------------------------------- discovery and GZIP input
def test_read_scenarios_on_the_directory_picks_womd_and_skips_the_binproto(shared_data):
    try:
        scenes = list(read_scenarios(shared_data / "womd_tfrecord"))
    except ModuleNotFoundError as exc:  # another format module of the dispatcher not written yet
        pytest.skip(f"readers dispatcher cannot import every format module yet: {exc}")
    assert [s.scenario_id for s in scenes] == ["637f20cafde22ff8", "ee519cf571686d19"]
    assert {s.source for s in scenes} == {"womd"}


def test_gzip_copy_reads_identically_and_is_sniffed(sample_path, tmp_path, sample_record_scenario):
    src = sample_path
    gz = tmp_path / "copy.tfrecord.gz"
    with open(src, "rb") as fin, gzip.open(gz, "wb") as fout:
        shutil.copyfileobj(fin, fout)
    head = gz.read_bytes()[:4096]
    assert womd.sniff(str(gz), head)
    [again] = list(womd.read(gz))
    assert again.equals(sample_record_scenario)


def test_sniff_rejects_other_files(shared_data):
    sub = shared_data / SUBMISSION
    assert not womd.sniff(str(sub), sub.read_bytes()[:4096])
    assert not womd.sniff("x", b"\x1f\x8bnot really gzip")
    assert not womd.sniff("x", b'{"objects": []}')


# ---------------------------------------------------------------------------------- submission
def test_submission_parses_and_round_trips_byte_exactly(shared_data, tmp_path):
    path = shared_data / SUBMISSION
    message = read_submission(path)
    assert message.submission_type == pb.SimAgentsChallengeSubmission.SIM_AGENTS_SUBMISSION
    [rollouts] = message.scenario_rollouts
    assert rollouts.scenario_id == "637f20cafde22ff8"
    assert len(rollouts.joint_scenes) == 32
    assert {len(j.simulated_trajectories) for j in rollouts.joint_scenes} == {50}
    lengths = {(len(t.center_x), len(t.center_y), len(t.center_z), len(t.heading))
               for j in rollouts.joint_scenes for t in j.simulated_trajectories}
    assert lengths == {(80, 80, 80, 80)}
    assert rollouts.joint_scenes[0].simulated_trajectories[0].object_id == 1580  # track 0 of the scenario
    out = tmp_path / "again.binproto"
    assert write_submission(message, out) == path.stat().st_size
    assert out.read_bytes() == path.read_bytes()


def test_bad_submission_file_names_the_file(tmp_path):
    path = tmp_path / "bad.binproto"
    path.write_bytes(b"\x0a\xff\xff\xff\x0f broken")
    with pytest.raises(ScenarioReadError, match=r"bad\.binproto: not a SimAgentsChallengeSubmission"):
        read_submission(path)
    with pytest.raises(ScenarioReadError, match=r"missing\.binproto: cannot open"):
        read_submission(tmp_path / "missing.binproto")


# ------------------------------------------------------------------- vectorised decoding path
@pytest.mark.parametrize("name", [ONE_SCENARIO, INPUT_SCENARIO])
def test_numpy_scanner_path_equals_the_plain_protobuf_path(shared_data, name):
    [payload] = list(tfrecord.iter_records(shared_data / name))
    fast = womd.decode_scenario(payload)
    plain = womd.scenario_from_proto(pb.Scenario.FromString(payload))
    assert fast.equals(plain, ignore=())


def test_unknown_field_inside_a_map_point_falls_back_to_protobuf(sample_proto):
    view = pb.RAW_POINTS["Scenario"].FromString(sample_proto.SerializeToString())
    lane = next(f for f in view.map_features if f.HasField("lane"))
    lane.lane.polyline[0] = lane.lane.polyline[0] + b"\x20\x05"  # field 4, varint 5: unknown to MapPoint
    with_unknown = view.SerializeToString()
    assert womd.scan_fixed_width_messages([lane.lane.polyline[0]], womd._MAP_POINT_FIELDS) is None
    assert womd.decode_scenario(with_unknown).equals(womd.decode_scenario(sample_proto.SerializeToString()))


def test_scanner_decodes_fields_in_any_order_and_absent_ones_as_zero():
    chunks = [
        pb.ObjectState(center_x=1.5, valid=True).SerializeToString(),
        pb.ObjectState(length=3.0, heading=2.0).SerializeToString(),
        b"\x45\x00\x00\x80\x3f\x2d\x00\x00\x40\x40",  # heading 1.0 then length 3.0: same length, other order
        b"",
    ]
    out = womd.scan_fixed_width_messages(chunks, womd._OBJECT_STATE_FIELDS)
    assert out["center_x"].tolist() == [1.5, 0.0, 0.0, 0.0]
    assert out["heading"].tolist() == [0.0, 2.0, 1.0, 0.0]
    assert out["length"].tolist() == [0.0, 3.0, 3.0, 0.0]
    assert out["valid"].tolist() == [1, 0, 0, 0]


@pytest.mark.parametrize("which", ["sample", "real"])
def test_numpy_encoding_is_what_protobuf_itself_writes(request, which):
    """On the sample scene and on the real WOMD scene (more kinds of map features)."""
    scene = request.getfixturevalue("sample_record_scenario" if which == "sample" else "one_scenario")
    encoded = womd.encode_scenario(scene)
    assert pb.Scenario.FromString(encoded).SerializeToString() == encoded
    rotated = scene.to_frame(3.0, 4.0, 1.1)  # float64 velocities cast to the float fields
    encoded = womd.encode_scenario(rotated)
    assert pb.Scenario.FromString(encoded).SerializeToString() == encoded


def test_truncated_gzip_file_names_file_and_record(tmp_path, sample_path):
    gz = tmp_path / "cut.tfrecord.gz"
    whole = gzip.compress(sample_path.read_bytes())
    gz.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(ScenarioReadError, match=r"cut\.tfrecord\.gz, record 0: ") as info:
        list(womd.read(gz))
    assert info.value.record == 0


def test_reading_with_the_numpy_crc_gives_the_same_scene(monkeypatch, sample_path, sample_record_scenario):
    monkeypatch.setattr(tfrecord, "_crc32c_fast", None)  # as without the crc32c package
    [again] = list(womd.read(sample_path))
    assert again.equals(sample_record_scenario)
