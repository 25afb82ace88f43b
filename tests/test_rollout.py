"""Closed-loop rollouts (smart_marl.rollout): the KV cache equals a full re-computation, sampling
respects top-k / temperature / forced tokens, outputs are sane on the package's sample scenes and
reproducible.

A small randomly initialised smart-1m (vocabularies of 16 tokens per type built from the sample
scenes' snippets) is enough: none of these properties needs a trained model. The sample scenes
(sumo-7-000000-00 .. -03) have 22, 25, 44 and 10 tracks, 22, 22, 43 and 10 of them valid at the
current frame.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math

import numpy as np
import pytest
import torch

from smart_marl.model.batch import SmartBatch
from smart_marl.model.checkpoint import load_embedded
from smart_marl.model.smart import SMART, get_config
from smart_marl.rollout import RolloutState, rollout, sample_tokens
from smart_marl.rollout.frames import hermite_frames
from smart_marl.tokens import token_poses_from_contours
from smart_marl.scenario import AgentType, SignalState
from smart_marl.tokens import collect_snippets, compose_poses, uniform_grid_vocabulary
from model_variants import with_speed_change

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture(scope="module")
def scenes(sample_scenes):
    return sample_scenes


@pytest.fixture(scope="module")
def vocab(scenes):
    snippets, _ = collect_snippets(scenes)
    return uniform_grid_vocabulary(snippets, 16)


@pytest.fixture(scope="module")
def model(vocab):
    torch.manual_seed(0)
    cfg = get_config("smart-1m", motion_vocab_sizes=(16, 16, 16), road_vocab_size=8, num_freq_bands=8, dropout=0.1,
                     agent_neighbours=16, map_neighbours=16)  # fewer than the candidates: the top-k choice is exercised
    return SMART(cfg, [torch.from_numpy(vocab[t].contour) for t in range(3)]).eval()


def _start(model, vocab, scenes, mode="cached", **kw):
    kw.setdefault("num_rollouts", 1)
    return RolloutState.start(model, scenes, mode=mode, motion_vocab=vocab, **kw)


def test_incremental_logits_equal_full_recomputation_at_every_step(model, vocab, scenes):
    two = [scenes[0], scenes[2]]  # 22 and 43 agents valid at the current frame
    cached = _start(model, vocab, two, num_rollouts=1, seed=3)
    full = _start(model, vocab, two, mode="full", num_rollouts=1, seed=3)
    assert cached.num_history_steps == 2  # tokens 0-5 and 5-10 before the current frame
    worst = 0.0
    for k in range(16):
        if k == 9:  # removing an agent mid-rollout keeps both paths equal
            keep = torch.ones_like(cached.valid)
            keep[0, int(cached.valid[0].nonzero()[0])] = False
            cached.set_agent_valid(keep)
            full.set_agent_valid(keep)
        a = cached.step()
        b = full.step(a.tokens)  # the same tokens, so the two histories stay identical
        finite = torch.isfinite(a.logits)
        assert torch.equal(finite, torch.isfinite(b.logits))
        assert finite.any(-1).sum() == a.simulated.sum() >= 64  # 65, one removed from step 9 on
        worst = max(worst, float((a.logits[finite] - b.logits[finite]).abs().max()))
    print(f"max |incremental - full| logit error over 16 steps: {worst:.3g}")
    assert worst < 1e-4, worst
    # and "full" is the model's own forward: one SmartBatch over history + 15 generated steps
    tok, valid, start, end = full.history
    g, n, s = tok.shape
    road_points = full.road_points[full.scene_of_group]
    zeros = torch.zeros(g, n, s, dtype=torch.long)
    batch = SmartBatch(agent_tokens=tok, agent_valid=valid, agent_type=full.agent_type, agent_shape=full.agent_shape,
                       agent_start_pose=start, agent_pose=end, target_tokens=zeros, target_valid=zeros.bool(),
                       road_points=road_points, road_pose=full.road_pose[full.scene_of_group], road_type=full.road_type[full.scene_of_group],
                       road_light=full.road_light[full.scene_of_group], road_valid=full.road_valid[full.scene_of_group],
                       road_token=torch.zeros(g, road_points.shape[1], dtype=torch.long),
                       road_masked=torch.zeros(g, road_points.shape[1], dtype=torch.bool),
                       road_pairs=torch.zeros(g, 1, 2, dtype=torch.long), road_pair_valid=torch.zeros(g, 1, dtype=torch.bool))
    with torch.no_grad():
        feats, _ = model(batch)
    last = feats[:, :, -1]
    rows = valid[:, :, -1]
    veh = rows & (full.agent_type == 0)
    ref = model.motion_heads[0](last[veh])
    assert torch.allclose(ref, full.logits()[veh][:, :16], atol=1e-5)
    assert torch.allclose(ref, cached.logits()[veh][:, :16], atol=1e-4)


def _appearing_late(scene, count: int):
    """``scene`` with its first ``count`` non-SDC tracks valid at the current frame first seen 3 frames
    before it (less than a token: no complete history token)."""
    tr, cf = scene.tracks, scene.current_frame
    picked = [i for i in np.flatnonzero(tr.valid[:, cf]) if i != scene.sdc_index][:count]
    valid = tr.valid.copy()
    valid[picked, : cf - 3] = False
    return dataclasses.replace(scene, tracks=dataclasses.replace(tr, valid=valid))


def test_rollouts_are_finite_wrapped_in_vocabulary_and_in_the_source_frame(model, vocab, scenes):
    scenes = [scenes[0], _appearing_late(scenes[1], 7), *scenes[2:]]
    res = rollout(model, scenes, num_rollouts=3, num_steps=16, seed=0, motion_vocab=vocab)
    g = len(scenes) * 3
    assert res.trajectory.shape == (g, 44, 80, 4) and res.tokens.shape == (g, 44, 16)  # padded to the largest scene
    assert np.isfinite(res.trajectory).all() and np.isfinite(res.log_probs).all()
    heading = res.trajectory[..., 3]
    assert (heading >= -math.pi).all() and (heading < math.pi).all()
    sim = res.simulated
    assert ((res.tokens[sim] >= 0) & (res.tokens[sim] < 16)).all() and (res.tokens[~sim] == -1).all()
    assert (res.log_probs[sim] <= 0).all()
    for gi in range(g):
        sc = scenes[res.scene_index[gi]]
        tr, cf = sc.tracks, sc.current_frame
        nt = tr.num_tracks
        # every agent valid at the current frame has a trajectory; the motion types are simulated
        assert np.array_equal(res.has_trajectory[gi, :nt], tr.valid[:, cf])
        assert np.array_equal(res.simulated[gi, :nt], tr.valid[:, cf] & (tr.types != AgentType.OTHER))
        assert np.array_equal(res.agent_ids[gi, :nt], tr.ids)
        # the first future frame is 0.1 s from the logged current pose, in the source frame
        logged = sc.frame.to_source(tr.position[:, cf])
        step_m = np.linalg.norm(res.trajectory[gi, :nt, 0, :2] - logged[:, :2], axis=-1)[tr.valid[:, cf]]
        assert step_m.max() < 4.0, step_m.max()
        # z is carried from the current frame
        assert np.allclose(res.trajectory[gi, :nt, :, 2][tr.valid[:, cf]], logged[tr.valid[:, cf], 2][:, None], atol=1e-4)
    # agents that appeared less than a token before the current frame are simulated too (synthetic last token)
    tr = scenes[1].tracks
    late = tr.valid[:, 10] & ~tr.valid[:, 5] & (tr.types != AgentType.OTHER)
    assert late.sum() == 7 and res.simulated[3][: tr.num_tracks][late].all()


def test_same_seed_same_rollouts_other_seed_differs(model, vocab, scenes):
    a = rollout(model, scenes[:1], num_rollouts=4, num_steps=6, seed=11, motion_vocab=vocab)
    b = rollout(model, scenes[:1], num_rollouts=4, num_steps=6, seed=11, motion_vocab=vocab)
    c = rollout(model, scenes[:1], num_rollouts=4, num_steps=6, seed=12, motion_vocab=vocab)
    assert np.array_equal(a.tokens, b.tokens) and np.array_equal(a.trajectory, b.trajectory)
    assert not np.array_equal(a.tokens, c.tokens)
    # rollouts of one scene are batch copies with their own draws
    assert not np.array_equal(a.tokens[0], a.tokens[1])


def test_sampled_tokens_are_inside_the_top_k_with_unclipped_log_probs(model, vocab, scenes):
    # plain top-k (collision-aware sampling, traffic control and speed persistence may go below the top k:
    # tests/test_avoidance.py, tests/test_stop_lines.py, tests/test_persistence.py)
    state = _start(model, vocab, scenes[:2], num_rollouts=8, seed=5, top_k=3, temperature=0.7, avoid_collisions=False,
                   stop_lines=False, persistence=0.0)
    for _ in range(3):
        out = state.step()
        sim = out.simulated
        logits = out.logits[sim]  # (M, Vmax)
        chosen = out.tokens[sim]
        third = torch.topk(logits, 3, dim=-1).values[:, -1]
        assert (logits.gather(1, chosen[:, None])[:, 0] >= third).all()
        expected = torch.log_softmax(logits / 0.7, -1).gather(1, chosen[:, None])[:, 0]
        assert torch.allclose(out.log_probs[sim], expected, atol=1e-6)
        assert (out.tokens[~sim] == -1).all() and torch.isinf(out.logits[~sim]).all()
    # with 8 copies x 44 agents (22 + 22) x 3 steps, more than one of the top 3 is used
    assert len(torch.unique(out.tokens[sim])) > 1


def test_sampler_top1_is_argmax_and_forced_overrides():
    gen = torch.Generator().manual_seed(0)
    logits = torch.randn(50, 9)
    logits[:, 7:] = float("-inf")  # a type with 7 tokens in a 9-wide table
    tok, logp = sample_tokens(logits, gen, top_k=1)
    assert torch.equal(tok, logits.argmax(-1))
    forced = torch.full((50,), -1)
    forced[::2] = 6
    tok, logp = sample_tokens(logits, gen, top_k=0, temperature=2.0, forced=forced)
    assert (tok[::2] == 6).all() and (tok < 7).all()
    assert torch.allclose(logp, torch.log_softmax(logits / 2.0, -1).gather(1, tok[:, None])[:, 0])


@pytest.mark.parametrize("interpolation", ["contour", "spline"])
def test_forced_tokens_are_obeyed_and_placed_at_the_agents_pose(model, vocab, scenes, interpolation):
    """The token's end lands at its contour's end placed at the agent's pose; with
    interpolation="contour" the in-between frames are the contour's too."""
    state = _start(model, vocab, scenes[:1], num_rollouts=2, seed=0, interpolation=interpolation)
    sim = state.valid.clone()
    forced = torch.full(sim.shape, -1, dtype=torch.long)
    forced[0] = torch.arange(sim.shape[1]) % 16  # group 0 forced, group 1 sampled
    before = state.current_pose.clone().numpy()
    out = state.step(forced)
    assert torch.equal(out.tokens[0][sim[0]], forced[0][sim[0]])
    # independent placement: the tokenizer's compose_poses with the vocabulary's poses
    types = state.agent_type[0].numpy()
    toks = forced[0].numpy()
    local = np.stack([vocab[int(t)].poses[k, 1:] for t, k in zip(types, toks)])  # (N, 5, 3)
    expected = compose_poses(before[0][:, None].astype(np.float64), local.astype(np.float64))
    got = out.poses[0].numpy()
    if interpolation == "spline":
        got, expected = got[:, -1:], expected[:, -1:]
    assert np.allclose(got[sim[0].numpy()][..., :2], expected[sim[0].numpy()][..., :2], atol=1e-3)
    dh = (got[..., 2] - expected[..., 2] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(dh[sim[0].numpy()]).max() < 1e-4
    assert torch.equal(state.current_pose[0], out.poses[0, :, -1])
    with pytest.raises(ValueError, match="outside"):
        bad = torch.full(sim.shape, 16, dtype=torch.long)
        state.step(bad)


def test_hermite_frames_continue_steady_motion_and_wrap_headings():
    # steady motion (equal displacements, a steady turn): the in-between frames are evenly spaced
    before, start, end = torch.tensor([[0.0, 0.0, 0.1]]), torch.tensor([[5.0, 1.0, 0.2]]), torch.tensor([[10.0, 2.0, 0.3]])
    frames = hermite_frames(before, start, end)[0]
    fractions = torch.tensor([0.2, 0.4, 0.6, 0.8])[:, None]
    torch.testing.assert_close(frames, start + fractions * (end - start))
    # no previous motion (NaN, e.g. after a pose override): the token's own displacement is the start tangent
    torch.testing.assert_close(hermite_frames(torch.full((1, 3), torch.nan), start, end)[0], frames)
    # from rest to moving: it starts slowly (the first 10 Hz step is the shortest)
    x = hermite_frames(start, start, end)[0, :, 0]
    steps = torch.diff(torch.cat([start[0, :1], x, end[0, :1]]))
    assert steps[0] == steps.min() and steps[0] < 0.5 * steps[-1]
    # a token that stops dead after fast motion: the curve goes no further than the token's end
    stop = hermite_frames(torch.tensor([[-5.0, 0.0, 0.0]]), torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[0.5, 0.0, 0.0]]))[0]
    assert (torch.diff(stop[:, 0]) > 0).all() and stop[:, 0].max() < 0.5
    # headings across +-pi turn the short way and stay wrapped
    h = hermite_frames(torch.tensor([[0.0, 0.0, 3.0]]), torch.tensor([[1.0, 0.0, 3.1]]), torch.tensor([[2.0, 0.0, -3.1]]))[0, :, 2]
    assert (h.abs() > 3.0).all() and (h >= -math.pi).all() and (h < math.pi).all()


def test_spline_frames_keep_the_closed_loop_and_smooth_the_speed(scenes):
    """The interpolation only draws the frames between token ends: same tokens, same token-end
    poses as the contour frames; the 10 Hz speed changes less across token boundaries (the
    embedded prior on a sample scene: realistic tokens). Plain sampling: collision-aware sampling and traffic control
    check candidate tokens along the frames the rollout draws (or its end speed), so their tokens may differ."""
    prior = load_embedded()
    scene = scenes[2]  # 26 agents faster than 2 m/s
    spline = rollout(prior, scene, num_rollouts=2, num_steps=6, seed=4, avoid_collisions=False, stop_lines=False)
    contour = rollout(prior, scene, num_rollouts=2, num_steps=6, seed=4, interpolation="contour", avoid_collisions=False,
                      stop_lines=False)
    np.testing.assert_array_equal(spline.tokens, contour.tokens)
    np.testing.assert_allclose(spline.trajectory[:, :, 4::5], contour.trajectory[:, :, 4::5], atol=1e-4)
    assert not np.allclose(spline.trajectory, contour.trajectory, atol=1e-3)
    sim = spline.simulated[0]

    def boundary_speed_jumps(result):
        xy = result.trajectory[:, sim, :, :2]
        speed = np.linalg.norm(np.diff(xy, axis=2), axis=-1) / 0.1  # speed[t]: frames t -> t + 1
        after = speed[:, :, 4::5]  # the 10 Hz step that leaves each token end
        return np.abs(after - speed[:, :, 3::5][:, :, : after.shape[2]]).mean()  # against the step that reaches it

    # measured on sumo-7-000000-02: 0.14 vs 0.39 m/s (on the real WOMD scene 637f20cafde22ff8, before: 0.20 vs 0.35)
    assert boundary_speed_jumps(spline) < 0.7 * boundary_speed_jumps(contour)
    with pytest.raises(ValueError, match="interpolation"):
        RolloutState.start(prior, scenes[0], interpolation="linear")


def test_removed_agent_stops_and_overridden_pose_is_used(model, vocab, scenes):
    state = _start(model, vocab, scenes[:1], seed=0)
    slots = state.valid[0].nonzero()[:, 0]
    gone, moved = int(slots[0]), int(slots[1])
    keep = torch.ones_like(state.valid)
    keep[0, gone] = False
    state.set_agent_valid(keep)
    pose = state.current_pose.clone()
    pose[0, moved] = torch.tensor([5.0, -3.0, 0.5])
    mask = torch.zeros_like(keep)
    mask[0, moved] = True
    state.set_agent_pose(pose, mask)
    out = state.step()
    assert out.tokens[0, gone] == -1 and torch.isinf(out.logits[0, gone]).all()
    assert torch.equal(out.poses[0, gone], state.current_pose[0, gone][None].expand(5, 3))
    first = out.poses[0, moved, 0].numpy()
    assert np.hypot(first[0] - 5.0, first[1] + 3.0) < 4.0


def test_other_agents_move_at_constant_velocity(model, vocab, scenes):
    sc = scenes[2]  # 26 agents faster than 2 m/s
    tr, cf = sc.tracks, sc.current_frame
    moving = np.flatnonzero(tr.valid[:, cf] & (np.linalg.norm(tr.velocity[:, cf], axis=-1) > 2.0))[:2]
    types = tr.types.copy()
    types[moving] = AgentType.OTHER
    sc2 = dataclasses.replace(sc, tracks=dataclasses.replace(tr, types=types))
    res = rollout(model, [sc2], num_rollouts=1, num_steps=4, seed=0, motion_vocab=vocab)
    assert not res.simulated[0, moving].any() and res.has_trajectory[0, moving].all()
    t_s = 0.1 * np.arange(1, 21)
    expect = sc.frame.to_source(tr.position[moving, cf, None, :2] + tr.velocity[moving, cf, None] * t_s[:, None])
    assert np.allclose(res.trajectory[0, moving, :, :2], expect, atol=1e-3)
    assert np.allclose(res.trajectory[0, moving, :, 3], sc.frame.heading_to_source(tr.heading[moving, cf, None]).repeat(20, 1))


def test_token_poses_from_contours_recover_the_vocabulary_poses(vocab):
    for t in range(3):
        poses = token_poses_from_contours(torch.from_numpy(vocab[t].contour)).numpy()
        assert np.allclose(poses[..., :2], vocab[t].poses[..., :2], atol=1e-4)
        dh = (poses[..., 2] - vocab[t].poses[..., 2] + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(dh).max() < 1e-4


def test_rollout_from_a_checkpoint_path_equals_rollout_from_its_model(model, vocab, scenes, tmp_path):
    from smart_marl.model.checkpoint import save_checkpoint
    from smart_marl.tokens.road import RoadVocabulary

    road_vocab = RoadVocabulary(points=np.zeros((8, 11, 2), np.float32), tolerance_m=0.0, requested_size=8)
    path = save_checkpoint(tmp_path / "prior", model, vocab, road_vocab)
    a = rollout(path, scenes[:1], num_rollouts=2, num_steps=3, seed=4)
    b = rollout(model, scenes[:1], num_rollouts=2, num_steps=3, seed=4, motion_vocab=vocab)
    assert np.array_equal(a.tokens, b.tokens) and np.allclose(a.trajectory, b.trajectory)


def test_scenes_with_different_history_lengths_batch_together_and_stay_exact(model, vocab, scenes):
    # a scene cut to start at frame 4: current frame 6, one history token (frames 1-6), next to a
    # whole scene's two; histories are right-aligned so both end at their current frame
    short = scenes[2].window(4, 91)
    assert short.current_frame == 6
    pair = [scenes[0], short]
    cached = _start(model, vocab, pair, seed=1)
    full = _start(model, vocab, pair, mode="full", seed=1)
    assert cached.num_history_steps == 2 and not cached.history[1][1, :, 0].any()
    for _ in range(4):
        a = cached.step()
        b = full.step(a.tokens)
        finite = torch.isfinite(a.logits)
        assert torch.equal(finite, torch.isfinite(b.logits)) and finite[1].any()
        assert float((a.logits[finite] - b.logits[finite]).abs().max()) < 1e-4
    res = rollout(model, pair, num_rollouts=1, num_steps=2, seed=0, motion_vocab=vocab)
    tr = short.tracks
    logged = short.frame.to_source(tr.position[:, 6])
    first = res.trajectory[1, : tr.num_tracks, 0, :2][tr.valid[:, 6]]
    assert np.linalg.norm(first - logged[tr.valid[:, 6], :2], axis=-1).max() < 4.0


def test_set_road_light_re_encodes_the_road_and_reaches_the_next_logits(model, vocab, scenes):
    cached, full = _start(model, vocab, scenes[:1], seed=0), _start(model, vocab, scenes[:1], mode="full", seed=0)
    light = torch.where(cached.road_valid, torch.tensor(int(SignalState.STOP)), cached.road_light)
    assert not torch.equal(light, cached.road_light)
    before = cached.road_x.clone()
    for state in (cached, full):
        state.set_road_light(light)
    fresh = model.road_net(cached.road_points, cached.road_pose, cached.road_type, light, cached.road_valid)
    torch.testing.assert_close(cached.road_x, fresh)
    assert not torch.allclose(before, fresh)
    # the next step's logits see it (the KV cache keeps the history steps as they were computed,
    # under the old lights; the full path re-computes them, so the two paths differ from here on)
    unchanged = _start(model, vocab, scenes[:1], seed=0)
    for state in (cached, full):
        assert not torch.allclose(state.logits(), unchanged.logits())
    with pytest.raises(ValueError, match="road_light must have shape"):
        cached.set_road_light(light[:, :-1])


def test_speed_change_input_starts_as_the_model_without_it_and_stays_exact_in_the_cached_step(model, vocab, scenes, monkeypatch):
    """SmartConfig.speed_change_input: zero at first (the same logits as without it); once its weights are not,
    the logits change, and the cached step still equals the full recomputation (both read the ends of the
    agent's last tokens)."""
    two = [scenes[0], scenes[2]]
    plain = _start(model, vocab, two, seed=3)
    same = _start(with_speed_change(model, 0.0), vocab, two, seed=3)
    torch.testing.assert_close(same.logits(), plain.logits(), rtol=0, atol=0)
    changed = with_speed_change(model, 0.5)
    cached = _start(changed, vocab, two, seed=3)
    full = _start(changed, vocab, two, mode="full", seed=3)
    finite = torch.isfinite(plain.logits())
    assert float((cached.logits()[finite] - plain.logits()[finite]).abs().max()) > 1e-3
    from smart_marl.model import motionnet  # the change itself is read, not only the MLP's constant at change 0
    @contextlib.contextmanager
    def blind_to_the_change():
        """While it lasts, every token's speed change reads as 0 (the same model, blind to the change)."""
        with monkeypatch.context() as m:
            m.setattr(motionnet, "speed_change", lambda start, end, before, had: torch.zeros_like(before))
            yield

    with blind_to_the_change():
        blind = _start(changed, vocab, two, seed=3)
    seen = 0.0
    for _ in range(6):
        a = cached.step()
        b = full.step(a.tokens)
        finite = torch.isfinite(a.logits)
        assert float((a.logits[finite] - b.logits[finite]).abs().max()) < 1e-4
        with blind_to_the_change():
            blind.step(a.tokens)  # the same tokens: the histories differ in what the model makes of them only
            blind_logits = blind.logits()
        now = torch.isfinite(cached.logits())
        seen = max(seen, float((cached.logits()[now] - blind_logits[now]).abs().max()))
    assert seen > 1e-3  # sampled tokens change speed: the model sees it
