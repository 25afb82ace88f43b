"""Checkpoint selection of a fine-tuning run on validation scenes (agents/select_policy.py, issue 58): every
checkpoint scored alone on the same scenes and seeds, the best by goal rate less collision and offroad rates (the
earliest among equals), its files copied to ``policy_best``, and validation scenes that the run trained or is tested
on refused by id. The prior is the tests' small random model (tests/test_finetune.py's setup)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("pettingzoo", reason="the env extra (pettingzoo) is not installed")
pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from agents.finetune import FinetuneError, evaluate_finetuned, finetune, load_finetune_config, load_policy  # noqa: E402
from agents.policy import FinetunedTensorPolicy  # noqa: E402
from agents.select_policy import BEST, run_checkpoints, score, select_policy  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py

WOMD, GPUDRIVE, NOCTURNE = "womd_tfrecord/*.tfrecord", "gpudrive_json", "nocturne_json"


@pytest.fixture(scope="module")
def run(shared_data, womd_vocab, save_tiny_prior, tmp_path_factory):
    """Three tiny iterations on the two WOMD scenes, a checkpoint after each, tested (eval_scenes) on GPUDrive."""
    out = tmp_path_factory.mktemp("select")
    cfg = load_finetune_config("tiny", {"scenes": str(shared_data / WOMD), "prior": str(save_tiny_prior(womd_vocab)),
                                        "out_dir": str(out), "tensorboard": False, "eval_scenes": str(shared_data / GPUDRIVE),
                                        "eval_num_scenes": 1, "reference_top_k": 5, "top_k": 5, "iterations": 3,
                                        "frames_per_batch": 32, "minibatch_size": 32, "ppo_epochs": 1, "eval_episodes": 0,
                                        "checkpoint_every": 1})
    finetune(cfg)
    return out


def test_every_checkpoint_is_scored_alone_on_the_validation_scenes_and_the_best_is_kept(run, shared_data):
    val = str(shared_data / NOCTURNE)
    assert [p.stem for p in run_checkpoints(run)] == ["policy_0001", "policy_0002", "policy_0003"]  # last = 0003
    selection = select_policy(run, val, episodes=2, num_scenes=1)
    rows = selection["checkpoints"]
    assert [r["checkpoint"] for r in rows] == ["policy_0001", "policy_0002", "policy_0003"]
    assert [r["iteration"] for r in rows] == [1, 2, 3] and all(r["seeds"] == rows[0]["seeds"] for r in rows)
    for r in rows:
        assert r["score"] == pytest.approx(r["row"]["goal_rate"] - r["row"]["collision_rate"] - r["row"]["offroad_rate"])
    top = max(r["score"] for r in rows)
    assert selection["best"] == next(r["checkpoint"] for r in rows if r["score"] == top)  # the earliest of the best
    # the row is the policy's own evaluation on those scenes and seeds, recomputed independently
    cfg, net, _ = load_policy(run / "checkpoints" / "policy_0002")
    again = evaluate_finetuned(load_finetune_config(cfg.to_dict(), {"eval_scenes": val, "eval_num_scenes": 1}), net,
                               episodes=2, baselines=False)
    numbers = {k: v for k, v in rows[1]["row"].items() if isinstance(v, (int, float))}
    assert {k: again["rows"][FinetunedTensorPolicy.name][k] for k in numbers} == pytest.approx(numbers)
    # policy_best is the chosen checkpoint's files, and the selection is written beside them
    ckpt = run / "checkpoints"
    for ext in ("json", "safetensors"):
        assert (ckpt / f"{BEST}.{ext}").read_bytes() == (ckpt / f"{selection['best']}.{ext}").read_bytes()
    assert load_policy(ckpt / BEST)[2]["iteration"] == selection["best_iteration"]
    assert json.loads((ckpt / "selection.json").read_text())["best"] == selection["best"]


def test_validation_scenes_the_run_trained_or_is_tested_on_are_refused_by_id(run, shared_data):
    with pytest.raises(FinetuneError, match="run's training scenes"):
        select_policy(run, str(shared_data / WOMD), episodes=1)
    with pytest.raises(FinetuneError, match=r"run's test \(eval_scenes\) scenes"):
        select_policy(run, str(shared_data / GPUDRIVE), episodes=1)


def test_a_run_without_checkpoints_is_refused_by_folder(tmp_path):
    (tmp_path / "checkpoints").mkdir()
    with pytest.raises(FinetuneError, match="no policy checkpoint"):
        run_checkpoints(tmp_path)


def test_the_score_is_goal_rate_less_collision_and_offroad_rates():
    assert score({"goal_rate": 0.5, "collision_rate": 0.1, "offroad_rate": 0.05}) == pytest.approx(0.35)


def test_the_select_command_prints_the_scores_and_refuses_half_its_arguments(run, shared_data, capsys):
    from smart_marl.cli import main

    assert main(["finetune", "--select", str(run), "--val-scenes", str(shared_data / NOCTURNE), "--episodes", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["best"] in {"policy_0001", "policy_0002", "policy_0003"} and len(out["checkpoints"]) == 3
    assert main(["finetune", "--select", str(run)]) == 2
    assert "go together" in capsys.readouterr().err
    assert main(["finetune", "--select", str(run), "--val-scenes", str(shared_data / NOCTURNE), "--config", "tiny"]) == 2
    assert "--select takes only" in capsys.readouterr().err
    assert main(["finetune", "--select", str(run), "--val-scenes", str(shared_data / NOCTURNE), "--print-config"]) == 2
    assert "--select takes only" in capsys.readouterr().err


def test_a_selection_run_again_scores_only_the_checkpoints_it_has_not(run, shared_data, tmp_path, monkeypatch):
    import shutil

    import agents.select_policy as sp

    copy = tmp_path / "run"
    shutil.copytree(run / "checkpoints", copy / "checkpoints")
    val = str(shared_data / NOCTURNE)
    calls = []
    real = sp.evaluate_finetuned
    monkeypatch.setattr(sp, "evaluate_finetuned", lambda *a, **k: calls.append(1) or real(*a, **k))
    first = select_policy(copy, val, episodes=1, num_scenes=1)
    assert len(calls) == 3
    again = select_policy(copy, val, episodes=1, num_scenes=1)  # nothing new: every row kept
    assert len(calls) == 3 and again["checkpoints"] == first["checkpoints"] and again["best"] == first["best"]
    # a new checkpoint (the run went on) is scored, the others kept; a changed one is scored again
    ckpt = copy / "checkpoints"
    meta = json.loads((ckpt / "policy_0003.json").read_text())
    (ckpt / "policy_0004.json").write_text(json.dumps({**meta, "iteration": 4}))
    shutil.copyfile(ckpt / "policy_0003.safetensors", ckpt / "policy_0004.safetensors")
    (ckpt / "policy_0001.json").write_text(json.dumps({**json.loads((ckpt / "policy_0001.json").read_text()), "note": "edited"}))
    grown = select_policy(copy, val, episodes=1, num_scenes=1)
    assert len(calls) == 5 and [r["checkpoint"] for r in grown["checkpoints"]] == [f"policy_000{i}" for i in (1, 2, 3, 4)]
    assert grown["checkpoints"][3]["row"] == first["checkpoints"][2]["row"]  # the same weights score the same
    # other settings, or a selection file that does not read: every checkpoint scored again
    select_policy(copy, val, episodes=2, num_scenes=1)
    assert len(calls) == 9
    (ckpt / "selection.json").write_text("{not json")
    select_policy(copy, val, episodes=2, num_scenes=1)
    assert len(calls) == 13
