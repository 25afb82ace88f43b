"""The PettingZoo environment envs.smart_traffic_v0 on real WOMD scenes: PettingZoo's API, seed and
render checks, TorchRL wrapping, the prior's logits against the model, trajectories against the
rollout engine, events, observations and clear errors.

The prior here is a small randomly initialised SMART model whose motion vocabulary is built from
the real scenes (a trained prior is not needed for the equalities pinned here)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

pytest.importorskip("pettingzoo", reason="the env extra (pettingzoo) is not installed")

from envs import smart_traffic_v0  # noqa: E402
from envs._observation import observation_layout  # noqa: E402
from envs._reward import REWARD_TERMS, collisions  # noqa: E402
from smart_marl.rollout import DEFAULT_TOP_K, RolloutState, rollout, sample_tokens  # noqa: E402
from smart_marl.scenario import AgentType  # noqa: E402

VOCAB = 32  # tokens per type of conftest's womd_vocab
ONE_SCENE = "womd_tfrecord/motion_data_one_scenario.tfrecord"


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def make(scenes, vocab, model, **kw):
    args = dict(scenarios=scenes[:1], prior=model, motion_vocab=vocab, controlled="vehicles", max_agents=3, horizon_steps=3)
    args.update(kw)
    return smart_traffic_v0.parallel_env(**args)


# ------------------------------------------------------------------------------ PettingZoo
@pytest.mark.parametrize("background,observation", [("prior", "dict"), ("log", "vector"), ("constant_velocity", "vector")])
def test_parallel_api_test_passes_on_a_real_scene(scenes, vocab, model, background, observation):
    from pettingzoo.test import parallel_api_test

    env = make(scenes, vocab, model, background=background, observation=observation)
    parallel_api_test(env, num_cycles=5)
    assert env.possible_agents[0].startswith("vehicle_")
    assert env.observation_space(env.possible_agents[0]) is env.observation_space(env.possible_agents[0])


def test_parallel_api_test_passes_across_two_scenes_without_a_prior(scenes, vocab):
    from pettingzoo.test import parallel_api_test

    env = smart_traffic_v0.parallel_env(scenarios=scenes, prior=None, motion_vocab=vocab, controlled="predict",
                                        background="log", horizon_steps=2)
    parallel_api_test(env, num_cycles=3)
    env.reset(options={"scene_index": 1})
    assert env.static.scenario.scenario_id == scenes[1].scenario_id


def test_aec_api_test_passes(scenes, vocab, model):
    from pettingzoo.test import api_test

    aec = smart_traffic_v0.env(scenarios=scenes[:1], prior=model, motion_vocab=vocab, controlled="vehicles", max_agents=2,
                               horizon_steps=2)
    api_test(aec, num_cycles=6)


def test_parallel_seed_test_passes(scenes, vocab, model):
    from pettingzoo.test import parallel_seed_test

    parallel_seed_test(lambda: make(scenes, vocab, model, observation="dict"), num_cycles=4)


def test_random_scene_order_follows_the_reset_seed(scenes, vocab):
    env = smart_traffic_v0.parallel_env(scenarios=scenes, prior=None, motion_vocab=vocab, background="log", scene_order="random")
    picks = []
    for seed in (3, 3, 4, 4):
        env.reset(seed=seed)
        picks.append(env.scene_index)
    assert picks[0] == picks[1] and picks[2] == picks[3]


def test_rgb_array_render_draws_the_scene_and_the_recorder_writes_a_gif(scenes, vocab, model, tmp_path):
    env = make(scenes, vocab, model, render_mode="rgb_array", render_size_px=200)
    env.reset(seed=0)
    env.start_recording(tmp_path / "episode.gif")
    frames = [env.render()]
    while env.agents:
        env.step({a: 0 for a in env.agents})
        frames.append(env.render())
    assert all(f.shape == (200, 200, 3) and f.dtype == np.uint8 for f in frames)
    assert len(np.unique(frames[0].reshape(-1, 3), axis=0)) > 10  # a map and agents, not a blank image
    assert not np.array_equal(frames[0], frames[-1])  # agents moved
    path = env.save_recording()
    assert path.stat().st_size > 1000
    from PIL import Image

    assert Image.open(path).n_frames == 1 + env.horizon_steps


def test_human_render_without_a_display_is_a_clear_error(scenes, vocab, model, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(smart_traffic_v0.EnvConfigError, match="no display"):
        make(scenes, vocab, model, render_mode="human")


# ---------------------------------------------------------------------------------- TorchRL
@pytest.mark.parametrize("with_prior", [True, False])
def test_torchrl_wrapper_passes_check_env_specs(scenes, vocab, model, with_prior):
    pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")
    from torchrl.envs import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    if with_prior:
        env = make(scenes, vocab, model, observation="dict", horizon_steps=4)
    else:
        env = make(scenes, vocab, None, background="log", horizon_steps=4)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="PettingZoo in TorchRL is tested")
        wrapped = PettingZooWrapper(env, use_mask=True, done_on_any=False, categorical_actions=True)
    check_env_specs(wrapped, seed=0)
    td = wrapped.rollout(3)
    assert td["vehicle", "action"].shape == (3, 3)
    assert td["vehicle", "info", "reward_terms"].shape == (3, 3, len(REWARD_TERMS))
    if with_prior:
        assert td["vehicle", "info", "prior_logits"].shape == (3, 3, VOCAB)
        # the logits TorchRL carries are the env's, for the step each action was taken from
        assert torch.isfinite(td["vehicle", "info", "prior_logits"]).all() and td["vehicle", "info", "prior_logits"].abs().sum() > 0


# ------------------------------------------------------------------------- prior equalities
def test_prior_logits_in_infos_equal_the_full_model_forward_at_every_step(scenes, vocab, model):
    """Everyone controlled: the tokens are known, so a full (non-cached) MotionNet re-run forced
    with the same tokens is an independent computation of the same logits."""
    env = make(scenes, vocab, model, controlled="all", max_agents=None, horizon_steps=4, terminate_on=())
    obs, infos = env.reset(seed=5)
    full = RolloutState.start(model, scenes[0], seed=5, mode="full", motion_vocab=vocab, lights="log")  # the env sees the log's lights
    slots = env.slot_of_track[env.ctrl_tracks]
    rng = np.random.default_rng(0)
    for step in range(4):
        ref = full.logits()[0]
        for a, k in zip(env.possible_agents, env.ctrl_tracks):
            np.testing.assert_allclose(infos[a]["prior_logits"], ref[env.slot_of_track[k]].numpy(), rtol=1e-4, atol=1e-4)
            np.testing.assert_allclose(obs[a]["prior_logits"] if isinstance(obs[a], dict) else infos[a]["prior_logits"],
                                       infos[a]["prior_logits"])
        actions = {a: int(rng.integers(VOCAB)) for a in env.agents}
        forced = torch.full((1, full.num_slots), -1, dtype=torch.long)
        forced[0, slots] = torch.tensor([actions[a] for a in env.possible_agents])
        out = full.step(forced)
        obs, rewards, terms, truncs, infos = env.step(actions)
        for a, k in zip(env.possible_agents, env.ctrl_tracks):
            assert infos[a]["action_log_prob"] == pytest.approx(float(out.log_probs[0, env.slot_of_track[k]]), abs=1e-4)
            j = REWARD_TERMS.index("prior_log_likelihood")
            assert infos[a]["reward_terms"][j] == pytest.approx(infos[a]["action_log_prob"], abs=1e-6)


def test_sdc_logits_equal_the_rollout_engine_conditioned_on_its_tokens(scenes, vocab, model):
    """SDC controlled, everyone else sampled by the prior: the same engine, seed and forced SDC
    tokens give the same background samples, so the SDC's logits must match at every step."""
    env = make(scenes, vocab, model, controlled="sdc", background="prior", horizon_steps=5, terminate_on=())
    _, infos = env.reset(seed=11)
    ref = RolloutState.start(model, scenes[0], seed=11, motion_vocab=vocab, lights="log")
    (a,) = env.possible_agents
    slot = env.slot_of_track[env._agent_track[a]]
    for step in range(5):
        np.testing.assert_array_equal(infos[a]["prior_logits"], ref.logits()[0, slot].numpy())
        tok = (7 * step + 3) % VOCAB
        forced = torch.full((1, ref.num_slots), -1, dtype=torch.long)
        forced[0, slot] = tok
        ref.step(forced)
        _, _, _, _, infos = env.step({a: tok})


def test_prior_driven_episode_equals_the_rollout_engine_on_the_same_seed(scenes, vocab, model):
    """Every agent controlled and acting by sampling the infos' logits with the engine's sampler:
    the episode's trajectories equal rollout() on the same seed."""
    seed, steps = 21, 6
    env = make(scenes, vocab, model, controlled="all", max_agents=None, horizon_steps=steps, terminate_on=())
    env.reset(seed=seed + 1)
    env.step({a: 0 for a in env.agents})
    _, infos = env.reset(seed=seed)  # a second reset: the prior's state comes from the env's per-scene cache
    gen = torch.Generator().manual_seed(seed)
    while env.agents:
        logits = torch.from_numpy(np.stack([infos[a]["prior_logits"] for a in env.agents]))
        tokens, _ = sample_tokens(logits, gen, top_k=DEFAULT_TOP_K, temperature=1.0)  # rollout() samples with the default
        _, _, _, _, infos = env.step(dict(zip(env.agents, tokens.tolist())))
    poses, present = env.trajectories()
    res = rollout(model, scenes[0], num_rollouts=1, num_steps=steps, seed=seed, motion_vocab=vocab, avoid_collisions=False,
                  stop_lines=False, lights="log", persistence=0.0)  # the env's lights; no rules: the plain draw the env's agents took
    sc = scenes[0]
    sim = res.simulated[0]
    assert sim.sum() == len(env.possible_agents) and present[sim].all()
    xyz = np.concatenate([poses[sim, :, :2], np.zeros((sim.sum(), poses.shape[1], 1))], -1)
    src_xy = sc.frame.to_source(xyz)[..., :2]
    np.testing.assert_allclose(src_xy, res.trajectory[0, sim, :, :2], atol=1e-3)
    np.testing.assert_allclose(np.cos(sc.frame.heading_to_source(poses[sim, :, 2]) - res.trajectory[0, sim, :, 3]), 1.0, atol=1e-6)


# ------------------------------------------------------------------------ backgrounds, events
def test_log_background_replays_the_logged_poses(scenes, vocab):
    env = smart_traffic_v0.parallel_env(scenarios=scenes[:1], prior=None, motion_vocab=vocab, controlled="sdc", background="log",
                                        horizon_steps=2)
    env.reset(seed=0)
    a = env.agents[0]
    env.step({a: 0})
    env.step({a: 0})
    tr, cf = scenes[0].tracks, scenes[0].current_frame
    other = np.flatnonzero(tr.valid[:, cf + 10] & tr.valid[:, cf] & (np.arange(tr.num_tracks) != scenes[0].sdc_index))
    np.testing.assert_allclose(env.pose[other, :2], tr.position[other, cf + 10, :2], atol=1e-5)
    np.testing.assert_allclose(env.pose[other, 2], tr.heading[other, cf + 10], atol=1e-6)


def test_constant_velocity_background_moves_at_the_logged_current_velocity(scenes, vocab):
    env = smart_traffic_v0.parallel_env(scenarios=scenes[:1], prior=None, motion_vocab=vocab, background="constant_velocity",
                                        horizon_steps=3)
    env.reset(seed=0)
    for _ in range(3):
        env.step({a: 0 for a in env.agents})
    tr, cf = scenes[0].tracks, scenes[0].current_frame
    bg = np.flatnonzero(tr.valid[:, cf] & (np.arange(tr.num_tracks) != scenes[0].sdc_index))
    np.testing.assert_allclose(env.pose[bg, :2], tr.position[bg, cf, :2] + 1.5 * tr.velocity[bg, cf], atol=1e-4)


def test_driving_through_the_car_ahead_is_a_collision_that_terminates_the_agent(scenes, vocab):
    fast = int(np.argmax(vocab[AgentType.VEHICLE].poses[:, -1, 0]))  # the token that goes farthest forward
    env = smart_traffic_v0.parallel_env(scenarios=scenes[:1], prior=None, motion_vocab=vocab, controlled="sdc", background="log",
                                        horizon_steps=16, terminate_on=("collision",), reward={"collision": -3.0, "progress": 0.0})
    env.reset(seed=0)
    (a,) = env.agents
    for _ in range(16):
        _, rewards, terms, truncs, infos = env.step({a: fast})
        if terms[a]:
            break
    assert terms[a] and infos[a]["collision"] and not truncs[a]
    assert rewards[a] == pytest.approx(-3.0 + 0.0 * infos[a]["reward_terms"][0])
    assert env.agents == []
    k = env._agent_track[a]
    assert not env.present[k]  # it left the scene
    with pytest.raises(RuntimeError, match="reset"):
        env.step({a: 0})


def test_collisions_match_overlapping_and_separated_boxes():
    frames = torch.zeros(1, 3, 5, 3, dtype=torch.float64)
    frames[0, 1, :, 0] = 3.0  # 3 m ahead of track 0: overlaps a 4.5 m car
    frames[0, 2, :, 0] = 30.0
    size = torch.tensor([[[4.5, 2.0, 1.5]] * 3], dtype=torch.float64)
    both = torch.ones(1, 2, dtype=torch.bool)
    hit = collisions(torch.tensor([[0, 2]]), both, frames, torch.ones(1, 3, dtype=torch.bool), size)
    assert hit.tolist() == [[True, False]]
    hit = collisions(torch.tensor([[0]]), both[:, :1], frames, torch.tensor([[True, False, True]]), size)  # an absent agent is never hit
    assert hit.tolist() == [[False]]
    hit = collisions(torch.tensor([[0, 2]]), torch.tensor([[False, True]]), frames, torch.ones(1, 3, dtype=torch.bool), size)
    assert hit.tolist() == [[False, False]]  # an agent that does not act this step has no event


def test_observation_blocks_match_independent_computations(scenes, vocab):
    env = smart_traffic_v0.parallel_env(scenarios=scenes[:1], prior=None, motion_vocab=vocab, controlled="sdc", background="log")
    obs, _ = env.reset(seed=0)
    (a,) = env.agents
    o = obs[a]
    lay = {name: (off, size) for name, off, size in observation_layout(env.obs_config)}
    sc = scenes[0]
    tr, cf, k = sc.tracks, sc.current_frame, sc.sdc_index
    assert o.shape == (473,)
    off, _ = lay["ego_speed"]
    assert o[off] == pytest.approx(np.linalg.norm(tr.velocity[k, cf]), rel=1e-5)
    off, _ = lay["ego_size"]
    np.testing.assert_allclose(o[off : off + 2], tr.box_size()[k, :2], rtol=1e-6)
    # nearest other agent: its distance equals the smallest centre distance among present agents
    off, _ = lay["agents"]
    d = np.linalg.norm(tr.position[tr.valid[:, cf], cf, :2] - tr.position[k, cf, :2], axis=1)
    assert o[off] == 1.0 and np.hypot(o[off + 1], o[off + 2]) == pytest.approx(np.sort(d)[1], rel=1e-4)
    # goal: the SDC's last logged position, its distance
    off, _ = lay["goal"]
    last = np.flatnonzero(tr.valid[k])[-1]
    assert o[off + 3] == pytest.approx(np.linalg.norm(tr.position[k, last, :2] - tr.position[k, cf, :2]), rel=1e-4)


# ----------------------------------------------------------------------------------- errors
def test_bad_inputs_are_clear_errors(scenes, vocab, model):
    env = make(scenes, vocab, model)
    env.reset(seed=0)
    a = env.agents[0]
    good = {x: 0 for x in env.agents}
    with pytest.raises(ValueError, match="outside its vocabulary"):
        env.step({**good, a: VOCAB})
    with pytest.raises(KeyError, match="unknown agent"):
        env.step({**good, "vehicle_999999": 0})
    with pytest.raises(ValueError, match="no action for live agent"):
        env.step({x: 0 for x in env.agents[1:]})
    with pytest.raises(smart_traffic_v0.EnvConfigError, match="no controllable agent"):
        make(scenes, vocab, model, controlled=lambda sc: np.zeros(sc.num_tracks, bool))
    with pytest.raises(smart_traffic_v0.EnvConfigError, match="is not a track"):
        make(scenes, vocab, model, controlled=[123456789])
    with pytest.raises(smart_traffic_v0.EnvConfigError, match="needs a prior"):
        make(scenes, vocab, None, background="prior")
    with pytest.raises(smart_traffic_v0.EnvConfigError, match="background"):
        make(scenes, vocab, model, background="replay")


def test_controlled_selection_by_names_ids_predict_and_a_path(shared_data, scenes, vocab):
    sc = scenes[0]
    sdc_name = sc.tracks.names()[sc.sdc_index]
    predict = [sc.tracks.names()[k] for k in sc.predict_indices if sc.tracks.valid[k, sc.current_frame]]
    path = str(shared_data / ONE_SCENE)
    kw = dict(prior=None, motion_vocab=vocab, background="log")
    assert smart_traffic_v0.parallel_env(scenarios=path, controlled=[sdc_name], **kw).possible_agents == [sdc_name]
    assert smart_traffic_v0.parallel_env(scenarios=path, controlled=[int(sc.tracks.ids[sc.sdc_index])], **kw).possible_agents == [sdc_name]
    assert smart_traffic_v0.parallel_env(scenarios=path, controlled="sdc", **kw).possible_agents == [sdc_name]
    assert sorted(smart_traffic_v0.parallel_env(scenarios=path, controlled="predict", **kw).possible_agents) == sorted(predict)
    veh = smart_traffic_v0.parallel_env(scenarios=path, controlled="vehicles", max_agents=4, **kw)
    assert len(veh.possible_agents) == 4 and sdc_name in veh.possible_agents  # the nearest to the SDC, itself first
    cf = sc.current_frame
    assert len(smart_traffic_v0.parallel_env(scenarios=path, controlled="vehicles", **kw).possible_agents) == int(
        (sc.tracks.valid[:, cf] & (sc.tracks.types == int(AgentType.VEHICLE))).sum())


def test_embedded_prior_and_sample_scenes_run_an_episode():
    """The defaults need no data on disk: the package's sample scenes driven by its embedded prior."""
    from smart_marl.embedded import sample_scenarios

    env = smart_traffic_v0.parallel_env(scenarios="embedded", prior="embedded", controlled="sdc", horizon_steps=3)
    obs, infos = env.reset(seed=0)
    first = sample_scenarios()[0]
    assert env.agents == [first.tracks.names()[first.sdc_index]]
    agent = env.agents[0]
    logits = infos[agent]["prior_logits"]
    assert env.action_space(agent).n == 1024 == len(logits) and np.isfinite(logits).all()  # 1024: the embedded vehicle tokens
    steps = 0
    while env.agents:
        obs, rewards, terms, truncs, infos = env.step({a: int(np.argmax(infos[a]["prior_logits"])) for a in env.agents})
        steps += 1
    assert steps <= 3 and (truncs[agent] or terms[agent])
