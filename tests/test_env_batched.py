"""The batched TorchRL environment envs.smart_traffic_batched_v0 on the package's sample scenes and
embedded prior: TorchRL's spec check, every row against the one-scene PettingZoo env on the same
scene (the same core: observations, prior logits, rewards and events must agree), refills in place,
seeding, and a TorchRL collector that resets only the scenes that are done."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from torchrl.envs.utils import check_env_specs, step_mdp  # noqa: E402

from envs import smart_traffic_batched_v0, smart_traffic_v0  # noqa: E402
from envs._setup import select_controlled  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture(scope="module")
def prior(embedded_prior):
    """(model, motion vocabulary) of the embedded prior (tests/conftest.py)."""
    return embedded_prior


@pytest.fixture(scope="module")
def samples(sample_scenes):
    """The package's sample scenes (tests/conftest.py)."""
    return sample_scenes


def batched(samples, prior, **kw):
    model, vocab = prior
    args = dict(scenarios=samples, prior=model, motion_vocab=vocab, num_scenes=3, controlled="vehicles", max_agents=2,
                horizon_steps=3, scene_order="sequential")
    args.update(kw)
    return smart_traffic_batched_v0.SmartTrafficBatchedEnv(**args)


def test_check_env_specs_passes_and_a_rollout_refills_done_scenes(samples, prior):
    env = batched(samples, prior, terminate_on=())  # no event ends a scene early: each one ends at its horizon
    check_env_specs(env, seed=0)
    torch.manual_seed(0)  # the rollout's random actions come from torch's global generator
    td = env.rollout(8, break_when_any_done=False)
    assert td["agents", "observation", "observation"].shape == (3, 8, 2, 473)
    assert td["agents", "observation", "prior_logits"].shape == (3, 8, 2, 1024)
    done = td["next", "done"].squeeze(-1)
    assert done[:, 2].all()  # horizon 3: every scene finishes at its third step, and is refilled
    assert td["agents", "mask"][:, 3].any()  # the refilled scenes have agents acting again


def test_every_row_equals_the_pettingzoo_env_on_its_scene(samples, prior):
    """Log background (deterministic): the batched env's rows, padded to the largest scene, and the
    one-scene env step the same core on the same scene with the same actions, through a refill."""
    model, vocab = prior
    env = batched(samples, prior, background="log", terminate_on=(), horizon_steps=2)
    td = env.reset()
    singles = {}
    for step in range(4):  # two episodes per row: the second after a refill
        if step % 2 == 0:
            for row, i in enumerate(env.scene_indices):
                pz = smart_traffic_v0.parallel_env(scenarios=[samples[i]], prior=model, motion_vocab=vocab, controlled="vehicles",
                                                   max_agents=2, background="log", horizon_steps=2, terminate_on=(), observation="dict")
                obs, infos = pz.reset(seed=0)
                singles[row] = (pz, obs, infos)
        actions = td["agents", "observation", "prior_logits"].argmax(-1)
        td["agents", "action"] = actions
        for row in range(3):
            pz, obs, infos = singles[row]
            names = pz.possible_agents
            assert len(names) <= 2 and td["agents", "mask"][row, : len(names)].all() and not td["agents", "mask"][row, len(names):].any()
            for j, a in enumerate(names):
                np.testing.assert_allclose(td["agents", "observation", "observation"][row, j].numpy(), obs[a]["observation"],
                                           rtol=1e-4, atol=1e-3)
                np.testing.assert_allclose(td["agents", "observation", "prior_logits"][row, j].numpy(), obs[a]["prior_logits"],
                                           rtol=1e-4, atol=1e-3)
        td = env.step(td)
        for row in range(3):
            pz, _, _ = singles[row]
            names = pz.possible_agents
            obs, rewards, terms, truncs, infos = pz.step({a: int(actions[row, j]) for j, a in enumerate(names)})
            singles[row] = (pz, obs, infos)
            for j, a in enumerate(names):
                assert td["next", "agents", "reward"][row, j, 0].item() == pytest.approx(rewards[a], rel=1e-4, abs=1e-4)
                assert bool(td["next", "agents", "truncated"][row, j]) == truncs[a]
                for key in ("collision", "offroad", "goal_reached"):
                    assert bool(td["next", "agents", "info", key][row, j]) == infos[a][key]
        td = step_mdp(td)
        if step % 2 == 1:
            assert td["done"].all()
            td = env.reset(td.set("_reset", td["done"].clone()))


def test_one_scene_batch_samples_the_background_as_the_pettingzoo_env_with_the_same_seed(samples, prior):
    model, vocab = prior
    env = batched(samples[:1], prior, num_scenes=1, horizon_steps=4, terminate_on=())
    env.set_seed(7)
    td = env.reset()
    pz = smart_traffic_v0.parallel_env(scenarios=samples[:1], prior=model, motion_vocab=vocab, controlled="vehicles", max_agents=2,
                                       horizon_steps=4, terminate_on=(), observation="dict")
    obs, _ = pz.reset(seed=7)
    for _ in range(4):
        actions = td["agents", "observation", "prior_logits"].argmax(-1)
        td["agents", "action"] = actions
        td = step_mdp(env.step(td))
        obs, *_ = pz.step({a: int(actions[0, j]) for j, a in enumerate(pz.possible_agents)})
        for j, a in enumerate(pz.possible_agents):
            np.testing.assert_allclose(td["agents", "observation", "observation"][0, j].numpy(), obs[a]["observation"], rtol=1e-4,
                                       atol=1e-3)


def test_same_seed_same_rollout_and_another_seed_another(samples, prior):
    def run(seed):
        env = batched(samples, prior, horizon_steps=3, scene_order="random")
        env.set_seed(seed)
        policy = lambda td: td.set(("agents", "action"), td["agents", "observation", "prior_logits"].argmax(-1))  # noqa: E731
        return env.rollout(5, policy, break_when_any_done=False)["next", "agents", "observation", "observation"]

    a, b, c = run(3), run(3), run(4)
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_controlled_agents_are_the_selection_of_the_group_vocabulary(samples, prior):
    env = batched(samples, prior, controlled="all", max_agents=3, num_scenes=2)
    env.reset()
    for row, i in enumerate(env.scene_indices):
        static = env.pool.static(i)
        want = select_controlled("all", static, 3, env.group_types)
        got = env.core.ctrl_track[row]
        assert got[got >= 0].tolist() == list(want)
        assert all(static.types[k] == 0 for k in want)  # the group's 1024-token vocabulary is the vehicles'


def test_a_collector_resets_only_the_done_scenes(samples, prior):
    from torchrl.collectors import Collector

    env = batched(samples, prior, num_scenes=2, horizon_steps=2)
    policy = lambda td: td.set(("agents", "action"), td["agents", "observation", "prior_logits"].argmax(-1))  # noqa: E731
    collector = Collector(env, policy, frames_per_batch=12, total_frames=24)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2 and batches[0].batch_size == (2, 6)
    done = batches[0]["next", "done"].squeeze(-1)
    assert done[:, 1].all() and not done[:, 0].any()  # every 2 steps each scene ends and is refilled
    assert (batches[0]["agents", "mask"][:, 2].any(-1)).all()


def test_refills_of_a_one_scene_batch_leave_the_kept_fresh_states_as_they_were(samples, prior):
    """A batch of one scene is a copy of the scene's kept fresh prior state, not a fork sharing its tensors:
    refills write into the batch's state in place and must not write into the kept ones (a later episode of
    the scene would start from another scene's agents, or fail on tensors that alias)."""
    env = batched(samples, prior, num_scenes=1, horizon_steps=1, terminate_on=())
    td = env.reset()
    kept = {key: {name: getattr(st, name).clone() for name in ("agent_type", "pose", "simulated", "road_x")}
            for key, st in env.core._pristine.items()}
    for _ in range(2 * len(samples)):  # every scene twice: each refill puts the next one in the row
        td["agents", "action"] = td["agents", "observation", "prior_logits"].argmax(-1)
        td = step_mdp(env.step(td))
        td = env.reset(td.set("_reset", td["done"].clone()))
    for key, before in kept.items():
        for name, value in before.items():
            assert torch.equal(getattr(env.core._pristine[key], name), value), (key, name)


def test_the_prior_scores_the_controlled_agents_tokens_only_through_refills(samples, prior):
    """The environments read the log-probability of the controlled (forced) agents' tokens and never the
    background's, so the core's prior computes those only (``log_probs_of="forced"``: the sampler's largest
    cost after ranking otherwise); a refill keeps that, and the controlled agents' values are the prior's."""
    env = batched(samples, prior, num_scenes=2, horizon_steps=1, terminate_on=())
    td = env.reset()
    for _ in range(3):  # every step ends the episodes: each refill puts new scenes in both rows
        assert env.core.prior.log_probs_of == "forced"
        logits = td["agents", "observation", "prior_logits"].clone()
        action = logits.argmax(-1)
        td["agents", "action"] = action
        out = env.step(td)
        live = td["agents", "mask"]
        got = out["next", "agents", "info", "action_log_prob"][..., 0][live]
        want = logits.log_softmax(-1).gather(-1, action[..., None])[..., 0][live]
        assert torch.allclose(got.float(), want.float(), atol=1e-5) and bool((got < 0).all())
        td = env.reset(step_mdp(out).set("_reset", step_mdp(out)["done"].clone()))
