"""The reward's gap terms (issue 58, "rewards that keep gaps"): ``headway`` (time headway to the car ahead
below ``headway_s``) and ``ttc`` (time to collision with it below ``ttc_s``), envs/_reward.py.

Hand-made two-car states whose gaps are computed by hand (a follower 10 m behind its leader at 20 m/s: headway
0.5 s; closing at 5 m/s: time to collision 2 s), the cases without a penalty (no leader, a car in the next
lane, one behind, an opening gap, a stopped follower), many agents of many scenes at once, the default
reward unchanged (weights 0), the terms in both environments' infos equal to a per-agent loop over the
recorded frames, and the new settings' bounds."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytest.importorskip("pettingzoo", reason="the env extra (pettingzoo) is not installed")

from envs._arguments import MAX_HEADWAY_S, MAX_REWARD_WEIGHT, MAX_TTC_S  # noqa: E402
from envs._reward import REWARD_TERMS, RewardConfig, gap_terms, time_gaps  # noqa: E402
from envs.errors import EnvConfigError  # noqa: E402
from smart_marl.scenario import DT_S  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py

LENGTH, WIDTH = 4.5, 2.0
HEADWAY, TTC = REWARD_TERMS.index("headway"), REWARD_TERMS.index("ttc")


def frames_of(cars, heading=0.0):
    """[1, N, 5, 3] frames of cars driving straight along ``heading`` at constant speed: ``cars`` holds
    (metres ahead, metres to the left, speed m/s along ``heading``, own heading offset) at the last frame."""
    c, s = math.cos(heading), math.sin(heading)
    out = torch.zeros(1, len(cars), 5, 3, dtype=torch.float64)
    for i, (ahead, left, speed, turn) in enumerate(cars):
        for f in range(5):
            along = ahead + speed * DT_S * (f - 4)
            out[0, i, f] = torch.tensor([along * c - left * s, along * s + left * c, heading + turn], dtype=torch.float64)
    return out


def gaps(cars, heading=0.0, live=True, present=None, ctrl=0):
    """(time headway, time to collision) of car ``ctrl`` among ``cars`` (:func:`frames_of`), boxes 4.5 x 2 m."""
    n = len(cars)
    box = torch.tensor([[LENGTH, WIDTH, 1.5]] * n, dtype=torch.float64)[None]
    present = torch.ones(1, n, dtype=torch.bool) if present is None else torch.tensor([present])
    headway, ttc = time_gaps(torch.tensor([[ctrl]]), torch.tensor([[live]]), frames_of(cars, heading), present, box)
    return float(headway), float(ttc)


# ------------------------------------------------------------------------------- by hand
@pytest.mark.parametrize("heading", [0.0, 0.7, -2.5])
def test_a_follower_ten_metres_behind_at_twenty_metres_a_second_has_half_a_second_and_two_seconds(heading):
    """Gap 10 m bumper to bumper (centres 14.5 m apart, 4.5 m cars), follower 20 m/s, leader 15 m/s:
    headway 10 / 20 = 0.5 s, time to collision 10 / (20 - 15) = 2 s; terms 1 - 0.5 / 1 = 0.5 and 1 - 2 / 3 = 1/3.
    The same in any direction the pair drives."""
    cars = [(0.0, 0.0, 20.0, 0.0), (10.0 + LENGTH, 0.0, 15.0, 0.0)]
    assert gaps(cars, heading) == (pytest.approx(0.5, abs=1e-9), pytest.approx(2.0, abs=1e-9))
    box = torch.tensor([[[LENGTH, WIDTH, 1.5]] * 2], dtype=torch.float64)
    args = (torch.tensor([[0]]), torch.tensor([[True]]), frames_of(cars, heading), torch.ones(1, 2, dtype=torch.bool), box)
    headway, ttc = gap_terms(*args, headway_s=1.0, ttc_s=3.0)
    assert float(headway) == pytest.approx(0.5, abs=1e-9) and float(ttc) == pytest.approx(1 / 3, abs=1e-9)
    headway, ttc = gap_terms(*args, headway_s=0.25, ttc_s=1.5)  # above both thresholds: no penalty
    assert float(headway) == 0.0 and float(ttc) == 0.0


def test_the_gap_is_bumper_to_bumper_and_a_turned_leader_counts_its_extent_along_the_heading():
    """A leader at right angles across the path (a car crossing) takes half its width along the follower's
    heading, not half its length: centres 12.25 m apart -> gap 12.25 - 2.25 - 1 = 9 m."""
    crossing = [(0.0, 0.0, 18.0, 0.0), (12.25, 0.0, 0.0, math.pi / 2)]
    assert gaps(crossing)[0] == pytest.approx(9.0 / 18.0, abs=1e-9)
    touching = [(0.0, 0.0, 10.0, 0.0), (LENGTH - 0.5, 0.0, 0.0, 0.0)]  # boxes overlap: gap 0
    assert gaps(touching) == (0.0, 0.0)


@pytest.mark.parametrize("cars, why", [
    ([(0.0, 0.0, 20.0, 0.0)], "alone"),
    ([(0.0, 0.0, 20.0, 0.0), (14.5, 3.5, 15.0, 0.0)], "the next lane (3.5 m to the left)"),
    ([(0.0, 0.0, 20.0, 0.0), (14.5, -3.5, 15.0, 0.0)], "the next lane (3.5 m to the right)"),
    ([(0.0, 0.0, 20.0, 0.0), (-14.5, 0.0, 25.0, 0.0)], "a car behind, closing in"),
])
def test_no_leader_no_penalty(cars, why):
    assert gaps(cars) == (math.inf, math.inf), why


def test_an_opening_gap_has_no_time_to_collision_and_a_stopped_follower_no_headway():
    """Leader faster (25 m/s against 20): the gap opens, no time to collision, the headway stays 0.5 s; same speed:
    the gap holds, none either; a stopped follower behind a stopped leader: no headway, no time to collision."""
    assert gaps([(0.0, 0.0, 20.0, 0.0), (14.5, 0.0, 25.0, 0.0)]) == (pytest.approx(0.5), math.inf)
    assert gaps([(0.0, 0.0, 20.0, 0.0), (14.5, 0.0, 20.0, 0.0)]) == (pytest.approx(0.5), math.inf)
    assert gaps([(0.0, 0.0, 0.0, 0.0), (14.5, 0.0, 0.0, 0.0)]) == (math.inf, math.inf)
    assert gaps([(0.0, 0.0, -3.0, 0.0), (14.5, 0.0, 0.0, 0.0)]) == (math.inf, math.inf)  # reversing away


def test_the_nearest_car_in_the_path_leads_and_absent_or_not_live_ones_do_not_count():
    """Two cars ahead in the path: the nearer one leads (gap 5 m at 10 m/s: 0.5 s, closing 10 m/s: 0.5 s); a
    car that is not present is not anyone's leader; a slot that is not live has neither."""
    cars = [(0.0, 0.0, 10.0, 0.0), (30.0, 0.5, 0.0, 0.0), (5.0 + LENGTH, -0.5, 0.0, 0.0)]
    assert gaps(cars) == (pytest.approx(0.5), pytest.approx(0.5))
    assert gaps(cars, present=[True, True, False]) == (pytest.approx((30.0 - LENGTH) / 10), pytest.approx((30.0 - LENGTH) / 10))
    assert gaps(cars, live=False) == (math.inf, math.inf)


def test_every_agent_of_every_scene_at_once_as_one_at_a_time():
    """B scenes x C controlled slots (a padded slot -1 not live) in one call give what each slot gives alone."""
    gen = torch.Generator().manual_seed(5)
    b, n, c = 3, 7, 3
    pos = torch.rand(b, n, 2, generator=gen, dtype=torch.float64) * 40
    heading = (torch.rand(b, n, generator=gen, dtype=torch.float64) - 0.5) * 0.6  # mostly along +x
    speed = torch.rand(b, n, generator=gen, dtype=torch.float64) * 15
    step = torch.arange(-4, 1, dtype=torch.float64) * DT_S  # the 5 frames' times, the last at 0
    velocity = speed[..., None] * torch.stack([heading.cos(), heading.sin()], -1)  # [B, N, 2]
    xy = pos[:, :, None] + velocity[:, :, None] * step[None, None, :, None]  # [B, N, 5, 2]
    frames = torch.cat([xy, heading[:, :, None, None].expand(-1, -1, 5, 1)], -1)  # [B, N, 5, 3]
    box = torch.cat([torch.full((b, n, 1), LENGTH), torch.full((b, n, 1), WIDTH), torch.ones(b, n, 1)], -1).double()
    present = torch.rand(b, n, generator=gen) > 0.2
    ctrl = torch.tensor([[0, 3, 5], [1, 2, -1], [6, 4, 0]])
    live = ctrl >= 0
    headway, ttc = time_gaps(ctrl, live, frames, present, box)
    for i in range(b):
        for j in range(c):
            one = time_gaps(ctrl[i:i + 1, j:j + 1], live[i:i + 1, j:j + 1], frames[i:i + 1], present[i:i + 1], box[i:i + 1])
            assert (float(headway[i, j]), float(ttc[i, j])) == (float(one[0]), float(one[1]))
    assert math.isinf(headway[1, 2]) and math.isinf(ttc[1, 2])
    assert bool(torch.isfinite(headway).any())  # not vacuous: some slot has a leader


# ------------------------------------------------------------------------------- in the environments
def loop_terms(frames: np.ndarray, present: np.ndarray, box: np.ndarray, ctrl, headway_s: float, ttc_s: float):
    """The gap terms of each track of ``ctrl`` by the module docstring's words, one agent and one other at a time
    (plain Python): frames [N, 5, 3], present [N], box [N, 2+]."""
    out = []
    for k in ctrl:
        x, y, h = frames[k, -1]
        fwd, left = np.array([math.cos(h), math.sin(h)]), np.array([-math.sin(h), math.cos(h)])
        v = (frames[k, -1, :2] - frames[k, -2, :2]) / DT_S
        best, lead = math.inf, None
        for j in range(len(frames)):
            if j == k or not present[j]:
                continue
            rel = frames[j, -1, :2] - np.array([x, y])
            turn = frames[j, -1, 2] - h
            along = box[j, 0] / 2 * abs(math.cos(turn)) + box[j, 1] / 2 * abs(math.sin(turn))
            across = box[j, 0] / 2 * abs(math.sin(turn)) + box[j, 1] / 2 * abs(math.cos(turn))
            if rel @ fwd > 0 and abs(rel @ left) < box[k, 1] / 2 + across:
                gap = max(rel @ fwd - box[k, 0] / 2 - along, 0.0)
                if gap < best:
                    best, lead = gap, j
        speed = v @ fwd
        headway = ttc = 0.0
        if lead is not None:
            closing = speed - ((frames[lead, -1, :2] - frames[lead, -2, :2]) / DT_S) @ fwd
            if speed > 0:
                headway = max(0.0, 1 - best / speed / headway_s)
            if closing > 0:
                ttc = max(0.0, 1 - best / closing / ttc_s)
        out.append((headway, ttc))
    return out


@pytest.fixture(scope="module")
def prior_and_scenes(embedded_prior, sample_scenes):
    model, vocab = embedded_prior
    return model, vocab, sample_scenes


def pettingzoo_episode(prior_and_scenes, reward, seed=3, steps=8):
    """(rewards, infos) per step of one PettingZoo episode, every controlled vehicle taking its prior's most likely
    token, nobody removed; and the env."""
    from envs import smart_traffic_v0

    model, vocab, scenes = prior_and_scenes
    env = smart_traffic_v0.parallel_env(scenarios=scenes[2:3], prior=model, motion_vocab=vocab, controlled="vehicles", max_agents=8,
                                        horizon_steps=steps, terminate_on=(), reward=reward)
    _, infos = env.reset(seed=seed)
    out = []
    while env.agents:
        actions = {a: int(np.argmax(infos[a]["prior_logits"])) for a in env.agents}
        frames_before = len(env.core.episode)
        _, rewards, _, _, infos = env.step(actions)
        assert len(env.core.episode) == frames_before + 1
        frames, present = (t[0].cpu().numpy() for t in env.core.episode[-1])
        out.append((rewards, infos, frames, present))
    return env, out


def test_the_pettingzoo_env_reports_the_gap_terms_of_every_agent_as_a_loop_over_its_frames_computes_them(prior_and_scenes):
    """The infos' ``reward_terms`` carry ``headway`` and ``ttc`` (positions 6 and 7), equal to the per-agent loop
    over the step's recorded frames, and the reward with ``headway`` at -0.5 and ``ttc`` at -0.25 is the default
    reward plus those weights times them (the same episode: the reward changes nothing the agents do)."""
    weights = {"headway": -0.5, "ttc": -0.25, "headway_s": 2.0, "ttc_s": 4.0}
    env, tuned = pettingzoo_episode(prior_and_scenes, weights)
    _, plain = pettingzoo_episode(prior_and_scenes, None)
    assert env.reward_config.headway == -0.5 and REWARD_TERMS[-2:] == ("headway", "ttc")
    box = env.static.box_size
    seen = np.zeros(2)
    for (rewards, infos, frames, present), (rewards0, infos0, frames0, _) in zip(tuned, plain):
        np.testing.assert_array_equal(frames, frames0)
        agents = sorted(rewards)
        track = dict(zip(env.possible_agents, env.ctrl_tracks))
        expected = loop_terms(frames, present, box, [int(track[a]) for a in agents], 2.0, 4.0)
        for a, (headway, ttc) in zip(agents, expected):
            terms = infos[a]["reward_terms"]
            assert terms.shape == (len(REWARD_TERMS),)
            assert (terms[HEADWAY], terms[TTC]) == (pytest.approx(headway, abs=1e-5), pytest.approx(ttc, abs=1e-5)), a
            np.testing.assert_array_equal(terms[:HEADWAY], infos0[a]["reward_terms"][:HEADWAY])
            assert rewards[a] == pytest.approx(rewards0[a] - 0.5 * terms[HEADWAY] - 0.25 * terms[TTC], abs=1e-6)
            seen += terms[[HEADWAY, TTC]] > 0
    assert seen[0] > 0 and seen[1] > 0  # not vacuous: the episode has followers too close and closing in


def test_with_the_weights_at_zero_the_reward_is_the_other_terms_alone(prior_and_scenes):
    """The default (weights 0): the gap terms are reported and weigh nothing; every reward equals the dot product of
    the six other terms with the default weights, exactly as before the gap terms existed."""
    _, plain = pettingzoo_episode(prior_and_scenes, None)
    old = np.array([getattr(RewardConfig(), t) for t in REWARD_TERMS[:HEADWAY]])
    assert RewardConfig().headway == RewardConfig().ttc == 0.0
    for rewards, infos, _, _ in plain:
        for a, r in rewards.items():
            assert r == pytest.approx(float(infos[a]["reward_terms"][:HEADWAY].astype(np.float64) @ old), abs=1e-6)


def test_the_batched_env_takes_the_gap_weights_and_reports_the_terms(prior_and_scenes):
    """``reward={"headway": -0.5}`` in the batched env: its ``reward_terms`` hold the gap terms (in [0, 1]), and the
    reward is the default env's plus -0.5 x ``headway`` on the same scenes and seeds."""
    from envs.smart_traffic_batched_v0 import SmartTrafficBatchedEnv

    model, vocab, scenes = prior_and_scenes
    runs = []
    for reward in ({"headway": -0.5}, None):
        env = SmartTrafficBatchedEnv(scenarios=scenes, prior=model, motion_vocab=vocab, num_scenes=4, max_agents=4, horizon_steps=6,
                                     terminate_on=(), seed=0, reward=reward)
        td = env.reset()
        steps = []
        for _ in range(6):
            td["agents", "action"] = td["agents", "observation", "prior_logits"].argmax(-1)
            step, td = env.step_and_maybe_reset(td)
            steps.append((step["next", "agents", "reward"][..., 0].double(), step["next", "agents", "info", "reward_terms"].double()))
        runs.append((env, steps))
    (env, tuned), (_, plain) = runs
    assert env.core.reward_config.headway == -0.5
    assert tuned[0][1].shape[-1] == len(REWARD_TERMS)
    for (r, terms), (r0, terms0) in zip(tuned, plain):
        torch.testing.assert_close(terms, terms0)
        assert bool(((terms[..., HEADWAY:] >= 0) & (terms[..., HEADWAY:] <= 1)).all())
        torch.testing.assert_close(r, r0 - 0.5 * terms[..., HEADWAY], atol=1e-5, rtol=0)
    assert any(bool((terms[..., HEADWAY] > 0).any()) for _, terms in tuned)


# ------------------------------------------------------------------------------- the settings' bounds
@pytest.mark.parametrize("reward, accepted", [
    ({"headway_s": MAX_HEADWAY_S, "ttc_s": MAX_TTC_S}, True), ({"headway_s": 1e-3, "ttc_s": 1e-3}, True),
    ({"headway": MAX_REWARD_WEIGHT, "ttc": -MAX_REWARD_WEIGHT}, True),
    ({"headway_s": 0.0}, "headway_s"), ({"headway_s": -1.0}, "headway_s"), ({"headway_s": math.nextafter(MAX_HEADWAY_S, 99)}, "headway_s"),
    ({"ttc_s": 0.0}, "ttc_s"), ({"ttc_s": 30.5}, "ttc_s"), ({"ttc_s": math.inf}, "ttc_s"), ({"ttc_s": True}, "ttc_s"),
    ({"headway": -1001.0}, "headway"), ({"ttc": 1e300}, "ttc"), ({"ttc": "-1"}, "ttc"),
])
def test_the_gap_settings_are_bounded_by_name(prior_and_scenes, reward, accepted):
    from envs import smart_traffic_v0

    _, vocab, scenes = prior_and_scenes
    make = lambda: smart_traffic_v0.parallel_env(scenarios=scenes[:1], prior=None, motion_vocab=vocab,  # noqa: E731
                                                 background="log", reward=reward)
    if accepted is True:
        config = make().reward_config
        assert all(getattr(config, k) == v for k, v in reward.items())
        return
    with pytest.raises(EnvConfigError, match=f"reward\\['{accepted}'\\]"):
        make()


def test_fine_tuning_configs_take_the_gap_terms():
    pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")
    from agents.finetune_config import FinetuneConfigError, load_finetune_config

    cfg = load_finetune_config("tiny", ["reward.headway=-0.5", "reward.ttc=-0.25", "reward.ttc_s=2.5"])
    assert cfg.reward == {"headway": -0.5, "ttc": -0.25, "ttc_s": 2.5}
    with pytest.raises(FinetuneConfigError, match="headway_s"):
        load_finetune_config("tiny", ["reward.headway_s=0"])
