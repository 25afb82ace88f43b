"""KL-regularised fine-tuning (agents/): the prior as a policy, the top-k reference and its exact KL,
the PPO + KL loss against an independent KL computation, the residual actor starting at the
reference, the evaluation (every policy on the same held-out scenes and seeds, realism of the
controlled agents), a tiny fine-tuning run on real scenes that beats the prior on the same scenes
and seeds, a large-beta run that stays at the prior, and the ``smart-marl finetune`` command.

The prior is a small randomly initialised SMART model whose motion vocabulary is built from the
two real WOMD scenes (as in tests/test_env_smart_traffic.py), saved as a checkpoint in a temporary
folder: a trained prior is not needed for the properties pinned here."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

pytest.importorskip("pettingzoo", reason="the env extra (pettingzoo) is not installed")
pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from agents import PriorPolicy, kl_to_prior, run_episode  # noqa: E402
from agents.evaluate import evaluate_policies, first_collision_kinds  # noqa: E402
from agents.finetune import (  # noqa: E402
    FinetuneConfigError, FinetuneError, build_modules, controlled_selection, core_scenes, evaluation_core, evaluation_policies, finetune, held_out_scenes,
    load_finetune_config, load_policy, load_prior, training_env, training_pool,
)
from agents.kl_ppo import PriorKLPPOLoss  # noqa: E402
from agents.policy import FinetunedTensorPolicy, PolicyError, PolicyLogits, PriorTensorPolicy, token_motion_features  # noqa: E402
from envs import smart_traffic_v0  # noqa: E402
from envs._core import TrafficCore  # noqa: E402
from smart_marl.rollout import DEFAULT_TOP_K, reference_log_probs, sample_tokens  # noqa: E402

VOCAB = 32  # tokens per type of conftest's womd_vocab
WOMD = "womd_tfrecord/*.tfrecord"  # the two real WOMD scenes (17 and 4 moving vehicles)


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture(scope="module")
def prior_path(womd_vocab, save_tiny_prior):
    return save_tiny_prior(womd_vocab)


GPUDRIVE = "gpudrive_json"  # held-out scenes of the tiny runs that fine-tune on both WOMD scenes


def tiny(shared_data, prior_path, out_dir, **over) -> dict:
    """The tests' overrides of the ``tiny`` config: the real scenes, the test prior, a top-5 reference and a
    background that samples its top 5 too (so the evaluation has one prior top-k row)."""
    return {"scenes": str(shared_data / WOMD), "prior": str(prior_path), "out_dir": str(out_dir), "tensorboard": False,
            "eval_scenes": str(shared_data / GPUDRIVE), "eval_num_scenes": 1, "reference_top_k": 5, "top_k": 5, **over}


def pettingzoo_env(cfg, model, vocab, scenes, **kw):
    """The one-scene PettingZoo env with the run's settings."""
    return smart_traffic_v0.parallel_env(scenarios=scenes, prior=model, motion_vocab=vocab, controlled=controlled_selection(cfg),
                                         max_agents=cfg.max_agents, background=cfg.background, horizon_steps=cfg.horizon_steps,
                                         observation="dict", top_k=cfg.top_k, temperature=cfg.temperature,
                                         reference_top_k=cfg.reference_top_k, **kw)


def training_scenes(cfg):
    pool = training_pool(cfg)
    return [pool.scenario(i) for i in range(len(pool))]


@pytest.fixture(scope="module")
def tiny_run(shared_data, prior_path, tmp_path_factory):
    """The named ``tiny`` config on the two real scenes: about one minute on one CPU thread (measured
    59 s with a training run busy on the other core), shared by the two tests that use it; its
    evaluation runs on one held-out GPUDrive scene, 2 seeds."""
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path_factory.mktemp("tiny"), eval_episodes=2))
    return cfg, finetune(cfg)


def test_evaluation_has_a_row_for_the_reference_k_and_one_for_the_background_k_when_they_differ():
    """The defaults: a top-3 reference and a background sampling DEFAULT_TOP_K; each k gets its row, once."""
    cfg = load_finetune_config("tiny", {"reference_top_k": 3, "top_k": DEFAULT_TOP_K})
    names = list(evaluation_policies(cfg, net=None))
    assert names == ["expert (log)", "prior top-3", f"prior top-{DEFAULT_TOP_K}", "prior full softmax"]
    same = load_finetune_config("tiny", {"reference_top_k": 5, "top_k": 5})
    assert list(evaluation_policies(same, net=None)) == ["expert (log)", "prior top-5", "prior full softmax"]


# ------------------------------------------------------------------------------- the prior
def test_prior_policy_samples_the_infos_logits_and_has_zero_kl(shared_data, prior_path):
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, "unused"))
    model, vocab = load_prior(cfg.prior)
    env = pettingzoo_env(cfg, model, vocab, training_scenes(cfg))
    obs, infos = env.reset(seed=3)
    policy = PriorPolicy(top_k=None)
    policy.reset(3)
    actions = policy(obs, infos)
    gen = torch.Generator().manual_seed(3)
    expect, _ = sample_tokens(torch.from_numpy(np.stack([infos[a]["prior_logits"] for a in env.agents])), gen, top_k=None)
    assert list(actions) == env.agents and list(actions.values()) == expect.tolist()
    ep = run_episode(env, PriorPolicy(top_k=None), seed=3)
    assert sum(ep["steps"].values()) > 0
    assert max(ep["kl_to_full_prior"].values()) < 1e-5  # the prior's KL to itself
    assert min(ep["kl_to_reference"].values()) == float("inf")  # the full softmax puts mass outside the top-5 reference
    ep = run_episode(env, PriorPolicy(top_k=cfg.reference_top_k), seed=3)
    assert max(ep["kl_to_reference"].values()) < 1e-5 < min(ep["kl_to_full_prior"].values())


def test_top_k_reference_kl_is_exact_on_a_hand_made_case():
    """Prior probabilities 4:3:2:1 (logits log 4 .. log 1, float64); the top-2 reference is (4/7, 3/7, 0, 0)."""
    prior = torch.log(torch.tensor([[4.0, 3.0, 2.0, 1.0]], dtype=torch.float64))
    half = torch.log(torch.tensor([[0.5, 0.5, 0.0, 0.0]], dtype=torch.float64))  # log 0 = -inf: tokens the policy never takes
    expect = 0.5 * np.log(0.5 / (4 / 7)) + 0.5 * np.log(0.5 / (3 / 7))
    assert float(kl_to_prior(half, prior, top_k=2)) == pytest.approx(expect, rel=1e-12)
    # against the full softmax (0.4, 0.3, 0.2, 0.1) the same policy is further away
    assert float(kl_to_prior(half, prior)) == pytest.approx(0.5 * np.log(0.5 / 0.4) + 0.5 * np.log(0.5 / 0.3), rel=1e-12)
    # the reference itself: 0; mass on a token outside the top-2: infinite
    assert float(kl_to_prior(reference_log_probs(prior, 2), prior, top_k=2)) == pytest.approx(0.0, abs=1e-15)
    assert float(kl_to_prior(torch.log(torch.tensor([[0.5, 0.0, 0.5, 0.0]], dtype=torch.float64)), prior, top_k=2)) == float("inf")
    # temperature 2: logits halved, probabilities ~ sqrt(4), sqrt(3) on the top-2
    p = np.sqrt([4.0, 3.0]) / np.sqrt([4.0, 3.0]).sum()
    assert float(kl_to_prior(half, prior, temperature=2.0, top_k=2)) == pytest.approx(float((0.5 * np.log(0.5 / p)).sum()), rel=1e-12)
    # the gradient through a policy masked to the top-2 stays finite
    logits = torch.tensor([[1.0, 0.5, float("-inf"), float("-inf")]], requires_grad=True)
    kl_to_prior(torch.log_softmax(logits, -1), prior, top_k=2).sum().backward()
    assert torch.isfinite(logits.grad).all() and logits.grad[0, :2].abs().sum() > 0


def test_first_collision_kinds_say_who_ran_into_whom():
    """Four cars (4.5 x 2 m) in a row of frames: 0 heads +x at 5 m/s, 1 starts 8 m behind it at 10 m/s and
    runs into it (0 is rear-ended, 1 hits the one ahead); 2 comes at 0's left side, down the y axis; 3 is
    far away; 4 sits on top of 0 but is never present."""
    f = 20
    t = np.arange(f) * 0.1
    poses = np.zeros((5, f, 3))
    poses[0, :, 0] = 5 * t
    poses[1, :, 0] = -8 + 10 * t
    poses[2, :, 0], poses[2, :, 1], poses[2, :, 2] = 4.0, 6 - 4 * t, -np.pi / 2
    poses[3, :, 0], poses[3, :, 1] = 200.0, 50.0
    poses[4, :, 0] = 5 * t  # on top of 0, but absent
    present = np.ones((5, f), bool)
    present[4] = False
    box = np.tile([4.5, 2.0, 1.5], (5, 1))
    assert first_collision_kinds(poses, present, box, [0, 1, 3]) == ["rear_ended", "front", None]
    # without car 1, car 2 drives into 0's side: 0 is hit on its side, 2 hit what was ahead of it
    present[1] = False
    assert first_collision_kinds(poses, present, box, [0, 2]) == ["side", "front"]


def test_env_action_mask_and_infos_carry_the_top_k_reference(shared_data, prior_path):
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, "unused", reference_top_k=3))
    model, vocab = load_prior(cfg.prior)
    env = pettingzoo_env(cfg, model, vocab, training_scenes(cfg))
    obs, infos = env.reset(seed=1)
    assert env.reference == "prior top-3"
    for a in env.agents:
        logits = torch.from_numpy(obs[a]["prior_logits"])
        top3 = set(torch.topk(logits, 3).indices.tolist())
        assert set(np.flatnonzero(obs[a]["action_mask"]).tolist()) == top3
        logp = torch.from_numpy(infos[a]["prior_log_probs"])
        assert set(torch.isfinite(logp).nonzero().flatten().tolist()) == top3
        assert float(torch.logsumexp(logp, -1)) == pytest.approx(0.0, abs=1e-5)  # renormalised on the top-3
        assert infos[a]["reference_top_k"] == 3


def test_residual_actor_starts_exactly_at_the_prior_logits():
    net = PolicyLogits(obs_dim=10, vocab_size=VOCAB, n_agents=3, hidden=16, depth=2, residual=True, temperature=0.5)
    obs, prior = torch.randn(5, 3, 10) * 30, torch.randn(5, 3, VOCAB)
    torch.testing.assert_close(net(obs, prior), prior / 0.5, rtol=0, atol=0)
    free = PolicyLogits(obs_dim=10, vocab_size=VOCAB, n_agents=3, hidden=16, depth=2, residual=False)
    assert not torch.allclose(free(obs, prior), prior)


def test_residual_actor_with_a_top_k_reference_starts_at_it_and_samples_what_the_prior_top_k_samples():
    net = PolicyLogits(obs_dim=10, vocab_size=VOCAB, n_agents=3, hidden=16, depth=2, residual=True, temperature=0.5, top_k=5)
    obs, prior = torch.randn(5, 3, 10) * 30, torch.randn(5, 3, VOCAB)
    logp = torch.log_softmax(net(obs, prior), -1)
    torch.testing.assert_close(logp, reference_log_probs(prior, 5, 0.5), rtol=0, atol=1e-6)
    assert float(kl_to_prior(logp, prior, 0.5, 5).abs().max()) < 1e-6
    tuned, prior_top5 = FinetunedTensorPolicy(net), PriorTensorPolicy(top_k=5, temperature=0.5)
    for seed in range(3):
        tuned.reset(seed)
        prior_top5.reset(seed)
        a = tuned.act(tuned.log_probs(None, obs, prior))
        b = prior_top5.act(prior_top5.log_probs(None, obs, prior))
        assert a.tolist() == b.tolist()


def test_motion_head_scores_each_token_by_its_types_motion_features_and_starts_at_the_prior(womd_vocab):
    """actor_head="motion": f(obs) gives 6 weights and token v of an agent of type t scores
    sum_p w_p feat[t, v, p], the features being where the token ends (forward, left, turn) and their
    squares, standardised over the type's tokens; the type comes from the observation's one-hot."""
    feats = token_motion_features(womd_vocab, VOCAB)
    assert feats.shape == (3, VOCAB, 6)
    torch.testing.assert_close(feats.mean(1), torch.zeros(3, 6), rtol=0, atol=1e-5)
    torch.testing.assert_close(feats.std(1), torch.ones(3, 6), rtol=0, atol=1e-4)
    end = torch.as_tensor(np.asarray(womd_vocab[0].poses)[:, -1], dtype=torch.float32)  # vehicle tokens (V, 3)
    forward = end[:, 0]
    assert torch.corrcoef(torch.stack([feats[0, :, 0], forward]))[0, 1] > 0.999  # the first feature is how far it goes
    assert token_motion_features(womd_vocab, VOCAB + 1).abs().sum() == 0  # no type has that many tokens
    from envs.smart_traffic_v0 import ObservationConfig, observation_layout, observation_size

    obs_dim = observation_size(ObservationConfig())  # the env's default observation
    off = next(o for name, o, _ in observation_layout(ObservationConfig()) if name == "ego_type")  # vehicle, pedestrian, cyclist
    net = PolicyLogits(obs_dim, VOCAB, n_agents=3, hidden=16, depth=2, residual=True, temperature=0.5, motion_features=feats)
    obs, prior = torch.randn(5, 3, obs_dim), torch.randn(5, 3, VOCAB)
    obs[..., off : off + 3] = 0
    obs[:, 0, off] = obs[:, 1, off + 1] = 1  # agent 0 a vehicle, agent 1 a pedestrian, agent 2 a padded slot (no type)
    torch.testing.assert_close(net(obs, prior), prior / 0.5, rtol=0, atol=0)  # starts exactly at the prior
    w = torch.tensor([2.0, -1.0, 0.5, -3.0, 0.0, 1.0])
    with torch.no_grad():
        params = dict(net.f.named_parameters())
        last_bias = max((n for n in params if n.endswith("bias")), key=lambda n: int(n.split(".")[1]))
        params[last_bias].copy_(w)  # the last layer's weights are 0: f(obs) = w for every agent
    delta = net(obs, prior) - prior / 0.5
    torch.testing.assert_close(delta[:, 0], (feats[0] @ w).expand(5, -1), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(delta[:, 1], (feats[1] @ w).expand(5, -1), rtol=1e-5, atol=1e-5)
    assert delta[:, 2].abs().max() == 0
    with pytest.raises(PolicyError, match="motion_features"):
        PolicyLogits(obs_dim, VOCAB + 1, n_agents=3, hidden=16, depth=2, motion_features=feats)


def test_prior_kl_loss_adds_beta_times_the_exact_kl_of_agents_that_acted():
    """The loss's extra term equals beta * mean over acting agents of sum_v pi (log pi - log prior),
    computed here independently from the actor's logits; masked agents do not count."""
    from tensordict import TensorDict

    cfg = load_finetune_config({"hidden": 16, "critic": "ippo", "normalize_advantage": False, "reference_top_k": 5})
    obs_dim, n_agents, batch = 7, 3, 6
    net, actor, critic = build_modules(cfg, obs_dim, VOCAB, n_agents)
    torch.manual_seed(1)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0, 0.3)  # move the policy off the prior
    prior = torch.randn(batch, n_agents, VOCAB)
    prior[0, 2] = 0  # an agent the prior no longer simulates
    mask = torch.ones(batch, n_agents, dtype=torch.bool)
    mask[1, 0] = mask[4, 1] = False  # done agents
    td = TensorDict({"agents": TensorDict({
        "observation": TensorDict({"observation": torch.randn(batch, n_agents, obs_dim), "prior_logits": prior}, [batch, n_agents]),
        "mask": mask, "advantage": torch.randn(batch, n_agents, 1), "value_target": torch.randn(batch, n_agents, 1)},
        [batch, n_agents])}, [batch])
    with torch.no_grad():
        actor(td)
    losses = {}
    for beta in (0.0, 2.5):
        loss = PriorKLPPOLoss(actor, critic, beta=beta, entropy_bonus=False, normalize_advantage=False)
        loss.set_keys(action=("agents", "action"), sample_log_prob=("agents", "action_log_prob"), value=("agents", "state_value"),
                      advantage=("agents", "advantage"), value_target=("agents", "value_target"))
        with torch.no_grad():
            losses[beta] = loss(td.clone())
    logp = torch.log_softmax(net(td["agents", "observation", "observation"], prior), -1)
    kl = torch.where(logp.exp() > 0, logp.exp() * (logp - torch.log_softmax(prior, -1)), torch.zeros(())).sum(-1)  # 0 log 0 = 0
    valid = mask & prior.ne(0).any(-1)
    expect = kl[valid].mean()
    assert float(losses[2.5]["loss_prior_kl"]) == pytest.approx(2.5 * float(expect), rel=1e-5)
    assert float(losses[2.5]["kl_to_prior"]) == pytest.approx(float(expect), rel=1e-5)
    assert float(losses[0.0]["loss_prior_kl"]) == 0.0
    assert float(losses[2.5]["loss_objective"]) == pytest.approx(float(losses[0.0]["loss_objective"]), rel=1e-6)
    assert float(expect) > 0.05
    # the top-5 reference (the tests' config; the actor is masked to it): renormalised on the prior's top 5
    assert net.top_k == cfg.reference_top_k == 5
    loss = PriorKLPPOLoss(actor, critic, beta=1.0, entropy_bonus=False, normalize_advantage=False, reference_top_k=5)
    loss.set_keys(action=("agents", "action"), sample_log_prob=("agents", "action_log_prob"), value=("agents", "state_value"),
                  advantage=("agents", "advantage"), value_target=("agents", "value_target"))
    with torch.no_grad():
        out = loss(td.clone())
    top5 = torch.zeros_like(prior, dtype=torch.bool).scatter(-1, torch.topk(prior, 5).indices, True)
    ref = torch.log_softmax(prior.masked_fill(~top5, float("-inf")), -1)
    kl5 = torch.where(logp.exp() > 0, logp.exp() * (logp - ref), torch.zeros(())).sum(-1)
    assert loss.reference == "prior top-5"
    assert float(out["kl_to_prior"]) == pytest.approx(float(kl5[valid].mean()), rel=1e-5)


# ------------------------------------------------------------------------------- the runs
def test_tiny_finetuning_reaches_logged_goals_more_often_than_the_prior(tiny_run, prior_path):
    """On the two real scenes it was trained on, same 8 seeds (background sampler and policy
    sampler), 64 agent-episodes per policy, the training env (events end an agent's episode): the
    fine-tuned agents reach their logged goals more often (or collide less) than the prior top-5
    (the reference they started from), by at least 3 agent-episodes in 64, with the KL reported."""
    cfg, result = tiny_run
    model, vocab = load_prior(cfg.prior)
    pool = training_pool(cfg)
    assert pool.scenario_ids() == result.scene_ids
    scenes = core_scenes(cfg, pool, vocab, len(pool))
    core = TrafficCore(model, vocab, cfg.background, cfg.horizon_steps, terminate_on=cfg.terminate_on, top_k=cfg.top_k, record=True)
    _, net, _ = load_policy(result.checkpoint)
    seeds = list(range(cfg.eval_seed, cfg.eval_seed + 8))
    rows = evaluate_policies(core, scenes, {"prior top-5": PriorTensorPolicy(top_k=5), "fine-tuned": FinetunedTensorPolicy(net)},
                             seeds, num_envs=4, vocab_size=VOCAB, num_agents=cfg.max_agents, reference_top_k=5)["rows"]
    prior, tuned = rows["prior top-5"], rows["fine-tuned"]
    print("\n" + json.dumps(rows, indent=1))
    assert prior["agent_episodes"] == tuned["agent_episodes"] == 2 * 4 * 8
    assert prior["kl_to_reference"] < 1e-5 < tuned["kl_to_reference"] < float("inf")
    assert tuned["goal_rate"] >= prior["goal_rate"] + 0.05 or tuned["collision_rate"] <= prior["collision_rate"] - 0.05
    assert tuned["return"] > prior["return"]
    for row in rows.values():  # every collision has one kind
        kinds = row["rear_ended_rate"] + row["front_collision_rate"] + row["side_collision_rate"]
        assert kinds == pytest.approx(row["collision_rate"])
    # the training log: every iteration, KL to the prior grows from 0 as the policy leaves it
    hist = result.history
    assert len(hist) == cfg.iterations and hist[0]["kl_to_prior"] < 1e-3 < hist[-1]["kl_to_prior"]
    csv_rows = (result.out_dir / "finetune.csv").read_text().splitlines()
    assert len(csv_rows) == 1 + cfg.iterations and csv_rows[0].startswith("iteration,frames")


def test_evaluation_refuses_an_override_of_the_saved_policys_network(tiny_run, capsys):
    """Issue 34: ``hidden=128`` at evaluation was ignored (the network is the checkpoint's); it is refused, before
    anything runs, as is ``--episodes 0`` (which became one seed)."""
    from agents.finetune import evaluate_checkpoint
    from smart_marl.cli import main

    cfg, result = tiny_run
    assert main(["finetune", "--evaluate", str(result.checkpoint), "hidden=128"]) == 2
    err = capsys.readouterr().err
    assert f"hidden=128 (the checkpoint's: {cfg.hidden})" in err and "the policy's network was built with" in err
    with pytest.raises(FinetuneConfigError, match="--episodes must be at least 1, got 0"):
        evaluate_checkpoint(result.checkpoint, episodes=0)
    with pytest.raises(FinetuneConfigError, match=r"--episodes must be at least 1, got -3"):
        evaluate_checkpoint(result.checkpoint, episodes=-3)


def test_policy_checkpoint_round_trips_and_evaluate_command_prints_the_table(tiny_run, capsys):
    from smart_marl.cli import main

    cfg, result = tiny_run
    cfg2, net, meta = load_policy(result.checkpoint)
    assert cfg2.to_dict() == cfg.to_dict() and meta["iteration"] == cfg.iterations
    obs, prior = torch.randn(2, 4, meta["obs_dim"]), torch.randn(2, 4, VOCAB)
    assert not torch.allclose(net(obs, prior), prior)  # trained weights, not the zero-initialised residual
    assert main(["finetune", "--evaluate", str(result.checkpoint), "--episodes", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert list(out["rows"]) == ["expert (log)", f"prior top-{cfg.top_k}", "prior full softmax", "fine-tuned"]
    assert out["seeds"] == [cfg.eval_seed] and out["reference"] == "prior top-5"
    assert not set(out["scenes"]) & set(out["training_scenes"])  # held-out scenes
    # the same scenes and seeds give the same episodes: a second evaluation reproduces every number
    assert main(["finetune", "--evaluate", str(result.checkpoint), "--episodes", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["rows"] == out["rows"]
    assert main(["finetune", "--evaluate", str(result.checkpoint), "--episodes", "1"]) == 0
    table = capsys.readouterr().out
    assert "collision" in table and "fine-tuned" in table and "KL/step" in table and "realism" in table


def test_a_short_run_collects_its_first_batch_at_the_prior_and_writes_its_files(shared_data, prior_path, tmp_path):
    """Two small iterations: the first batch is collected by the zero-initialised residual actor,
    so its KL to the prior is 0; the update moves it; CSV, config, checkpoints and the resume state are written."""
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path, iterations=2, frames_per_batch=32,
                                            minibatch_size=32, ppo_epochs=1, eval_episodes=0, checkpoint_every=1, critic="ippo",
                                            tensorboard=True))
    result = finetune(cfg)
    assert result.evaluation is None and len(result.history) == 2
    assert result.history[0]["kl_to_prior"] < 1e-6 < result.history[1]["kl_to_prior"]
    assert result.history[1]["frames"] == 64
    names = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    assert names == [f"{n}.{ext}" for n in ("policy_0001", "policy_0002", "policy_last", "resume") for ext in ("json", "safetensors")]
    assert json.loads((tmp_path / "config.json").read_text())["critic"] == "ippo"
    assert len((tmp_path / "finetune.csv").read_text().splitlines()) == 3
    try:
        import torch.utils.tensorboard  # noqa: F401
    except ImportError:
        return
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))


def test_a_short_run_with_the_motion_head_saves_its_features_and_loads_back(shared_data, prior_path, tmp_path):
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path, iterations=2, frames_per_batch=32,
                                            minibatch_size=32, ppo_epochs=1, eval_episodes=0, actor_head="motion"))
    result = finetune(cfg)
    assert result.history[0]["kl_to_prior"] < 1e-6 < result.history[1]["kl_to_prior"]
    cfg2, net, meta = load_policy(result.checkpoint)
    assert cfg2.actor_head == "motion"
    _, vocab = load_prior(cfg.prior)
    torch.testing.assert_close(net.motion_features, token_motion_features(vocab, meta["vocab_size"]), rtol=0, atol=0)
    config = result.checkpoint.with_suffix(".json")
    meta_json = json.loads(config.read_text())
    meta_json["config"]["actor_head"] = "per_token"
    config.write_text(json.dumps(meta_json))
    with pytest.raises(FinetuneError, match="actor_head"):
        load_policy(result.checkpoint)
    with pytest.raises(FinetuneError, match="actor_head"):
        load_finetune_config("tiny", {"actor_head": "tokens"})


def test_with_a_large_beta_the_kl_stays_near_zero_and_behaviour_matches_the_prior(shared_data, prior_path, tmp_path):
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path, beta=100.0, iterations=4, eval_episodes=4))
    result = finetune(cfg)
    assert max(r["kl_to_prior"] for r in result.history) < 1e-3
    rows = result.evaluation["rows"]
    prior, tuned = rows["prior top-5"], rows["fine-tuned"]
    assert tuned["kl_to_reference"] < 1e-3
    # episode rates agree up to sampling noise: 32 agent-episodes per policy whose trajectories part
    # after the first token drawn differently (binomial standard error ~0.07 at these rates)
    for key in ("goal_rate", "collision_rate", "offroad_rate"):
        assert abs(tuned[key] - prior[key]) <= 0.15, (key, prior, tuned)
    # state by state: the fine-tuned action distribution is the prior's (total variation, Pinsker: <= sqrt(KL / 2))
    model, vocab = load_prior(cfg.prior)
    env = training_env(cfg, training_pool(cfg), model, vocab, seed=0)
    _, net, _ = load_policy(result.checkpoint)
    td = env.reset()
    obs, prior = td["agents", "observation", "observation"], td["agents", "observation", "prior_logits"]
    mask = td["agents", "mask"]
    p_prior = PriorTensorPolicy(top_k=5).log_probs(env.core, obs, prior).exp()
    p_tuned = FinetunedTensorPolicy(net).log_probs(env.core, obs, prior).exp()
    tv = 0.5 * (p_prior - p_tuned).abs().sum(-1)
    assert mask.sum() >= 4 and float(tv[mask].max()) < 0.05


# ------------------------------------------------------------------------------- the config
def test_config_names_overrides_and_errors(shared_data, prior_path):
    cfg = load_finetune_config("tiny", ["beta=0.5", "reward.collision=-2", "critic=ippo"])
    assert cfg.beta == 0.5 and cfg.reward == {"collision": -2} and cfg.critic == "ippo" and cfg.max_agents == 4
    # a whole reward dict replaces the config's (a dict of overrides, as the trade-off sweep passes it, or key=value)
    assert load_finetune_config(cfg.to_dict(), {"reward": {"prior_log_likelihood": 0.05}}).reward == {"prior_log_likelihood": 0.05}
    assert load_finetune_config(cfg.to_dict(), ['reward={"goal_reached": 2}', "reward.comfort=-0.1"]).reward == {
        "goal_reached": 2, "comfort": -0.1}
    assert load_finetune_config("default").iterations > cfg.iterations
    with pytest.raises(FinetuneError, match="unknown fine-tuning config key"):
        load_finetune_config("tiny", ["betta=1"])
    with pytest.raises(FinetuneError, match="neither a file nor a named config"):
        load_finetune_config("huge")
    with pytest.raises(FinetuneError, match="critic"):
        load_finetune_config("tiny", ["critic=central"])
    with pytest.raises(FinetuneError, match="no checkpoint"):
        load_prior(str(prior_path.parent / "missing"))
    # the named configs' default scenes: the package's SUMO samples
    cfg = load_finetune_config("tiny", {"prior": str(prior_path)})
    assert [i[:4] for i in training_pool(cfg).scenario_ids()] == ["sumo", "sumo"]
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, "unused", num_scenes=40))
    with pytest.raises(FinetuneError, match="holds 2 scene"):
        training_pool(cfg)
    with pytest.raises(FinetuneError, match="num_envs"):
        load_finetune_config("tiny", ["num_envs=200"])


# ------------------------------------------------------------------------------- the evaluation
class _Spy(PriorTensorPolicy):
    """The prior top-5, recording the scenes and seed of every wave of episodes it drives."""

    def __init__(self):
        super().__init__(top_k=5)
        self.waves, self.core = [], None

    def log_probs(self, core, observation, prior_logits):
        if self.core is None:
            self.core = core
            self.waves.append(([st.scenario.scenario_id for st in core.scenes.statics], self.seed))
        return super().log_probs(core, observation, prior_logits)

    def reset(self, seed):
        super().reset(seed)
        self.core, self.seed = None, int(seed)


def test_evaluation_runs_every_policy_on_the_same_scenes_and_seeds(shared_data, prior_path):
    """Every policy drives the same (scene, seed) episodes in the same waves; two copies of one policy
    therefore give identical rows, realism of the controlled agents included (the full 8 s, nobody removed)."""
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, "unused", background="prior", eval_num_scenes=2))
    model, vocab = load_prior(cfg.prior)
    scenes = held_out_scenes(cfg, vocab, training_pool(cfg).scenario_ids())
    core = evaluation_core(cfg, model, vocab, len(scenes))
    spies = {"a": _Spy(), "b": _Spy(), "full": PriorTensorPolicy(top_k=None)}
    result = evaluate_policies(core, scenes, spies, [7, 8], num_envs=3, vocab_size=VOCAB, num_agents=cfg.max_agents,
                               reference_top_k=5)
    ids = [sc.static.scenario.scenario_id for sc in scenes]
    assert spies["a"].waves == spies["b"].waves == [([ids[0], ids[0], ids[1]], 7), ([ids[1]], 8)]  # 4 episodes, 3 at a time
    assert result["rows"]["a"] == result["rows"]["b"]
    a, full = result["rows"]["a"], result["rows"]["full"]
    assert a["steps"] == a["agent_episodes"] * cfg.horizon_steps  # no termination: every agent drives the horizon
    assert result["realism_scenes"] == ids and 0 < a["meta_metric"] < 1 and a["min_ade"] >= 0
    assert a != full and full["kl_to_reference"] == float("inf") and full["kl_to_full_prior"] < 1e-5


def test_a_run_on_a_pool_larger_than_its_batch_plays_every_scene(tmp_path):
    """The package's 4 sample scenes, 2 at a time, episodes of 2 steps: finished scenes are refilled
    from the pool, so after 3 iterations of 8 scene-steps every scene has been played."""
    cfg = load_finetune_config("tiny", {"num_scenes": 4, "num_envs": 2, "horizon_steps": 2, "iterations": 3, "frames_per_batch": 8,
                                        "minibatch_size": 8, "ppo_epochs": 1, "eval_episodes": 0, "out_dir": str(tmp_path),
                                        "tensorboard": False, "controlled": "vehicles"})
    result = finetune(cfg)
    assert [r["scenes_seen"] for r in result.history][-1] == 4
    assert result.history[-1]["frames"] == 24 and result.history[0]["agent_episodes"] > 0


def test_a_time_limit_ends_the_run_after_the_iteration_that_passes_it_and_saves_the_last_policy(tmp_path):
    cfg = load_finetune_config("tiny", {"num_scenes": 2, "num_envs": 2, "horizon_steps": 2, "iterations": 50, "frames_per_batch": 4,
                                        "minibatch_size": 4, "ppo_epochs": 1, "eval_episodes": 0, "out_dir": str(tmp_path),
                                        "tensorboard": False, "controlled": "vehicles", "time_limit_s": 1e-6})
    result = finetune(cfg)
    assert len(result.history) == 1 and result.history[0]["seconds"] >= 1e-6
    assert result.checkpoint is not None and result.checkpoint.name.startswith("policy_last")
    assert json.loads(result.checkpoint.read_text())["iteration"] == 1
    with pytest.raises(FinetuneConfigError, match="time_limit_s"):
        load_finetune_config("tiny", ["time_limit_s=-1"])


def test_tiny_finetune_then_evaluate_on_held_out_scenes(shared_data, prior_path, tmp_path):
    """Fine-tune on one WOMD scene, evaluate on a held-out GPUDrive scene: the four rows, the same
    seeds for all, the KL of each row to the top-5 reference, realism of the controlled agents."""
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path, num_scenes=1, iterations=2, frames_per_batch=32,
                                            minibatch_size=32, ppo_epochs=1, eval_episodes=2, checkpoint_every=2))
    result = finetune(cfg)
    ev = result.evaluation
    assert json.loads((tmp_path / "evaluation.json").read_text())["rows"].keys() == ev["rows"].keys()
    assert list(ev["rows"]) == ["expert (log)", "prior top-5", "prior full softmax", "fine-tuned"]
    assert ev["training_scenes"] == result.scene_ids and len(ev["scenes"]) == 1 and ev["scenes"][0] not in result.scene_ids
    assert ev["seeds"] == [cfg.eval_seed, cfg.eval_seed + 1] and ev["reference"] == "prior top-5"
    rows = ev["rows"]
    assert len({r["agent_episodes"] for r in rows.values()}) == 1
    assert rows["prior top-5"]["kl_to_reference"] < 1e-5 < rows["fine-tuned"]["kl_to_reference"] < float("inf")
    assert rows["prior full softmax"]["kl_to_full_prior"] < 1e-5 and rows["prior full softmax"]["kl_to_reference"] == float("inf")
    for r in rows.values():
        assert 0 < r["meta_metric"] < 1 and 0 <= r["collision_rate"] <= 1 and np.isfinite(r["progress_m"])
    assert rows["expert (log)"]["min_ade"] < rows["prior full softmax"]["min_ade"]  # the log-follower stays near its log


def test_a_short_run_with_the_shield_trains_on_masked_logits_and_evaluates_with_it(shared_data, prior_path, tmp_path, monkeypatch):
    """The shield puts -inf in the prior's logits: PPO, the KL and the evaluation must stay finite, and the
    checkpoint keeps the setting (the policy is evaluated with the shield it was trained with)."""
    import envs._core

    taken_out = []
    shield = envs._core.unsafe_tokens
    monkeypatch.setattr(envs._core, "unsafe_tokens", lambda *a: taken_out.append(int((out := shield(*a)).sum())) or out)
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path, iterations=2, frames_per_batch=32, minibatch_size=32,
                                            ppo_epochs=1, eval_episodes=1, critic="ippo", shield=["collision", "offroad"]))
    result = finetune(cfg)
    for row in result.history:
        assert all(math.isfinite(row[k]) for k in ("loss_objective", "loss_critic", "loss_prior_kl", "kl_to_prior")), row
    assert result.history[1]["kl_to_prior"] > 1e-6  # it learnt something
    saved, _, _ = load_policy(result.checkpoint)
    assert saved.shield == ("collision", "offroad")
    rows = result.evaluation["rows"]
    assert math.isfinite(rows["fine-tuned"]["kl_to_reference"]) and rows["fine-tuned"]["agent_episodes"] > 0
    assert sum(taken_out) > 0  # the shield did take tokens out along the way


def test_a_run_started_from_a_checkpoint_takes_its_actor_and_critic_and_refuses_another_network(shared_data, prior_path, tmp_path):
    """``init=CHECKPOINT``: the run's first batch is collected by the checkpoint's actor (not at the prior, as a
    fresh run's is), both networks hold its weights, and a checkpoint of another network is refused by name."""
    from agents.finetune import start_from
    from agents.policy import read_policy

    short = dict(iterations=2, frames_per_batch=32, minibatch_size=32, ppo_epochs=1, eval_episodes=0, critic="ippo", lr=0.01)
    first = finetune(load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path / "a", **short)))
    assert first.history[-1]["kl_to_prior"] > 1e-6
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path / "b", **short, init=str(first.checkpoint)))
    second = finetune(cfg)
    assert second.history[0]["kl_to_prior"] > 1e-6  # a fresh run's first batch is at the prior (KL 0)
    meta, weights = read_policy(first.checkpoint)
    model, vocab = load_prior(cfg.prior)
    dims = {k: meta[k] for k in ("obs_dim", "vocab_size", "n_agents")} | {"prior_sha256": meta["prior_sha256"]}
    net, _, critic = build_modules(cfg, dims["obs_dim"], dims["vocab_size"], dims["n_agents"], vocab)
    start_from(first.checkpoint, cfg, dims, net, critic.module)
    for prefix, module in (("actor.", net), ("critic.", critic.module)):
        for k, v in module.state_dict().items():
            torch.testing.assert_close(v, weights[prefix + k], rtol=0, atol=0)
    other = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path / "c", **short, init=str(first.checkpoint), hidden=16))
    with pytest.raises(FinetuneConfigError, match=r"hidden=16 \(the checkpoint's: 64\)"):
        finetune(other)
    with pytest.raises(FinetuneError, match="init: .*not a policy checkpoint"):
        finetune(load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path / "d", **short, init=str(tmp_path / "none"))))
