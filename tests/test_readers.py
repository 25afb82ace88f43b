"""read_scenarios over every real file: the format is detected per file, non-scene files are refused clearly."""

from __future__ import annotations

import numpy as np
import pytest

from smart_marl import ScenarioReadError, UnknownFormatError, detect_format, read_scenarios
from smart_marl.readers import expand_paths, format_names

SCENE_FOLDERS = {
    "womd_tfrecord": "womd",
    "scenarionet": "scenarionet",
    "smart_pkl": "smart_pkl",
    "gpudrive_json": "gpudrive_json",
    "nocturne_json": "gpudrive_json",
    "av2": "av2",
}


def test_every_format_module_is_registered():
    assert format_names() == ["scene_cache", "womd", "scenarionet", "smart_pkl", "gpudrive_json", "av2"]


@pytest.mark.parametrize("folder", sorted(SCENE_FOLDERS))
def test_every_scene_file_reads_through_read_scenarios(shared_data, folder):
    files = expand_paths(shared_data / folder)
    assert files, f"no scene files under {folder}"
    for path in files:
        assert detect_format(path) == SCENE_FOLDERS[folder]
        scenes = list(read_scenarios(path))
        assert scenes, path
        for s in scenes:
            assert s.num_tracks > 0 and s.num_frames >= 11
            assert s.road_map.num_features > 0
            pos = s.tracks.position[s.tracks.valid]
            assert np.isfinite(pos).all()
            # the local frame keeps coordinates small enough for float32
            assert np.abs(pos[:, :2]).max() < 5e3


def test_a_whole_data_folder_reads_as_one_stream(shared_data):
    scenes = list(read_scenarios([shared_data / f for f in SCENE_FOLDERS]))
    assert len(scenes) == 2 + 7 + 2 + 11 + 3 + 1
    assert len({(s.source, s.scenario_id) for s in scenes}) == len(scenes)


@pytest.mark.parametrize("name,match", [
    ("womd_tfrecord/sim_agents_test_submission.binproto", "not a scene file"),
    ("README.md", "not a scene file"),
])
def test_non_scene_files_are_refused_naming_the_file(shared_data, name, match):
    with pytest.raises(UnknownFormatError, match=match) as info:
        list(read_scenarios(shared_data / name))
    assert name.split("/")[-1] in str(info.value)


def test_missing_paths_and_empty_globs_are_errors(tmp_path):
    with pytest.raises(ScenarioReadError, match="no such file"):
        list(read_scenarios(tmp_path / "nope.tfrecord"))
    with pytest.raises(ScenarioReadError, match="matches no file"):
        list(read_scenarios(str(tmp_path / "*.tfrecord")))


def test_unknown_forced_format_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="unknown format"):
        list(read_scenarios(tmp_path, format="csv"))
