"""The smart-marl command line: info, preprocess and the demo, run as a user would."""

from __future__ import annotations

import json
import subprocess
import sys

from smart_marl.cli import main
from smart_marl.cache import write_shard
from smart_marl.synthetic import synthetic_scenario


def test_info_prints_one_json_object_per_scene(tmp_path, capsys):
    write_shard(tmp_path / "a.smsc", [synthetic_scenario(0), synthetic_scenario(1)])
    assert main(["info", str(tmp_path), "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2
    first = json.loads(lines[0])
    assert first["scenario_id"] == "synthetic-0000" and first["format"] == "scene_cache"
    assert first["tracks_per_type"] == {"vehicle": 6, "pedestrian": 2, "cyclist": 0, "other": 0}
    assert (first["lanes"], first["lanes_with_successors"], first["road_edges"], first["crosswalks"],
            first["traffic_light_frames"]) == (6, 3, 2, 1, 91)


def test_info_on_the_real_womd_file(shared_data, capsys):
    assert main(["info", str(shared_data / "womd_tfrecord" / "motion_data_one_scenario.tfrecord")]) == 0
    out = capsys.readouterr().out
    assert "637f20cafde22ff8" in out and "tracks=83" in out and "veh 70, ped 10, cyc 3" in out


def test_info_reports_a_bad_file_and_exits_1(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("this is not json")
    assert main(["info", str(bad)]) == 1
    assert "bad.json" in capsys.readouterr().err


def test_preprocess_skip_bad_reports_and_goes_on(tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    write_shard(src / "good.smsc", [synthetic_scenario(0)])
    (src / "broken.smsc").write_bytes(b"SMSC0001garbage")
    assert main(["preprocess", str(src), "--out", str(tmp_path / "strict"), "--quiet"]) == 1
    assert "broken.smsc" in capsys.readouterr().err
    assert main(["preprocess", str(src), "--out", str(tmp_path / "c"), "--skip-bad", "--quiet", "--workers", "1"]) == 0
    out = capsys.readouterr().out
    assert "1 scenes" in out and "skipped" in out and "broken.smsc" in out


def test_console_script_help_lists_the_commands():
    out = subprocess.run([sys.executable, "-m", "smart_marl.cli", "--help"], capture_output=True, text=True, check=True).stdout
    for command in ("info", "preprocess", "demo"):
        assert command in out


def test_demo_simulates_the_sample_scenes_with_the_embedded_prior(tmp_path, capsys):
    """The README's main command, as a fresh machine runs it (no ../shared/data needed)."""
    out_dir = tmp_path / "demo"
    assert main(["demo", "--out", str(out_dir), "--rollouts", "2", "--format", "gif"]) == 0
    out = capsys.readouterr().out
    assert "SMART prior: embedded" in out and "realism meta-metric" in out
    import imageio.v3 as iio

    videos = list(out_dir.glob("*_rollout.gif"))
    assert len(videos) == 1 and iio.imread(videos[0]).shape[0] == 11 + 80  # history and 16 tokens of 5 frames
    realism = json.loads((out_dir / "realism.json").read_text())
    assert set(realism) == {"prior", "constant_velocity", "log_replay"}
    assert realism["log_replay"]["min_ade"] == 0.0 and 0 < realism["prior"]["meta_metric"] < 1
