"""Imitation in fine-tuning (``imitation > 0``): the env labels every state with the log-following
expert's token restricted to the policy's action space (the prior's top k), and the loss adds the
cross-entropy of those labels under the policy (DAgger: labels on the states the policy reaches)."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from tensordict import TensorDict  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

from agents.finetune import EXPERT_KEY, PRIOR_KEY, ExpertLabelledEnv, build_modules, load_finetune_config  # noqa: E402
from agents.kl_ppo import PriorKLPPOLoss  # noqa: E402
from agents.policy import ExpertWithinTopK  # noqa: E402
from agents.scripted import log_following_tokens  # noqa: E402
from smart_marl.embedded import sample_scenarios  # noqa: E402
from smart_marl.model.checkpoint import load_prior  # noqa: E402
from smart_marl.rollout import top_k_mask  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py

K = 8


@pytest.fixture(scope="module")
def env():
    model, vocab = load_prior("embedded", "cpu")
    return ExpertLabelledEnv(scenarios=sample_scenarios(), prior=model, motion_vocab=vocab, num_scenes=2, controlled="vehicles",
                             max_agents=3, horizon_steps=4, scene_order="sequential", reference_top_k=K, terminate_on=())


def _loss(actor, critic, imitation: float) -> PriorKLPPOLoss:
    loss = PriorKLPPOLoss(actor, critic, beta=0.0, entropy_bonus=False, normalize_advantage=False, reference_top_k=K,
                          imitation=imitation, expert_action_key=EXPERT_KEY)
    loss.set_keys(action=("agents", "action"), sample_log_prob=("agents", "action_log_prob"), value=("agents", "state_value"),
                  advantage=("agents", "advantage"), value_target=("agents", "value_target"))
    return loss


def test_labels_are_the_restricted_experts_tokens_inside_the_top_k(env):
    """Every live agent's label is a token of the prior's top k; it is the expert's own token wherever
    that one is in the top k, and the evaluation's restricted expert picks the same tokens."""
    check_env_specs(env, seed=0)
    td = env.reset()
    checked = own = 0
    for _ in range(3):
        live = env.core.live
        label, prior = td[EXPERT_KEY], td[PRIOR_KEY]
        inside = top_k_mask(prior, K).gather(-1, label[..., None]).squeeze(-1)
        assert inside[live].all() and (label[~live] == 0).all()
        expert = log_following_tokens(env.core)
        expert_inside = top_k_mask(prior, K).gather(-1, expert[..., None]).squeeze(-1) & live
        assert torch.equal(label[expert_inside], expert[expert_inside])
        evaluated = ExpertWithinTopK(K).log_probs(env.core, None, prior).argmax(-1)
        assert torch.equal(evaluated[live], label[live])
        checked, own = checked + int(live.sum()), own + int(expert_inside.sum())
        td["agents", "action"] = prior.argmax(-1)
        td = env.step(td)["next"]
    assert checked >= 12 and 0 < own < checked  # both cases happen: the expert's token inside and outside the top k


def test_imitation_loss_is_the_cross_entropy_of_the_labels_and_training_on_it_learns_them(env):
    """``loss_imitation`` = imitation x mean over acting agents of -log pi(label); a few gradient steps
    on it alone raise the labels' probability on the collected states."""
    cfg = load_finetune_config({"hidden": 32, "critic": "ippo", "reference_top_k": K, "residual": True})
    obs_dim = int(env.observation_spec["agents", "observation", "observation"].shape[-1])
    net, actor, critic = build_modules(cfg, obs_dim, env.vocab_size, env.max_agents)
    torch.manual_seed(0)
    with torch.no_grad():
        td = env.rollout(4, policy=actor, break_when_any_done=False)
    td["agents", "advantage"] = torch.zeros(td["agents", "mask"].shape + (1,))
    td["agents", "value_target"] = torch.zeros_like(td["agents", "advantage"])
    mask = td["agents", "mask"] & td[PRIOR_KEY].ne(0).any(-1)
    label = td[EXPERT_KEY]

    def cross_entropy() -> float:
        with torch.no_grad():
            logp = torch.log_softmax(net(td["agents", "observation", "observation"], td[PRIOR_KEY]), -1)
        return float(-logp.gather(-1, label[..., None]).squeeze(-1)[mask].mean())

    before = cross_entropy()
    with torch.no_grad():
        out = _loss(actor, critic, 2.0)(td.clone())
    assert float(out["loss_imitation"]) == pytest.approx(2.0 * before, rel=1e-5)
    with torch.no_grad():
        assert "loss_imitation" not in _loss(actor, critic, 0.0)(td.clone()).keys()
    loss = _loss(actor, critic, 1.0)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(30):
        opt.zero_grad()
        loss(td.clone())["loss_imitation"].backward()
        opt.step()
    assert cross_entropy() < 0.5 * before


def test_imitation_is_a_config_field_with_a_named_error():
    assert load_finetune_config("tiny", ["imitation=0.5"]).imitation == 0.5
    with pytest.raises(ValueError, match="imitation"):
        load_finetune_config("tiny", ["imitation=-1"])


def test_a_batch_without_labels_is_refused_by_name():
    cfg = load_finetune_config({"hidden": 8, "critic": "ippo", "reference_top_k": K})
    net, actor, critic = build_modules(cfg, 5, 16, 2)
    td = TensorDict({"agents": TensorDict({
        "observation": TensorDict({"observation": torch.randn(3, 2, 5), "prior_logits": torch.randn(3, 2, 16)}, [3, 2]),
        "mask": torch.ones(3, 2, dtype=torch.bool), "advantage": torch.zeros(3, 2, 1), "value_target": torch.zeros(3, 2, 1)},
        [3, 2])}, [3])
    with torch.no_grad():
        actor(td)
    with pytest.raises(KeyError, match="expert_action"):
        _loss(actor, critic, 1.0)(td)
