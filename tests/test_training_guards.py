"""Training fails loudly (issue 34 item 2): a training state is checked against the model and optimizer it is
loaded into (shapes, finiteness, the step within the run) before anything trains, and a non-finite loss stops
the run before the optimizer steps, keeping the last good checkpoint."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
import torch

from smart_marl.model.checkpoint import CheckpointError, checkpoint_paths, load_checkpoint, load_train_state
from smart_marl.train import NonFiniteLossError, load_train_config, train

from model_variants import TINY_TRAIN_MODEL

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py

ROOT = Path(__file__).resolve().parents[1]
EMBEDDED = ROOT / "smart_marl" / "checkpoints" / "embedded" / "smart-1m-sumo"
CONFIG = {"data": str(ROOT / "smart_marl" / "samples" / "sumo_samples.smsc"), "motion_vocab": f"{EMBEDDED}.motion_vocab",
          "road_vocab": f"{EMBEDDED}.road_vocab", "batch_size": 1, "num_workers": 0, "max_steps": 2, "lr": 1e-3,
          "log_every": 1, "val_every": 0, "ckpt_every": 1, "tensorboard": False, "progress": False, "token_noise_topk": 0,
          "road_keep_radius_m": 20.0, "model": {"name": "smart-1m", "road_types": "sumo"},
          "model_overrides": TINY_TRAIN_MODEL}


def _rows(run: Path) -> list[dict]:
    with open(run / "train.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A 2-step run whose last checkpoint (step 2) has a training state."""
    out = tmp_path_factory.mktemp("run") / "run"
    assert train(load_train_config(CONFIG, {"out_dir": str(out)})).step == 2
    return out


def _moment(state: dict) -> torch.Tensor:
    entry = next(v for v in state["optimizer"]["state"].values() if v["exp_avg"].dim() == 2)
    return entry["exp_avg"]


def _set_lr_nan(state):
    state["optimizer"]["param_groups"][0]["lr"] = float("nan")


def _set_exp_avg_nan(state):
    _moment(state)[0, 0] = float("nan")


def _set_exp_avg_shape(state):
    entry = next(v for v in state["optimizer"]["state"].values() if v["exp_avg"].dim() == 2)
    entry["exp_avg"] = entry["exp_avg"][:, :1].clone()


@pytest.mark.parametrize("damage, message", [
    (lambda s: s["optimizer"].__setitem__("param_groups", []), r"has 0 parameter group\(s\), this run's optimizer 2"),
    (lambda s: s.__setitem__("scheduler", {"garbage": 1}), "the scheduler state's last_epoch None does not match"),
    (_set_exp_avg_shape, r"exp_avg of parameter \d+ has shape \[\d+, 1\], the parameter \[\d+, \d+\]"),
    (_set_lr_nan, "parameter group 0 has lr nan, not a finite number >= 0"),
    (_set_exp_avg_nan, r"exp_avg of parameter \d+ holds NaN or infinite values"),
    (lambda s: s.__setitem__("step", 10**15), r"at step 1000000000000000, outside this run's 0..max_steps=3"),
], ids=["empty_param_groups", "garbage_scheduler", "exp_avg_shape", "lr_nan", "exp_avg_nan", "step_1e15"])
def test_a_training_state_that_does_not_fit_the_run_is_refused_before_anything_trains(finished_run, tmp_path, damage, message):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    path = checkpoint_paths(run / "checkpoints" / "last")["train_state"]
    state = load_train_state(run / "checkpoints" / "last")
    damage(state)
    torch.save(state, path)
    with pytest.raises(CheckpointError, match=message) as info:
        train(load_train_config(CONFIG, {"out_dir": str(run), "max_steps": 3}))
    assert str(path) in str(info.value)
    assert len(_rows(run)) == 2 and load_checkpoint(run / "checkpoints" / "last").step == 2  # nothing trained


def test_a_non_finite_loss_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path, monkeypatch):
    from smart_marl.model.losses import NextTokenLoss

    real = NextTokenLoss.forward
    calls = []

    def nan_at_the_third_step(self, *args, **kwargs):
        out = real(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 3:
            out["loss"] = out["loss"] * float("nan")
        return out

    monkeypatch.setattr(NextTokenLoss, "forward", nan_at_the_third_step)
    out = tmp_path / "run"
    with pytest.raises(NonFiniteLossError, match=r"step 3: the loss is nan .* the last good checkpoint is .*last\.json \(step 2\)"):
        train(load_train_config(CONFIG, {"out_dir": str(out), "max_steps": 5}))
    last = load_checkpoint(out / "checkpoints" / "last")  # loads: every weight finite (NaN weights are refused)
    assert last.step == 2 and [r["step"] for r in _rows(out)] == ["1", "2"]
    assert not (out / "checkpoints" / "final.json").exists()
    assert json.loads((out / "checkpoints" / "last.json").read_text())["step"] == 2
