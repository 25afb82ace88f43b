"""The arithmetic precision option (smart_marl.model.precision): bfloat16 inference keeps what must stay float32 in
float32 and picks the same top token as float32 on at least 99% of a real scene's teacher-forced steps; every
surface that takes ``precision`` refuses an unknown one by name; bfloat16 training on the CPU runs a bfloat16
working copy and keeps float32 weights, its gradients close to float32's; the rows padded for oneDNN change none of
the rows given. (Speed and realism side by side: benchmarks/precision.py, docs/model_card.md.)"""

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


def _training_setup(prior):
    from smart_marl.model.losses import NextTokenLoss
    from smart_marl.train import load_train_config, make_optimizer, make_scheduler

    if not (SHARED / SCENES[0]).is_file():
        pytest.skip("no shared WOMD scene")
    scene = next(iter(read_scenarios(SHARED / SCENES[0])))
    batch = collate_scenes([scene_tensors(scene, prior.motion_vocab, scene_road(scene, prior.road_vocab), rng=0)])
    model = load_checkpoint(resolve_checkpoint_path(EMBEDDED)).model.train()
    cfg = load_train_config("smart-1m", {"max_steps": 10, "precision": "bfloat16", "dropout": 0.0})
    opt = make_optimizer(model, cfg)
    return batch, model, NextTokenLoss(model, 0.1), opt, make_scheduler(opt, cfg)


def _gradients(module, batch, precision):
    """Every parameter's gradient [P] of one step's loss (no optimizer step), at ``precision``."""
    from smart_marl.model.precision import return_gradients, training_copy

    module.zero_grad(set_to_none=True)
    torch.manual_seed(0)
    work = training_copy(module) if precision == "bfloat16" else module
    work(batch, motion_normaliser=1000.0, road_normaliser=1000.0)["loss"].backward()
    if work is not module:
        return_gradients(module, work)
    return torch.cat([p.grad.reshape(-1) for p in module.parameters() if p.grad is not None])


def test_bfloat16_training_on_the_cpu_steps_float32_weights_with_a_bfloat16_working_copy(prior):
    from smart_marl.model.precision import training_copy
    from smart_marl.train import DistInfo, train_step

    batch, model, module, opt, sched = _training_setup(prior)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    out = train_step(module, opt, sched, batch, 1.0, DistInfo(), torch.device("cpu"), amp=False, precision="bfloat16")
    assert torch.isfinite(torch.tensor(out["loss"])) and out["grad_norm"] > 0
    assert all(p.dtype == torch.float32 for p in model.parameters())  # the optimizer's weights and state stay float32
    assert all(v.dtype == torch.float32 for st in opt.state.values() for v in st.values() if v.is_floating_point())
    assert any(not torch.equal(before[k], v) for k, v in model.state_dict().items())
    work = training_copy(module)  # the same copy, loaded with the weights after the step
    assert training_copy(module) is work
    for (name, w), m in zip(work.named_parameters(), module.parameters()):
        want = torch.float32 if name.rsplit(".", 1)[-1] in FLOAT32_PARAMETERS else torch.bfloat16
        assert w.dtype == want, name
        assert torch.equal(w.float(), m.to(want).float()), name


def test_bfloat16_gradients_point_where_the_float32_ones_do(prior):
    batch, model, module, _, _ = _training_setup(prior)
    module.eval()  # no dropout: the padded rows would draw other masks
    fp32, bf16 = _gradients(module, batch, "float32"), _gradients(module, batch, "bfloat16")
    assert bf16.dtype == torch.float32 and bool(torch.isfinite(bf16).all())
    cosine = float(torch.nn.functional.cosine_similarity(fp32, bf16, dim=0))
    assert cosine > 0.99, cosine
    assert 0.9 < float(bf16.norm() / fp32.norm()) < 1.1


def test_a_distributed_or_gpu_run_autocasts_instead():
    from smart_marl.model.precision import uses_training_copy

    assert uses_training_copy("bfloat16", "cpu")
    assert not uses_training_copy("float32", "cpu")
    assert not uses_training_copy("bfloat16", "cpu", distributed=True)
    assert not uses_training_copy("bfloat16", "cuda")
    with pytest.raises(PrecisionError, match="precision"):
        uses_training_copy("half", "cpu")


def test_bucketed_row_counts_are_few_and_waste_at_most_an_eighth():
    from smart_marl.model.precision import bucket_rows

    sizes = [bucket_rows(n) for n in range(1, 200_001)]
    assert all(b >= n for n, b in zip(range(1, 200_001), sizes))
    assert all(b <= max(16, n * 1.125) for n, b in zip(range(1, 200_001), sizes))
    assert len(set(sizes)) <= 8 * 15  # eight a doubling
    assert sizes[16 - 1] == 16 and sizes[1000 - 1] == 1024 and sizes[1025 - 1] == 1152


def test_padded_bfloat16_products_give_the_unpadded_rows(prior):
    """The padding (rows appended, cut off again) changes no row: the MLPs, the Fourier embeddings and the
    attention of a bfloat16 model against the same layers run on exactly the rows given."""
    from smart_marl.model.layers import FourierEmbedding, NeighbourAttention

    torch.manual_seed(0)
    bf16 = inference_model(prior.model, "bfloat16")
    head = bf16.motion_heads[0]
    x = torch.randn(1001, head[0].in_features, dtype=torch.bfloat16)
    unpadded = torch.nn.Sequential.forward(head, x)
    assert torch.allclose(head(x).float(), unpadded.float(), atol=1e-2, rtol=1e-2)
    fourier = next(m for m in bf16.modules() if isinstance(m, FourierEmbedding))
    g = torch.randn(777, fourier.input_dim)
    assert torch.allclose(fourier(g).float(), fourier._embed_rows(g, None, ()).float(), atol=1e-2, rtol=1e-2)
    att = next(m for m in bf16.modules() if isinstance(m, NeighbourAttention))
    q, k, d = 333, 8, att.to_q.in_features
    x_q = torch.randn(q, d, dtype=torch.bfloat16)
    index, mask = torch.randint(0, q, (q, k)), torch.rand(q, k) > 0.3
    rpe = torch.randn(q, k, d, dtype=torch.bfloat16)
    out = att(x_q, (index, rpe), mask)
    assert out.shape == (q, d)
    assert torch.allclose(out.float(), att._attend(x_q, (index, rpe), mask, None).float(), atol=2e-2, rtol=2e-2)
