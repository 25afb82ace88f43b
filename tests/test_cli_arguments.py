"""Bad arguments exit 2 with one ``error:`` line naming the argument, before any work (issue 15
item 6); scenes the metrics cannot score are skipped by name, not averaged in as NaN (item 4)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from smart_marl.cache import write_shard
from test_commands_consistency import _exit_code as _run  # (exit code, stdout, stderr) of the command line


@pytest.mark.parametrize("argv, names", [
    (["info", "SRC", "--format", "nosuch"], "--format"),
    (["preprocess", "SRC", "--out", "FILE"], "--out"),
    (["preprocess", "SRC", "--out", "OUT", "--workers", "0"], "--workers"),
    (["preprocess", "SRC", "--out", "OUT", "--workers", "-1"], "--workers"),
    (["preprocess", "SRC", "--out", "OUT", "--scenes-per-shard", "0"], "--scenes-per-shard"),
    (["preprocess", "SRC", "--out", "OUT", "--format", "nosuch"], "--format"),
    (["demo", "--out", "FILE"], "--out"),
    (["demo", "--out", "OUT", "--device", "bogus"], "--device"),
    (["generate-sumo", "--scenes", "1", "--out", "FILE"], "--out"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--workers", "0"], "--workers"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--speed-weights", "1,2"], "--speed-weights: needs --speed-limits"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--speed-limits", "30,fast"], "--speed-limits"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--speed-limits", "0,50"], "--speed-limits: every value must be >= 5"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--speed-limits", "30,50", "--speed-weights", "1"],
     "--speed-weights: 1 weights for 2 speed limits"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--junction-weights", "1,2"],
     "--junction-weights: 2 weights for the 5 junction kinds"),
    (["vocab", "build", "SRC", "--out", "FILE"], "--out"),
    (["train", "--config", "smart-1m", "--out", "FILE"], "--out"),
    (["train", "--config", "smart-1m", "--device", "bogus"], "--device"),
    (["train", "--config", "smart-1m", "lr=abc", "--out", "OUT"], "lr must be a finite number"),
    (["train", "--config", "smart-1m", "batch_size=0", "--out", "OUT"], "batch_size must be at least 1"),
    (["train", "--config", "smart-1m", "max_steps=-1", "--out", "OUT"], "max_steps must be at least 1"),
    (["train", "--config", "smart-1m", "max_step=3", "--out", "OUT"], "unknown training config key"),
    (["train", "--config", "smart-1m", "device=bogus", "--out", "OUT"], "'bogus' is not a torch device"),
    (["train", "--config", "smart-1m", "out_dir=FILE"], "exists and is not a folder"),
    (["eval", "--scenes", "SRC", "--policy", "random", "--device", "bogus"], "--device"),
    (["eval", "--scenes", "SRC", "--policy", "random", "--format", "nosuch"], "--format"),
    (["eval", "--scenes", "SRC", "--policy", "random", "--any-rollout-count"], "--any-rollout-count"),
    (["eval", "--scenes", "SRC", "--policy", "random", "--top-k", "10"], "--top-k only applies to --policy prior"),
    (["eval", "--scenes", "SRC", "--policy", "prior", "--top-k", "-1"], "--top-k"),
    (["eval", "--scenes", "SRC", "--policy", "prior", "--temperature", "0"], "--temperature"),
    (["eval", "--scenes", "SRC", "--policy", "prior", "--temperature", "nan"], "--temperature"),
    (["info", "EMPTY"], "no scene file in this folder"),
    (["whatif", "SRC", "--script", "SRC", "--out", "FILE"], "--out"),
    (["finetune", "--config", "tiny", "--out", "FILE"], "--out"),
    (["finetune", "--config", "tiny", "--device", "bogus"], "--device"),
    (["finetune", "--config", "tiny", "lr=abc", "--print-config"], "fine-tuning config: lr must be a finite number"),
    (["finetune", "--config", "tiny", "iterations=0", "--print-config"], "fine-tuning config: iterations must be at least 1"),
    (["whatif", "SRC", "--script", "SRC", "--out", "OUT", "--steps", "1000"], "--steps: must be at most 64"),
    (["whatif", "SRC", "--script", "SRC", "--out", "OUT", "--rollouts", "0"], "--rollouts"),
], ids=lambda a: " ".join(a) if isinstance(a, list) else None)
def test_bad_arguments_exit_2_with_one_error_line_before_any_work(argv, names, tmp_path, capsys):
    (tmp_path / "FILE").write_text("a file, not a folder")
    (tmp_path / "EMPTY").mkdir()
    argv = [str(tmp_path / a) if a in ("OUT", "SRC", "FILE", "EMPTY") else
            a.replace("FILE", str(tmp_path / "FILE")) for a in argv]
    code, _, err = _run(argv, capsys)
    assert code == 2, err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and errors[0].startswith(f"smart-marl {argv[0]}") and names in errors[0], err
    assert not (tmp_path / "OUT").exists()
    assert (tmp_path / "FILE").read_text() == "a file, not a folder"


# ----------------------------------------------------------------- eval over a folder
def _scene_without_evaluated_agents(scenario, scenario_id="no-evaluated-agent", frozen=False):
    """``scenario`` without a self-driving car or tracks to predict; ``frozen``: every track also stands at its
    current-frame position all along, so no agent moves the 2 m the windows' rule asks for."""
    from smart_marl.scenario import Scenario

    arrays, meta = scenario.to_arrays()
    arrays = {**arrays, "predict_indices": np.zeros(0, np.int64), "predict_difficulty": np.zeros(0, np.int8)}
    if frozen:
        position = arrays["tracks.position"]
        arrays = {**arrays, "tracks.position": np.repeat(position[:, 10:11], position.shape[1], axis=1)}
    return Scenario.from_arrays(arrays, {**meta, "sdc_index": -1, "scenario_id": scenario_id})


def test_metrics_name_a_scene_without_evaluated_agents_instead_of_returning_nan(sample_scenes):
    """Without an SDC or tracks to predict: eval's window scores the scene around an anchor; the plain inputs, and a
    window where no agent moves 2 m, name it instead."""
    from smart_marl.metrics import SceneNotScorableError, logged_scene
    from smart_marl.metrics.windows import scene_windows

    scene = _scene_without_evaluated_agents(sample_scenes[0])
    with pytest.raises(SceneNotScorableError, match="no-evaluated-agent: no agent to evaluate"):
        logged_scene(scene)  # the plain inputs evaluate exactly the SDC and the tracks to predict: none here
    # eval's window evaluates the agent that moves farthest (ties: the lower id) and up to 8 more nearest to it, each
    # a vehicle, pedestrian or cyclist valid now and on >= 40 of the 80 future frames that moves >= 2 m
    [window] = scene_windows(scene)
    tr = window.scenario.tracks
    now = tr.position[:, 10, :2].astype(np.float64)
    travel = np.where(tr.valid, np.linalg.norm(tr.position[..., :2] - now[:, None], axis=-1), 0.0).max(axis=1)
    eligible = np.flatnonzero(np.isin(tr.types, [0, 1, 2]) & tr.valid[:, 10] & (tr.valid[:, 11:].sum(axis=1) >= 40)
                              & (travel >= 2.0))
    assert len(eligible) > 9  # enough for the cap to bite
    anchor = min(eligible, key=lambda i: (-travel[i], tr.ids[i]))
    others = sorted((i for i in eligible if i != anchor), key=lambda i: (np.linalg.norm(now[i] - now[anchor]), tr.ids[i]))[:8]
    logged = window.logged()
    assert sorted(logged.evaluated_ids.tolist()) == sorted(int(tr.ids[i]) for i in [anchor, *others])
    assert len(logged.evaluated_ids) == 9
    frozen = _scene_without_evaluated_agents(sample_scenes[0], frozen=True)
    with pytest.raises(SceneNotScorableError, match="no-evaluated-agent: no agent to evaluate: no self-driving car, no track "
                                                    "to predict, and no agent for the rule to anchor on"):
        scene_windows(frozen)[0].logged()


def test_eval_over_a_folder_skips_unscorable_scenes_by_name_and_averages_the_rest(sample_scenes, tmp_path, capsys):
    scenario = sample_scenes[0]
    folder = tmp_path / "scenes"
    folder.mkdir()
    write_shard(folder / "a.smsc", [scenario])
    write_shard(folder / "short.smsc", [scenario.window(0, 11)])  # an 11-frame scene
    write_shard(folder / "anchored.smsc", [_scene_without_evaluated_agents(scenario, "anchored")])  # scored by the rule
    write_shard(folder / "none.smsc", [_scene_without_evaluated_agents(scenario, frozen=True)])  # no one moves: skipped
    code, out, err = _run(["eval", "--scenes", str(folder), "--policy", "constant_velocity", "--rollouts", "2", "--json"],
                          capsys)
    assert code == 0, err
    result = json.loads(out)
    assert result["num_scenarios"] == 2 and math.isfinite(result["meta_metric"])
    skipped = {entry["scenario_id"]: entry for entry in result["skipped"]}
    assert set(skipped) == {scenario.scenario_id, "no-evaluated-agent"}
    assert "need 91 frames" in skipped[scenario.scenario_id]["reason"] and skipped[scenario.scenario_id]["path"].endswith("short.smsc")
    assert "no agent to evaluate: no self-driving car, no track to predict" in skipped["no-evaluated-agent"]["reason"]
    assert skipped["no-evaluated-agent"]["path"].endswith("none.smsc")
    warnings = [line for line in err.splitlines() if "warning:" in line]
    assert any("short.smsc: skipped" in w for w in warnings) and any("none.smsc: skipped" in w for w in warnings)
    assert not any("anchored" in w for w in warnings)


def test_eval_stops_on_an_unreadable_file_unless_skip_bad(sample_scene_file, tmp_path, capsys):
    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / "a.smsc").write_bytes(sample_scene_file.read_bytes())
    (folder / "b.json").write_text('{"objects": [{"position": []}], "roads": []}')
    argv = ["eval", "--scenes", str(folder), "--policy", "constant_velocity", "--rollouts", "2", "--json"]
    code, _, err = _run(argv, capsys)
    assert code == 1 and "b.json, record objects[0]: missing field 'heading'" in err
    code, out, err = _run([*argv, "--skip-bad"], capsys)
    assert code == 0 and json.loads(out)["num_scenarios"] == 1
    assert "warning: skipped the bad file" in err and "b.json" in err


@pytest.fixture(scope="module")
def random_submission(sample_scenes) -> bytes:
    """A submission of 32 random rollouts of the first sample scene (what the eval command scores)."""
    from smart_marl.metrics.baselines import random_rollouts
    from smart_marl.metrics.submission import ScenarioRolloutArrays, build_submission

    scenario = sample_scenes[0]
    ro = random_rollouts(scenario, 32)
    arrays = ScenarioRolloutArrays(scenario.scenario_id, ro.object_ids, ro.to_source(scenario.frame).astype(np.float32))
    return build_submission([arrays]).SerializeToString()


@pytest.mark.parametrize("count", [1, 31, 40])
def test_eval_refuses_a_submission_without_32_rollouts_unless_asked(random_submission, sample_scene_file, tmp_path, capsys, count):
    from smart_marl.proto.womd import SimAgentsChallengeSubmission

    message = SimAgentsChallengeSubmission.FromString(random_submission)
    scenes = message.scenario_rollouts[0].joint_scenes
    assert len(scenes) == 32
    if count < 32:
        del scenes[count:]
    else:
        for k in range(count - 32):
            scenes.add().CopyFrom(scenes[k])
    path = tmp_path / "sub.binproto"
    path.write_bytes(message.SerializeToString())
    argv = ["eval", "--scenes", str(sample_scene_file), "--submission", str(path), "--json", "--rules", "2024"]
    code, _, err = _run(argv, capsys)
    assert code == 1 and f"{count} rollouts (joint scenes), WOSAC requires 32" in err and str(path) in err
    code, out, err = _run([*argv, "--any-rollout-count"], capsys)
    assert code == 0 and math.isfinite(json.loads(out)["meta_metric"])
    assert f"{count} rollouts instead of WOSAC's 32" in err
