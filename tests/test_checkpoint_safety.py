"""Checkpoints and training states from untrusted run folders (issue 15 items 1, 3, 4): a crafted
training state is refused before anything in it runs, an old one still resumes, and every broken
checkpoint file is a CheckpointError naming it (never a raw SafetensorError, RuntimeError,
BadZipFile, KeyError), NaN weights included."""

from __future__ import annotations

import json
import os
import random
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from smart_marl.cli import main
from smart_marl.errors import SmartMarlError
from smart_marl.model.checkpoint import (CheckpointError, checkpoint_paths, load_checkpoint, load_train_state,
                                         save_checkpoint)
from smart_marl.tokens.vocab_io import VocabularyFileError, load_motion_vocabulary
from smart_marl.train import TrainConfig, make_optimizer, make_scheduler
from smart_marl.train_state import rng_state, set_rng_state


class _RunsCode:
    """Unpickling this runs ``touch marker`` (what a crafted ``last.train_state.pt`` would do)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _copy_checkpoint(src: Path, dst_dir: Path, name: str = "last") -> Path:
    """The checkpoint ``src`` (JSON path) copied into ``dst_dir`` as NAME.*; returns the new JSON path."""
    dst_dir.mkdir(parents=True, exist_ok=True)
    stem = checkpoint_paths(src)["meta"].with_suffix("")
    for f in stem.parent.glob(stem.name + ".*"):
        shutil.copy(f, dst_dir / (name + f.name[len(stem.name):]))
    meta = json.loads((dst_dir / f"{name}.json").read_text())
    for kind in ("motion", "road"):
        meta["vocabularies"][kind]["file"] = f"{name}.{kind}_vocab"
    (dst_dir / f"{name}.json").write_text(json.dumps(meta))
    return dst_dir / f"{name}.json"


def _train_state(model) -> dict:
    cfg = TrainConfig(max_steps=10)
    optimizer = make_optimizer(model, cfg)
    for p in model.parameters():
        p.grad = torch.full_like(p, 1e-3)
    optimizer.step()
    scheduler = make_scheduler(optimizer, cfg)
    return {"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(), "rng": rng_state(), "step": 3}


# ------------------------------------------------------------------------------ item 1
def test_hostile_training_state_is_refused_and_runs_nothing(tiny_prior, tmp_path):
    marker = tmp_path / "pwned"
    last = _copy_checkpoint(tiny_prior, tmp_path / "run" / "checkpoints")
    torch.save({"optimizer": {}, "step": _RunsCode(marker)}, checkpoint_paths(last)["train_state"])
    with pytest.raises(CheckpointError, match=r"last\.train_state\.pt: refused: .*posix\.system.*nothing in it was run"):
        load_train_state(last)
    assert not marker.exists()


def test_train_resuming_from_a_hostile_run_folder_exits_1_and_runs_nothing(sample_scene_file, tiny_prior, tmp_path, capsys):
    """`smart-marl train --out DIR` resumes from DIR/checkpoints/last: a crafted training state there
    stops the run with a named error; the command it holds never runs."""
    from smart_marl.tokens.vocab_io import save_motion_vocabulary, save_road_vocabulary

    ck = load_checkpoint(tiny_prior)
    run = tmp_path / "run"
    last = _copy_checkpoint(tiny_prior, run / "checkpoints")
    save_motion_vocabulary(ck.motion_vocab, run / "motion_vocab")
    save_road_vocabulary(ck.road_vocab, run / "road_vocab")
    marker = tmp_path / "pwned"
    torch.save({**_train_state(ck.model), "rng": _RunsCode(marker)}, checkpoint_paths(last)["train_state"])
    config = tmp_path / "train.json"
    config.write_text(json.dumps({"model": ck.meta["model_config"], "data": str(sample_scene_file), "num_workers": 0,
                                  "tensorboard": False, "progress": False, "max_steps": 5, "device": "cpu"}))
    assert main(["train", "--config", str(config), "--out", str(run)]) == 1
    err = capsys.readouterr().err
    assert "smart-marl train: error:" in err and "last.train_state.pt: refused" in err
    assert not marker.exists()


def test_training_state_round_trips_with_weights_only_and_restores_every_rng(tiny_prior, tmp_path):
    ck = load_checkpoint(tiny_prior)
    random.seed(5), np.random.seed(6), torch.manual_seed(7)
    state = _train_state(ck.model)
    expected = (random.random(), float(np.random.rand()), float(torch.rand(1)))
    path = save_checkpoint(tmp_path / "last", ck.model, ck.motion_vocab, ck.road_vocab, train_state=state)
    torch.load(checkpoint_paths(path)["train_state"], weights_only=True)  # plain tensors and values: loads as is
    loaded = load_train_state(path)
    assert loaded["step"] == 3 and loaded["optimizer"]["param_groups"][0]["lr"] == state["optimizer"]["param_groups"][0]["lr"]
    random.seed(0), np.random.seed(0), torch.manual_seed(0)
    set_rng_state(loaded["rng"])
    assert (random.random(), float(np.random.rand()), float(torch.rand(1))) == expected


def test_a_version_1_training_state_with_numpy_rng_arrays_still_resumes(tiny_prior, tmp_path):
    """Run folders written before the safe format hold numpy's RNG state as a pickled array: they
    load with numpy's array reconstruction allowed, and nothing else."""
    ck = load_checkpoint(tiny_prior)
    np.random.seed(11), random.seed(12)
    legacy = {**_train_state(ck.model), "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
                                                "python": random.getstate()}}
    expected = (float(np.random.rand()), random.random())
    last = _copy_checkpoint(tiny_prior, tmp_path)
    torch.save(legacy, checkpoint_paths(last)["train_state"])
    loaded = load_train_state(last)
    np.random.seed(0), random.seed(0)
    set_rng_state(loaded["rng"])
    assert (float(np.random.rand()), random.random()) == expected
    marker = tmp_path / "pwned"  # the same old format plus one more global: refused
    torch.save({**legacy, "extra": _RunsCode(marker)}, checkpoint_paths(last)["train_state"])
    with pytest.raises(CheckpointError, match="refused"):
        load_train_state(last)
    assert not marker.exists()


# ------------------------------------------------------------------------- items 3, 4
@pytest.fixture
def ckpt(tiny_prior, tmp_path) -> Path:
    return _copy_checkpoint(tiny_prior, tmp_path / "ck", "model")


def _rewrite_meta(ckpt: Path, meta) -> None:
    ckpt.write_text(json.dumps(meta))


@pytest.mark.parametrize("change, expected", [
    (lambda m: m.pop("vocabularies"), r"vocabularies\.motion \(file and content_hash\) is missing"),
    (lambda m: m.__setitem__("vocabularies", {"motion": {"file": "../../etc/x", "content_hash": "0"}, "road": {}}),
     "is not a file name next to the checkpoint"),
    (lambda m: m.pop("model_config"), "has no model_config object"),
    (lambda m: m["model_config"].__setitem__("hidden_dim", "wide"), "model_config does not make a SMART model"),
    (lambda m: m["model_config"].update(hidden_dim=4096, head_dim=2048), "holds .* bytes, too few for the .* values"),
])
def test_broken_checkpoint_json_is_a_named_error(ckpt, change, expected):
    meta = json.loads(ckpt.read_text())
    change(meta)
    _rewrite_meta(ckpt, meta)
    with pytest.raises(CheckpointError, match=expected) as info:
        load_checkpoint(ckpt)
    assert str(ckpt.parent) in str(info.value)


def test_checkpoint_json_that_is_not_an_object_is_named(ckpt):
    ckpt.write_text("[1, 2, 3]")
    with pytest.raises(CheckpointError, match=r"model\.json: not a smart-marl checkpoint \(the JSON is a list"):
        load_checkpoint(ckpt)


@pytest.mark.parametrize("damage", ["truncated", "empty", "huge_header"])
def test_broken_safetensors_weights_are_a_named_error(ckpt, damage):
    weights = checkpoint_paths(ckpt)["weights"]
    raw = weights.read_bytes()
    weights.write_bytes({"truncated": raw[: len(raw) // 2], "empty": b"",
                         "huge_header": struct.pack("<Q", 2**62) + raw[8:]}[damage])
    with pytest.raises(CheckpointError, match=r"model\.safetensors: ") as info:
        load_checkpoint(ckpt)
    assert "SafetensorError" in str(info.value) or "too few" in str(info.value)


def test_a_weight_of_the_wrong_shape_is_named(ckpt):
    weights = checkpoint_paths(ckpt)["weights"]
    state = load_file(str(weights))
    name = next(k for k, v in state.items() if v.dim() == 2)
    state[name] = state[name][:-1].contiguous()
    save_file(state, str(weights))
    with pytest.raises(CheckpointError, match=rf"weight {name} has shape"):
        load_checkpoint(ckpt)


def test_a_checkpoint_with_nan_weights_is_refused(ckpt):
    weights = checkpoint_paths(ckpt)["weights"]
    state = load_file(str(weights))
    name = next(k for k, v in state.items() if v.is_floating_point() and v.numel() > 1)
    state[name][0] = float("nan")
    save_file(state, str(weights))
    with pytest.raises(CheckpointError, match=rf"weight {name} holds NaN or infinite values"):
        load_checkpoint(ckpt)


def test_a_truncated_vocabulary_npz_is_a_named_smart_marl_error(ckpt):
    vocab = checkpoint_paths(ckpt)["motion_vocab"]
    npz = vocab.with_name(vocab.name + ".npz")
    npz.write_bytes(npz.read_bytes()[:100])
    with pytest.raises(VocabularyFileError, match=r"motion_vocab\.npz: cannot read the arrays: BadZipFile") as info:
        load_motion_vocabulary(vocab)
    assert isinstance(info.value, SmartMarlError) and isinstance(info.value, ValueError)
    with pytest.raises(CheckpointError, match=r"stored vocabulary: .*motion_vocab\.npz"):
        load_checkpoint(ckpt)
