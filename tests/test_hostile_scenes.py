"""Hostile scene inputs, one case each (issue 15 items 2-5): tensor views past their storage, wrongly
typed fields, silent wrong results (string validity, float ids, negative sizes, tampered shards and
manifests, a cache replaced by another), declared sizes the file cannot hold, inputs that would
block. Every one is a named :class:`~smart_marl.errors.SmartMarlError` or the right result."""

from __future__ import annotations

import gzip
import json
import os
import pickle
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from smart_marl import ScenarioReadError, read_scenarios
from smart_marl.cache import PreprocessError, SceneCache, preprocess, write_shard
from smart_marl.readers.scene_cache import MAGIC
from smart_marl.cli import main
from smart_marl.errors import SmartMarlError, UsageError
from smart_marl.readers.safe_pickle import SCENARIONET_GLOBALS, load_restricted, smart_pickle_globals

ROOT = Path(__file__).resolve().parents[1]
SN = "scenarionet/waymo/sd_waymo_v1.2_eb4b91b10ca94ff2.pkl"
SMART = "smart_pkl/1d71990efc3c6c0e.pkl"
GPUDRIVE = "gpudrive_json/tfrecord-00000-of-01000_222.json"  # GPUDrive flavour with ids and metadata


def _read_error(path, named=None) -> ScenarioReadError:
    """The ScenarioReadError reading ``path`` raises; its message names ``named`` (default: ``path``)."""
    with pytest.raises(ScenarioReadError) as info:
        list(read_scenarios(path))
    assert str(named or path) in str(info.value)
    return info.value


# ------------------------------------------------------------------- item 2: tensor views
class _OversizedView:
    """Pickles as a torch tensor whose view (1000 elements) reaches past its 4-element storage."""

    def __reduce__(self):
        import collections

        import torch

        return (torch._utils._rebuild_tensor_v2, (torch.zeros(4).storage(), 0, (1000,), (1,), False, collections.OrderedDict()))


@pytest.mark.filterwarnings("ignore:TypedStorage is deprecated")
def test_smart_pickle_tensor_view_larger_than_its_storage_is_refused(shared_data, tmp_path):
    data = load_restricted(shared_data / SMART, smart_pickle_globals())
    bad = tmp_path / "view.pkl"
    bad.write_bytes(pickle.dumps({**data, "agent": {**data["agent"], "heading": _OversizedView()}}, protocol=4))
    err = _read_error(bad)
    assert "reaches element 999 of a storage of 4 elements" in str(err)
    # a view inside its storage (a slice) still loads
    import torch

    ok = pickle.dumps({"t": torch.arange(12.0).reshape(3, 4)[:, 1:3]}, protocol=4)
    import io

    assert load_restricted(io.BytesIO(ok), smart_pickle_globals(), path="ok").get("t").tolist() == [[1, 2], [5, 6], [9, 10]]


# ---------------------------------------------------------- item 3: wrongly typed fields
def _scenarionet(shared_data, tmp_path, change) -> Path:
    data = load_restricted(shared_data / SN, SCENARIONET_GLOBALS)
    change(data)
    path = tmp_path / "sn.pkl"
    path.write_bytes(pickle.dumps(data, protocol=4))
    return path


def _smart(shared_data, tmp_path, change) -> Path:
    data = load_restricted(shared_data / SMART, smart_pickle_globals())
    change(data)
    path = tmp_path / "smart.pkl"
    path.write_bytes(pickle.dumps(data, protocol=4))
    return path


def _gpudrive(shared_data, tmp_path, change, name="scene.json") -> Path:
    data = json.loads((shared_data / GPUDRIVE).read_text())
    change(data)
    path = tmp_path / name
    path.write_text(json.dumps(data))
    return path


def _first_track(data):
    return data["tracks"][next(iter(data["tracks"]))]


@pytest.mark.parametrize("case, expected", [
    ("sn_current_time_index", "current_time_index: expected an integer, got 'ten'"),
    ("sn_valid_strings", "valid: expected booleans, got values of type str"),
    ("sn_position_strings", "not numeric"),
    ("smart_num_nodes_none", "num_nodes: expected an integer, got None"),
    ("smart_float_id", "is not a whole number"),
    ("gpudrive_sdc_string", "sdc_track_index: expected an integer, got 'x'"),
    ("gpudrive_sdc_null", "sdc_track_index: expected an integer, got None"),
    ("gpudrive_sdc_infinity", "sdc_track_index: inf is not a whole number"),
    ("gpudrive_difficulty", "1000 is outside the range of int8"),
    ("gpudrive_float_id", "object id: 12.7 is not a whole number"),
    ("gpudrive_string_position", "not a number"),
    ("gpudrive_negative_length", "Tracks.size is negative"),
])
def test_wrongly_typed_fields_are_named_errors_never_tracebacks_or_truncations(shared_data, tmp_path, case, expected):
    def state(d):
        return _first_track(d)["state"]

    changes = {
        "sn_current_time_index": ("sn", lambda d: d["metadata"].__setitem__("current_time_index", "ten")),
        "sn_valid_strings": ("sn", lambda d: state(d).__setitem__("valid", np.array(["False"] * len(state(d)["valid"])))),
        "sn_position_strings": ("sn", lambda d: state(d).__setitem__("position", state(d)["position"].astype(str))),
        "smart_num_nodes_none": ("smart", lambda d: d["agent"].__setitem__("num_nodes", None)),
        "smart_float_id": ("smart", lambda d: d["agent"].__setitem__("id", [i + 0.7 for i in d["agent"]["id"]])),
        "gpudrive_sdc_string": ("gpu", lambda d: d["metadata"].__setitem__("sdc_track_index", "x")),
        "gpudrive_sdc_null": ("gpu", lambda d: d["metadata"].__setitem__("sdc_track_index", None)),
        "gpudrive_sdc_infinity": ("gpu", lambda d: d["metadata"].__setitem__("sdc_track_index", float("inf"))),
        "gpudrive_difficulty": ("gpu", lambda d: d["metadata"]["tracks_to_predict"][0].__setitem__("difficulty", 1000)),
        "gpudrive_float_id": ("gpu", lambda d: d["objects"][0].__setitem__("id", 12.7)),
        "gpudrive_string_position": ("gpu", lambda d: d["objects"][0]["position"][0].__setitem__("x", "12.5")),
        "gpudrive_negative_length": ("gpu", lambda d: d["objects"][0].__setitem__("length", -4.5)),
    }
    kind, change = changes[case]
    path = {"sn": _scenarionet, "smart": _smart, "gpu": _gpudrive}[kind](shared_data, tmp_path, change)
    err = _read_error(path)
    assert expected in str(err), str(err)
    assert err.__class__ is ScenarioReadError or isinstance(err, SmartMarlError)


def test_silently_truncated_float_ids_were_id_12_now_refused(shared_data, tmp_path):
    """Before: id 12.7 was read as track 12. The same scene with whole-number float ids still reads."""
    ids = json.loads((shared_data / GPUDRIVE).read_text())["objects"]
    whole = _gpudrive(shared_data, tmp_path, lambda d: [o.__setitem__("id", float(o["id"])) for o in d["objects"]], "whole.json")
    scene = next(read_scenarios(whole))
    assert scene.tracks.ids.tolist() == [o["id"] for o in ids]


def test_deeply_nested_json_is_a_named_error(shared_data, tmp_path):
    path = tmp_path / "deep.json"
    text = (shared_data / GPUDRIVE).read_text()
    path.write_text(text.replace('"metadata":', '"deep": ' + "[" * 200_000 + "]" * 200_000 + ', "metadata":', 1))
    assert "nested too deeply" in str(_read_error(path))


def test_av2_non_utf8_map_and_string_positions_are_named(shared_data, tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    src = next((shared_data / "av2").glob("scenario_*.parquet"))
    map_src = next((shared_data / "av2").glob("log_map_archive_*.json"))
    scenario, map_path = tmp_path / src.name, tmp_path / map_src.name
    scenario.write_bytes(src.read_bytes())
    map_path.write_bytes(map_src.read_bytes().replace(b'"lane_segments"', b'"lane_\x80segments"', 1))
    err = _read_error(scenario, named=map_path)
    assert "not UTF-8" in str(err)
    map_path.write_bytes(map_src.read_bytes())
    table = pq.read_table(src)
    x = table.column("position_x").to_numpy().astype(str)
    pq.write_table(table.set_column(table.column_names.index("position_x"), "position_x", pa.array(x)), scenario)
    assert "position_x: expected numbers, got values of type str" in str(_read_error(scenario))


def test_av2_declared_frames_beyond_the_data_are_refused_before_allocating(shared_data, tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    src = next((shared_data / "av2").glob("scenario_*.parquet"))
    map_src = next((shared_data / "av2").glob("log_map_archive_*.json"))
    (tmp_path / map_src.name).write_bytes(map_src.read_bytes())
    table = pq.read_table(src)
    column = table.column_names.index("num_timestamps")  # AV2 files carry it: 110
    declared = table.set_column(column, "num_timestamps", pa.array(np.full(len(table), 10**9, np.int64)))
    pq.write_table(declared, tmp_path / src.name)
    t0 = time.perf_counter()
    assert "num_timestamps 1000000000 is more than the 2000 frames" in str(_read_error(tmp_path / src.name))
    assert time.perf_counter() - t0 < 5


def test_preprocess_skip_bad_records_a_wrongly_typed_file_and_goes_on(shared_data, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    _gpudrive(shared_data, src, lambda d: d["metadata"].__setitem__("sdc_track_index", "x"), "bad.json")
    (src / "good.json").write_bytes((shared_data / GPUDRIVE).read_bytes())
    with pytest.raises(PreprocessError, match=r"bad\.json.*sdc_track_index"):
        preprocess(src, tmp_path / "strict", workers=1, progress=False)
    report = preprocess(src, tmp_path / "cache", workers=1, skip_bad=True, progress=False)
    assert report.scenes == 1 and len(report.skipped) == 1 and "bad.json" in report.skipped[0]["input"]
    manifest = json.loads((tmp_path / "cache" / "manifest.json").read_text())
    assert "sdc_track_index" in manifest["skipped"][0]["error"]


# -------------------------------------------------------------- item 4: the scene cache
@pytest.fixture
def shard(sample_scenes, tmp_path):
    path = tmp_path / "a.smsc"
    write_shard(path, sample_scenes[3:])  # the smallest sample scene (10 tracks)
    return path


def _header(path: Path) -> tuple[dict, bytes]:
    blob = path.read_bytes()
    (n,) = struct.unpack_from("<Q", blob, len(MAGIC))
    return json.loads(blob[len(MAGIC) + 8 : len(MAGIC) + 8 + n]), blob[len(MAGIC) + 8 + n :]


def _write_header(path: Path, header: dict, data: bytes) -> None:
    text = json.dumps(header).encode()
    pad = (-(len(MAGIC) + 8 + len(text))) % 64
    path.write_bytes(MAGIC + struct.pack("<Q", len(text) + pad) + text + b" " * pad + data)


@pytest.mark.parametrize("tamper, expected", [
    (lambda h: h["scenes"][0]["arrays"]["tracks.position"].__setitem__(0, "<f8"), "has dtype '<f8', expected '<f4'"),
    (lambda h: h["scenes"][0]["arrays"]["tracks.ids"].__setitem__(0, "|O"), "has dtype '|O'"),
    (lambda h: h["scenes"][0]["arrays"]["tracks.heading"].__setitem__(2, 10**12), "runs past the end of the file"),
    # the 10-track scene's [10, 91] headings declared transposed (the same bytes): a wrong shape, not wrong data
    (lambda h: h["scenes"][0]["arrays"]["tracks.heading"].__setitem__(1, [91, 10]), "Tracks.heading has shape (91, 10)"),
    (lambda h: h["scenes"][0]["meta"].__setitem__("sdc_index", 999), "sdc_index 999 outside"),
    (lambda h: h["scenes"][0]["meta"].__setitem__("current_frame", "10"), "current_frame: expected an integer"),
    (lambda h: h["scenes"][0]["arrays"].pop("tracks.valid"), "missing or unknown: ['tracks.valid']"),
])
def test_tampered_shard_headers_are_named_not_returned_as_data(shard, tamper, expected):
    header, data = _header(shard)
    tamper(header)
    _write_header(shard, header, data)
    err = _read_error(shard)
    assert expected in str(err) and err.record == 0


def test_truncated_shard_is_one_named_error_without_a_buffer_error(shard):
    shard.write_bytes(shard.read_bytes()[:-3000])
    err = _read_error(shard)
    assert "runs past the end of the file" in str(err)


def _cache_of(out: Path, *sources: Path) -> Path:
    preprocess(list(sources), out, workers=1, progress=False)
    return out


@pytest.fixture
def second_scene_file(sample_scenes, tmp_path) -> Path:
    """The second sample scene (sumo-7-000000-01) alone in a scene file: another input than ``sample_scene_file``."""
    path = tmp_path / "other" / "sumo-7-000000-01.smsc"
    path.parent.mkdir()
    write_shard(path, sample_scenes[1:2])
    return path


def test_manifest_entry_outside_the_cache_folder_is_refused(sample_scene_file, tmp_path):
    cache = _cache_of(tmp_path / "c", sample_scene_file)
    manifest = json.loads((cache / "manifest.json").read_text())
    outside = tmp_path / "elsewhere.smsc"
    outside.write_bytes((cache / manifest["shards"][0]["file"]).read_bytes())
    for name in (str(outside), "../elsewhere.smsc"):
        manifest["shards"][0]["file"] = name
        (cache / "manifest.json").write_text(json.dumps(manifest))
        with pytest.raises(ScenarioReadError, match="not a plain file name inside the cache folder"):
            SceneCache(cache)


def test_manifest_ids_are_checked_against_the_shards(sample_scene_file, tmp_path):
    cache = _cache_of(tmp_path / "c", sample_scene_file)
    manifest = json.loads((cache / "manifest.json").read_text())
    manifest["shards"][0]["scenes"][0]["scenario_id"] = "someone-else"
    (cache / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ScenarioReadError, match="holds scene 'sumo-7-000000-00' where the manifest lists 'someone-else'"):
        SceneCache(cache)[0]
    manifest["shards"][0]["scenes"].append(dict(manifest["shards"][0]["scenes"][0]))
    (cache / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ScenarioReadError, match="holds 1 scenes, the manifest lists 2"):
        SceneCache(cache)[0]


def test_preprocess_over_a_cache_of_other_inputs_is_refused_and_append_keeps_both(sample_scene_file, second_scene_file, tmp_path):
    first, other = sample_scene_file, second_scene_file
    cache = _cache_of(tmp_path / "c", first)
    with pytest.raises(UsageError, match="already holds a scene cache of 1 other input"):
        preprocess([other], cache, workers=1, progress=False)
    assert [s.scenario_id for s in SceneCache(cache)] == ["sumo-7-000000-00"]  # untouched
    assert main(["preprocess", str(other), "--out", str(cache), "--quiet", "--workers", "1"]) == 2
    report = preprocess([other], cache, workers=1, progress=False, append=True)
    assert report.scenes == 2
    assert [s.scenario_id for s in SceneCache(cache)] == ["sumo-7-000000-00", "sumo-7-000000-01"]
    # rerunning with the same inputs (resume) is no conflict
    assert preprocess([first, other], cache, workers=1, progress=False).files_done_before == 2


# ------------------------------------------------------------ item 5: memory and hangs
def _gzip_record_declaring(path: Path, length: int, payload: bytes) -> None:
    from smart_marl.readers.tfrecord import masked_crc32c

    head = struct.pack("<Q", length)
    with gzip.open(path, "wb") as f:
        f.write(head + struct.pack("<I", masked_crc32c(head)) + payload)


def test_gzip_tfrecord_declaring_a_huge_record_is_refused_before_reading_it(tmp_path):
    path = tmp_path / "bomb.tfrecord.gz"
    _gzip_record_declaring(path, 2**30, b"\0" * (8 << 20))  # 8 MB of zeros: a few kB compressed
    code = ("import resource, sys\nfrom smart_marl.readers.tfrecord import iter_records\nfrom smart_marl.errors import ScenarioReadError\n"
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n"
            f"try:\n    list(iter_records({str(path)!r}))\nexcept ScenarioReadError as e:\n    print(e)\n"
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120).stdout.splitlines()
    assert "record 0: record length 1073741824 bytes is implausible" in out[1] and str(path) in out[1]
    assert int(out[2]) - int(out[0]) < 50_000  # kB of peak memory the read added: nothing near the declared GB
    plain = tmp_path / "plain.tfrecord"
    _gzip_record_declaring(plain, 2**20, b"")  # a plain file declaring 1 MB that holds 100 bytes
    plain.write_bytes(gzip.decompress(plain.read_bytes())[:12] + b"\0" * 100)
    err = _read_error(plain)
    assert "declares 1048576 payload bytes but only 100 bytes are left in the file" in str(err)


def test_a_fifo_given_as_input_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "scene.tfrecord"
    os.mkfifo(fifo)
    result = {}

    def read():
        try:
            list(read_scenarios(fifo))
        except SmartMarlError as exc:
            result["error"] = exc

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(10)
    if reader.is_alive():  # unblock the stuck open() so the thread can end, then fail
        with open(fifo, "wb"):
            pass
        pytest.fail("reading a FIFO blocked")
    assert "is a FIFO, not a regular file" in str(result["error"]) and str(fifo) in str(result["error"])
    assert main(["info", str(fifo)]) == 1


def test_pool_workers_die_when_their_parent_is_killed(tmp_path):
    """SIGKILL of a process running a worker_pool (as `preprocess --workers 2` does) leaves no
    orphaned worker behind."""
    code = ("import os, sys, time\nfrom smart_marl.workers import worker_pool\n"
            "pool = worker_pool(2)\nfutures = [pool.submit(time.sleep, 600) for _ in range(2)]\n"
            "time.sleep(1.0)\nprint(' '.join(str(p) for p in pool._processes), flush=True)\ntime.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    workers = [int(p) for p in proc.stdout.readline().split()]
    assert len(workers) == 2 and all(_alive(p) for p in workers)
    proc.kill()
    proc.wait(10)
    deadline = time.time() + 10
    while time.time() < deadline and any(_alive(p) for p in workers):
        time.sleep(0.1)
    assert not any(_alive(p) for p in workers), "orphaned pool workers outlived their parent"


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False
