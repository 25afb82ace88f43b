"""Environment stage, the shield: the tokens a controlled agent may not take because they would run it
into another agent or off the road (safe RL's action shielding, here a mask on the prior's logits).

What comes in: the prior's state (every simulated agent's pose, the pose its last token started at,
box, type; :class:`smart_marl.rollout.RolloutState`), the scenes' road edges, the controlled agents'
slots and their prior logits ``[B, C, V]``, the checks and the ``k`` the policy draws from. What goes
out: ``bool [B, C, V]``, true on the tokens to take out (their logits become ``-inf``).

The checks (``SHIELD_CHECKS``), on the tokens most likely first, until ``k`` pass both:

* ``"collision"``: the background's collision-aware rule (:mod:`smart_marl.rollout.avoidance`, the same
  code): the token's five 10 Hz frames overlap the box of one of the agent's 16 nearest others on the
  same frame, every box the scene's (:func:`event_boxes`: what the collision event measures, not the prior's shapes). The background's tokens of the step are drawn before the policy acts
  (:func:`envs._dynamics.draw_background`), so the background agents are checked on the frames they will
  really take; the other controlled agents, whose tokens come with the policy's, both at constant velocity
  and standing where they are (one that drives on, one that brakes);
* ``"offroad"``: a vehicle whose box, at the token's end (the step's last frame, where the reward's
  offroad event is measured), has a corner beyond a road edge (:func:`envs._reward.offroad`'s test).

So the top ``k`` of the shielded logits are the ``k`` most likely tokens that pass, and the reference of
fine-tuning (the prior's top ``k``, renormalised) is the prior as the shield lets it drive. An agent
all of whose tokens fail keeps them all (nothing is taken out), as in the background's rule. What the
shield cannot see: another controlled agent's move other than driving on or standing (a turn across, a swerve), an
agent beyond the 16 nearest, a pair whose boxes overlap already (left alone, as in the background's rule), offroad on the
step's in-between frames. The events' boxes are rounded (a little smaller than the exact boxes checked
here), so a token the shield allows does not collide with a background agent within the step.
"""

from __future__ import annotations

from typing import Sequence

import torch

from smart_marl.geometry_torch import boxes_overlap
from smart_marl.rollout import Draw, RolloutState
from smart_marl.rollout.avoidance import excluded_tokens, off_road_test
from smart_marl.rollout.frames import token_frames
from smart_marl.scenario import AgentType

from ._scene_batch import SceneBatch

SHIELD_CHECKS = ("collision", "offroad")


def unsafe_tokens(checks: Sequence[str], prior: RolloutState, scenes: SceneBatch, ctrl_track: torch.Tensor,
                  ctrl_slot: torch.Tensor, acting: torch.Tensor, logits: torch.Tensor, top_k: int | None,
                  ahead: Draw | None = None) -> torch.Tensor:
    """bool [B, C, V]: the tokens the shield takes out (module docstring) for the controlled agents
    ``acting`` [B, C] (tracks ``ctrl_track`` [B, C], slots ``ctrl_slot`` [B, C] in ``prior``, one group
    per scene), whose prior logits are ``logits`` [B, C, V]; ``top_k`` the policy's k (None: every token);
    ``ahead`` the background's tokens of the step, drawn already (the others are checked where they go)."""
    out = torch.zeros(logits.shape, dtype=torch.bool, device=logits.device)
    if not checks or not bool(acting.any()):
        return out
    cb, cc = acting.nonzero(as_tuple=True)  # [M] the agents, scene by scene
    slot = ctrl_slot[cb, cc]
    tests = []
    boxes = event_boxes(prior, scenes)
    if "offroad" in checks:
        track = ctrl_track[cb, cc]
        tests.append(_offroad_test(scenes, cb, track, prior.current_pose[cb, slot], prior.token_poses[prior.agent_type[cb, slot], :, -1]))
    if "collision" in checks and acting.shape[1] > 1:
        tests.append(_standing_test(prior, boxes, cb, cc, slot, acting, ctrl_slot))
    also = None if not tests else tests[0] if len(tests) == 1 else (lambda r, tok: tests[0](r, tok) | tests[1](r, tok))
    present = prior.simulated if "collision" in checks else torch.zeros_like(prior.simulated)  # no other agent blocks
    rows = cb * prior.num_slots + slot
    k = 0 if top_k is None else int(top_k)
    known_frames, known = ahead.frames(prior) if ahead is not None else (None, None)
    out[cb, cc] = excluded_tokens(logits[cb, cc], rows, prior.pose, prior.previous_pose, boxes, present,
                                  prior.agent_type, prior.token_poses.to(prior.pose.dtype), k, prior.interpolation,
                                  known_frames=known_frames, known=known, also=also)
    return out


def _standing_test(prior: RolloutState, boxes: torch.Tensor, cb: torch.Tensor, cc: torch.Tensor, slot: torch.Tensor,
                   acting: torch.Tensor, ctrl_slot: torch.Tensor):
    """An ``also`` of :func:`~smart_marl.rollout.avoidance.excluded_tokens` for the M acting agents (scenes ``cb``,
    controlled slots ``cc``, prior slots ``slot``): a token whose frames overlap the box of another controlled agent
    of the scene standing where it is now (one that brakes, whose token the shield cannot know), pairs overlapping
    already left alone. With the constant-velocity check of the main rule, a controlled agent is kept off another's
    path both ways: whether that one drives on or stops."""
    m = len(cb)
    other_cc = torch.arange(acting.shape[1], device=cb.device)[None].expand(m, -1)  # [M, C] every controlled slot
    ok = acting[cb] & (other_cc != cc[:, None])  # [M, C] the others acting in the same scene
    other_slot = ctrl_slot[cb].clamp(min=0)  # [M, C]
    pose = prior.pose[cb[:, None], other_slot]  # [M, C, 3] where they stand
    half = boxes[cb[:, None], other_slot, :2].to(pose.dtype) / 2
    own_pose, own_before = prior.pose[cb, slot], prior.previous_pose[cb, slot]
    own_half = boxes[cb, slot, :2].to(pose.dtype) / 2
    ok = ok & ~boxes_overlap(own_pose[:, None, :2], own_pose[:, None, 2], own_half[:, None], pose[..., :2], pose[..., 2], half)
    token_poses = prior.token_poses.to(pose.dtype)
    kind = prior.agent_type[cb, slot]

    def test(r: torch.Tensor, tok: torch.Tensor) -> torch.Tensor:
        local = token_poses[kind[r][:, None], tok]  # [R, c, 6, 3]
        frames = token_frames(local, own_pose[r][:, None].expand(-1, tok.shape[1], -1),
                              own_before[r][:, None].expand(-1, tok.shape[1], -1), prior.interpolation)  # [R, c, 5, 3]
        hit = boxes_overlap(frames[:, :, None, :, :2], frames[:, :, None, :, 2], own_half[r][:, None, None, None],
                            pose[r][:, None, :, None, :2], pose[r][:, None, :, None, 2], half[r][:, None, :, None])  # [R, c, C, 5]
        return (hit.any(-1) & ok[r][:, None]).any(-1)
    return test


def event_boxes(prior: RolloutState, scenes: SceneBatch) -> torch.Tensor:
    """[B, Ns, 3] the box of every prior slot as the environment's events measure it (the scene's box of the slot's
    track, :attr:`SceneBatch.box_size`), the prior's own shape where a slot has no track. The prior's shapes come from
    the tokenized history and may be some 20 cm shorter: checked with them, a token could pass the shield and still
    touch another agent by the events' boxes."""
    track = prior.track_index
    boxes = scenes.box_size.gather(1, track.clamp(min=0)[..., None].expand(-1, -1, scenes.box_size.shape[-1]))
    return torch.where((track >= 0)[..., None], boxes.to(prior.agent_shape.dtype), prior.agent_shape)


def _offroad_test(scenes: SceneBatch, scene: torch.Tensor, track: torch.Tensor, pose: torch.Tensor, token_ends: torch.Tensor):
    """``also`` of :func:`~smart_marl.rollout.avoidance.excluded_tokens` for agents ``track`` [M] of scenes ``scene``
    [M] (ascending) at ``pose`` [M, 3], their type's token ends ``token_ends`` [M, V, 3] in their own frame: a
    vehicle's token that ends with a bottom corner of its box beyond a road edge
    (:func:`~smart_marl.rollout.avoidance.off_road_test`, the reward's offroad event)."""
    vehicle = scenes.types[scene, track] == int(AgentType.VEHICLE)
    return off_road_test(scenes.edges, scene, pose, token_ends, scenes.box_size[scene, track], scenes.z[scene, track], vehicle)


__all__ = ["SHIELD_CHECKS", "event_boxes", "unsafe_tokens"]
