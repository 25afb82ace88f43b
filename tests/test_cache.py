"""The scene cache: exact shards, DataLoader workers, resumable atomic preprocess, bad inputs reported."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import smart_marl.cache as cache_mod
from smart_marl import read_scenarios
from smart_marl.cache import PreprocessError, SceneCache, ShardReader, preprocess, write_shard
from smart_marl.synthetic import synthetic_scenario


@pytest.fixture
def inputs(tmp_path):
    """Three input files of synthetic scenes (2 scenes each), written as cache shards."""
    folder = tmp_path / "inputs"
    folder.mkdir()
    scenes = {}
    for k in range(3):
        batch = [synthetic_scenario(seed=10 * k + j) for j in range(2)]
        write_shard(folder / f"part{k}.smsc", batch)
        scenes.update({s.scenario_id: s for s in batch})
    return folder, scenes


def test_shard_round_trip_is_exact(tmp_path):
    scenes = [synthetic_scenario(seed=s, num_frames=40 + s) for s in range(4)]
    write_shard(tmp_path / "x.smsc", scenes)
    reader = ShardReader(tmp_path / "x.smsc")
    assert len(reader) == 4
    for i, s in enumerate(scenes):
        assert reader[i].equals(s, ignore=())


def test_preprocess_then_dataloader_with_workers_reads_every_scene(inputs, tmp_path):
    folder, scenes = inputs
    report = preprocess(folder, tmp_path / "cache", workers=2, scenes_per_shard=1, progress=False)
    assert (report.files, report.scenes, report.shards) == (3, 6, 6)
    cache = SceneCache(tmp_path / "cache")
    loader = torch.utils.data.DataLoader(cache, batch_size=4, num_workers=2, collate_fn=list)
    got = [s for batch in loader for s in batch]
    assert sorted(s.scenario_id for s in got) == sorted(scenes)
    for s in got:
        assert s.equals(scenes[s.scenario_id])
    manifest = json.loads((tmp_path / "cache" / "manifest.json").read_text())
    entry = manifest["shards"][0]["scenes"][0]
    assert entry["tracks_per_type"]["vehicle"] == 6 and entry["frames"] == 91
    # a cache folder reads through read_scenarios like any source
    assert len(list(read_scenarios(tmp_path / "cache"))) == 6


def test_killed_preprocess_leaves_no_partial_shard_and_rerun_continues(inputs, tmp_path, monkeypatch):
    folder, scenes = inputs
    out = tmp_path / "cache"
    real_write = cache_mod.write_shard
    calls = {"n": 0}

    def dying_write(path, batch):
        calls["n"] += 1
        if calls["n"] == 4:  # die in the middle of the second input file
            raise KeyboardInterrupt
        return real_write(path, batch)

    monkeypatch.setattr(cache_mod, "write_shard", dying_write)
    with pytest.raises(KeyboardInterrupt):
        preprocess(folder, out, workers=1, scenes_per_shard=1, progress=False)
    # what a SIGKILL would leave behind: a temporary file
    (out / ".stale.smsc.tmp-999").write_bytes(b"partial")
    assert [p.name for p in out.glob("parts/*.json")].__len__() == 1
    for shard in out.glob("*.smsc"):
        ShardReader(shard)  # every shard on disk is whole
    monkeypatch.setattr(cache_mod, "write_shard", real_write)
    report = preprocess(folder, out, workers=1, scenes_per_shard=1, progress=False)
    assert report.files_done_before == 1 and report.scenes == 6
    assert not list(out.glob(".*.tmp-*"))
    assert sorted(s.scenario_id for s in SceneCache(out)) == sorted(scenes)


def test_a_bad_file_stops_preprocess_naming_it_unless_skip_bad(inputs, tmp_path):
    folder, scenes = inputs
    bad = folder / "broken.smsc"
    bad.write_bytes(b"SMSC0001" + b"\xff" * 40)
    with pytest.raises(PreprocessError, match="broken.smsc"):
        preprocess(folder, tmp_path / "strict", workers=1, progress=False)
    report = preprocess(folder, tmp_path / "lenient", workers=2, skip_bad=True, progress=False)
    assert report.scenes == 6
    assert len(report.skipped) == 1 and "broken.smsc" in report.skipped[0]["error"]
    manifest = json.loads((tmp_path / "lenient" / "manifest.json").read_text())
    assert manifest["skipped"][0]["input"].endswith("broken.smsc")


def test_changed_input_is_converted_again(inputs, tmp_path):
    folder, _ = inputs
    out = tmp_path / "cache"
    preprocess(folder, out, progress=False)
    write_shard(folder / "part0.smsc", [synthetic_scenario(seed=99)])
    report = preprocess(folder, out, progress=False)
    assert report.files_done_before == 2
    assert "synthetic-0099" in {s.scenario_id for s in SceneCache(out)}


def test_real_scenes_of_every_format_preprocess_exactly(shared_data, tmp_path):
    sources = [shared_data / d for d in ("womd_tfrecord", "scenarionet", "smart_pkl", "gpudrive_json", "nocturne_json", "av2")]
    direct = {}
    for src in sources:
        for s in read_scenarios(src):
            direct[(s.source, s.scenario_id)] = s
    report = preprocess(sources, tmp_path / "cache", workers=2, progress=False)
    assert report.scenes == len(direct) and not report.skipped
    cached = SceneCache(tmp_path / "cache")
    assert len(cached) == len(direct)
    for s in cached:
        assert s.equals(direct[(s.source, s.scenario_id)])
    assert np.isfinite(cached[0].tracks.position[cached[0].tracks.valid]).all()
