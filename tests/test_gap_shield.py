"""The shield's gap check (envs._shield, ``shield=[..., "gap"]``): a controlled vehicle's token after which it could
not stop behind the agent ahead should that one brake hard is taken out, unless the token brakes. Checked against a
brute force over every other agent (the check itself looks at the 8 nearest ahead), on the package's sample scenes
with the agents driving at the fastest token every other step, where followers close in."""

from __future__ import annotations

import math

import pytest
import torch

from envs import smart_traffic_v0
from envs._shield import GAP_BRAKING, GAP_LEADER_BRAKE, GAP_MARGIN_M, GAP_OWN_BRAKE, GAP_RESPONSE_S, event_boxes
from smart_marl.rollout import FORCED_LATER
from smart_marl.rollout.frames import token_frames
from smart_marl.scenario import AgentType
from test_shield import shielded_steps

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py
K = 3


def _env(scenes, prior, shield):
    model, vocab = prior
    return smart_traffic_v0.parallel_env(scenarios=scenes, prior=model, motion_vocab=vocab, controlled="vehicles", max_agents=8,
                                         horizon_steps=8, terminate_on=(), reference_top_k=K, observation="dict", shield=shield)


def _too_close(core, b: int, c: int, tokens: list[int], slack: float = 0.0) -> list[bool]:
    """For each token of controlled slot ``c`` of scene ``b``: does it end closer to some agent ahead than the distance
    the rule asks (plus ``slack`` metres), without braking (the rule of envs._shield._gap_test, one token and one other
    agent at a time, in float64)."""
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
    out = []
    for t in tokens:
        f = token_frames(pr.token_poses[pr.agent_type[b, s], t][None].double(), pose[s][None], before[s][None], pr.interpolation)[0]
        x, y, h = (float(v) for v in f[-1])
        fwd, left = (math.cos(h), math.sin(h)), (-math.sin(h), math.cos(h))
        v = max(0.0, ((float(f[-1, 0] - f[-2, 0])) * fwd[0] + float(f[-1, 1] - f[-2, 1]) * fwd[1]) / dt)
        brakes = v <= max(own_speed - GAP_BRAKING, 0.0) or v < 0.5
        short = False
        for o, (end, vel) in ends.items():
            if float((end[0] - pose[s, 0]) * math.cos(pose[s, 2]) + (end[1] - pose[s, 1]) * math.sin(pose[s, 2])) <= 0:
                continue  # behind the agent now
            dx, dy = float(end[0]) - x, float(end[1]) - y
            ahead, side = dx * fwd[0] + dy * fwd[1], dx * left[0] + dy * left[1]
            turn = float(end[2]) - h
            along = float(half[o, 0]) * abs(math.cos(turn)) + float(half[o, 1]) * abs(math.sin(turn))
            across = float(half[o, 0]) * abs(math.sin(turn)) + float(half[o, 1]) * abs(math.cos(turn))
            if ahead <= 0 or abs(side) >= float(half[s, 1]) + across:
                continue
            u = max(0.0, float(vel[0]) * fwd[0] + float(vel[1]) * fwd[1])
            need = v * GAP_RESPONSE_S + v * v / (2 * GAP_OWN_BRAKE) - u * u / (2 * GAP_LEADER_BRAKE) + GAP_MARGIN_M
            short |= ahead - float(half[s, 0]) - along < need + slack
        out.append(short and not brakes and int(pr.agent_type[b, s]) == int(AgentType.VEHICLE))
    return out


def test_the_gap_check_takes_out_the_tokens_that_close_in_and_keeps_those_that_brake(sample_scenes, embedded_prior):
    env = _env(sample_scenes, embedded_prior, ["gap"])
    taken_out = checked = 0
    for core, shielded, plain, _ in shielded_steps(env, embedded_prior, len(sample_scenes), 8):
        for c in core.live[0].nonzero().squeeze(1).tolist():
            gone = (torch.isinf(shielded[0, c]) & torch.isfinite(plain[0, c])).nonzero().squeeze(1).tolist()
            top = torch.topk(shielded[0, c], K).indices.tolist()
            top = [t for t in top if math.isfinite(float(shielded[0, c, t]))]
            if gone:  # what it took out ends too close without braking; what it leaves on top does not
                assert all(_too_close(core, 0, c, gone[:64], slack=1e-3))
                assert not any(_too_close(core, 0, c, top, slack=-1e-3))
                taken_out += len(gone)
            else:  # nothing taken out: its top k keep their distance, or every token fails (left alone)
                assert not any(_too_close(core, 0, c, top, slack=-1e-3)) or all(
                    _too_close(core, 0, c, torch.topk(plain[0, c], 64).indices.tolist()))
            checked += 1
    assert checked > 20 and taken_out > 0  # the sample scenes exercise it
