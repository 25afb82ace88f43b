"""Collision-aware sampling (smart_marl.rollout.avoidance): the box test, which tokens are excluded,
that sampling with the exclusions is top-k of the distribution without the colliding tokens, and that
rollouts keep the model's own logits and log-probabilities while their agents collide less."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import torch

from smart_marl import geometry
from smart_marl.embedded import sample_files, sample_scenarios
from smart_marl.model.checkpoint import load_embedded
from smart_marl.readers import read_scenarios
from smart_marl.rollout import RolloutState, sample_tokens
from smart_marl.rollout.avoidance import boxes_overlap, excluded_tokens, constant_velocity_pose

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def test_boxes_overlap_equals_the_metrics_plain_box_geometry_on_random_boxes():
    rng = np.random.default_rng(0)
    n = 4000
    a = rng.uniform([-3, -3, 0.5, 0.5, -math.pi], [3, 3, 5, 2.5, math.pi], (n, 5))
    b = rng.uniform([-3, -3, 0.5, 0.5, -math.pi], [3, 3, 5, 2.5, math.pi], (n, 5))
    want = geometry.boxes_overlap(*a.T, *b.T, rounding=0.0)
    t = torch.from_numpy
    got = boxes_overlap(t(a[:, :2]), t(a[:, 4]), t(a[:, 2:4] / 2), t(b[:, :2]), t(b[:, 4]), t(b[:, 2:4] / 2)).numpy()
    assert 0.2 < want.mean() < 0.8  # both outcomes are exercised
    # boxes within a hair of touching may go either way in float arithmetic
    dist = geometry.rounded_box_signed_distance(*a.T, *b.T, rounding=0.0)
    clear = np.abs(dist) > 1e-9
    np.testing.assert_array_equal(got[clear], want[clear])


def test_a_rotated_box_beside_a_corner_does_not_overlap_although_its_bounding_box_would():
    t = torch.tensor
    # a 2 x 2 square at the origin and a square turned 45 degrees whose corner points at (1.05, 1.05)'s side
    half = t([1.0, 1.0], dtype=torch.float64)
    centre = t([1.0 + math.sqrt(2) / 2 + 0.3, 1.0 + math.sqrt(2) / 2 + 0.3], dtype=torch.float64)
    assert not boxes_overlap(t([0.0, 0.0], dtype=torch.float64), t(0.0, dtype=torch.float64), half, centre,
                             t(math.pi / 4, dtype=torch.float64), half)
    assert boxes_overlap(t([0.0, 0.0], dtype=torch.float64), t(0.0, dtype=torch.float64), half, centre - 0.5,
                         t(math.pi / 4, dtype=torch.float64), half)


def test_constant_velocity_pose_repeats_the_last_displacement_and_holds_still_without_one():
    pose = torch.tensor([[2.0, 1.0, 0.3], [5.0, 5.0, 1.0]])
    prev = torch.tensor([[1.0, 1.5, 0.1], [float("nan")] * 3])
    out = constant_velocity_pose(pose, prev)
    torch.testing.assert_close(out, torch.tensor([[3.0, 0.5, 0.3], [5.0, 5.0, 1.0]]))


# --------------------------------------------------------------------- a scene of three slots
# slot 0 samples, heading +x from the origin; its type's tokens end 5, 0, 2 or 8 m ahead, or 3 m to
# the left; slot 1 is a car standing at x = 7 (from 5 to 9 m); slot 2 overlaps slot 0 now (a pedestrian beside it)
ENDS = torch.tensor([[[5.0, 0, 0], [0.0, 0, 0], [2.0, 0, 0], [8.0, 0, 0], [0.0, 3.0, 0]]], dtype=torch.float32)


def _poses(ends):
    """[types, V, 6, 3] tokens moving evenly from the origin to ``ends`` [types, V, 3]."""
    return torch.linspace(0, 1, 6)[None, None, :, None] * ends[:, :, None, :]


def _scene(third_present=True):
    pose = torch.tensor([[[0.0, 0, 0], [7.0, 0, 0], [0.5, 0.5, 0]]])
    prev = pose.clone()
    size = torch.tensor([[[4.0, 2.0, 1.5], [4.0, 2.0, 1.5], [0.8, 0.8, 1.8]]])
    present = torch.tensor([[True, True, third_present]])
    types = torch.zeros(1, 3, dtype=torch.long)
    return pose, prev, size, present, types


def test_tokens_ending_in_a_standing_car_are_excluded_most_likely_first_until_k_are_free():
    pose, prev, size, present, types = _scene()
    logits = torch.tensor([[4.0, 1.0, 3.0, 2.0, 0.0]])  # most likely: 5 m (into the car), then 2 m, 8 m, 0 m
    rows = torch.tensor([0])
    everything = excluded_tokens(logits, rows, pose, prev, size, present, types, _poses(ENDS), top_k=0)
    # 5 m ahead and 8 m ahead end inside the car (centres 2 and 1 m apart, boxes 4 m long); 2 m ahead stops short
    assert everything.tolist() == [[True, False, False, True, False]]
    # with k = 1 the check stops at the first free token, but the first chunk covers all five here
    assert excluded_tokens(logits, rows, pose, prev, size, present, types, _poses(ENDS), top_k=1).tolist() == everything.tolist()


def test_the_search_stops_at_its_depth_and_a_row_short_of_k_free_tokens_draws_from_the_free_ones_it_found():
    pose, prev, size, present, types = _scene()
    # ranked: 5 m (into the car), 8 m (into it), 2 m (free), 0 m (free), left (free)
    logits = torch.tensor([[4.0, 1.0, 2.0, 3.0, 0.0]])
    args = (logits, torch.tensor([0]), pose, prev, size, present, types, _poses(ENDS))
    whole = excluded_tokens(*args, top_k=2, depth=None)
    assert whole.tolist() == [[True, False, False, True, False]]  # the two blocked ones; 2 m and 0 m are the top 2 left
    # checked to the 3rd token only: one free (2 m) among them, so it alone may be drawn (the unchecked 0 m and
    # "left" are excluded with the two that collide)
    assert excluded_tokens(*args, top_k=2, depth=3).tolist() == [[True, True, False, True, True]]
    # no free token among the first 2: the search goes on through the whole vocabulary, as without a depth
    assert torch.equal(excluded_tokens(*args, top_k=2, depth=2), whole)
    # a top-k draw from the shortened row takes the free token every time
    tokens, _ = sample_tokens(logits.expand(50, -1), torch.Generator().manual_seed(0), 2,
                              exclude=excluded_tokens(*args, top_k=2, depth=3).expand(50, -1))
    assert set(tokens.tolist()) == {2}
    # top_k <= 0 (the whole distribution) checks every token whatever the depth
    assert torch.equal(excluded_tokens(*args, top_k=0, depth=2), excluded_tokens(*args, top_k=0, depth=None))


def test_pairs_overlapping_now_and_absent_agents_do_not_block():
    pose, prev, size, present, types = _scene()
    # slot 2 (the pedestrian overlapping slot 0 now) stands at (0.5, 0.5): "stay" (token 1) would hit
    # it if pairs overlapping now were checked
    logits = torch.tensor([[0.0, 5.0, 0.0, 0.0, 0.0]])
    out = excluded_tokens(logits, torch.tensor([0]), pose, prev, size, present, types, _poses(ENDS), top_k=0)
    assert not out[0, 1]
    absent = excluded_tokens(logits, torch.tensor([0]), pose, prev, size, _scene(third_present=True)[3] & torch.tensor(
        [[True, False, True]]), types, _poses(ENDS), top_k=0)
    assert not absent.any()  # the car is not present: nothing blocks


def test_the_other_agent_is_checked_where_it_will_be_at_constant_velocity():
    pose, prev, size, present, types = _scene()
    prev[0, 1, 0] = 9.0  # the car drives toward slot 0 at 2 m per token: it will be at x = 5 (from 3 to 7 m)
    logits = torch.tensor([[0.0, 5.0, 4.0, 0.0, 0.0]])
    out = excluded_tokens(logits, torch.tensor([0]), pose, prev, size, present, types, _poses(ENDS), top_k=0)
    assert out.tolist() == [[True, False, True, True, False]]  # 2 m ahead now collides too; stopping does not


def test_a_forced_neighbour_is_checked_on_the_frames_its_token_really_takes_it_to():
    """Issue 33: a leader whose token is forced (a policy's controlled car, a scripted braking car) is seen where
    that token puts it, not at constant velocity."""
    pose, prev, size, present, types = _scene(third_present=False)
    prev[0, 1, 0] = 3.0  # the car ahead drives away at 4 m per token: at constant velocity it will be at x = 11 (9 to 13 m)
    logits = torch.tensor([[5.0, 0.0, 4.0, 3.0, 0.0]])
    args = (logits, torch.tensor([0]), pose, prev, size, present, types, _poses(ENDS))
    assert excluded_tokens(*args, top_k=0).tolist() == [[False, False, False, True, False]]  # only 8 m ahead reaches it
    # its forced token this step stands still at x = 7: then 5 m ahead runs into it as well
    known = torch.tensor([[False, True, False]])
    frames = pose[:, :, None, :].expand(-1, -1, 5, -1).clone()
    got = excluded_tokens(*args, top_k=0, known_frames=frames, known=known)
    assert got.tolist() == [[True, False, False, True, False]]


@pytest.mark.parametrize("interpolation", ["spline", "contour"])
def test_a_token_that_passes_through_an_agent_between_its_ends_is_excluded(interpolation):
    """14 m in 0.5 s past a pedestrian standing 7 m ahead: neither end box touches it, the frames in
    between do."""
    pose = torch.tensor([[[0.0, 0, 0], [7.0, 0, 0]]])
    size = torch.tensor([[[4.0, 2.0, 1.5], [0.8, 0.8, 1.8]]])
    prev = torch.tensor([[[-14.0, 0, 0], [7.0, 0, 0]]])
    ends = torch.tensor([[[14.0, 0, 0], [3.0, 0, 0]]])
    out = excluded_tokens(torch.tensor([[1.0, 0.0]]), torch.tensor([0]), pose, prev, size, torch.ones(1, 2, dtype=torch.bool),
                          torch.zeros(1, 2, dtype=torch.long), _poses(ends), top_k=0, interpolation=interpolation)
    assert out.tolist() == [[True, False]]


def test_a_row_whose_every_token_collides_is_left_alone():
    pose, prev, size, present, types = _scene()
    ends = torch.tensor([[[5.0, 0, 0], [6.0, 0, 0]]])
    out = excluded_tokens(torch.tensor([[1.0, 0.0]]), torch.tensor([0]), pose, prev, size, present, types, _poses(ends), top_k=1)
    assert not out.any()


def test_tokens_beyond_the_types_vocabulary_are_never_checked_or_counted():
    pose, prev, size, present, types = _scene()
    logits = torch.tensor([[4.0, 1.0, 3.0, float("-inf"), float("-inf")]])
    out = excluded_tokens(logits, torch.tensor([0]), pose, prev, size, present, types, _poses(ENDS), top_k=0)
    assert out.tolist() == [[True, False, False, False, False]]


def test_a_vocabulary_size_given_stands_for_counting_the_finite_logits():
    """The engine hands over its types' vocabulary sizes (a model's logits are finite on them): the same
    exclusions as counting; a size that does not match the logits (here 5 where 3 are finite) is noticed."""
    pose, prev, size, present, types = _scene()
    logits = torch.tensor([[4.0, 1.0, 3.0, float("-inf"), float("-inf")]])
    counted = excluded_tokens(logits, torch.tensor([0]), pose, prev, size, present, types, _poses(ENDS), top_k=0)
    given = excluded_tokens(logits, torch.tensor([0]), pose, prev, size, present, types, _poses(ENDS), top_k=0,
                            vocab_sizes=torch.tensor([3]))
    assert given.tolist() == counted.tolist()
    wrong = excluded_tokens(logits, torch.tensor([0]), pose, prev, size, present, types, _poses(ENDS), top_k=0,
                            vocab_sizes=torch.tensor([5]))
    assert wrong.tolist() != counted.tolist()


def test_sampling_with_exclusions_is_top_k_of_the_distribution_without_them():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(500, 40)
    exclude = torch.rand(500, 40) < 0.4
    tokens, logp = sample_tokens(logits, g, top_k=5, exclude=exclude)
    assert not exclude.gather(1, tokens[:, None]).any()
    allowed = torch.topk(logits.masked_fill(exclude, float("-inf")), 5, dim=-1).indices
    assert (allowed == tokens[:, None]).any(-1).all()
    # the reported log-probabilities are the model's, before the exclusions
    torch.testing.assert_close(logp, torch.log_softmax(logits, -1).gather(1, tokens[:, None]).squeeze(1))


def _token_end_overlaps(state, outs):
    """Per step, the (group, i, j) pairs of simulated slots whose boxes overlap at the token's end but
    did not at its start."""
    count = 0
    half = state.agent_shape[..., :2].double() / 2
    start = None
    for out in outs:
        end = out.poses[:, :, -1].double()
        sim = out.simulated
        if start is not None:
            def pairs(p):
                return boxes_overlap(p[:, :, None, :2], p[:, :, None, 2], half[:, :, None], p[:, None, :, :2], p[:, None, :, 2],
                                     half[:, None])
            both = sim[:, :, None] & sim[:, None, :] & ~torch.eye(sim.shape[1], dtype=torch.bool)[None]
            count += int((pairs(end) & ~pairs(start) & both).sum())
        start = end
    return count


def test_rollouts_of_the_embedded_prior_collide_less_and_keep_the_models_logits(shared_data):
    # a real scene where the plain prior walks a pedestrian into a car that waits for it
    scene = next(read_scenarios(shared_data / "smart_pkl" / "2a716fad0956ffcf.pkl"))
    ck = load_embedded()
    runs = {}
    for avoid in (False, True):
        state = RolloutState.start(ck, scene, num_rollouts=8, seed=3, avoid_collisions=avoid)
        outs = state.run(16)
        runs[avoid] = (state, outs)
    plain, avoiding = (_token_end_overlaps(*runs[a]) for a in (False, True))
    assert avoiding < plain, (avoiding, plain)
    # the first step sees the same history: identical logits; the reported log-probabilities are the
    # model's own log-softmax at the drawn tokens
    torch.testing.assert_close(runs[True][1][0].logits, runs[False][1][0].logits)
    for out in runs[True][1]:
        rows = out.simulated
        logp = torch.log_softmax(out.logits[rows], -1).gather(1, out.tokens[rows][:, None]).squeeze(1)
        torch.testing.assert_close(out.log_probs[rows], logp)


# ------------------------------------------------------------------------------ how it is reached
def test_commands_sample_collision_aware_unless_told_not_to():
    from smart_marl.cli import build_parser

    parser = build_parser()
    for argv in (["eval", "--scenes", "x", "--policy", "prior"], ["whatif", "x", "--script", "s.yaml", "--out", "o"]):
        assert parser.parse_args(argv).avoid_collisions is True
        assert parser.parse_args(argv + ["--no-collision-avoidance"]).avoid_collisions is False


def test_whatif_passes_the_choice_to_both_of_its_runs_and_on_to_the_engine(monkeypatch):
    from agents.whatif import WhatIf

    compare = importlib.import_module("agents.whatif.compare")  # the modules (the package exports functions of these names)
    simulate_module = importlib.import_module("agents.whatif.simulate")

    scene = sample_scenarios()[0]
    runs = []
    monkeypatch.setattr(compare, "simulate", lambda *a, avoid_collisions=True, **k: runs.append(avoid_collisions))
    monkeypatch.setattr(compare, "compare", lambda *a, **k: [])
    compare.run_whatif(None, scene, WhatIf([]), num_rollouts=1, num_steps=1, avoid_collisions=False)
    assert runs == [False, False]  # baseline and what-if

    started = []

    def start(*args, avoid_collisions=True, **kwargs):
        started.append(avoid_collisions)
        raise StopIteration  # the engine is not needed past its arguments

    monkeypatch.setattr(simulate_module.RolloutState, "start", start)
    with pytest.raises(StopIteration):
        simulate_module.simulate(None, None, compare.Prepared(scene=scene, scripts=[], removals=[], lights=[], affected={},
                                                              followers={}, onset_step={}), 1, 0, avoid_collisions=False)
    assert started == [False]


def test_eval_hands_the_flag_to_the_rollouts(monkeypatch):
    from smart_marl.cli import main

    eval_module = importlib.import_module("smart_marl.commands.eval")
    seen = []

    def fake_rollout(*args, avoid_collisions=True, **kwargs):
        seen.append(avoid_collisions)
        raise StopIteration  # the choice is all this test needs

    monkeypatch.setattr(eval_module, "rollout", fake_rollout)
    scene = str(sample_files()[0])  # the package's sample scenes
    for extra, want in (([], True), (["--no-collision-avoidance"], False)):
        with pytest.raises(StopIteration):
            main(["eval", "--scenes", scene, "--policy", "prior", "--rules", "2024"] + extra)
        assert seen[-1] is want
