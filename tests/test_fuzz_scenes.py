"""Hostile scene files: mutated copies of a real file of every format read as valid Scenarios or
raise a SmartMarlError naming the file; nothing else escapes, nothing invalid comes back.

Mutations (tests/fuzzing.py): structural ones on the parsed file (a field replaced by a value of the
wrong type, None, NaN, a huge number, a nested container, deeply nested JSON; a field deleted; an
array's dtype, shape or one element changed), then written back in the format (JSON, pickle,
protobuf records with valid CRCs, parquet, a shard header), and byte-level ones (bit flips,
truncations, duplicated slices, overwritten regions) on the file itself. Each target runs a
fixed-seed budget in the default run and a long random one under ``-m slow``
(:data:`fuzzing.BUDGETS`)."""

from __future__ import annotations

import io
import json
import os
import pickle
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume
from hypothesis import strategies as st

from fuzzing import mutate_bytes, mutate_structure, run_fuzz, to_json
from smart_marl.cache import scene_entry, write_manifest, write_shard
from smart_marl.readers.scene_cache import MAGIC
from smart_marl.errors import SmartMarlError
from smart_marl.readers import read_scenarios
from smart_marl.scenario import Scenario

BUDGET = [pytest.param("default", id="default"), pytest.param("long", id="long", marks=pytest.mark.slow)]


def assert_scenes_or_named_error(read, *named: str | os.PathLike) -> str:
    """``read()`` gives Scenarios that pass the Scenario checks again, or raises a SmartMarlError
    whose message holds one of ``named`` (the file, or the folder around it). Returns which."""
    try:
        scenes = list(read())
    except SmartMarlError as exc:
        assert any(os.fspath(p) in str(exc) for p in named), f"{type(exc).__name__} names none of {named}: {exc}"
        return "error"
    for sc in scenes:
        arrays, meta = sc.to_arrays()
        Scenario.from_arrays({k: np.array(v) for k, v in arrays.items()}, json.loads(json.dumps(meta)), validate=True)
    return "scenes"


def _structure_or_bytes(data) -> bool:
    return data.draw(st.integers(0, 2), label="structural?") > 0  # two structural mutations for one byte-level one


# ------------------------------------------------------------------------------------ JSON
@pytest.mark.parametrize("budget", BUDGET)
@pytest.mark.parametrize("name", ["gpudrive_json/tfrecord-00000-of-01000_222.json", "nocturne_json/example_scenario.json"])
def test_mutated_gpudrive_and_nocturne_json_read_as_scenes_or_a_named_error(shared_data, tmp_path, name, budget):
    raw = (shared_data / name).read_bytes()
    base = json.loads(raw)
    path = tmp_path / "scene.json"

    def check(data):
        if _structure_or_bytes(data):
            path.write_text(to_json(mutate_structure(data, base)))
        else:
            path.write_bytes(mutate_bytes(data, raw))
        assert_scenes_or_named_error(lambda: read_scenarios(path), path)

    run_fuzz(budget, check)


# ---------------------------------------------------------------------------------- pickles
@pytest.mark.parametrize("budget", BUDGET)
@pytest.mark.parametrize("name", ["scenarionet/waymo/sd_waymo_v1.2_eb4b91b10ca94ff2.pkl", "smart_pkl/1d71990efc3c6c0e.pkl"])
def test_mutated_scenarionet_and_smart_pickles_read_as_scenes_or_a_named_error(shared_data, tmp_path, name, budget):
    from smart_marl.readers.safe_pickle import SCENARIONET_GLOBALS, load_restricted, smart_pickle_globals

    raw = (shared_data / name).read_bytes()
    base = load_restricted(io.BytesIO(raw), smart_pickle_globals() if "smart_pkl" in name else SCENARIONET_GLOBALS, path=name)
    path = tmp_path / Path(name).name

    def check(data):
        if _structure_or_bytes(data):
            path.write_bytes(pickle.dumps(mutate_structure(data, base), protocol=4))
        else:
            path.write_bytes(mutate_bytes(data, raw))
        assert_scenes_or_named_error(lambda: read_scenarios(path), path)

    run_fuzz(budget, check)


# ------------------------------------------------------------------------------------- WOMD
def _mutate_womd(data, message) -> None:
    """Change one thing of a parsed WOMD Scenario in place: counts, indices and values protobuf's
    types allow but a scene cannot hold."""
    big = st.sampled_from([-(2**31), -2, -1, 0, 10, 90, 91, 2**31 - 1])
    bad_float = st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e300, -1.0])
    kind = data.draw(st.sampled_from(["current", "sdc", "predict", "states", "state_value", "ids", "timestamps",
                                      "map_points", "map_value", "dynamic", "interest", "scenario_id"]), label="womd edit")
    tracks = message.tracks
    if kind == "current":
        message.current_time_index = data.draw(big)
    elif kind == "sdc":
        message.sdc_track_index = data.draw(big)
    elif kind == "predict":
        message.tracks_to_predict.add(track_index=data.draw(big))
    elif kind == "states":
        track = tracks[data.draw(st.integers(0, len(tracks) - 1))]
        del track.states[data.draw(st.integers(0, len(track.states) - 1)):]
    elif kind == "state_value":
        state = tracks[data.draw(st.integers(0, len(tracks) - 1))].states[data.draw(st.integers(0, 90))]
        setattr(state, data.draw(st.sampled_from(["center_x", "heading", "length", "velocity_y"])), data.draw(bad_float))
        state.valid = True
    elif kind == "ids":
        tracks[1].id = tracks[0].id
    elif kind == "timestamps":
        if data.draw(st.booleans()):
            del message.timestamps_seconds[:]
        else:
            message.timestamps_seconds[0] = data.draw(bad_float)
    elif kind == "map_points":
        feature = message.map_features[data.draw(st.integers(0, len(message.map_features) - 1))]
        oneof = feature.WhichOneof("feature_data")
        points = getattr(getattr(feature, oneof), "polyline" if oneof in ("lane", "road_line", "road_edge") else "polygon", None)
        if points is not None:
            del points[:]
    elif kind == "map_value":
        lane = next(f.lane for f in message.map_features if f.WhichOneof("feature_data") == "lane")
        lane.polyline[0].x = data.draw(bad_float)
    elif kind == "dynamic":
        for _ in range(data.draw(st.integers(1, 200))):
            message.dynamic_map_states.add()
    elif kind == "interest":
        message.objects_of_interest.append(data.draw(st.sampled_from([-1, 2**31 - 1, 0])))
    else:
        message.scenario_id = ""


@pytest.mark.parametrize("budget", BUDGET)
def test_mutated_womd_records_read_as_scenes_or_a_named_error(shared_data, tmp_path, budget):
    from smart_marl.proto import womd as pb
    from smart_marl.readers import tfrecord

    source = shared_data / "womd_tfrecord" / "motion_data_one_scenario.tfrecord"
    raw = source.read_bytes()
    payload = next(tfrecord.iter_records(source))
    path = tmp_path / "scene.tfrecord"

    def check(data):
        if _structure_or_bytes(data):
            message = pb.Scenario.FromString(payload)
            _mutate_womd(data, message)
            path.write_bytes(tfrecord.frame_record(message.SerializeToString()))
        else:
            path.write_bytes(mutate_bytes(data, raw))
        assert_scenes_or_named_error(lambda: read_scenarios(path), path)

    run_fuzz(budget, check)


# -------------------------------------------------------------------------------------- AV2
@pytest.mark.parametrize("budget", BUDGET)
def test_mutated_av2_scenarios_and_maps_read_as_scenes_or_a_named_error(shared_data, tmp_path, budget):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from fuzzing import _mutated_array

    scenario_src = next((shared_data / "av2").glob("scenario_*.parquet"))
    map_src = next((shared_data / "av2").glob("log_map_archive_*.json"))
    table = pq.read_table(scenario_src)
    map_raw = map_src.read_bytes()
    map_base = json.loads(map_raw)
    scenario_path, map_path = tmp_path / scenario_src.name, tmp_path / map_src.name

    def check(data):
        t, m = table, map_raw
        target = data.draw(st.sampled_from(["column", "parquet_bytes", "map", "map_bytes"]), label="av2 target")
        if target == "column":
            name = data.draw(st.sampled_from(table.column_names), label="column")
            values = table.column(name).to_numpy(zero_copy_only=False)
            new = data.draw(st.sampled_from(["array", "huge", "constant"]), label="column change")
            if new == "array":
                values = _mutated_array(data, values)
                if len(values) != len(table):  # a column must keep the table's length: shorten the table
                    t = t.slice(0, len(values))
            elif new == "huge":
                values = np.full(len(values), data.draw(st.sampled_from([10**9, 2**40, -(10**9)])), np.int64)
            else:
                values = np.full(len(values), data.draw(st.sampled_from(["x", "12.5", "AV"])), object)
            try:
                column = pa.array(list(values[: len(t)]) if values.dtype == object else values[: len(t)])
            except (pa.ArrowException, ValueError, TypeError):
                assume(False)  # a column parquet cannot hold: not a file anyone can write
            t = t.set_column(t.column_names.index(name), name, column)
        elif target == "map":
            m = to_json(mutate_structure(data, map_base)).encode()
        pq.write_table(t, scenario_path)
        if target == "parquet_bytes":
            scenario_path.write_bytes(mutate_bytes(data, scenario_path.read_bytes()))
        map_path.write_bytes(mutate_bytes(data, map_raw) if target == "map_bytes" else m)
        assert_scenes_or_named_error(lambda: read_scenarios(scenario_path), scenario_path, map_path)

    run_fuzz(budget, check)


# ------------------------------------------------------------------------------ scene cache
def _rewrite_header(blob: bytes, header: object) -> bytes:
    """A shard with another JSON header and the same array data."""
    (old_len,) = struct.unpack_from("<Q", blob, len(MAGIC))
    data_region = blob[len(MAGIC) + 8 + old_len:]
    text = json.dumps(header).encode()
    pad = (-(len(MAGIC) + 8 + len(text))) % 64
    return MAGIC + struct.pack("<Q", len(text) + pad) + text + b" " * pad + data_region


@pytest.mark.parametrize("budget", BUDGET)
def test_mutated_scene_cache_shards_and_manifests_read_as_scenes_or_a_named_error(sample_scenes, tmp_path, budget):
    scene = sample_scenes[3]  # the smallest sample scene (10 tracks)
    cache = tmp_path / "cache"
    cache.mkdir()
    shard = cache / "a.smsc"
    write_shard(shard, [scene, scene.select_tracks(np.arange(5))])
    blob = shard.read_bytes()
    (header_len,) = struct.unpack_from("<Q", blob, len(MAGIC))
    header = json.loads(blob[len(MAGIC) + 8 : len(MAGIC) + 8 + header_len])
    write_manifest(cache, [{"file": "a.smsc", "input": "fuzz", "scenes": [scene_entry(scene, "a.smsc")] * 2}])
    manifest_raw = (cache / "manifest.json").read_bytes()
    manifest = json.loads(manifest_raw)

    def check(data):
        target = data.draw(st.sampled_from(["header", "header", "shard_bytes", "manifest"]), label="cache target")
        shard.write_bytes(_rewrite_header(blob, mutate_structure(data, header)) if target == "header"
                          else mutate_bytes(data, blob) if target == "shard_bytes" else blob)
        (cache / "manifest.json").write_text(to_json(mutate_structure(data, manifest)) if target == "manifest"
                                             else manifest_raw.decode())
        assert_scenes_or_named_error(lambda: read_scenarios(shard), shard)
        assert_scenes_or_named_error(lambda: read_scenarios(cache), cache)

    run_fuzz(budget, check)
