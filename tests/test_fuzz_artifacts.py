"""Hostile model and evaluation files: mutated checkpoints (JSON, safetensors weights, vocabulary
files), training states, vocabularies and sim-agents submissions load as what they should be or
raise a SmartMarlError naming the file; nothing else escapes, and what loads passes the checks
(finite weights, a training state a run can resume from, rollouts that fit the scene).

Same mutations and budgets as tests/test_fuzz_scenes.py (tests/fuzzing.py)."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest
import torch
from hypothesis import strategies as st

from fuzzing import mutate_bytes, mutate_structure, run_fuzz, to_json
from smart_marl.errors import SmartMarlError
from smart_marl.model.checkpoint import checkpoint_paths, load_checkpoint, load_train_state, save_checkpoint
from smart_marl.tokens.vocab_io import load_motion_vocabulary, load_road_vocabulary

BUDGET = [pytest.param("default", id="default"), pytest.param("long", id="long", marks=pytest.mark.slow)]


def _files(json_path) -> list:
    """Every file of a checkpoint (JSON, weights, vocabulary pairs, training state when there is one)."""
    paths = checkpoint_paths(json_path)
    out = [paths["meta"], paths["weights"]]
    for key in ("motion_vocab", "road_vocab"):
        out += [paths[key].with_name(paths[key].name + suffix) for suffix in (".npz", ".json")]
    if paths["train_state"].is_file():
        out.append(paths["train_state"])
    return out


def _named(exc: Exception, *paths) -> None:
    assert any(os.fspath(p) in str(exc) for p in paths), f"{type(exc).__name__} names none of the files: {exc}"


def _mutate_file(data, path) -> None:
    """Mutate one file in place: its JSON structure (a .json) or its bytes."""
    raw = path.read_bytes()
    if path.suffix == ".json" and data.draw(st.booleans(), label="structural?"):
        path.write_text(to_json(mutate_structure(data, json.loads(raw))))
    else:
        path.write_bytes(mutate_bytes(data, raw))


@pytest.fixture(scope="module")
def trained_checkpoint(tiny_prior, tmp_path_factory):
    """The tiny prior saved again with a training state, as `smart-marl train` saves its checkpoints."""
    from smart_marl.train import TrainConfig, make_optimizer, make_scheduler
    from smart_marl.train_state import rng_state

    ck = load_checkpoint(tiny_prior)
    cfg = TrainConfig(max_steps=10)
    optimizer = make_optimizer(ck.model, cfg)
    scheduler = make_scheduler(optimizer, cfg)
    for p in ck.model.parameters():  # one step with made-up gradients: an AdamW state with its moments and step counts
        p.grad = torch.full_like(p, 1e-3)
    optimizer.step()
    scheduler.step()
    state = {"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(), "rng": rng_state(), "step": 1}
    return save_checkpoint(tmp_path_factory.mktemp("trained") / "last", ck.model, ck.motion_vocab, ck.road_vocab, step=1,
                           train_state=state)


@pytest.mark.parametrize("budget", BUDGET)
def test_mutated_checkpoints_load_or_raise_a_named_error(trained_checkpoint, tmp_path, budget):
    originals = _files(trained_checkpoint)
    work = tmp_path / "ck"

    def check(data):
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir()
        for f in originals:
            shutil.copy(f, work / f.name)
        files = [work / f.name for f in originals if not f.name.endswith(".train_state.pt")]
        _mutate_file(data, files[data.draw(st.integers(0, len(files) - 1), label="file")])
        try:
            ck = load_checkpoint(work / trained_checkpoint.name)
        except SmartMarlError as exc:
            _named(exc, *files)
            return
        for name, tensor in ck.model.state_dict().items():
            assert not tensor.is_floating_point() or bool(torch.isfinite(tensor).all()), name

    run_fuzz(budget, check)


@pytest.mark.parametrize("budget", BUDGET)
def test_mutated_training_states_load_or_raise_a_named_error(trained_checkpoint, tmp_path, budget):
    source = checkpoint_paths(trained_checkpoint)["train_state"]
    raw = source.read_bytes()
    base = torch.load(source, weights_only=True)
    target = tmp_path / "last.train_state.pt"

    def check(data):
        if data.draw(st.booleans(), label="structural?"):
            torch.save(mutate_structure(data, base), target)
        else:
            target.write_bytes(mutate_bytes(data, raw))
        try:
            state = load_train_state(tmp_path / "last")
        except SmartMarlError as exc:
            _named(exc, target)
            return
        assert isinstance(state["step"], int) and state["step"] >= 0
        assert isinstance(state["optimizer"]["param_groups"], list) and state["rng"]["torch"].dtype == torch.uint8

    run_fuzz(budget, check)


@pytest.mark.parametrize("budget", BUDGET)
@pytest.mark.parametrize("kind", ["motion", "road"])
def test_mutated_vocabularies_load_or_raise_a_named_error(trained_checkpoint, tmp_path, kind, budget):
    paths = checkpoint_paths(trained_checkpoint)[f"{kind}_vocab"]
    originals = [paths.with_name(paths.name + suffix) for suffix in (".npz", ".json")]
    load = load_motion_vocabulary if kind == "motion" else load_road_vocabulary

    def check(data):
        for f in originals:
            shutil.copy(f, tmp_path / f.name)
        files = [tmp_path / f.name for f in originals]
        _mutate_file(data, files[data.draw(st.integers(0, 1), label="file")])
        try:
            vocab = load(tmp_path / paths.name)
        except SmartMarlError as exc:
            _named(exc, *files)
            return
        arrays = [vocab.points] if kind == "road" else [v.contour for v in vocab.types.values()]
        assert all(np.isfinite(a).all() for a in arrays)

    run_fuzz(budget, check)


def _mutate_submission(data, message) -> None:
    kind = data.draw(st.sampled_from(["drop_scene", "drop_object", "steps", "value", "object_id", "duplicate", "empty"]),
                     label="submission edit")
    rollouts = message.scenario_rollouts[0]
    scenes = rollouts.joint_scenes
    if kind == "drop_scene":
        del scenes[data.draw(st.integers(0, len(scenes) - 1)):]
    elif kind == "drop_object":
        del scenes[data.draw(st.integers(0, len(scenes) - 1))].simulated_trajectories[0]
    elif kind == "steps":
        del scenes[0].simulated_trajectories[0].center_x[data.draw(st.integers(0, 79)):]
    elif kind == "value":
        trajectory = scenes[data.draw(st.integers(0, len(scenes) - 1))].simulated_trajectories[0]
        getattr(trajectory, data.draw(st.sampled_from(["center_x", "center_y", "heading"])))[0] = data.draw(
            st.sampled_from([float("nan"), float("inf"), 1e30]))
    elif kind == "object_id":
        scenes[0].simulated_trajectories[0].object_id = data.draw(st.sampled_from([-1, 2**31 - 1, 0]))
    elif kind == "duplicate":
        message.scenario_rollouts.add().CopyFrom(rollouts)
    else:
        del message.scenario_rollouts[:]


@pytest.mark.parametrize("budget", BUDGET)
def test_mutated_submissions_score_or_raise_a_named_error(shared_data, tmp_path, budget):
    from smart_marl.metrics import align_rollouts, logged_scene
    from smart_marl.metrics.submission import check_against_scene, rollouts_from_submission
    from smart_marl.proto.womd import SimAgentsChallengeSubmission
    from smart_marl.readers import read_scenario

    source = shared_data / "womd_tfrecord" / "sim_agents_test_submission.binproto"
    raw = source.read_bytes()
    scene = logged_scene(read_scenario(shared_data / "womd_tfrecord" / "motion_data_one_scenario.tfrecord"))
    path = tmp_path / "submission.binproto"

    def check(data):
        if data.draw(st.booleans(), label="structural?"):
            message = SimAgentsChallengeSubmission.FromString(raw)
            _mutate_submission(data, message)
            path.write_bytes(message.SerializeToString())
        else:
            path.write_bytes(mutate_bytes(data, raw))
        try:
            arrays = rollouts_from_submission(path).get(scene.scenario_id)
            if arrays is None:
                return
            check_against_scene(arrays, scene, str(path), num_rollouts=32)
            rollouts = align_rollouts(scene, arrays.to_rollouts(scene.frame), str(path))  # what scoring does first
        except SmartMarlError as exc:
            _named(exc, path)
            return
        assert arrays.trajectories.shape == (32, len(scene.object_ids), 80, 4) and np.isfinite(np.stack([rollouts.x, rollouts.y, rollouts.z, rollouts.heading])).all()

    run_fuzz(budget, check)
