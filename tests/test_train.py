"""SMART training: overfitting two real scenes, DDP equivalence, exact resume after a kill, clear errors.

The training runs (resume, mixing, fine-tuning, train_only) read the package's sample scenes, each
written to its own scene file; overfitting real scenes reads ../shared/data."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import pytest
import torch

from smart_marl.cli import main as cli_main
from smart_marl.model.batch import SmartBatch, collate_scenes
from smart_marl.model.checkpoint import CheckpointError, load_checkpoint
from smart_marl.model.losses import NextTokenLoss
from smart_marl.model.smart import SMART, get_config, model_parameter_count
from smart_marl.train import (DistInfo, MixedScenes, TokenizedScenes, TrainError, build_vocabularies, evaluate, load_train_config, open_scenes,
                              train, train_step)
from smart_marl.tokens.vocab_io import save_motion_vocabulary, save_road_vocabulary

from model_variants import TINY_TRAIN_MODEL
from test_model import random_batch, tiny_config

ROOT = Path(__file__).resolve().parents[1]
GPUDRIVE = "gpudrive_json"
TWO_SCENES = ("tfrecord-00001-of-01000_307.json", "tfrecord-00002-of-01000_407.json")  # 19 and 14 agents, 175 and 163 tokens


def _vocab_files(scenes, tmp: Path, motion_size: int, road_size: int) -> dict[str, str]:
    """Small k-disks vocabularies (the tokenizer's builders) from ``scenes``."""
    cfg = tiny_config(motion_vocab_sizes=(motion_size,) * 3, road_vocab_size=road_size)
    mv, rv = build_vocabularies(scenes, cfg, len(scenes), seed=0)
    save_motion_vocabulary(mv, tmp / "motion_vocab")
    save_road_vocabulary(rv, tmp / "road_vocab")
    return {"motion_vocab": str(tmp / "motion_vocab"), "road_vocab": str(tmp / "road_vocab")}


@pytest.mark.slow
def test_smart_1m_overfits_two_real_scenes_to_90_percent_top1(shared_data, tmp_path):
    """smart-1m (its parameters; dense neighbourhoods trimmed to K = 4 road / 4 map / 8 agents for
    CPU speed), 16-token vocabularies per type and 64 road tokens, no token noise, no dropout."""
    from smart_marl.readers import read_scenarios

    # from the 11 GPUDrive scenes: the two training scenes alone hold no cyclist, and a vocabulary needs every type
    vocab = _vocab_files(list(read_scenarios(shared_data / GPUDRIVE)), tmp_path, 16, 64)
    data = [str(shared_data / GPUDRIVE / f) for f in TWO_SCENES]
    cfg = load_train_config("smart-1m", {
        "data": data[0], "out_dir": str(tmp_path / "run"), **vocab, "batch_size": 2, "num_workers": 0, "max_steps": 60, "lr": 5e-3,
        "warmup_steps": 5, "dropout": 0.0, "label_smoothing": 0.0, "token_noise_topk": 0, "log_every": 10, "val_every": 0,
        "ckpt_every": 0, "tensorboard": False, "progress": False, "road_keep_radius_m": 30.0,
        "model.map_neighbours": 4, "model.road_neighbours": 4, "model.agent_neighbours": 8})
    from smart_marl.readers import read_scenario

    scenes = [read_scenario(p) for p in data]
    t0 = time.perf_counter()
    res = train(cfg, scenes=scenes)
    seconds = time.perf_counter() - t0
    ck = load_checkpoint(tmp_path / "run" / "checkpoints" / "final")
    # smart-1m's architecture; fewer parameters only in the heads (16-token vocabularies)
    assert (ck.model.config.hidden_dim, ck.model.config.num_agent_blocks, ck.model.config.num_road_layers) == (64, 2, 1)
    assert sum(p.numel() for p in ck.model.parameters()) == model_parameter_count(
        get_config("smart-1m", motion_vocab_sizes=(16, 16, 16), road_vocab_size=64))
    ds = TokenizedScenes(scenes, ck.motion_vocab, ck.road_vocab, seed=0, noise_topk=0, road_mask_prob=0.0, road_keep_radius_m=30.0)
    metrics = evaluate(ck.model, [collate_scenes([ds[0], ds[1]])], torch.device("cpu"))
    print(f"overfit: {res.step} steps in {seconds:.1f} s, teacher-forced top-1 {metrics['motion_top1_acc']:.3f} "
          f"over {metrics['motion_tokens']:.0f} tokens")
    assert metrics["motion_tokens"] > 300
    assert metrics["motion_top1_acc"] >= 0.9
    assert seconds < 120


# ------------------------------------------------------------------------------------- DDP
def _cat(a: SmartBatch, b: SmartBatch) -> SmartBatch:
    return SmartBatch(**{k: torch.cat([getattr(a, k), getattr(b, k)]) for k in vars(a)})


def _one_step(batch: SmartBatch, info: DistInfo, wrap: bool) -> dict[str, dict[str, torch.Tensor]]:
    """One train_step of a fresh tiny model with SGD: the gradients it applied and the weights after.

    SGD because its update is linear in the gradient: what DDP guarantees is the all-reduced
    gradient, equal to the single-process gradient up to float summation order; AdamW divides by
    sqrt(v) and turns a near-zero gradient's rounding difference into a full-size step of either sign."""
    torch.manual_seed(0)
    model = SMART(tiny_config())
    module = NextTokenLoss(model, 0.1)
    wrapped = torch.nn.parallel.DistributedDataParallel(module) if wrap else module
    opt = torch.optim.SGD(model.parameters(), lr=1e-2)
    train_step(wrapped, opt, torch.optim.lr_scheduler.LambdaLR(opt, lambda step: 1.0), batch, 1.0, info, torch.device("cpu"),
               amp=False)
    return {"grads": {k: p.grad.detach().clone() for k, p in model.named_parameters() if p.grad is not None},
            "weights": {k: v.detach().clone() for k, v in model.state_dict().items()}}


def _ddp_worker(rank: int, world: int, init_file: str, out: str) -> None:
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    batch = random_batch(seed=11 + rank)
    state = _one_step(batch, DistInfo(rank=rank, world_size=world), wrap=True)
    if rank == 0:
        torch.save(state, out)
    dist.barrier()
    dist.destroy_process_group()


def test_ddp_step_on_two_gloo_ranks_equals_one_process_on_the_union(tmp_path):
    """The all-reduced gradients of two ranks are the gradients of one process on the union of their
    batches, and so is the (SGD) step they take."""
    out = tmp_path / "ddp.pt"
    torch.multiprocessing.spawn(_ddp_worker, args=(2, str(tmp_path / "init"), str(out)), nprocs=2, join=True)
    ddp = torch.load(out)
    single = _one_step(_cat(random_batch(seed=11), random_batch(seed=12)), DistInfo(), wrap=False)
    assert set(ddp["grads"]) == set(single["grads"]) and len(single["grads"]) > 10
    scale = max(float(g.abs().max()) for g in single["grads"].values())
    for k, g in single["grads"].items():
        assert torch.allclose(ddp["grads"][k], g, rtol=1e-4, atol=1e-6 * scale), k
    torch.manual_seed(0)
    before = SMART(tiny_config()).state_dict()
    changed = 0
    for k, v in single["weights"].items():
        assert torch.allclose(ddp["weights"][k], v, rtol=0, atol=1e-7), k
        changed += int(not torch.equal(v, before[k]))
    assert changed > 10  # the step moved the weights


# ---------------------------------------------------------------------------------- resume
@pytest.fixture(scope="module")
def sample_data(sample_scenes, tmp_path_factory) -> Path:
    """The four sample scenes, one scene file each (scene_0.smsc .. scene_3.smsc), in one folder."""
    from smart_marl.cache import write_shard

    folder = tmp_path_factory.mktemp("sample_data")
    for i, scene in enumerate(sample_scenes):
        write_shard(folder / f"scene_{i}.smsc", [scene])
    return folder


@pytest.fixture
def small_vocab(sample_scenes, tmp_path) -> dict[str, str]:
    """8 motion tokens per type and 16 road tokens from the four sample scenes, as files."""
    return _vocab_files(sample_scenes, tmp_path, 8, 16)


def _losses(run: Path) -> list[tuple[str, str, str]]:
    with open(run / "train.csv", newline="") as f:
        return [(r["step"], r["loss"], r["motion_top1_acc"]) for r in csv.DictReader(f)]


def test_run_killed_and_resumed_matches_an_uninterrupted_run(sample_data, small_vocab, tmp_path):
    vocab = small_vocab
    base = {"data": str(sample_data / "scene_0.smsc"), **vocab, "batch_size": 1, "num_workers": 0, "max_steps": 6,
            "lr": 1e-3, "log_every": 1, "val_every": 3, "val_scenes": 1, "ckpt_every": 2, "tensorboard": False, "progress": False,
            "token_noise_topk": 3, "dropout": 0.1, "road_keep_radius_m": 20.0,
            "model_overrides": TINY_TRAIN_MODEL}
    full = train(load_train_config(base, {"out_dir": str(tmp_path / "full")}))
    assert full.step == 6
    cfg_file = tmp_path / "killed.json"
    cfg_file.write_text(json.dumps({**base, "out_dir": str(tmp_path / "killed")}))
    # the run is SIGKILLed (a hard kill, as a power cut would) by its own on_step hook right after step 5
    kill_after_step_5 = textwrap.dedent(f"""
        import os, signal
        from smart_marl.train import load_train_config, train

        def kill_after_step_5(step):
            if step == 5:
                os.kill(os.getpid(), signal.SIGKILL)

        train(load_train_config({str(cfg_file)!r}), on_step=kill_after_step_5)
    """)
    proc = subprocess.run([sys.executable, "-c", kill_after_step_5], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr[-2000:]  # SIGKILLed after step 5; its last checkpoint is step 4
    assert len(_losses(tmp_path / "killed")) == 5
    resumed = train(load_train_config(str(cfg_file)))
    assert resumed.resumed_from == 4 and resumed.step == 6
    assert _losses(tmp_path / "killed") == _losses(tmp_path / "full")
    a = load_checkpoint(tmp_path / "full" / "checkpoints" / "final").model.state_dict()
    b = load_checkpoint(tmp_path / "killed" / "checkpoints" / "final").model.state_dict()
    for k in a:
        assert torch.equal(a[k], b[k]), k


# ------------------------------------------------------------------------- mixing real scenes in
def test_mixed_scenes_give_the_extra_scenes_their_share_of_samples():
    main, extra = [f"m{i}" for i in range(100)], ["x0", "x1", "x2", "x3"]
    mixed = MixedScenes(main, extra, 0.2)
    assert mixed.repeat == 6 and len(mixed) == 124  # 0.2 / 0.8 * 100 / 4 = 6.25 repeats -> 6
    assert abs(mixed.share - 24 / 124) < 1e-12
    assert [mixed[i] for i in range(100)] == main  # the first scenes are data's (validation reads them)
    assert [mixed[i] for i in range(100, 124)] == extra * 6 and mixed[-1] == "x3"
    with pytest.raises(IndexError, match="124"):
        mixed[124]
    assert MixedScenes(["m"], extra, 0.01).repeat == 1  # every extra scene is sampled at least once per epoch


def test_a_run_records_the_mixed_in_data_and_rejects_a_bad_share(sample_data, small_vocab, tmp_path):
    vocab = small_vocab
    cfg = {"data": str(sample_data / "scene_0.smsc"), "extra_data": str(sample_data / "scene_1.smsc"),
           "extra_data_share": 0.5, **vocab, "batch_size": 1, "num_workers": 0, "max_steps": 1, "log_every": 1, "val_every": 0,
           "ckpt_every": 0, "tensorboard": False, "progress": False, "out_dir": str(tmp_path / "run"),
           "model_overrides": TINY_TRAIN_MODEL}
    result = train(load_train_config(cfg))
    data = json.loads(Path(result.checkpoint).read_text())["data"]
    assert data["num_scenes"] == 2 and data["extra_scenes"] == 1 and data["extra_share"] == 0.5
    assert data["extra_data"].endswith("scene_1.smsc")
    for share in (0, 1, 1.5):
        with pytest.raises(TrainError, match="extra_data_share"):
            load_train_config(cfg, [f"extra_data_share={share}"])


# ---------------------------------------------------------------------------------- errors
def test_unknown_config_is_a_clear_cli_error(capsys):
    assert cli_main(["train", "--config", "smart-3m"]) == 1
    err = capsys.readouterr().err
    assert "unknown config 'smart-3m'" in err and "smart-1m" in err
    with pytest.raises(TrainError, match="unknown training config key.*max_step"):
        load_train_config("smart-1m", ["max_step=3"])


def test_empty_dataset_is_a_clear_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(TrainError, match="dataset is empty"):
        open_scenes(str(tmp_path / "empty"))


def test_models_command_prints_every_named_config_with_its_parameter_count(capsys):
    assert cli_main(["models", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["name"] for r in rows] == ["smart-1m", "smart-7m", "smart-26m", "smart-101m"]
    for r in rows:
        assert abs(r["parameters"] / r["paper_parameters"] - 1) < 0.1


def _one_step_run(sample_data: Path, vocab: dict[str, str]) -> dict:
    """A training config (without model or output folder) of one step on one sample scene."""
    return {"data": str(sample_data / "scene_0.smsc"), **vocab, "batch_size": 1, "num_workers": 0, "max_steps": 1,
            "log_every": 1, "val_every": 0, "ckpt_every": 0, "tensorboard": False, "progress": False}


def test_fine_tuning_warns_when_the_run_config_differs_from_the_checkpoints(sample_data, small_vocab, tmp_path):
    """With init=, the run's model config wins; a field that changes behaviour but not the weights'
    shapes (road_types here) must not change silently."""
    base = _one_step_run(sample_data, small_vocab)
    first = train(load_train_config({**base, "model_overrides": {**TINY_TRAIN_MODEL, "road_types": "sumo"}, "out_dir": str(tmp_path / "a")}))
    init = str(first.checkpoint)
    with pytest.warns(UserWarning, match=r"differs from the checkpoint's in \['road_types'\]"):
        train(load_train_config({**base, "model_overrides": TINY_TRAIN_MODEL, "init": init, "out_dir": str(tmp_path / "b")}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same config: no warning
        train(load_train_config({**base, "model_overrides": {**TINY_TRAIN_MODEL, "road_types": "sumo"}, "init": init,
                                 "out_dir": str(tmp_path / "c")}))


def test_fine_tuning_with_an_input_the_checkpoint_lacks(sample_data, small_vocab, tmp_path):
    """init= a checkpoint without an input the run switches on (speed_change_input): the checkpoint's weights
    load, the new input starts as a fresh model's (its last layer at zero: the model starts as the
    checkpoint's) and the warning names it; the other way round (weights the run's model has no place for)
    is an error naming the checkpoint."""
    base = _one_step_run(sample_data, small_vocab)
    first = train(load_train_config({**base, "model_overrides": TINY_TRAIN_MODEL, "out_dir": str(tmp_path / "a")}))
    with_input = {**TINY_TRAIN_MODEL, "speed_change_input": True}
    with pytest.warns(UserWarning, match=r"in \['speed_change_input'\].*fresh model's: \['motion_net.speed_change'\]"):
        second = train(load_train_config({**base, "model_overrides": with_input, "init": str(first.checkpoint),
                                          "train_only": ["motion_net.speed_change"], "out_dir": str(tmp_path / "b")}))
    before, after = load_checkpoint(first.checkpoint).model.state_dict(), load_checkpoint(second.checkpoint).model.state_dict()
    assert set(after) - set(before) == {k for k in after if k.startswith("motion_net.speed_change.")} != set()
    for k, v in before.items():  # all but the new input frozen: the run keeps what it loaded
        torch.testing.assert_close(after[k], v, rtol=0, atol=0, msg=k)
    with pytest.raises(CheckpointError, match=r"checkpoints/\w+\.json: its weights do not fit .*modules the model lacks: \['motion_net\.speed_change'\]"):
        train(load_train_config({**base, "model_overrides": TINY_TRAIN_MODEL, "init": str(second.checkpoint), "out_dir": str(tmp_path / "c")}))


def _trend_batch() -> SmartBatch:
    """One scene of 18 tokens, agents moving along x at a constant speed, then at another speed in the
    last two tokens (7.5-8 s after the current one): a vehicle that speeds up (6 -> 9 m/s), one that
    keeps its speed (10 -> 11), one that slows (10 -> 5), one too slow to count (3 -> 9) and a
    pedestrian at the first vehicle's speeds; the pedestrian and the slow vehicle weigh 1."""
    b = random_batch(b=1, n=5, s=18, seed=3)
    types = torch.tensor([[0, 0, 0, 0, 1]])
    speeds = torch.tensor([[6.0, 10.0, 10.0, 3.0, 6.0]])[..., None].repeat(1, 1, 18)
    speeds[..., 16:] = torch.tensor([9.0, 11.0, 5.0, 9.0, 9.0])[:, None]
    x = torch.cumsum(speeds * 0.5, dim=-1)
    pose = torch.zeros(1, 5, 18, 3)
    pose[..., 0] = x
    start = pose.clone()
    start[..., 0] = x - speeds * 0.5
    valid = torch.ones(1, 5, 18, dtype=torch.bool)
    return SmartBatch(**{**vars(b), "agent_type": types, "agent_pose": pose, "agent_start_pose": start,
                         "agent_valid": valid, "target_valid": valid})


def test_speed_trend_weights_pick_each_vehicles_trend_and_weigh_its_cross_entropy():
    from smart_marl.model.losses import speed_trend_weights
    batch = _trend_batch()
    w = speed_trend_weights(batch, (4.0, 0.75, 0.5))
    assert w.tolist() == [[4.0, 0.75, 0.5, 1.0, 1.0]]
    short = SmartBatch(**{k: (v[:, :, :12] if v.dim() >= 3 and k.startswith(("agent_tokens", "agent_valid", "agent_start", "agent_pose", "target"))
                              else v) for k, v in vars(batch).items()})
    assert speed_trend_weights(short, (4.0, 0.75, 0.5)).tolist() == [[1.0] * 5]  # no 8 s after the current token

    torch.manual_seed(0)
    model = SMART(tiny_config()).eval()
    plain = NextTokenLoss(model, 0.1)
    weighted = NextTokenLoss(model, 0.1, trend_weights=(4.0, 0.75, 0.5))
    ones = NextTokenLoss(model, 0.1, trend_weights=(1.0, 1.0, 1.0))
    with torch.no_grad():
        feats, _ = model(batch, road_masked=batch.road_masked)
        per_agent = []
        for i, t in enumerate(batch.agent_type[0].tolist()):
            logits = model.motion_heads[t](feats[0, i]).float()
            per_agent.append(torch.nn.functional.cross_entropy(logits, batch.target_tokens[0, i], reduction="sum", label_smoothing=0.1))
        per_agent = torch.stack(per_agent)
        n = batch.target_valid.sum()
        expected = (per_agent * w[0]).sum() / n
        assert torch.allclose(weighted(batch)["motion_loss"], expected, rtol=1e-5)
        assert torch.allclose(plain(batch)["motion_loss"], per_agent.sum() / n, rtol=1e-5)
        assert torch.allclose(ones(batch)["motion_loss"], plain(batch)["motion_loss"], rtol=1e-6)


def test_speed_trend_weights_config_is_checked():
    assert load_train_config("smart-1m", ["speed_trend_weights=[4.1,0.74,0.58]"]).speed_trend_weights == [4.1, 0.74, 0.58]
    for bad in ("[1,2]", "[1,-1,1]", "fast"):
        with pytest.raises(TrainError, match="speed_trend_weights"):
            load_train_config("smart-1m", [f"speed_trend_weights={bad}"])


def test_train_only_trains_the_named_parameters_and_freezes_the_rest(sample_data, small_vocab, tmp_path):
    """train_only=["motion_heads.1"]: a step from a checkpoint moves the pedestrian head and nothing else."""
    vocab = small_vocab
    base = {"data": str(sample_data), **vocab, "model_overrides": TINY_TRAIN_MODEL, "batch_size": 4, "num_workers": 0,
            "max_steps": 2, "lr": 1e-2, "log_every": 1, "val_every": 0, "ckpt_every": 0, "tensorboard": False, "progress": False}
    first = train(load_train_config({**base, "out_dir": str(tmp_path / "a")}))
    timed = train(load_train_config({**base, "out_dir": str(tmp_path / "timed"), "max_steps": 50, "time_limit_s": 1e-6}))
    assert timed.step == 1 and load_checkpoint(tmp_path / "timed" / "checkpoints" / "final").step == 1  # the time limit ends it
    second = train(load_train_config({**base, "init": str(first.checkpoint), "train_only": ["motion_heads.1"],
                                      "out_dir": str(tmp_path / "b")}))
    before = load_checkpoint(first.checkpoint).model.state_dict()
    after = load_checkpoint(second.checkpoint).model.state_dict()
    moved = sorted(k for k in before if not torch.equal(before[k], after[k]))
    assert moved and all(k.startswith("motion_heads.1.") for k in moved), moved


def test_train_only_names_a_prefix_that_matches_nothing():
    from smart_marl.train import TrainConfigError, freeze_except

    model = SMART(tiny_config(), [torch.zeros(8, 6, 4, 2)] * 3)
    assert freeze_except(model, ["motion_heads.1"]) == sum(p.numel() for p in model.motion_heads[1].parameters())
    assert not any(p.requires_grad for n, p in model.named_parameters() if not n.startswith("motion_heads.1"))
    with pytest.raises(TrainConfigError, match=r"train_only: no model parameter starts with \['motion_head.1'\]"):
        freeze_except(model, ["motion_head.1"])
    with pytest.raises(TrainConfigError, match="train_only"):
        load_train_config({"train_only": "motion_heads.1"})


def test_lr_scale_gives_the_named_parameters_their_own_rate_on_the_same_schedule():
    from smart_marl.train import TrainConfigError, make_optimizer, make_scheduler

    model = SMART(tiny_config(), [torch.zeros(8, 6, 4, 2)] * 3)
    cfg = load_train_config({"lr": 1e-3, "warmup_steps": 2, "max_steps": 10, "lr_scale": {"motion_heads.1": 10}})
    opt = make_optimizer(model, cfg)
    fast = {id(p) for p in model.motion_heads[1].parameters()}
    assert sum(len(g["params"]) for g in opt.param_groups) == len(list(model.parameters()))
    for g in opt.param_groups:  # a group is all fast or all not, matrices alone decayed
        kinds = {id(p) in fast for p in g["params"]}
        assert len(kinds) <= 1 and g["lr"] == pytest.approx(1e-2 if kinds == {True} else 1e-3)
        assert g["weight_decay"] == (cfg.weight_decay if all(p.dim() >= 2 for p in g["params"]) else 0.0) or not g["params"]
    sched = make_scheduler(opt, cfg)
    for _ in range(5):
        opt.step()
        sched.step()
    fractions = [g["lr"] / g["initial_lr"] for g in opt.param_groups]
    assert max(fractions) - min(fractions) < 1e-9 and fractions[0] < 1  # one schedule: each group at the same share of its rate
    plain = make_optimizer(model, load_train_config({"lr": 1e-3}))
    assert [len(g["params"]) for g in plain.param_groups] == [sum(p.dim() >= 2 for p in model.parameters()),
                                                              sum(p.dim() < 2 for p in model.parameters())]
    with pytest.raises(TrainConfigError, match=r"lr_scale: no trained parameter starts with \['motion_head.1'\]"):
        make_optimizer(model, load_train_config({"lr_scale": {"motion_head.1": 10}}))
    with pytest.raises(TrainConfigError, match="lr_scale"):
        load_train_config({"lr_scale": {"motion_heads.1": 0}})


def test_a_cuda_device_without_an_index_is_this_processs(monkeypatch):
    """torch.cuda.set_device refuses a bare "cuda" (the --device cuda of a lent GPU machine failed so)."""
    from smart_marl.train import resolve_device

    monkeypatch.delenv("LOCAL_RANK", raising=False)
    assert resolve_device("cuda") == torch.device("cuda", 0)
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert resolve_device("cuda") == torch.device("cuda", 1)
    assert resolve_device("cuda:3") == torch.device("cuda", 3)
    assert resolve_device("cpu") == torch.device("cpu")
