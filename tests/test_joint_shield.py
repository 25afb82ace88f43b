"""The shield's joint check (envs._shield.joint_actions, ``shield=[..., "joint"]``): once the controlled agents have
chosen, an agent whose token would run into an earlier controlled agent's token, as taken, takes the most likely token
of its shielded top k that does not; the chosen token stays where none does. Checked against a brute force (the tokens'
frames placed one agent at a time, boxes tested pair by pair and frame by frame) on the two real WOMD scenes, the
controlled vehicles driving at the fastest token every other step whatever their masks say, where they run into each
other."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs import smart_traffic_v0
from envs._shield import event_boxes
from smart_marl.geometry_torch import boxes_overlap
from smart_marl.rollout.frames import token_frames
from smart_marl.scenario import AgentType

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py
K = 16


def _env(scenes, prior, shield):
    model, vocab = prior
    return smart_traffic_v0.parallel_env(scenarios=scenes, prior=model, motion_vocab=vocab, controlled="vehicles", max_agents=8,
                                         horizon_steps=8, terminate_on=(), reference_top_k=K, observation="dict", shield=shield)


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
    """Each step of both scenes' episodes: (core before the step, the chosen tokens by controlled slot, the step's infos)."""
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


def test_the_joint_check_replaces_exactly_the_tokens_that_run_into_an_earlier_agents(womd_scenes, embedded_prior):
    env = _env(womd_scenes, embedded_prior, ["collision", "offroad", "gap", "joint"])
    replaced = checked = 0
    for (core, before, tracks, slots, tokens, start), chosen_frames, half, infos in _steps(env, embedded_prior):
        taken = {}  # controlled slot -> the frames it took (where the step put it)
        for c, name in enumerate(env.possible_agents):
            if tokens[c] is None or not bool(before["live"][c]):
                continue
            taken[c] = core.hist_pose[0, tracks[c], -5:].double()
            s = slots[c]
            earlier = [j for j in taken if j < c and not bool(boxes_overlap(start[c][:2], start[c][2], half[s], start[j][:2], start[j][2],
                                                                             half[slots[j]]))]

            def runs_into(frames, c=c, s=s, earlier=earlier, taken=taken):
                return any(_overlap(frames, half[s], taken[j], half[slots[j]]) for j in earlier)
            top = torch.topk(before["shielded"][0, c], K)
            clear = [int(t) for v, t in zip(top.values, top.indices) if torch.isfinite(v) and not runs_into(_frames(core, before, s, int(t)))]
            if infos[name]["shield_replaced"]:  # its choice ran into an earlier agent's: it took the most likely clear token
                assert runs_into(chosen_frames[c]) and clear
                assert torch.allclose(taken[c], _frames(core, before, s, clear[0]), atol=1e-3)
                replaced += 1
            else:  # it took its choice: clear of the earlier agents, or with no clear token in its top k
                assert torch.allclose(taken[c], chosen_frames[c], atol=1e-3)
                assert not runs_into(chosen_frames[c]) or not clear
            checked += 1
    assert checked > 40 and replaced > 0  # the real scenes exercise it


def test_without_the_joint_check_the_chosen_tokens_are_taken(womd_scenes, embedded_prior):
    env = _env(womd_scenes, embedded_prior, ["collision", "offroad", "gap"])
    ran_into = 0
    for (core, before, tracks, slots, tokens, start), chosen_frames, half, infos in _steps(env, embedded_prior):
        for c, name in enumerate(env.possible_agents):
            if tokens[c] is not None and bool(before["live"][c]):
                assert not infos[name]["shield_replaced"]
                assert torch.allclose(core.hist_pose[0, tracks[c], -5:].double(), chosen_frames[c], atol=1e-3)
                ran_into += int(any(_overlap(chosen_frames[c], half[slots[c]], chosen_frames[j], half[slots[j]])
                                    for j in chosen_frames if j < c))
    assert ran_into > 0  # the same choices run controlled agents into each other here
