"""The shield (envs._shield): the tokens that would run a controlled agent into another agent or a
vehicle off the road are taken out of its prior logits. Checked against a brute force of its own
(every other agent at constant velocity, every frame; the reward's offroad test at the token's end),
through both faces of the environment and the fine-tuning config."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch

from envs import smart_traffic_v0
from envs._arguments import shield_option
from envs._reward import offroad
from envs._shield import DEFAULT_SHIELD_CHECKS, SHIELD_CHECKS, event_boxes
from envs.errors import EnvConfigError, EnvConfigTypeError
from smart_marl.geometry_torch import boxes_overlap
from smart_marl.rollout import FORCED_LATER
from smart_marl.rollout.avoidance import SEARCH_DEPTH, constant_velocity_pose, excluded_tokens
from smart_marl.rollout.frames import token_frames
from smart_marl.scenario import AgentType
from smart_marl.tokens import FRAMES_PER_TOKEN

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py
K = 3


def _env(scenes, prior, **kw):
    model, vocab = prior
    args = dict(scenarios=scenes, prior=model, motion_vocab=vocab, controlled="vehicles", max_agents=8, horizon_steps=6,
                terminate_on=(), reference_top_k=K, observation="dict", shield=True)
    args.update(kw)
    return smart_traffic_v0.parallel_env(**args)


def _brute_force(core, b: int, c: int, tokens: torch.Tensor, road: bool = False) -> torch.Tensor:
    """bool [T]: does each token of controlled slot ``c`` of scene row ``b`` overlap another simulated agent
    (exact boxes, on the same frame; a background agent where its token drawn ahead takes it, another
    controlled agent at constant velocity and standing where it is) or, for a vehicle, end with a corner off the road; pairs
    overlapping already now are left out (the rule's exception). ``road``: the offroad test alone."""
    pr = core.prior
    draw = pr.drawn_ahead()
    drawn = {int(r): int(t) for r, t, f in zip(draw.rows, draw.tokens, draw.forced.reshape(-1)[draw.rows]) if f != FORCED_LATER}
    track = int(core.ctrl_track[b, c])
    s = int(core.slot_of_track[b, track])
    pose, before = pr.pose[b], pr.previous_pose[b]
    local = pr.token_poses[pr.agent_type[b, s], tokens]  # [T, 6, 3]
    frames = token_frames(local, pose[s][None], before[s][None], pr.interpolation)  # [T, 5, 3]
    ahead = constant_velocity_pose(pose, before)
    step = torch.arange(1, FRAMES_PER_TOKEN + 1, dtype=pose.dtype) / FRAMES_PER_TOKEN
    half = event_boxes(pr, core.scenes)[b, :, :2] / 2  # the boxes the events measure (the scene's, not the prior's shapes)
    hit = torch.zeros(len(tokens), dtype=torch.bool)
    for o in pr.simulated[b].nonzero().squeeze(1).tolist():
        if o == s or boxes_overlap(pose[s, :2], pose[s, 2], half[s], pose[o, :2], pose[o, 2], half[o]):
            continue
        if b * pr.num_slots + o in drawn:  # where its token takes it
            other = token_frames(pr.token_poses[pr.agent_type[b, o], drawn[b * pr.num_slots + o]][None], pose[o][None],
                                 before[o][None], pr.interpolation)[0]  # [5, 3]
            other_xy, other_heading = other[:, :2], other[:, 2]
        else:  # another controlled agent: driving on at constant velocity, or standing where it is
            other_xy = pose[o, :2] + step[:, None] * (ahead[o, :2] - pose[o, :2])  # [5, 2]
            other_heading = pose[o, 2]
            hit |= boxes_overlap(frames[..., :2], frames[..., 2], half[s], pose[o, :2], pose[o, 2], half[o]).any(-1)
        hit |= boxes_overlap(frames[..., :2], frames[..., 2], half[s], other_xy, other_heading, half[o]).any(-1)
    ends = frames[:, -1].to(core.pose.dtype)  # [T, 3]
    ctrl = torch.full((core.num_scenes, len(tokens)), -1, dtype=torch.long)
    ctrl[b] = track
    last = torch.zeros(core.num_scenes, len(tokens), 3, dtype=core.pose.dtype)
    last[b] = ends
    off = offroad(core.scenes, ctrl, ctrl >= 0, last)[b]
    return off if road else hit | off


def test_shield_arguments_are_checked_and_normalised(sample_scenes, embedded_prior):
    assert _env(sample_scenes[:1], embedded_prior).shield == DEFAULT_SHIELD_CHECKS == ("collision", "offroad")
    assert _env(sample_scenes[:1], embedded_prior, shield=["offroad", "collision"]).shield == DEFAULT_SHIELD_CHECKS  # the canonical order
    assert _env(sample_scenes[:1], embedded_prior, shield=["gap", "collision"]).shield == ("collision", "gap")
    assert SHIELD_CHECKS == ("collision", "offroad", "gap", "joint")
    assert _env(sample_scenes[:1], embedded_prior, shield=["joint", "gap", "collision"]).shield == ("collision", "gap", "joint")
    assert _env(sample_scenes[:1], embedded_prior, shield="offroad").shield == ("offroad",)
    assert _env(sample_scenes[:1], embedded_prior, shield=False).shield == ()
    with pytest.raises(EnvConfigError, match=r"shield: unknown check\(s\) \['seatbelt'\]"):
        _env(sample_scenes[:1], embedded_prior, shield=["seatbelt"])
    with pytest.raises(EnvConfigTypeError, match="shield must be True, False or a list"):
        _env(sample_scenes[:1], embedded_prior, shield=3)
    # a command line's form (the benchmarks' --shield): checks joined with '+'
    assert shield_option("gap+collision") == ("collision", "gap") and shield_option("") == ()
    with pytest.raises(argparse.ArgumentTypeError, match=r"unknown check\(s\) \['seatbelt'\]"):
        shield_option("collision+seatbelt")


def shielded_steps(env, prior, num_scenes: int, steps: int, seed: int = 0):
    """Every step of ``env``'s episodes on each of its first ``num_scenes`` scenes, up to ``steps``: (core, shielded prior logits, plain prior
    logits, observations). Between steps the agents take a random token of their masks, and every other step the token
    that goes farthest ahead, whatever their masks say: off the road and into others, where the shield has work to do."""
    rng = np.random.default_rng(seed)
    fastest = int(prior[1][AgentType.VEHICLE].poses[:, -1, 0].argmax())
    for index in range(num_scenes):
        obs, _ = env.reset(seed=index, options={"scene_index": index})
        for step in range(steps):
            if not env.agents:
                break
            core, checks = env.core, env.core.shield
            shielded = core.prior_logits()
            core.shield = ()
            plain = core.prior_logits()
            core.shield = checks
            yield core, shielded, plain, obs
            obs, *_ = env.step({a: fastest if step % 2 else int(rng.choice(np.flatnonzero(obs[a]["action_mask"])))
                                for a in env.agents})


def test_the_shield_takes_out_exactly_unsafe_tokens_and_keeps_k_safe_ones_on_top(sample_scenes, embedded_prior):
    env = _env(sample_scenes, embedded_prior)
    taken_out, checked_agents, to_the_road = 0, 0, 0
    for core, shielded, plain, obs in shielded_steps(env, embedded_prior, len(sample_scenes), 4):
        for c in core.live[0].nonzero().squeeze(1).tolist():
            gone = torch.isinf(shielded[0, c]) & torch.isfinite(plain[0, c])
            assert torch.equal(shielded[0, c][~gone], plain[0, c][~gone])  # nothing else changes
            top = torch.topk(shielded[0, c], K).indices
            top = top[torch.isfinite(shielded[0, c][top])]  # fewer than k where the search found fewer free
            unsafe_top = _brute_force(core, 0, c, top)
            if gone.any():  # what it took out is unsafe (among the tokens it searched), and its top k are safe
                searched = torch.zeros_like(gone)
                searched[torch.topk(plain[0, c], SEARCH_DEPTH).indices] = True  # a row with fewer than k free there
                gone_searched = (gone & searched).nonzero().squeeze(1)
                assert _brute_force(core, 0, c, gone_searched).all()  # loses all the rest
                if unsafe_top.any():  # every token fails a check: those off the road are taken out, the rest kept
                    assert _brute_force(core, 0, c, torch.topk(plain[0, c], 64).indices).all()
                    assert not _brute_force(core, 0, c, top, road=True).any()
                    assert _brute_force(core, 0, c, gone_searched, road=True).all()
                    to_the_road += 1
                taken_out += int(gone.sum())
            else:  # nothing taken out: the prior's own top k are safe (or every token failed: left alone)
                assert not unsafe_top.any() or _brute_force(core, 0, c, torch.topk(plain[0, c], 64).indices).all()
            mask = obs[env.agents[c]]["action_mask"].astype(bool) if env.agents[c] in obs else None
            if mask is not None:  # the action mask is the shielded top k
                assert set(np.flatnonzero(mask)) == set(top.tolist())
            checked_agents += 1
    assert checked_agents > 20 and taken_out > 0 and to_the_road > 0  # the sample scenes exercise it


def test_an_agent_whose_every_token_fails_keeps_them_all_and_a_lone_agent_is_still_checked():
    """The search's rule (the shield searches such an agent again for the road alone: the test above)."""
    logits = torch.tensor([[3.0, 2.0, 1.0, 0.0]])
    pose = torch.zeros(1, 1, 3)
    size = torch.tensor([[[4.0, 2.0, 1.5]]])
    poses = torch.linspace(0, 1, 6)[None, None, :, None] * torch.tensor([[[1.0, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]]])[:, :, None]
    args = (logits, torch.tensor([0]), pose, pose.clone(), size, torch.ones(1, 1, dtype=torch.bool), torch.zeros(1, 1, dtype=torch.long),
            poses, 2)
    everything = excluded_tokens(*args, also=lambda r, tok: torch.ones(tok.shape, dtype=torch.bool))
    assert not everything.any()  # every token fails: none is taken out
    far = excluded_tokens(*args, also=lambda r, tok: tok <= 1)  # the first two fail; the next two pass
    assert far.tolist() == [[True, True, False, False]]
    assert not excluded_tokens(*args).any()  # without the second test a lone agent has nothing to avoid


def test_the_batched_env_and_a_finetuning_config_carry_the_shield(sample_scenes, embedded_prior):
    pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")
    from torchrl.envs.utils import check_env_specs

    from agents.finetune_config import FinetuneConfigError, load_finetune_config
    from envs import smart_traffic_batched_v0

    model, vocab = embedded_prior
    env = smart_traffic_batched_v0.SmartTrafficBatchedEnv(scenarios=sample_scenes, prior=model, motion_vocab=vocab, num_scenes=3,
                                                          controlled="vehicles", max_agents=4, horizon_steps=3, reference_top_k=K,
                                                          shield=True, scene_order="sequential")
    check_env_specs(env, seed=0)
    td = env.reset()
    fastest = int(vocab[AgentType.VEHICLE].poses[:, -1, 0].argmax())
    seen = 0
    for _ in range(2):  # the agents take the token that goes farthest ahead, whatever their masks say
        td["agents", "action"] = torch.full_like(td["agents", "mask"], fastest, dtype=torch.long)
        td = env.step(td)["next"]
        logits, live = td["agents", "observation", "prior_logits"], td["agents", "mask"]
        seen += int(torch.isinf(logits[live]).sum())
        assert torch.isfinite(logits[live]).sum(-1).min() >= K  # k tokens are always left to draw from
        assert not torch.isinf(logits[~live]).any()  # padded and done slots stay zeros
    assert seen > 0
    cfg = load_finetune_config("tiny", ["shield=true"])
    assert cfg.shield == DEFAULT_SHIELD_CHECKS and cfg.to_dict()["shield"] == list(DEFAULT_SHIELD_CHECKS)
    assert load_finetune_config("tiny", ['shield=["joint", "gap", "offroad", "collision"]']).shield == SHIELD_CHECKS
    assert load_finetune_config("tiny", ['shield=["offroad"]']).shield == ("offroad",)
    with pytest.raises(FinetuneConfigError, match=r"shield: unknown check\(s\) \['brakes'\]"):
        load_finetune_config("tiny", ['shield=["brakes"]'])


def test_boxes_off_road_is_the_offroad_event_in_any_blocks_of_rows(sample_scenes, monkeypatch):
    """The shield's offroad check (rows packed scene by scene, in blocks) against the reward's offroad test
    of the same boxes, scene by scene."""
    import smart_marl.geometry_torch as gt
    from envs._scene import scene_static
    from envs._scene_batch import SceneBatch

    sb = SceneBatch.build([scene_static(sc) for sc in sample_scenes[:3]], torch.float64, "cpu")
    gen = torch.Generator().manual_seed(0)
    scene = torch.tensor([0] * 5 + [2] * 7)  # rows of scenes 0 and 2, none of scene 1
    vehicles = [(sb.types[b] == int(AgentType.VEHICLE)).nonzero().squeeze(1) for b in range(sb.num_scenes)]
    track = torch.stack([vehicles[int(b)][k % len(vehicles[int(b)])] for k, b in enumerate(scene)])  # vehicles: the event's agents
    lo, hi = sb.log_pose[..., :2].amin((1, 2)), sb.log_pose[..., :2].amax((1, 2))  # [B, 2] each scene's extent
    xy = lo[scene][:, None] + (hi - lo)[scene][:, None] * torch.rand(len(scene), 6, 2, generator=gen, dtype=torch.float64)
    heading = torch.rand(len(scene), 6, generator=gen, dtype=torch.float64) * 6.28
    size, z = sb.box_size[scene, track], sb.z[scene, track]
    got = gt.boxes_off_road(sb.edges, scene, xy, heading, size, z)
    monkeypatch.setattr(gt, "OFF_ROAD_BLOCK_POINTS", 4 * 6 * 2)  # two rows a block
    assert torch.equal(gt.boxes_off_road(sb.edges, scene, xy, heading, size, z), got)
    for i in range(len(scene)):
        b = int(scene[i])
        ctrl = torch.full((sb.num_scenes, 6), -1, dtype=torch.long)
        ctrl[b] = track[i]
        last = torch.zeros(sb.num_scenes, 6, 3, dtype=torch.float64)
        last[b] = torch.cat([xy[i], heading[i][:, None]], -1)
        assert torch.equal(offroad(sb, ctrl, ctrl >= 0, last)[b], got[i])
    assert got.any() and not got.all()  # both outcomes exercised
