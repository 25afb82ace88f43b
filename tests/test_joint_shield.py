"""The shield's joint check (envs._shield.joint_actions, ``shield=[..., "joint"]``): once the controlled agents have
chosen, an agent whose token would run into an earlier controlled agent's token, as taken, takes the most likely token
of its shielded top k that does not; where none does and one earlier agent is in its way, that one yields if it can.
Checked against a brute force (the tokens' frames placed one agent at a time, boxes tested pair by pair and frame by
frame) on the two real WOMD scenes, the controlled vehicles driving at the fastest token every other step whatever
their masks say, where they run into each other."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs._shield import event_boxes
from smart_marl.geometry_torch import boxes_overlap
from smart_marl.rollout.frames import token_frames
from smart_marl.scenario import AgentType
from test_shield import _env as shield_env

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py
K = 16


def _env(scenes, prior, shield):
    return shield_env(scenes, prior, shield=shield, horizon_steps=8, reference_top_k=K)


def _frames(core, before: dict, slot: int, token: int) -> torch.Tensor:
    """[5, 3] float64: the step's frames of prior slot ``slot`` of scene 0 were it to take ``token`` (from the poses
    ``before`` the step)."""
    pr = core.prior
    return token_frames(pr.token_poses[pr.agent_type[0, slot], token][None].double(), before["pose"][0, slot][None].double(),
                        before["previous"][0, slot][None].double(), pr.interpolation)[0]


def _overlap(a: torch.Tensor, half_a: torch.Tensor, b: torch.Tensor, half_b: torch.Tensor) -> bool:
    """Do boxes of half sizes ``half_a`` / ``half_b`` on frames ``a`` / ``b`` [5, 3] overlap on some frame (one at a time)."""
    return any(bool(boxes_overlap(a[f, :2], a[f, 2], half_a, b[f, :2], b[f, 2], half_b)) for f in range(len(a)))


def _steps(env, prior, seed: int = 0):
    """Each step of both scenes' episodes, taken: ((the core, its state ``before`` the step, the controlled agents'
    tracks, prior slots, chosen tokens (None: not acting) and poses at the start), the chosen tokens' frames by
    controlled slot, every prior slot's half box, the step's infos)."""
    rng = np.random.default_rng(seed)
    fastest = int(prior[1][AgentType.VEHICLE].poses[:, -1, 0].argmax())
    for index in range(2):
        obs, _ = env.reset(seed=index, options={"scene_index": index})
        for step in range(8):
            if not env.agents:
                break
            chosen = {a: fastest if step % 2 else int(rng.choice(np.flatnonzero(obs[a]["action_mask"]))) for a in env.agents}
            core = env.core
            before = {"shielded": core.prior_logits().clone(), "live": core.live[0].clone(),
                      "pose": core.prior.pose.clone(), "previous": core.prior.previous_pose.clone()}
            tracks = [int(t) for t in core.ctrl_track[0]]
            slots = [int(core.slot_of_track[0, t]) for t in tracks]
            tokens = [chosen.get(name) for name in env.possible_agents]
            state = (core, before, tracks, slots, tokens, [core.prior.pose[0, s].clone() for s in slots])
            state_frames = {c: _frames(core, before, s, t) for c, (s, t) in enumerate(zip(slots, tokens)) if t is not None}
            half = event_boxes(core.prior, core.scenes)[0, :, :2].double() / 2
            obs, _, _, _, infos = env.step(chosen)
            yield state, state_frames, half, infos


def _joint_by_hand(core, before, slots, tokens, start, half, live, yields: list) -> dict[int, int]:
    """The tokens the joint check should take (controlled slot -> token): the rule of envs._shield.joint_actions one
    agent and one pair at a time, in float64. ``yields`` gets, for each agent with no way out that ran into one earlier
    agent, whether that one had a way to yield."""
    acting = [c for c, t in enumerate(tokens) if t is not None and bool(live[c])]
    final = {c: tokens[c] for c in acting}
    frames = {c: _frames(core, before, slots[c], final[c]) for c in acting}

    def apart(a: int, b: int) -> bool:
        return not bool(boxes_overlap(start[a][:2], start[a][2], half[slots[a]], start[b][:2], start[b][2], half[slots[b]]))

    def clear_token(c: int, others: list[int]):
        top = torch.topk(before["shielded"][0, c], K)
        for v, t in zip(top.values, top.indices):
            f = _frames(core, before, slots[c], int(t))
            if torch.isfinite(v) and not any(_overlap(f, half[slots[c]], frames[o], half[slots[o]]) for o in others):
                return int(t), f
        return None

    for i in acting:
        earlier = [j for j in acting if j < i and apart(i, j)]
        hit = [j for j in earlier if _overlap(frames[i], half[slots[i]], frames[j], half[slots[j]])]
        if not hit:
            continue
        who, out = i, clear_token(i, earlier)
        if out is None and len(hit) == 1:  # no way out: the one earlier agent in its way yields, if it can
            who = hit[0]
            out = clear_token(who, [o for o in acting if o <= i and o != who and apart(who, o)])
            yields.append(out is not None)
        if out is not None:
            final[who], frames[who] = out
    return final


def test_the_joint_check_replaces_exactly_the_tokens_that_run_into_an_earlier_agents(womd_scenes, embedded_prior):
    env = _env(womd_scenes, embedded_prior, ["collision", "offroad", "gap", "joint"])
    replaced = checked = 0
    yields = []
    for (core, before, tracks, slots, tokens, start), chosen_frames, half, infos in _steps(env, embedded_prior):
        final = _joint_by_hand(core, before, slots, tokens, start, half, before["live"], yields)
        for c, token in final.items():
            name = env.possible_agents[c]
            assert infos[name]["shield_replaced"] == (token != tokens[c])
            assert torch.allclose(core.hist_pose[0, tracks[c], -5:].double(), _frames(core, before, slots[c], token), atol=1e-3)
            replaced += int(token != tokens[c])
            checked += 1
    assert checked > 40 and replaced > 0 and any(yields)  # the real scenes exercise it, an earlier agent yielding included


def test_without_the_joint_check_the_chosen_tokens_are_taken(womd_scenes, embedded_prior):
    env = _env(womd_scenes, embedded_prior, ["collision", "offroad", "gap"])
    ran_into = 0
    for (core, before, tracks, slots, tokens, start), chosen_frames, half, infos in _steps(env, embedded_prior):
        for c, name in enumerate(env.possible_agents):
            if tokens[c] is not None and bool(before["live"][c]):
                assert not infos[name]["shield_replaced"]
                assert torch.allclose(core.hist_pose[0, tracks[c], -5:].double(), chosen_frames[c], atol=1e-3)
                ran_into += int(any(_overlap(chosen_frames[c], half[slots[c]], chosen_frames[j], half[slots[j]])
                                    and not _overlap(start[c][None], half[slots[c]], start[j][None], half[slots[j]])
                                    for j in chosen_frames if j < c))
    assert ran_into > 0  # the same choices run controlled agents into each other here
