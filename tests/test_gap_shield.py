"""The shield's gap check (envs._shield, ``shield=[..., "gap"]``): a controlled vehicle's token after which it could
not stop behind the agent ahead should that one brake hard is taken out, unless the token brakes early enough to stop
behind it braking hard, or ends standing. Checked against a brute force, one token and one other agent at a time, over
the 8 nearest ahead (the agents the check looks at), on the package's sample scenes with the agents driving at the
fastest token every other step, where followers close in."""

from __future__ import annotations

import math

import pytest
import torch

from envs._shield import GAP_BRAKING, GAP_CANDIDATES, GAP_HARDEST_BRAKE, GAP_LEADER_BRAKE, GAP_MARGIN_M, GAP_OWN_BRAKE, GAP_RESPONSE_S, event_boxes
from smart_marl.rollout import FORCED_LATER
from smart_marl.rollout.frames import token_frames
from smart_marl.scenario import AgentType
from test_shield import K, _env, shielded_steps

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def _too_close(core, b: int, c: int, tokens: list[int], slack: float = 0.0, late_brakes: list | None = None) -> list[bool]:
    """For each token of controlled slot ``c`` of scene ``b``: does it end closer to some agent ahead than the distance
    the rule asks (plus ``slack`` metres), without braking early enough to stop behind it (the rule of
    envs._shield._gap_test, one token and one other agent at a time, in float64). ``late_brakes``: where the tokens
    that brake, but too late, are listed."""
    pr = core.prior
    draw = pr.drawn_ahead()
    drawn = {int(r): int(t) for r, t, f in zip(draw.rows, draw.tokens, draw.forced.reshape(-1)[draw.rows]) if f != FORCED_LATER}
    s = int(core.slot_of_track[b, int(core.ctrl_track[b, c])])
    pose, before = pr.pose[b].double(), pr.previous_pose[b].double()
    half = event_boxes(pr, core.scenes)[b, :, :2].double() / 2
    dt = GAP_RESPONSE_S / 5
    ends = {}
    for o in pr.simulated[b].nonzero().squeeze(1).tolist():
        if o == s:
            continue
        if b * pr.num_slots + o in drawn:
            f = token_frames(pr.token_poses[pr.agent_type[b, o], drawn[b * pr.num_slots + o]][None].double(), pose[o][None],
                             before[o][None], pr.interpolation)[0]
            ends[o] = (f[-1], (f[-1, :2] - f[-2, :2]) / dt)
        else:
            ends[o] = (pose[o] + (pose[o] - before[o]), (pose[o, :2] - before[o, :2]) / GAP_RESPONSE_S)
    own_speed = float((pose[s, :2] - before[s, :2]).norm()) / GAP_RESPONSE_S
    ahead_now = {o: float((end[0] - pose[s, 0]) * math.cos(pose[s, 2]) + (end[1] - pose[s, 1]) * math.sin(pose[s, 2]))
                 for o, (end, _) in ends.items()}
    nearest = sorted((float((end[:2] - pose[s, :2]).norm()), o) for o, (end, _) in ends.items() if ahead_now[o] > 0)
    ends = {o: ends[o] for _, o in nearest[:GAP_CANDIDATES]}  # the rule looks at the nearest ahead only
    out = []
    for t in tokens:
        f = token_frames(pr.token_poses[pr.agent_type[b, s], t][None].double(), pose[s][None], before[s][None], pr.interpolation)[0]
        x, y, h = (float(v) for v in f[-1])
        fwd, left = (math.cos(h), math.sin(h)), (-math.sin(h), math.cos(h))
        v = max(0.0, ((float(f[-1, 0] - f[-2, 0])) * fwd[0] + float(f[-1, 1] - f[-2, 1]) * fwd[1]) / dt)
        short = late = False
        for o, (end, vel) in ends.items():
            dx, dy = float(end[0]) - x, float(end[1]) - y
            ahead, side = dx * fwd[0] + dy * fwd[1], dx * left[0] + dy * left[1]
            turn = float(end[2]) - h
            along = float(half[o, 0]) * abs(math.cos(turn)) + float(half[o, 1]) * abs(math.sin(turn))
            across = float(half[o, 0]) * abs(math.sin(turn)) + float(half[o, 1]) * abs(math.cos(turn))
            if ahead <= 0 or abs(side) >= float(half[s, 1]) + across:
                continue
            u = max(0.0, float(vel[0]) * fwd[0] + float(vel[1]) * fwd[1])
            gap, stops = ahead - float(half[s, 0]) - along, u * u / (2 * GAP_LEADER_BRAKE) - GAP_MARGIN_M
            short |= gap < v * GAP_RESPONSE_S + v * v / (2 * GAP_OWN_BRAKE) - stops + slack
            late |= gap < v * v / (2 * GAP_HARDEST_BRAKE) - stops + slack  # could not stop even braking hard
        sheds = v <= max(own_speed - GAP_BRAKING, 0.0)
        if late_brakes is not None and short and sheds and late and v >= 0.5:
            late_brakes.append(t)  # it brakes, but too late to stop behind the other
        out.append(short and not ((sheds and not late) or v < 0.5) and int(pr.agent_type[b, s]) == int(AgentType.VEHICLE))
    return out


def test_the_gap_check_takes_out_the_tokens_that_close_in_and_keeps_those_that_brake(sample_scenes, embedded_prior):
    env = _env(sample_scenes, embedded_prior, shield=["gap"], horizon_steps=8)
    taken_out = checked = 0
    late = []  # tokens taken out that brake, but too late
    for core, shielded, plain, _ in shielded_steps(env, embedded_prior, len(sample_scenes), 8):
        for c in core.live[0].nonzero().squeeze(1).tolist():
            gone = (torch.isinf(shielded[0, c]) & torch.isfinite(plain[0, c])).nonzero().squeeze(1).tolist()
            top = torch.topk(shielded[0, c], K).indices.tolist()
            top = [t for t in top if math.isfinite(float(shielded[0, c, t]))]
            if gone:  # what it took out ends too close without braking; what it leaves on top does not
                assert all(_too_close(core, 0, c, gone[:64], slack=1e-3, late_brakes=late))
                assert not any(_too_close(core, 0, c, top, slack=-1e-3))
                taken_out += len(gone)
            else:  # nothing taken out: its top k keep their distance, or every token fails (left alone)
                assert not any(_too_close(core, 0, c, top, slack=-1e-3)) or all(
                    _too_close(core, 0, c, torch.topk(plain[0, c], 64).indices.tolist()))
            checked += 1
    assert checked > 20 and taken_out > 0 and late  # the sample scenes exercise it, braking too late included


def _shielded_again(core, checks):
    """The step's prior logits shielded by ``checks`` (the core keeps one mask a step: computed afresh here)."""
    core.shield, core._unsafe = checks, None
    return core.prior_logits()


@pytest.mark.parametrize("fails", ["every token", "even tokens"])
def test_an_agent_the_gap_check_fails_everywhere_keeps_the_collision_and_offroad_checks(sample_scenes, embedded_prior, monkeypatch,
                                                                                         fails):
    """Every token of an agent failing the gap check (forced here) is no reason to give up the step's own checks: the
    agent is searched again without it, and its shielded logits are those of ``collision+offroad`` (not the road alone
    or nothing taken out, the fallbacks of an agent every token of which fails). Where it fails some tokens only (the
    even ones), its top k are odd, unless every token fails some check (then the agent is searched again without it)."""
    import envs._shield as shield_module

    def gap(*a, **k):
        return lambda r, tok, frames: torch.ones(tok.shape, dtype=torch.bool) if fails == "every token" else tok % 2 == 0
    monkeypatch.setattr(shield_module, "_gap_test", gap)
    env = _env(sample_scenes, embedded_prior, shield=["collision", "offroad", "gap"], horizon_steps=8)
    checked = beyond_the_road = gap_mattered = 0
    # every token failing is a search of the whole vocabulary: two scenes; three steps exercise both cases
    scenes, steps = (2, 3) if fails == "every token" else (len(sample_scenes), 3)
    for core, shielded, _, _ in shielded_steps(env, embedded_prior, scenes, steps):
        without_gap, road = (_shielded_again(core, checks) for checks in (("collision", "offroad"), ("offroad",)))
        _shielded_again(core, ("collision", "offroad", "gap"))  # the step goes on with its own mask
        for c in core.live[0].nonzero().squeeze(1).tolist():
            if fails == "every token":
                assert torch.equal(shielded[0, c], without_gap[0, c])
                beyond_the_road += int(not torch.equal(without_gap[0, c], road[0, c]))
            else:
                top = torch.topk(shielded[0, c], K).indices
                top = top[torch.isfinite(shielded[0, c, top])]
                if not (top % 2 == 1).all():  # every token failed a check: searched again without the gap check
                    assert torch.equal(shielded[0, c], without_gap[0, c])
                    continue
                before = torch.topk(without_gap[0, c], K).indices
                gap_mattered += int((before[torch.isfinite(without_gap[0, c, before])] % 2 == 0).any())  # an even one went
            checked += 1
    assert checked > 20 and (beyond_the_road > 0 if fails == "every token" else gap_mattered > 0)  # the scenes exercise it
