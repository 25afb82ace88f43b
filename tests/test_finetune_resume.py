"""Resuming a fine-tuning run (agents.finetune_state): a run stopped after an iteration and started again
with the same config goes on from there and ends at the uninterrupted run's policy, bit for bit, with the
same log; a saved state that is not this run's (another config, a tampered or foreign file) is refused
naming the file and the field, before anything is trained or written. The kill test
(tests/test_finetune_kill.py, slow) does the same across processes with SIGKILL."""

from __future__ import annotations

import csv
import json

import pytest
import torch
from safetensors.torch import load_file, save_file

pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from agents.finetune import finetune  # noqa: E402
from agents.finetune_config import FinetuneError, load_finetune_config  # noqa: E402
from agents.finetune_state import state_paths  # noqa: E402
from agents.policy import read_policy  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py

# the prior drives the background (its sampler is what a resume must restore), 4 scenes through 2 rows
SETTINGS = ["background=prior", "num_envs=2", "num_scenes=4", "frames_per_batch=128", "minibatch_size=64", "ppo_epochs=1",
            "eval_episodes=0", "tensorboard=false", "checkpoint_every=1"]


def run(out_dir, iterations: int, *extra: str):
    return finetune(load_finetune_config("tiny", [*SETTINGS, f"iterations={iterations}", f"out_dir={out_dir}", *extra]))


def log(out_dir) -> list[dict]:
    with open(out_dir / "finetune.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "seconds"} for r in csv.DictReader(f)]


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """The uninterrupted run of 4 iterations."""
    out = tmp_path_factory.mktemp("whole")
    run(out, 4)
    return out


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """A run of the same config stopped after its second iteration (iterations=2: the one field besides
    the evaluation and logging that a resumed run may change)."""
    out = tmp_path_factory.mktemp("stopped")
    run(out, 2)
    return out


def assert_same_policies(a, b, names):
    for name in names:
        _, expected = read_policy(a / "checkpoints" / name)
        _, got = read_policy(b / "checkpoints" / name)
        differ = [k for k in expected if not torch.equal(expected[k], got[k])]
        assert not differ, f"{name}: differs from the uninterrupted run's in {differ}"


def test_a_resumed_run_ends_at_the_uninterrupted_runs_policy_and_log(whole, stopped, tmp_path, capsys):
    out = tmp_path / "resumed"
    out.mkdir()
    for f in stopped.rglob("*"):  # a copy: the stopped run serves the other tests too
        if f.is_file():
            (out / f.relative_to(stopped)).parent.mkdir(parents=True, exist_ok=True)
            (out / f.relative_to(stopped)).write_bytes(f.read_bytes())
    first = (out / "checkpoints" / "policy_0002.safetensors").stat().st_mtime_ns
    result = run(out, 4)
    assert "resuming" in capsys.readouterr().out
    assert [int(r["iteration"]) for r in result.history] == [1, 2, 3, 4]
    assert (out / "checkpoints" / "policy_0002.safetensors").stat().st_mtime_ns == first, "iteration 2 was trained again"
    assert_same_policies(whole, out, ["policy_0002", "policy_0003", "policy_0004", "policy_last"])
    assert log(out) == log(whole)
    assert json.loads(state_paths(out, 0)[0].read_text())["iteration"] == 4


def test_a_finished_run_started_again_trains_nothing_and_keeps_its_policy(whole, tmp_path):
    before = {p.name: p.read_bytes() for p in (whole / "checkpoints").glob("policy_000*.safetensors")}
    result = run(whole, 4)
    assert [int(r["iteration"]) for r in result.history] == [1, 2, 3, 4]
    assert {p.name: p.read_bytes() for p in (whole / "checkpoints").glob("policy_000*.safetensors")} == before
    assert_same_policies(whole, whole, ["policy_last"])


def snapshot(folder) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.mark.parametrize("change, named", [("lr=0.01", "lr=0.01"), ("seed=5", "seed=5"), ("hidden=32", "hidden=32")])
def test_a_state_of_another_config_is_refused_naming_the_field_and_nothing_is_written(stopped, change, named):
    before = snapshot(stopped)
    with pytest.raises(FinetuneError, match="cannot resume") as info:
        run(stopped, 3, change)
    assert named in str(info.value) and "resume.json" in str(info.value)
    assert snapshot(stopped) == before


def test_a_state_past_the_runs_iterations_is_refused(whole):
    before = snapshot(whole)
    with pytest.raises(FinetuneError, match="past this run's iterations=2"):
        run(whole, 2)
    assert snapshot(whole) == before


def tampered(stopped, tmp_path, edit_meta=None, edit_tensors=None):
    out = tmp_path / "tampered"
    for f in stopped.rglob("*"):
        if f.is_file():
            (out / f.relative_to(stopped)).parent.mkdir(parents=True, exist_ok=True)
            (out / f.relative_to(stopped)).write_bytes(f.read_bytes())
    meta_path, tensor_path = state_paths(out, 0)
    if edit_meta:
        meta = json.loads(meta_path.read_text())
        edit_meta(meta)
        meta_path.write_text(json.dumps(meta))
    if edit_tensors:
        tensors = load_file(str(tensor_path))
        edit_tensors(tensors)
        save_file(tensors, str(tensor_path))
    return out


def _nan_weight(t):
    key = next(k for k in t if k.startswith("loss.actor_network_params") and t[k].is_floating_point())
    t[key] = torch.full_like(t[key], float("nan"))


def _wrong_moment_shape(t):
    key = next(k for k in t if k.endswith(".exp_avg"))
    t[key] = torch.zeros(3)


@pytest.mark.parametrize("edit_meta, edit_tensors, named", [
    (lambda m: m.update(format="something"), None, "not a smart-marl-finetune-state"),
    (lambda m: m.update(iteration=-1), None, "'iteration'"),
    (lambda m: m.update(world=2), None, "process 0 of 2"),
    (lambda m: m["pool"].update(queue=[10**9]), None, "outside this pool"),
    (lambda m: m["rng"]["python"].update(gauss_next="x"), None, "gauss_next"),
    (None, _nan_weight, "NaN"),
    (None, _wrong_moment_shape, "shape"),
    (None, lambda t: t.pop("rng.torch"), "rng.torch"),
])
def test_a_tampered_state_is_refused_naming_the_file(stopped, tmp_path, edit_meta, edit_tensors, named):
    out = tampered(stopped, tmp_path, edit_meta, edit_tensors)
    before = snapshot(out)
    with pytest.raises(FinetuneError, match="cannot resume") as info:
        run(out, 4)
    assert named in str(info.value) and str(out / "checkpoints") in str(info.value)
    assert snapshot(out) == before


def test_a_state_file_that_is_not_json_or_safetensors_is_refused(stopped, tmp_path):
    out = tampered(stopped, tmp_path)
    meta_path, tensor_path = state_paths(out, 0)
    tensor_path.write_bytes(b"\x00" * 64)
    with pytest.raises(FinetuneError, match="tensors are not readable"):
        run(out, 4)
    meta_path.write_text("{not json")
    with pytest.raises(FinetuneError, match="not readable JSON"):
        run(out, 4)
