"""The background's tokens drawn before the policy acts (smart_marl.rollout.drawing, envs._dynamics.draw_background),
and the shield that tests the controlled agents' tokens against where the background will really be (envs._shield).

Claims: with nothing forced later, drawing ahead is the plain step bit for bit (same seeds, same rollouts); with
controlled agents, the background draws what it drew before wherever collision-aware sampling did not react to a
controlled agent's token of the same step; a token the shield allows does not put a controlled agent into a
background agent's box on any frame of the step (real WOMD scenes, the embedded prior)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs import smart_traffic_v0
from smart_marl.geometry_torch import boxes_overlap
from smart_marl.rollout import FORCED_LATER, RolloutState
from smart_marl.scenario import AgentType
from smart_marl.rollout.frames import token_frames
from smart_marl.tokens import FRAMES_PER_TOKEN

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def _state(scene, rollouts: int = 8) -> RolloutState:
    return RolloutState.start("embedded", scene, num_rollouts=rollouts, seed=0)


def _vehicles(state: RolloutState, count: int) -> torch.Tensor:
    return ((state.agent_type[0] == int(AgentType.VEHICLE)) & state.simulated[0]).nonzero().squeeze(1)[:count]


def test_drawing_ahead_with_nothing_forced_later_is_the_plain_step_bit_for_bit(sample_scenes):
    plain, ahead = _state(sample_scenes[2]), _state(sample_scenes[2])
    follow = _vehicles(plain, 2)  # two agents forced with known tokens (as the env forces agents that follow the log)
    for _ in range(4):
        forced = torch.full(plain.simulated.shape, -1, dtype=torch.long)
        forced[:, follow] = plain.logits()[:, follow].argmax(-1)
        a = plain.step(forced)
        draw = ahead.draw_ahead(forced)
        assert ahead.drawn_ahead() is draw
        b = ahead.step(forced)
        assert ahead.drawn_ahead() is None  # a step takes the draw
        for name in ("tokens", "log_probs", "poses", "simulated", "forced"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_forced_later_slots_get_their_tokens_and_log_probs_at_the_step_and_mismatches_are_refused(sample_scenes):
    state = _state(sample_scenes[2])
    ctrl = _vehicles(state, 3)
    later = torch.full(state.simulated.shape, -1, dtype=torch.long)
    later[:, ctrl] = FORCED_LATER
    draw = state.draw_ahead(later)
    tokens = state.logits()[:, ctrl].topk(3, -1).indices[..., 2]  # their third most likely tokens
    given = torch.full_like(later, -1)
    given[:, ctrl] = tokens
    with pytest.raises(ValueError, match="differ from those the tokens were drawn ahead with"):
        state.step(torch.full_like(later, -1))  # the later slots not forced
    out = state.step(given)
    assert torch.equal(out.tokens[:, ctrl], tokens) and out.forced[:, ctrl].all()
    logp = torch.log_softmax(out.logits[:, ctrl], -1).gather(-1, tokens[..., None]).squeeze(-1)
    assert torch.allclose(out.log_probs[:, ctrl], logp)
    flat = out.tokens.reshape(-1)[draw.rows]
    drawn = draw.forced.reshape(-1)[draw.rows] == -1
    assert torch.equal(flat[drawn], draw.tokens[drawn])  # the others took what was drawn ahead
    # an edit between the draw and the step drops the draw: the step draws afresh
    state.draw_ahead(later)
    state.set_agent_valid(torch.ones_like(state.simulated))
    assert state.drawn_ahead() is None
    with pytest.raises(ValueError, match="outside its agent type's vocabulary"):
        state.draw_ahead(torch.full_like(later, -3))


def test_the_background_draws_as_before_where_no_controlled_agent_changed_its_avoidance(womd_scenes):
    """The old environment forced the controlled agents' tokens into the same step as the background's draw, and
    collision-aware sampling saw where those tokens took them; now it sees them at constant velocity. Controlled
    agents that act like the prior (its own top token) leave every background draw as it was, seed for seed;
    controlled agents that all take the fastest token change a few draws of the agents they run at."""
    for scene in womd_scenes:
        base = _state(scene, 16)
        ctrl = _vehicles(base, 20)
        background = base.simulated.clone()
        background[:, ctrl] = False
        fastest = int(base.token_poses[int(AgentType.VEHICLE), :, -1, 0].argmax())
        for tokens, least in ((base.logits()[:, ctrl].argmax(-1), 1.0), (torch.full((base.num_groups, len(ctrl)), fastest), 0.9)):
            forced = torch.full(base.simulated.shape, -1, dtype=torch.long)
            forced[:, ctrl] = tokens
            later = forced.clone()
            later[:, ctrl] = FORCED_LATER
            old = base.fork(1).step(forced)
            new_state = base.fork(1)
            new_state.draw_ahead(later)
            new = new_state.step(forced)
            same = (old.tokens == new.tokens)[background].float().mean().item()
            assert same >= least, (scene.scenario_id, same)
            assert torch.equal(old.tokens[:, ctrl], new.tokens[:, ctrl])


def _overlaps(pose_a: torch.Tensor, half_a: torch.Tensor, pose_b: torch.Tensor, half_b: torch.Tensor) -> bool:
    """Do two boxes overlap on any of the frames ``pose_*`` [F, 3] (exact oriented rectangles)?"""
    return bool(boxes_overlap(pose_a[:, :2], pose_a[:, 2], half_a, pose_b[:, :2], pose_b[:, 2], half_b).any())


def test_a_token_the_shield_allows_does_not_run_into_a_background_agent_within_the_step(womd_scenes, embedded_prior):
    """Real scenes, 16 controlled vehicles acting among the shielded top 3 (the policy's action mask): at random, and
    every other step the allowed token that goes farthest ahead (up to the car in front, where the near misses are).
    After each step, every token each agent was allowed, placed where the step places tokens, overlaps no background
    agent's box on the frames it really took (the scene's boxes, as the events measure them; exact rectangles) on any
    of the step's five frames, except a pair that overlapped already (the rule leaves such pairs alone) or an agent
    whose every token the shield looked at failed (it then takes nothing out). Nor does it overlap another controlled
    agent's box where that one stood (the shield keeps a controlled agent clear of another that might brake)."""
    model, vocab = embedded_prior
    env = smart_traffic_v0.parallel_env(scenarios=womd_scenes, prior=model, motion_vocab=vocab, controlled="vehicles",
                                        max_agents=16, horizon_steps=10, terminate_on=(), reference_top_k=3,
                                        observation="dict", shield=True)
    rng = np.random.default_rng(0)
    ahead_m = vocab[AgentType.VEHICLE].poses[:, -1, 0]  # how far ahead each vehicle token ends
    checked = shielded = standing_checked = 0
    for index in range(len(womd_scenes)):
        obs, _ = env.reset(seed=index, options={"scene_index": index})
        for step in range(10):
            if not env.agents:
                break
            core, pr = env.core, env.core.prior
            core.prior_logits()
            mask = core._unsafe[1][0]  # [C, V] what the shield took out of each controlled agent's logits
            allowed = {a: np.flatnonzero(obs[a]["action_mask"]) for a in env.agents}
            before, present = core.pose[0].clone(), core.present[0].clone()
            slot_pose, slot_before = pr.pose[0].clone(), pr.previous_pose[0].clone()
            live, ctrl = core.live[0].clone(), core.ctrl_track[0].clone()
            slots = core.slot_of_track[0].clone()
            pick = (lambda a: int(max(allowed[a], key=lambda t: ahead_m[t]))) if step % 2 else (lambda a: int(rng.choice(allowed[a])))
            obs, *_ = env.step({a: pick(a) for a in env.agents})
            frames = core.hist_pose[0, :, -FRAMES_PER_TOKEN:]  # [N, 5, 3] every track's frames of the step
            half = core.scenes.box_size[0, :, :2] / 2
            others = present.clone()
            others[ctrl[ctrl >= 0]] = False
            others &= core.scenes.is_motion[0]
            for c in live.nonzero().squeeze(1).tolist():
                t, s = int(ctrl[c]), int(slots[int(ctrl[c])])
                tokens = torch.as_tensor(allowed[env.possible_agents[c]])
                paths = token_frames(pr.token_poses[int(AgentType.VEHICLE), tokens], slot_pose[s].expand(len(tokens), 3),
                                     slot_before[s].expand(len(tokens), 3), pr.interpolation)  # [T, 5, 3]
                checked += 1
                shielded += int(mask[c].any())
                for o in others.nonzero().squeeze(1).tolist():
                    if _overlaps(before[t][None], half[t], before[o][None], half[o]):
                        continue  # overlapping already: left alone
                    hit = boxes_overlap(paths[..., :2], paths[..., 2], half[t], frames[o, :, :2], frames[o, :, 2], half[o]).any(-1)
                    assert not hit.any() or not mask[c].any(), (index, t, o, tokens[hit].tolist())  # only where it could not help
                for o in ctrl[live & (ctrl != t)].tolist():  # another controlled agent, were it to stand where it stood
                    if _overlaps(before[t][None], half[t], before[o][None], half[o]):
                        continue
                    hit = boxes_overlap(paths[..., :2], paths[..., 2], half[t], before[o, :2], before[o, 2], half[o]).any(-1)
                    assert not hit.any() or not mask[c].any(), (index, t, o, tokens[hit].tolist())
                    standing_checked += 1
    assert checked > 300 and shielded > 30 and standing_checked > 1000  # the scenes exercise it


def test_the_shield_measures_boxes_as_the_events_do_not_by_the_priors_shapes(womd_scenes, embedded_prior):
    """The prior's shapes come from the tokenized history and may be some 20 cm shorter than the scene's boxes, which the
    collision event measures: the shield takes the scene's (envs._shield.event_boxes), so shrinking the prior's
    shapes changes nothing it takes out."""
    model, vocab = embedded_prior
    env = smart_traffic_v0.parallel_env(scenarios=womd_scenes, prior=model, motion_vocab=vocab, controlled="vehicles",
                                        max_agents=16, horizon_steps=4, terminate_on=(), reference_top_k=3,
                                        observation="dict", shield=["collision"])
    taken = 0
    for index in range(len(womd_scenes)):
        obs, _ = env.reset(seed=index, options={"scene_index": index})
        core = env.core
        for _ in range(3):
            if not env.agents:
                break
            masked = core.prior_logits()
            taken += int(core._unsafe[1].sum())
            shape = core.prior.agent_shape
            core.prior.agent_shape, core._unsafe = shape * 0.1, None
            assert torch.equal(core.prior_logits(), masked)
            core.prior.agent_shape, core._unsafe = shape, None
            obs, *_ = env.step({a: int(np.flatnonzero(obs[a]["action_mask"])[-1]) for a in env.agents})
    assert taken > 0


def test_the_background_keeps_clear_of_a_controlled_agent_that_may_brake(sample_scenes):
    """A background car 2 m behind a controlled one, both driving at its speed: at constant velocity the controlled car
    drives off ahead, but its token comes with the policy's and it may brake. The background's draw keeps clear of it
    standing where it is too (:func:`smart_marl.rollout.drawing.later_standing_test`): no drawn token of the follower
    overlaps the controlled car's box there; without that test, many do (the scene exercises it)."""
    from smart_marl.rollout import drawing

    def follower_overlaps(with_test: bool) -> tuple[int, int]:
        state = _state(sample_scenes[2], 16)
        state.logits()
        speed = (state.pose[0, :, :2] - state.previous_pose[0, :, :2]).norm(dim=-1)
        veh = _vehicles(state, 100)
        back, ahead = int(veh[speed[veh].argmax()]), int(veh[speed[veh].argsort()[0]])  # the fastest follows, another leads
        pose, before = state.pose.clone(), state.previous_pose.clone()
        h = pose[:, back, 2]
        gap = float(state.agent_shape[0, back, 0] + state.agent_shape[0, ahead, 0]) / 2 + 2.0
        shift = torch.stack([gap * torch.cos(h), gap * torch.sin(h), torch.zeros_like(h)], -1)
        pose[:, ahead], before[:, ahead] = pose[:, back] + shift, before[:, back] + shift  # the same motion, 2 m ahead
        state.pose, state.previous_pose = pose, before
        later = torch.full(state.simulated.shape, -1, dtype=torch.long)
        later[:, ahead] = FORCED_LATER
        original = drawing.later_standing_test
        drawing.later_standing_test = original if with_test else (lambda *args: None)
        try:
            frames, known = state.draw_ahead(later).frames(state)
        finally:
            drawing.later_standing_test = original
        assert known[:, back].all()
        half = state.agent_shape[0, [back, ahead], :2].to(pose.dtype) / 2
        hit = boxes_overlap(frames[:, back, :, :2], frames[:, back, :, 2], half[0], pose[:, ahead, None, :2], pose[:, ahead, None, 2],
                            half[1]).any(-1)  # [G] the follower's step overlaps the leader standing
        return int(hit.sum()), int(speed[back])

    hits, speed = follower_overlaps(True)
    hits_without, _ = follower_overlaps(False)
    assert speed >= 2  # m per step: the follower drives on at constant velocity
    assert hits == 0 and hits_without >= 8, (hits, hits_without)
