"""KL-regularised fine-tuning (agents/): the prior as a policy, the PPO + KL loss against an
independent KL computation, the residual actor starting at the prior, a tiny fine-tuning run on
real scenes that beats the prior on the same scenes and seeds, a large-beta run that stays at the
prior, and the ``smart-marl finetune`` command.

The prior is a small randomly initialised SMART model whose motion vocabulary is built from the
two real WOMD scenes (as in tests/test_env_smart_traffic.py), saved as a checkpoint in a temporary
folder: a trained prior is not needed for the properties pinned here."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("pettingzoo", reason="the env extra (pettingzoo) is not installed")
pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from agents import PriorPolicy, run_episode  # noqa: E402
from agents.finetune import (  # noqa: E402
    FinetuneError, FinetunedPolicy, PolicyLogits, build_modules, finetune, load_finetune_config, load_policy, load_prior,
    scene_env, select_scenes,
)
from agents.kl_ppo import PriorKLPPOLoss  # noqa: E402
from smart_marl.rollout import sample_tokens  # noqa: E402

VOCAB = 32  # tokens per type of conftest's womd_vocab
WOMD = "womd_tfrecord/*.tfrecord"  # the two real WOMD scenes (17 and 4 moving vehicles)


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture(scope="module")
def prior_path(womd_vocab, save_tiny_prior):
    return save_tiny_prior(womd_vocab)


def tiny(shared_data, prior_path, out_dir, **over) -> dict:
    return {"scenes": str(shared_data / WOMD), "prior": str(prior_path), "out_dir": str(out_dir), "tensorboard": False, **over}


@pytest.fixture(scope="module")
def tiny_run(shared_data, prior_path, tmp_path_factory):
    """The named ``tiny`` config on the two real scenes: about one minute on one CPU thread (measured
    59 s with a training run busy on the other core), shared by the two tests that use it."""
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path_factory.mktemp("tiny")))
    return cfg, finetune(cfg)


# ------------------------------------------------------------------------------- the prior
def test_prior_policy_samples_the_infos_logits_and_has_zero_kl(shared_data, prior_path):
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, "unused"))
    model, vocab = load_prior(cfg.prior)
    env = scene_env(cfg, select_scenes(cfg, model, vocab), model, vocab)
    obs, infos = env.reset(seed=3)
    policy = PriorPolicy(top_k=None)
    policy.reset(3)
    actions = policy(obs, infos)
    gen = torch.Generator().manual_seed(3)
    expect, _ = sample_tokens(torch.from_numpy(np.stack([infos[a]["prior_logits"] for a in env.agents])), gen, top_k=None)
    assert list(actions) == env.agents and list(actions.values()) == expect.tolist()
    ep = run_episode(env, PriorPolicy(top_k=None), seed=3)
    assert sum(ep["steps"].values()) > 0
    assert max(ep["kl_to_prior"].values()) < 1e-5  # the prior's KL to itself


def test_residual_actor_starts_exactly_at_the_prior_logits():
    net = PolicyLogits(obs_dim=10, vocab_size=VOCAB, n_agents=3, hidden=16, depth=2, residual=True, temperature=0.5)
    obs, prior = torch.randn(5, 3, 10) * 30, torch.randn(5, 3, VOCAB)
    torch.testing.assert_close(net(obs, prior), prior / 0.5, rtol=0, atol=0)
    free = PolicyLogits(obs_dim=10, vocab_size=VOCAB, n_agents=3, hidden=16, depth=2, residual=False)
    assert not torch.allclose(free(obs, prior), prior)


def test_prior_kl_loss_adds_beta_times_the_exact_kl_of_agents_that_acted():
    """The loss's extra term equals beta * mean over acting agents of sum_v pi (log pi - log prior),
    computed here independently from the actor's logits; masked agents do not count."""
    from tensordict import TensorDict

    cfg = load_finetune_config({"hidden": 16, "critic": "ippo", "normalize_advantage": False})
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
    kl = (logp.exp() * (logp - torch.log_softmax(prior, -1))).sum(-1)
    valid = mask & prior.ne(0).any(-1)
    expect = kl[valid].mean()
    assert float(losses[2.5]["loss_prior_kl"]) == pytest.approx(2.5 * float(expect), rel=1e-5)
    assert float(losses[2.5]["kl_to_prior"]) == pytest.approx(float(expect), rel=1e-5)
    assert float(losses[0.0]["loss_prior_kl"]) == 0.0
    assert float(losses[2.5]["loss_objective"]) == pytest.approx(float(losses[0.0]["loss_objective"]), rel=1e-6)
    assert float(expect) > 0.05


# ------------------------------------------------------------------------------- the runs
def test_tiny_finetuning_reaches_logged_goals_more_often_than_the_prior(tiny_run):
    """Same two real scenes, same 8 seeds (background sampler and policy sampler), 64
    agent-episodes per policy: the fine-tuned agents reach their logged goals more often (or
    collide less), by at least 3 agent-episodes in 64, with the KL to the prior reported.
    Measured: goal rate 0.016 -> 0.234, collision 0.250 -> 0.250, offroad 0.812 -> 0.375, return
    1.38 -> 3.75 per agent-episode, KL 0.76 per step (deterministic on one thread)."""
    cfg, result = tiny_run
    rows = result.evaluation["rows"]
    prior, tuned = rows["prior"], rows["fine-tuned"]
    print("\n" + json.dumps(rows, indent=1))
    assert result.evaluation["seeds"] == list(range(cfg.eval_seed, cfg.eval_seed + cfg.eval_episodes))
    assert prior["agent_episodes"] == tuned["agent_episodes"] == 2 * 4 * cfg.eval_episodes
    assert prior["kl_to_prior"] < 1e-5 < tuned["kl_to_prior"]
    assert tuned["goal_rate"] >= prior["goal_rate"] + 0.05 or tuned["collision_rate"] <= prior["collision_rate"] - 0.05
    assert tuned["return"] > prior["return"]
    # the training log: every iteration, KL to the prior grows from 0 as the policy leaves it
    hist = result.history
    assert len(hist) == cfg.iterations and hist[0]["kl_to_prior"] < 1e-3 < hist[-1]["kl_to_prior"]
    csv_rows = (result.out_dir / "finetune.csv").read_text().splitlines()
    assert len(csv_rows) == 1 + cfg.iterations and csv_rows[0].startswith("iteration,frames")


def test_policy_checkpoint_round_trips_and_evaluate_command_prints_the_table(tiny_run, capsys):
    from smart_marl.cli import main

    cfg, result = tiny_run
    cfg2, net, meta = load_policy(result.checkpoint)
    assert cfg2.to_dict() == cfg.to_dict() and meta["iteration"] == cfg.iterations
    obs, prior = torch.randn(2, 4, meta["obs_dim"]), torch.randn(2, 4, VOCAB)
    assert not torch.allclose(net(obs, prior), prior)  # trained weights, not the zero-initialised residual
    assert main(["finetune", "--evaluate", str(result.checkpoint), "--episodes", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["rows"]) == {"prior", f"prior top-{cfg.top_k}", "fine-tuned"} and out["seeds"] == [cfg.eval_seed]
    # the same scenes and seeds give the same episodes: a second evaluation reproduces every number
    assert main(["finetune", "--evaluate", str(result.checkpoint), "--episodes", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["rows"] == out["rows"]
    assert main(["finetune", "--evaluate", str(result.checkpoint), "--episodes", "1"]) == 0
    table = capsys.readouterr().out
    assert "goal rate" in table and "fine-tuned" in table and "KL/step" in table


def test_a_short_run_collects_its_first_batch_at_the_prior_and_writes_its_files(shared_data, prior_path, tmp_path):
    """Two small iterations: the first batch is collected by the zero-initialised residual actor,
    so its KL to the prior is 0; the update moves it; CSV, config and checkpoints are written."""
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path, iterations=2, frames_per_batch=32,
                                            minibatch_size=32, ppo_epochs=1, eval_episodes=0, checkpoint_every=1, critic="ippo",
                                            tensorboard=True))
    result = finetune(cfg)
    assert result.evaluation is None and len(result.history) == 2
    assert result.history[0]["kl_to_prior"] < 1e-6 < result.history[1]["kl_to_prior"]
    assert result.history[1]["frames"] == 64
    names = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    assert names == [f"{n}.{ext}" for n in ("policy_0001", "policy_0002", "policy_last") for ext in ("json", "safetensors")]
    assert json.loads((tmp_path / "config.json").read_text())["critic"] == "ippo"
    assert len((tmp_path / "finetune.csv").read_text().splitlines()) == 3
    try:
        import torch.utils.tensorboard  # noqa: F401
    except ImportError:
        return
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))


def test_with_a_large_beta_the_kl_stays_near_zero_and_behaviour_matches_the_prior(shared_data, prior_path, tmp_path):
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, tmp_path, beta=100.0, iterations=4, eval_episodes=4))
    result = finetune(cfg)
    assert max(r["kl_to_prior"] for r in result.history) < 1e-3
    rows = result.evaluation["rows"]
    prior, tuned = rows["prior"], rows["fine-tuned"]
    assert tuned["kl_to_prior"] < 1e-3
    # episode rates agree up to sampling noise: 32 agent-episodes per policy whose trajectories part
    # after the first token drawn differently (binomial standard error ~0.07 at these rates)
    for key in ("goal_rate", "collision_rate", "offroad_rate"):
        assert abs(tuned[key] - prior[key]) <= 0.15, (key, prior, tuned)
    # state by state: the fine-tuned action distribution is the prior's (total variation, Pinsker: <= sqrt(KL / 2))
    model, vocab = load_prior(cfg.prior)
    env = scene_env(cfg, select_scenes(cfg, model, vocab), model, vocab)
    _, net, _ = load_policy(result.checkpoint)
    tv = []
    for seed in range(4):
        obs, infos = env.reset(seed=seed, options={"scene_index": seed % 2})
        p_prior = torch.softmax(PriorPolicy().logits(env.agents, obs, infos), -1)
        p_tuned = torch.softmax(FinetunedPolicy(net).logits(env.agents, obs, infos), -1)
        tv.append(0.5 * (p_prior - p_tuned).abs().sum(-1))
    assert float(torch.cat(tv).max()) < 0.05


# ------------------------------------------------------------------------------- the config
def test_config_names_overrides_and_errors(shared_data, prior_path):
    cfg = load_finetune_config("tiny", ["beta=0.5", "reward.collision=-2", "critic=ippo"])
    assert cfg.beta == 0.5 and cfg.reward == {"collision": -2} and cfg.critic == "ippo" and cfg.max_agents == 4
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
    assert [sc.scenario_id[:4] for sc in select_scenes(cfg, *load_prior(cfg.prior))] == ["sumo", "sumo"]
    cfg = load_finetune_config("tiny", tiny(shared_data, prior_path, "unused", max_agents=40))
    with pytest.raises(FinetuneError, match="40 controllable agents"):
        select_scenes(cfg, *load_prior(cfg.prior))
