"""The arithmetic precision option (smart_marl.model.precision): bfloat16 inference keeps what must stay float32 in
float32 and picks the same top token as float32 on at least 99% of a real scene's teacher-forced steps; every
surface that takes ``precision`` refuses an unknown one by name; bfloat16 training autocasts and keeps float32
weights. (Speed and realism side by side: benchmarks/precision.py, docs/model_card.md.)"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors
from smart_marl.model.checkpoint import EMBEDDED, load_checkpoint, resolve_checkpoint_path
from smart_marl.model.precision import FLOAT32_PARAMETERS, PrecisionError, autocast, inference_model
from smart_marl.readers import read_scenarios
from test_commands_consistency import _exit_code

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "womd_tfrecord"
SCENES = ("motion_data_one_scenario.tfrecord", "womd_scenario_input.tfrecord")


@pytest.fixture(scope="module")
def prior():
    return load_checkpoint(resolve_checkpoint_path(EMBEDDED))


def teacher_forced_top_tokens(model, batch) -> torch.Tensor:
    """Each (agent, step)'s most likely next token under its own type's head, teacher-forced on the log."""
    with torch.no_grad():
        feats, _ = model(batch)
        logits = model.motion_logits(feats, batch.agent_type)
    kind = batch.agent_type[..., None].expand(feats.shape[:-1])
    top = torch.full(feats.shape[:-1], -1, dtype=torch.long)
    for t, head_logits in enumerate(logits):
        top = torch.where(kind == t, head_logits.float().argmax(-1), top)
    return top


@pytest.mark.parametrize("name", SCENES)
def test_bfloat16_picks_the_float32_top_token_on_at_least_99_percent_of_a_real_scenes_steps(prior, name):
    if not (SHARED / name).is_file():
        pytest.skip(f"{SHARED / name} is not there")
    scene = next(iter(read_scenarios(SHARED / name)))
    batch = collate_scenes([scene_tensors(scene, prior.motion_vocab, scene_road(scene, prior.road_vocab), road_mask_prob=0.0)])
    model = prior.model.eval()
    fp32, bf16 = teacher_forced_top_tokens(model, batch), teacher_forced_top_tokens(inference_model(model, "bfloat16"), batch)
    valid = batch.target_valid
    assert int(valid.sum()) > 500
    agreement = float((fp32 == bf16)[valid].float().mean())
    assert agreement >= 0.99, f"{name}: the same top token on {agreement:.4f} of {int(valid.sum())} steps"


def test_the_bfloat16_copy_keeps_the_fourier_phases_and_the_geometry_in_float32_and_is_made_once(prior):
    model = prior.model
    bf16 = inference_model(model, "bfloat16")
    assert inference_model(model, "bfloat16") is bf16 and inference_model(bf16, "bfloat16") is bf16
    assert inference_model(model, "float32") is model
    for name, p in bf16.named_parameters():
        want = torch.float32 if name.rsplit(".", 1)[-1] in FLOAT32_PARAMETERS else torch.bfloat16
        assert p.dtype == want, name
    assert all(b.dtype != torch.bfloat16 for b in bf16.buffers())  # the vocabulary's contours
    assert all(p.dtype == torch.float32 for p in model.parameters())  # the original untouched


def test_a_bfloat16_rollout_hands_out_float32_logits_and_finite_trajectories():
    from smart_marl.embedded import sample_scenarios
    from smart_marl.rollout import RolloutState

    state = RolloutState.start("embedded", sample_scenarios()[:1], num_rollouts=2, seed=0, precision="bfloat16")
    assert state.logits().dtype == torch.float32
    outs = state.run(4)
    for out in outs:  # every simulated agent moved to finite poses, its logits float32
        sim = out.simulated
        assert bool(sim.any()) and out.logits.dtype == torch.float32
        assert bool(torch.isfinite(out.poses[sim]).all()) and bool((out.tokens[sim] >= 0).all())
    assert state.road_x.dtype == torch.bfloat16


def refusal(call) -> str:
    with pytest.raises((PrecisionError, ValueError)) as info:
        call()
    return str(info.value)


def test_every_surface_refuses_an_unknown_precision_by_name(tmp_path, capsys):
    from agents.finetune_config import load_finetune_config
    from envs.smart_traffic_batched_v0 import SmartTrafficBatchedEnv
    from envs.smart_traffic_v0 import parallel_env
    from smart_marl.embedded import sample_scenarios
    from smart_marl.rollout import RolloutState, rollout
    from smart_marl.train import load_train_config

    scene = sample_scenarios()[:1]
    calls = {
        "rollout": lambda: rollout("embedded", scene, num_rollouts=1, precision="float16"),
        "RolloutState.start": lambda: RolloutState.start("embedded", scene, precision="fp32"),
        "parallel_env": lambda: parallel_env(scenarios="embedded", precision="half"),
        "batched env": lambda: SmartTrafficBatchedEnv(scenarios="embedded", num_scenes=1, max_agents=1, precision="bf16"),
        "finetune config": lambda: load_finetune_config("tiny", ["precision=float64"]),
        "train config": lambda: load_train_config("smart-1m", {"precision": "int8"}),
        "autocast": lambda: autocast("float16", "cpu"),
    }
    for where, call in calls.items():
        message = refusal(call)
        assert "precision" in message and any(bad in message for bad in ("float16", "fp32", "half", "bf16", "float64", "int8")), \
            f"{where}: {message}"
    from agents.whatif import load_script, run_whatif
    from agents.whatif.edits import EXAMPLES_DIR

    script = load_script(sorted(EXAMPLES_DIR.glob("*.yaml"))[0])
    assert "precision" in refusal(lambda: run_whatif(None, scene[0], script, num_rollouts=1, precision="float16"))
    for argv in (["eval", "--scenes", "x", "--policy", "prior", "--precision", "half"],
                 ["whatif", "x", "--script", "brake_hard", "--out", str(tmp_path / "w"), "--precision", "half"]):
        code, _, err = _exit_code(argv, capsys)
        assert code == 2 and "--precision" in err and "half" in err, (argv, err)


def test_bfloat16_training_autocasts_and_keeps_float32_weights(prior):
    from smart_marl.model.losses import NextTokenLoss
    from smart_marl.train import DistInfo, load_train_config, make_optimizer, make_scheduler, train_step

    scene = next(iter(read_scenarios(SHARED / SCENES[0]))) if (SHARED / SCENES[0]).is_file() else None
    if scene is None:
        pytest.skip("no shared WOMD scene")
    batch = collate_scenes([scene_tensors(scene, prior.motion_vocab, scene_road(scene, prior.road_vocab), rng=0)])
    model = load_checkpoint(resolve_checkpoint_path(EMBEDDED)).model.train()
    module = NextTokenLoss(model, 0.1)
    cfg = load_train_config("smart-1m", {"max_steps": 10, "precision": "bfloat16"})
    opt = make_optimizer(model, cfg)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    out = train_step(module, opt, make_scheduler(opt, cfg), batch, 1.0, DistInfo(), torch.device("cpu"), amp=False,
                     precision="bfloat16")
    assert torch.isfinite(torch.tensor(out["loss"])) and out["grad_norm"] > 0
    assert all(p.dtype == torch.float32 for p in model.parameters())
    assert any(not torch.equal(before[k], v) for k, v in model.state_dict().items())
