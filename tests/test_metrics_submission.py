"""Sim-agents submission files <-> rollouts, and the ``smart-marl eval`` command."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smart_marl.cli import main
from smart_marl.metrics import RolloutError, logged_scene
from smart_marl.metrics.baselines import random_rollouts
from smart_marl.metrics.submission import (ScenarioRolloutArrays, build_submission, check_against_scene,
                                           rollouts_from_submission, write_rollouts)
from smart_marl.readers.submission import read_submission
from smart_marl.synthetic import synthetic_scenario


def test_submission_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    a = ScenarioRolloutArrays("scene-a", np.array([5, 3, 9]), rng.normal(0, 1000, (4, 3, 80, 4)).astype(np.float32),
                              rng.uniform(1, 5, (3, 3)).astype(np.float32))
    b = ScenarioRolloutArrays("scene-b", np.array([1]), rng.normal(0, 10, (2, 1, 80, 4)).astype(np.float32))
    path = tmp_path / "sub.binproto"
    write_rollouts(path, [a, b], account_name="me", unique_method_name="m")
    back = rollouts_from_submission(path)
    assert list(back) == ["scene-a", "scene-b"]
    for orig in (a, b):
        got = back[orig.scenario_id]
        np.testing.assert_array_equal(got.object_ids, orig.object_ids)
        assert got.trajectories.dtype == np.float32
        np.testing.assert_array_equal(got.trajectories, orig.trajectories)
    np.testing.assert_array_equal(back["scene-a"].sizes, a.sizes)
    assert back["scene-b"].sizes is None
    msg = read_submission(path)
    assert msg.submission_type == 1 and msg.account_name == "me"
    # the message built in memory serializes to the same bytes as the file
    assert build_submission([a, b], account_name="me", unique_method_name="m").SerializeToString() == path.read_bytes()


def test_official_test_submission_reads_as_32_rollouts_of_50_agents(shared_data):
    subs = rollouts_from_submission(shared_data / "womd_tfrecord" / "sim_agents_test_submission.binproto")
    arr = subs["637f20cafde22ff8"]
    assert arr.trajectories.shape == (32, 50, 80, 4)
    assert len(np.unique(arr.object_ids)) == 50


def test_submission_checks_name_file_scenario_and_object(tmp_path):
    scenario = synthetic_scenario(0)
    scene = logged_scene(scenario)
    ro = random_rollouts(scenario, 2)
    src = ro.to_source(scenario.frame).astype(np.float32)
    ok = ScenarioRolloutArrays(scenario.scenario_id, ro.object_ids, src)
    check_against_scene(ok, scene, "f.binproto", num_rollouts=2)
    with pytest.raises(RolloutError, match=r"f\.binproto: scenario synthetic-0000: trajectories have 79 steps"):
        check_against_scene(ScenarioRolloutArrays(ok.scenario_id, ok.object_ids, src[:, :, :79]), scene, "f.binproto")
    with pytest.raises(RolloutError, match=rf"f\.binproto: scenario synthetic-0000: simulated agent {ro.object_ids[0]} is missing"):
        check_against_scene(ScenarioRolloutArrays(ok.scenario_id, ok.object_ids[1:], src[:, 1:]), scene, "f.binproto")
    extra = ScenarioRolloutArrays(ok.scenario_id, np.concatenate([ok.object_ids, [4242]]), np.concatenate([src, src[:, :1]], 1))
    with pytest.raises(RolloutError, match="object 4242 is not a simulated agent"):
        check_against_scene(extra, scene, "f.binproto")
    # a joint scene with other objects than the first one
    path = tmp_path / "bad.binproto"
    msg = build_submission([ok])
    del msg.scenario_rollouts[0].joint_scenes[1].simulated_trajectories[0]
    path.write_bytes(msg.SerializeToString())
    with pytest.raises(RolloutError, match=rf"bad\.binproto: scenario synthetic-0000: joint scene 1 .*object {ro.object_ids[0]} is missing"):
        rollouts_from_submission(path)


def test_eval_command_scores_a_written_policy_submission_identically(tmp_path, capsys, sample_scene_file):
    scenes = str(sample_scene_file)
    sub = tmp_path / "cv.binproto"
    assert main(["eval", "--scenes", scenes, "--policy", "random", "--rollouts", "4", "--seed", "1", "--json",
                 "--rules", "2024", "--write-submission", str(sub)]) == 0
    first = json.loads(capsys.readouterr().out)
    assert main(["eval", "--scenes", scenes, "--submission", str(sub), "--json", "--rules", "2024", "--any-rollout-count"]) == 0
    second = json.loads(capsys.readouterr().out)
    assert set(first) == {"meta_metric", "kinematic", "interactive", "map_based", "min_ade", "likelihoods", "num_scenarios", "rules",
                          "skipped"}
    assert first["skipped"] == []
    assert first["rules"] == "2024" and first["num_scenarios"] == 1 and "traffic_light_violation" not in first["likelihoods"]
    for k in ("meta_metric", "kinematic", "interactive", "map_based", "min_ade"):
        assert second[k] == pytest.approx(first[k], abs=1e-12)


def test_eval_command_table_and_errors(tmp_path, capsys, shared_data):
    womd = shared_data / "womd_tfrecord"
    assert main(["eval", "--scenes", str(womd / "motion_data_one_scenario.tfrecord"),
                 "--submission", str(womd / "sim_agents_test_submission.binproto"), "--rules", "2025"]) == 0
    out = capsys.readouterr().out
    assert "traffic_light_violation" in out and "realism meta-metric" in out and "minADE" in out
    # the submission has no rollouts for the other scene: a named error, exit code 1
    assert main(["eval", "--scenes", str(womd / "womd_scenario_input.tfrecord"),
                 "--submission", str(womd / "sim_agents_test_submission.binproto")]) == 1
    assert "no rollouts for scenario ee519cf571686d19" in capsys.readouterr().err


def test_eval_policy_prior_scores_the_rollout_engines_rollouts(sample_scene_file, tiny_prior, capsys):
    import json

    from smart_marl.cli import main
    from smart_marl.commands.eval import prior_rollouts
    from smart_marl.metrics import logged_scene
    from smart_marl.model.checkpoint import load_checkpoint
    from smart_marl.readers import read_scenario

    path = sample_scene_file
    assert main(["eval", "--scenes", str(path), "--policy", "prior", "--checkpoint", str(tiny_prior),
                 "--rollouts", "4", "--rules", "2024", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["rules"] == "2024" and out["num_scenarios"] == 1 and 0.0 < out["meta_metric"] < 1.0
    # the rollouts cover exactly the agents valid at the current frame, in the scene's local frame
    scenario = read_scenario(path)
    rollouts = prior_rollouts(load_checkpoint(tiny_prior), scenario, 2, seed=0)
    scene = logged_scene(scenario)
    valid_now = scenario.tracks.ids[scenario.tracks.valid[:, scenario.current_frame]]
    assert sorted(rollouts.object_ids.tolist()) == sorted(valid_now.tolist())
    assert rollouts.x.shape == (2, len(valid_now), 80) and scene.scenario_id == scenario.scenario_id
    first = np.hypot(rollouts.x[:, :, 0], rollouts.y[:, :, 0])
    assert np.all(np.isfinite(first)) and first.max() < 5e3


def test_eval_policy_prior_samples_with_the_given_top_k(sample_scene_file, tiny_prior, capsys):
    """``--top-k 1`` drives by argmax, so the seed changes nothing; the default top-k samples, and
    ``--temperature`` changes what it samples."""
    import json

    from smart_marl.cli import main
    from smart_marl.commands.eval import prior_rollouts
    from smart_marl.model.checkpoint import load_checkpoint
    from smart_marl.readers import read_scenario

    path = sample_scene_file

    def scores(*flags):
        assert main(["eval", "--scenes", str(path), "--policy", "prior", "--checkpoint", str(tiny_prior), "--rollouts", "2",
                     "--rules", "2024", "--json", *flags]) == 0
        return json.loads(capsys.readouterr().out)["likelihoods"]

    assert scores("--top-k", "1", "--temperature", "0.5", "--seed", "0") == scores("--top-k", "1", "--temperature", "0.5", "--seed", "1")
    assert scores("--seed", "0") != scores("--temperature", "0.25", "--seed", "0")
    scenario = read_scenario(path)
    prior = load_checkpoint(tiny_prior)
    argmax = [prior_rollouts(prior, scenario, 2, seed=s, top_k=1) for s in (0, 1)]
    sampled = [prior_rollouts(prior, scenario, 2, seed=s) for s in (0, 1)]
    assert np.array_equal(argmax[0].x, argmax[1].x) and np.array_equal(argmax[0].x[0], argmax[0].x[1])
    assert not np.array_equal(sampled[0].x, sampled[1].x)
