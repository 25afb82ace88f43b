"""Environment stage, the shield: the tokens a controlled agent may not take because they would run it
into another agent or off the road (safe RL's action shielding, here a mask on the prior's logits).

What comes in: the prior's state (every simulated agent's pose, the pose its last token started at,
box, type; :class:`smart_marl.rollout.RolloutState`), the scenes' road edges, the controlled agents'
slots and their prior logits ``[B, C, V]``, the checks and the ``k`` the policy draws from. What goes
out: ``bool [B, C, V]``, true on the tokens to take out (their logits become ``-inf``).

The checks (``SHIELD_CHECKS``; ``shield=True`` is the first two, :data:`DEFAULT_SHIELD_CHECKS`), on the tokens most
likely first, until ``k`` pass every check asked for:

* ``"collision"``: the background's collision-aware rule (:mod:`smart_marl.rollout.avoidance`, the same
  code): the token's five 10 Hz frames overlap the box of one of the agent's 16 nearest others on the
  same frame, every box the scene's (:func:`event_boxes`: what the collision event measures, not the prior's shapes). The background's tokens of the step are drawn before the policy acts
  (:func:`envs._dynamics.draw_background`), so the background agents are checked on the frames they will
  really take; the other controlled agents, whose tokens come with the policy's, both at constant velocity
  and standing where they are (one that drives on, one that brakes);
* ``"offroad"``: a vehicle whose box, at the token's end (the step's last frame, where the reward's
  offroad event is measured), has a corner beyond a road edge (:func:`envs._reward.offroad`'s test);
* ``"gap"`` (asked for by name): a vehicle's token that ends closer to an agent ahead (of the 8 nearest ahead, where
  the step takes them) than the distance it would need to stop behind it should that one brake hard
  (responsibility-sensitive safety's longitudinal distance, :func:`_gap_test`), unless the token brakes early enough
  (sheds 1 m/s over the step, and from its end the agent could still stop behind that one braking hard) or ends
  standing. Collisions with a car ahead come from following too close: when the car ahead brakes, every token of the
  follower hits it, the shield can take nothing out, and the follower runs into it (issue 58's diagnosis); and from
  braking too gently once too close (a policy that wants speed takes the mildest brake it is allowed);
* ``"joint"`` (asked for by name; not a mask): when the step is taken and every controlled agent's token is known, a
  token that would run into another controlled agent's, as taken, is replaced by the most likely of the agent's
  shielded top ``k`` that does not, or the other one yields where this one cannot (:func:`joint_actions`). The mask
  sees another controlled agent driving on or standing only; the policy's collisions the other checks left were
  mostly with the other controlled agents.

So the top ``k`` of the shielded logits are the ``k`` most likely tokens that pass, and the reference of
fine-tuning (the prior's top ``k``, renormalised) is the prior as the shield lets it drive. An agent
all of whose tokens fail, the gap check among the failures, is searched again without the gap check (a gap already
too short to keep is no reason to give up the step's own collision and offroad checks); one all of whose tokens fail
still keeps the tokens that stay on the road (with ``"offroad"``: the road is where it is, the
others' moves are predictions), or all of them if none does (nothing is taken out, as in the background's rule).
Left alone, such agents (wedged between a road edge and an agent the collision or gap check expects to close in)
took any token, and they were where the fine-tuned policy's offroad events came from. What the
shield cannot see: another controlled agent's move other than driving on or standing (a turn across, a swerve; with
``"joint"``, where neither agent of the pair has a token that keeps clear of the other), an
agent beyond the 16 nearest, a pair whose boxes overlap already (left alone, as in the background's rule), offroad on the
step's in-between frames. The events' boxes are rounded (a little smaller than the exact boxes checked
here), so a token the shield allows does not collide with a background agent within the step.
"""

from __future__ import annotations

import functools
from typing import Sequence

import torch

from smart_marl.geometry_torch import boxes_overlap
from smart_marl.rollout import Draw, RolloutState
from smart_marl.rollout.avoidance import excluded_tokens, off_road_test, standing_test
from smart_marl.rollout.frames import candidate_frames
from smart_marl.scenario import AgentType
from smart_marl.tokens import FRAMES_PER_TOKEN

from ._reward import half_extents
from ._scene_batch import SceneBatch

SHIELD_CHECKS = ("collision", "offroad", "gap", "joint")
DEFAULT_SHIELD_CHECKS = ("collision", "offroad")
"""The checks of ``shield=True``; ``"gap"`` and ``"joint"`` are asked for by name."""

GAP_RESPONSE_S = 0.5
"""The gap check's reaction time: one token (the follower can brake from the next step on)."""
GAP_OWN_BRAKE = 4.0
"""m/s^2 the follower counts on braking at from the next step on."""
GAP_LEADER_BRAKE = 6.0
"""m/s^2 the hardest braking the gap check expects of the agent ahead."""
GAP_MARGIN_M = 1.0
"""Metres kept between the boxes when both have stopped."""
GAP_BRAKING = 1.0
"""m/s a token must shed (2 m/s^2 over the step) to be allowed closer than the gap check's distance."""
GAP_HARDEST_BRAKE = 6.0
"""m/s^2 the follower can brake at when it must: a braking token from whose end it could not stop behind the agent
ahead even so (that one braking at GAP_LEADER_BRAKE) is taken out too; a token that ends standing never is."""
GAP_CANDIDATES = 8
"""How many of the others nearest ahead of each agent the gap check looks at."""


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
    boxes = event_boxes(prior, scenes)
    token_poses = prior.token_poses.to(prior.pose.dtype)
    plain, framed = [], []  # tests of (rows, tokens), and of (rows, tokens, the tokens' frames)
    if "offroad" in checks:
        track = ctrl_track[cb, cc]
        plain.append(_offroad_test(scenes, cb, track, prior.current_pose[cb, slot], prior.token_poses[prior.agent_type[cb, slot], :, -1]))
    if "collision" in checks and acting.shape[1] > 1:
        framed.append(_standing_test(prior, boxes, cb, cc, slot, acting, ctrl_slot))
    known_frames, known = ahead.frames(prior) if ahead is not None else (None, None)
    gap = _gap_test(prior, boxes, cb, slot, known_frames, known) if "gap" in checks else None
    own = (prior.agent_type[cb, slot], prior.pose[cb, slot], prior.previous_pose[cb, slot], token_poses)
    fallback = "offroad" in checks and bool(framed or gap or "collision" in checks)  # a check the road alone can relax
    went_off = torch.zeros(len(cb), dtype=torch.bool, device=cb.device)  # rows with a searched token off the road
    gap_failed = torch.zeros(len(cb), dtype=torch.bool, device=cb.device)  # rows with a searched token too close

    def failing(tests: list, where: torch.Tensor | None = None):
        """The ``also`` of a search of the rows ``where`` (indices into the M agents; None: all), or None without a test:
        [R, c] does token ``tok`` of rows ``r`` fail a plain test or one of ``tests`` (the frames placed once for all
        that need them); the rows with a token off the road, or one the gap check fails, are noted."""
        def also(r: torch.Tensor, tok: torch.Tensor) -> torch.Tensor:
            r = r if where is None else where[r]
            fails = [t(r, tok) for t in plain]
            if fallback:
                went_off[r] |= fails[0].any(-1)
            if tests:
                frames = candidate_frames(*own, r, tok, prior.interpolation)  # [R, c, 5, 3]
                fails += [t(r, tok, frames) for t in tests]
                if tests[-1] is gap:
                    gap_failed[r] |= fails[-1].any(-1)
            return functools.reduce(torch.logical_or, fails)
        return also if plain or tests else None

    present = prior.simulated if "collision" in checks else torch.zeros_like(prior.simulated)  # no other agent blocks
    rows = cb * prior.num_slots + slot
    k = 0 if top_k is None else int(top_k)
    search = functools.partial(excluded_tokens, pose=prior.pose, previous_pose=prior.previous_pose, size=boxes,
                               agent_type=prior.agent_type, token_poses=token_poses, top_k=k, interpolation=prior.interpolation,
                               present=present, known_frames=known_frames, known=known)
    taken = search(logits[cb, cc], rows, also=failing(framed + ([gap] if gap else [])))
    # An agent every token of which failed some check, the gap check among them, is searched again without it: a gap
    # too short to keep already is no reason to give up the step's own collision and offroad checks.
    redo = (gap_failed & ~taken.any(-1)).nonzero().squeeze(1)
    if len(redo):
        taken[redo] = search(logits[cb[redo], cc[redo]], rows[redo], also=failing(framed, redo))
    # An agent every token of which failed some check has nothing taken out. If one of them went off the road, it
    # is searched again for the road alone: the road is where it is, the others' moves are predictions, so it
    # keeps the tokens that stay on the road (the k most likely of them), or all if none does.
    again = (went_off & ~taken.any(-1)).nonzero().squeeze(1)  # empty without the fallback
    if len(again):
        road = plain[0]
        taken[again] = search(logits[cb[again], cc[again]], rows[again], present=torch.zeros_like(prior.simulated),
                              known_frames=None, known=None, also=lambda r, tok: road(again[r], tok))
    out[cb, cc] = taken
    return out


def _gap_test(prior: RolloutState, boxes: torch.Tensor, cb: torch.Tensor, slot: torch.Tensor,
              known_frames: torch.Tensor | None, known: torch.Tensor | None):
    """An ``also`` of :func:`~smart_marl.rollout.avoidance.excluded_tokens` for the M acting agents (scenes ``cb``, prior
    slots ``slot``): a vehicle's token after which the gap to the agent ahead is shorter than the distance it needs to
    stop behind it should that one brake hard (a responsibility-sensitive-safety rule): gap < v GAP_RESPONSE_S +
    v^2 / (2 GAP_OWN_BRAKE) - u^2 / (2 GAP_LEADER_BRAKE) + GAP_MARGIN_M, v the agent's speed at the token's end, u the
    other's along the agent's heading, both at the step's end (the others where the step takes them: the background
    on its drawn frames, the rest at constant velocity). A token that brakes early enough is allowed all the same, so
    the check leaves a way out to an agent that is too close already: it sheds GAP_BRAKING m/s and the agent could
    still stop behind the other from its end at GAP_HARDEST_BRAKE (v^2 / (2 GAP_HARDEST_BRAKE) - u^2 / (2
    GAP_LEADER_BRAKE) + GAP_MARGIN_M <= gap), or it ends below 0.5 m/s (a way out that is always there)."""
    dtype = prior.pose.dtype
    dt = GAP_RESPONSE_S / FRAMES_PER_TOKEN
    pose, before = prior.pose[cb], prior.previous_pose[cb]  # [M, N, 3] every slot of each agent's scene
    end = pose + (pose - before)  # constant velocity over the step
    vel = (pose - before)[..., :2] / GAP_RESPONSE_S
    if known is not None:
        kf = known_frames[cb].to(dtype)
        end = torch.where(known[cb][..., None], kf[:, :, -1], end)
        vel = torch.where(known[cb][..., None], (kf[:, :, -1, :2] - kf[:, :, -2, :2]) / dt, vel)
    n = pose.shape[1]
    own_pose, own_before = prior.pose[cb, slot], prior.previous_pose[cb, slot]
    own_speed = (own_pose - own_before)[:, :2].norm(dim=-1) / GAP_RESPONSE_S  # [M]
    heading = torch.stack([own_pose[:, 2].cos(), own_pose[:, 2].sin()], -1)  # [M, 2]
    rel = end[..., :2] - own_pose[:, None, :2]
    ahead_now = (rel * heading[:, None]).sum(-1)  # [M, N]
    other = prior.simulated[cb] & (torch.arange(n, device=cb.device)[None] != slot[:, None]) & (ahead_now > 0)
    k = min(GAP_CANDIDATES, n)
    dist, near = rel.norm(dim=-1).masked_fill(~other, float("inf")).topk(k, dim=-1, largest=False)  # [M, K]
    near_ok = torch.isfinite(dist)
    o_end, o_vel = end.gather(1, near[..., None].expand(-1, -1, 3)), vel.gather(1, near[..., None].expand(-1, -1, 2))
    o_half = boxes[cb].gather(1, near[..., None].expand(-1, -1, boxes.shape[-1]))[..., :2].to(dtype) / 2  # [M, K, 2]
    own_half = boxes[cb, slot, :2].to(dtype) / 2  # [M, 2]
    vehicle = prior.agent_type[cb, slot] == int(AgentType.VEHICLE)

    def test(r: torch.Tensor, tok: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        last = frames[:, :, -1]  # [R, c, 3] (frames [R, c, 5, 3]: the tokens' step, candidate_frames)
        fwd = torch.stack([last[..., 2].cos(), last[..., 2].sin()], -1)  # [R, c, 2]
        left = torch.stack([-fwd[..., 1], fwd[..., 0]], -1)
        v = ((last[..., :2] - frames[:, :, -2, :2]) / dt * fwd).sum(-1).clamp(min=0.0)  # [R, c] own speed at the end
        rel = o_end[r][:, None, :, :2] - last[:, :, None, :2]  # [R, c, K, 2]
        ahead, side = (rel * fwd[:, :, None]).sum(-1), (rel * left[:, :, None]).sum(-1)
        along, across = half_extents(o_half[r][:, None], o_end[r][:, None, :, 2] - last[..., None, 2])  # [R, c, K]
        mine = own_half[r][:, None, None]  # [R, 1, 1, 2]
        in_path = near_ok[r][:, None] & (ahead > 0) & (side.abs() < mine[..., 1] + across)
        gap = ahead - mine[..., 0] - along  # [R, c, K]
        u = (o_vel[r][:, None] * fwd[:, :, None]).sum(-1).clamp(min=0.0)  # the other's speed along the heading
        stops = u * u / (2 * GAP_LEADER_BRAKE) - GAP_MARGIN_M  # how far ahead of its box the other stops, less the margin
        need = (v * GAP_RESPONSE_S + v * v / (2 * GAP_OWN_BRAKE))[..., None] - stops
        short = (in_path & (gap < need)).any(-1)  # [R, c]
        late = (in_path & (gap < (v * v / (2 * GAP_HARDEST_BRAKE))[..., None] - stops)).any(-1)  # even braking hard
        brakes = (v <= torch.clamp(own_speed[r][:, None] - GAP_BRAKING, min=0.0)) & ~late
        return short & ~(brakes | (v < 0.5)) & vehicle[r][:, None]
    return test


def _standing_test(prior: RolloutState, boxes: torch.Tensor, cb: torch.Tensor, cc: torch.Tensor, slot: torch.Tensor,
                   acting: torch.Tensor, ctrl_slot: torch.Tensor):
    """An ``also`` of :func:`~smart_marl.rollout.avoidance.excluded_tokens` for the M acting agents (scenes ``cb``,
    controlled slots ``cc``, prior slots ``slot``): a token whose frames overlap the box of another controlled agent
    of the scene standing where it is now (one that brakes, whose token the shield cannot know), pairs overlapping
    already left alone (:func:`~smart_marl.rollout.avoidance.standing_test`). With the constant-velocity check of the
    main rule, a controlled agent is kept off another's path both ways: whether that one drives on or stops."""
    m = len(cb)
    other_cc = torch.arange(acting.shape[1], device=cb.device)[None].expand(m, -1)  # [M, C] every controlled slot
    ok = acting[cb] & (other_cc != cc[:, None])  # [M, C] the others acting in the same scene
    other_slot = ctrl_slot[cb].clamp(min=0)  # [M, C]
    pose = prior.pose[cb[:, None], other_slot]  # [M, C, 3] where they stand
    half = boxes[cb[:, None], other_slot, :2].to(pose.dtype) / 2
    standing = standing_test(prior.pose[cb, slot], boxes[cb, slot, :2].to(pose.dtype) / 2, pose, half, ok)
    return lambda r, tok, frames: standing(r, frames)


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


def joint_actions(prior: RolloutState, scenes: SceneBatch, ctrl_slot: torch.Tensor, acting: torch.Tensor, actions: torch.Tensor,
                  logits: torch.Tensor, top_k: int | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``"joint"`` check, once the controlled agents have chosen: (the tokens taken [B, C], bool [B, C] where one
    was replaced). ``acting`` [B, C] the controlled agents with a prior slot ``ctrl_slot`` [B, C], ``actions`` [B, C]
    their chosen tokens, ``logits`` [B, C, V] their shielded prior logits (``-inf`` on what the mask takes out).

    The mask can only guess another controlled agent's move (driving on or standing); here every chosen token is
    known. In the order of the controlled slots, an agent whose chosen token's frames overlap (the scene's boxes, on
    any of the step's frames) those of earlier agents' tokens as taken is given the most likely of its top ``k``
    shielded tokens that overlaps none of them (the prior's choice among what the shield allows). Where it has none
    and runs into one earlier agent only, that one yields instead: it is given the most likely of its top ``k`` that
    overlaps none of the agents up to this one (a follower that brakes, where the leader cannot get away); otherwise
    the chosen tokens are kept. Pairs overlapping already are left alone, as in the mask's checks. So two controlled
    agents do not run into each other within a step where one of them has a way out."""
    taken = actions.clone()
    b, c = acting.shape
    if c < 2 or int(acting.sum(-1).max()) < 2:
        return taken, torch.zeros_like(acting)
    slot = ctrl_slot.clamp(min=0)
    at = (torch.arange(b, device=slot.device)[:, None].expand_as(slot), slot)  # [B, C] each agent's prior slot
    kind, pose, before = prior.agent_type[at], prior.pose[at], prior.previous_pose[at]  # [B, C] / [B, C, 3]
    half = event_boxes(prior, scenes)[at][..., :2].to(pose.dtype) / 2  # [B, C, 2]
    token_poses = prior.token_poses.to(pose.dtype)
    own = (kind.reshape(-1), pose.reshape(-1, 3), before.reshape(-1, 3), token_poses)
    frames = candidate_frames(*own, torch.arange(b * c, device=slot.device), actions.reshape(-1, 1),
                              prior.interpolation).reshape(b, c, -1, 3)
    apart = ~boxes_overlap(pose[:, :, None, :2], pose[:, :, None, 2], half[:, :, None], pose[:, None, :, :2], pose[:, None, :, 2],
                           half[:, None])  # [B, C, C] pairs not overlapping already
    cols = torch.arange(c, device=slot.device)
    k = logits.shape[-1] if top_k is None else min(int(top_k), logits.shape[-1])

    def hits(rows: torch.Tensor, me: torch.Tensor, mine: torch.Tensor, against: torch.Tensor) -> torch.Tensor:
        """[R, c, C]: do frames ``mine`` [R, c, 5, 3] of agents ``me`` [R] of scenes ``rows`` overlap those, as taken, of
        each of the agents ``against`` [R, C]."""
        ok = (acting[rows] & against & apart[rows, me])[:, None, :, None]  # [R, 1, C, 1]
        other = frames[rows][:, None]  # [R, 1, C, 5, 3]
        hit = boxes_overlap(mine[:, :, None, :, :2], mine[:, :, None, :, 2], half[rows, me][:, None, None, None], other[..., :2],
                            other[..., 2], half[rows][:, None, :, None])  # [R, c, C, 5]
        return (hit & ok).any(-1)

    def way_out(rows: torch.Tensor, me: torch.Tensor, against: torch.Tensor) -> torch.Tensor:
        """Agents ``me`` of scenes ``rows`` take the most likely of their shielded top k clear of ``against`` [R, C],
        where they have one; bool [R]: they had."""
        value, tok = logits[rows, me].topk(k, dim=-1)  # [R, k] most likely first
        mine = candidate_frames(*own, rows * c + me, tok, prior.interpolation)
        clear = torch.isfinite(value) & ~hits(rows, me, mine, against).any(-1)
        has = clear.any(-1)
        rows, me = rows[has], me[has]
        taken[rows, me] = tok[has].gather(1, clear[has].float().argmax(-1, keepdim=True)).squeeze(1)
        frames[rows, me] = candidate_frames(*own, rows * c + me, taken[rows, me][:, None], prior.interpolation)[:, 0]
        return has

    for i in range(1, c):
        rows = acting[:, i].nonzero().squeeze(1)
        me = torch.full_like(rows, i)
        hit = hits(rows, me, frames[rows, i][:, None], (cols < i)[None])[:, 0]  # [R, C] the earlier agents it runs into
        runs_into = hit.any(-1)
        rows, me, hit = rows[runs_into], me[runs_into], hit[runs_into]
        if not len(rows):
            continue
        stuck = ~way_out(rows, me, (cols < i)[None])
        stuck &= hit.sum(-1) == 1  # no way out, and one earlier agent in its way: that one yields, if it can
        if stuck.any():
            other = hit[stuck].float().argmax(-1)
            way_out(rows[stuck], other, (cols <= i)[None] & (cols[None] != other[:, None]))
    return taken, acting & (taken != actions)


__all__ = ["DEFAULT_SHIELD_CHECKS", "SHIELD_CHECKS", "event_boxes", "joint_actions", "unsafe_tokens"]
