"""The prior's own reinforcement learning (smart_marl.prior_rl): who is at fault in a collision, the sampled
rollouts' token sequences (scripted tracks follow their log), the batch's targets and weights, the loss's
direction, and a run that writes checkpoints and resumes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from smart_marl.catk import first_future_step, sampled_tokens
from smart_marl.model.batch import scene_road
from smart_marl.prior_rl import PriorRLConfig, at_fault_collisions, rl_loss, scene_batch, token_step_frames, train_prior_rl
from smart_marl.tokens import tokenize_motion
from smart_marl.tokens.road import RoadVocabulary, road_pieces


@pytest.fixture(scope="module")
def road_vocab(sample_scenes):
    pieces = road_pieces(sample_scenes[0].road_map).local
    return RoadVocabulary(points=pieces[np.random.default_rng(0).choice(len(pieces), 8)], tolerance_m=0.0, requested_size=8)


def _line(x0: float, speed: float, frames: int = 20) -> np.ndarray:
    x = x0 + speed * 0.1 * np.arange(frames)
    return np.stack([x, np.zeros(frames), np.zeros(frames)], -1)


def test_the_car_that_runs_into_the_one_ahead_is_at_fault_and_the_one_hit_is_not():
    size = np.array([[4.5, 2.0], [4.5, 2.0], [4.5, 2.0]])
    # track 0 drives at 10 m/s into track 1, standing 12 m ahead; track 2 drives beside them, 4 m to the left
    beside = _line(0.0, 10.0)
    beside[:, 1] = 4.0
    poses = np.stack([_line(0.0, 10.0), _line(12.0, 0.0), beside])
    present = np.ones(poses.shape[:2], bool)
    got = at_fault_collisions(poses, present, size)
    assert got[1] == -1 and got[2] == -1
    # bumpers touch when 0 has covered 12 - 4.5 = 7.5 m, 0.75 s: frame 8 (the rounded boxes' corners a frame later at most)
    assert 7 <= got[0] <= 9
    present[1, :] = False  # the standing car is not there: nobody is hit
    assert (at_fault_collisions(poses, present, size) == -1).all()


def test_sampled_rollouts_draw_from_the_top_k_and_scripted_tracks_follow_their_log(sample_scenes, sample_vocab, tiny_smart,
                                                                                   road_vocab, one_torch_thread):
    model = tiny_smart(sample_vocab)
    sc = sample_scenes[2]
    road = scene_road(sc, road_vocab)
    log = tokenize_motion(sc, sample_vocab)
    follow = np.zeros(sc.num_tracks, bool)
    follow[np.flatnonzero(log.valid.any(1))[:5]] = True
    runs = [sampled_tokens(model, [sc, sc], [road, road], sample_vocab, 3, torch.Generator().manual_seed(s), [follow, follow])
            for s in (0, 0, 1)]
    a, b = runs[0]
    np.testing.assert_array_equal(a.ids, runs[1][0].ids)  # the same seed draws the same rollout
    assert not np.array_equal(a.ids, b.ids)  # two copies of one scene are two rollouts
    assert not np.array_equal(a.ids, runs[2][0].ids)
    kc = first_future_step(sc)
    for mt in (a, b):
        np.testing.assert_array_equal(mt.valid, log.valid)
        np.testing.assert_array_equal(mt.ids[:, :kc][log.valid[:, :kc]], log.ids[:, :kc][log.valid[:, :kc]])  # the history
        np.testing.assert_array_equal(mt.ids[follow], log.ids[follow])  # scripted: the log's rolling matching
    assert (a.ids[~follow, kc:] != log.ids[~follow, kc:])[log.valid[~follow, kc:]].any()
    # every drawn token is among the model's top 3 where it was drawn (a full forward over the sequence)
    from smart_marl.model.batch import collate_scenes, scene_tensors

    batch = collate_scenes([scene_tensors(sc, sample_vocab, road, road_mask_prob=0.0, rng=0, motion_tokens=a)])
    with torch.no_grad():
        feats, _ = model(batch)
    keep = np.flatnonzero(a.valid.any(1))
    checked = 0
    for j, row in enumerate(keep):
        if follow[row]:
            continue
        for k in range(kc, a.num_steps):
            if a.valid[row, k] and a.valid[row, k - 1]:
                top = model.motion_heads[int(sc.tracks.types[row])](feats[0, j, k - 1]).topk(3).indices
                assert a.ids[row, k] in top.tolist()
                checked += 1
    assert checked > 100


def _one_rollout(sample_scenes, sample_vocab, tiny_smart, road_vocab):
    """A tiny model, a frozen copy (the reference), sample scene 3, its road, one top-3 rollout of it, its first drawn step."""
    model, ref = tiny_smart(sample_vocab).eval(), tiny_smart(sample_vocab).eval()
    ref.load_state_dict(model.state_dict())
    sc = sample_scenes[3]
    road = scene_road(sc, road_vocab)
    mt = sampled_tokens(model, [sc], [road], sample_vocab, 3, torch.Generator().manual_seed(0))[0]
    kc = first_future_step(sc)
    return model, ref, sc, road, mt, kc


def test_the_batch_trains_the_drawn_tokens_up_to_the_collision_and_the_loss_raises_a_rewarded_token(
        sample_scenes, sample_vocab, tiny_smart, road_vocab, one_torch_thread):
    model, ref, sc, road, mt, kc = _one_rollout(sample_scenes, sample_vocab, tiny_smart, road_vocab)
    keep = np.flatnonzero(mt.valid.any(1))
    adv = np.zeros(sc.num_tracks, np.float32)
    adv[keep[0]], adv[keep[1]] = 1.0, -1.0
    last = np.full(sc.num_tracks, mt.num_steps, np.int64)
    last[keep[1]] = kc + 2  # collided in its third drawn token
    scripted = np.zeros(sc.num_tracks, bool)
    scripted[keep[2]] = True
    batch, weight = scene_batch([sc], [mt], [road], sample_vocab, [adv], [last], [scripted], kc)
    tv = batch.target_valid[0]
    steps = torch.arange(tv.shape[1])
    assert not tv[2].any()  # scripted: no target
    assert tv[1, steps >= kc + 2].sum() == 0 and tv[1, kc - 1: kc + 2].all()  # targets: tokens kc .. kc + 2
    assert tv[0, : kc - 1].sum() == 0  # the history is no target
    assert torch.equal(batch.target_tokens[0, 0, kc - 1:-1], torch.from_numpy(mt.ids[keep[0], kc:]))  # the drawn tokens
    assert (weight[0, 0][tv[0]] == 1).all() and (weight[0, 1][tv[1]] == -1).all()
    per_step = np.zeros((sc.num_tracks, mt.num_steps), np.float32)  # advantages per token step
    per_step[keep[1]] = np.arange(mt.num_steps)
    _, w2 = scene_batch([sc], [mt], [road], sample_vocab, [per_step], [last], [scripted], kc)
    assert torch.equal(w2[0, 1, kc - 1: kc + 2], torch.tensor([kc, kc + 1.0, kc + 2]))  # row s weighs token s + 1
    res = rl_loss(model, ref, batch, weight, beta=0.1)
    assert float(res["kl"]) == pytest.approx(0.0, abs=1e-7)  # the same weights: no divergence
    opt = torch.optim.SGD(model.parameters(), lr=0.5)

    def logp(m):
        with torch.no_grad():
            feats, _ = m(batch)
        t = int(batch.agent_type[0, 0])
        lp = torch.log_softmax(m.motion_heads[t](feats[0, 0]), -1)
        return lp.gather(1, batch.target_tokens[0, 0][:, None])[:, 0][tv[0]].sum()

    before = logp(model)
    opt.zero_grad()
    res["loss"].backward()
    opt.step()
    assert logp(model) > before  # the rewarded agent's drawn tokens got likelier
    assert float(rl_loss(model, ref, batch, weight, beta=0.1)["kl"]) > 0


def test_token_step_frames_place_each_token_where_it_starts(sample_scenes, sample_vocab):
    sc = sample_scenes[3]
    mt = tokenize_motion(sc, sample_vocab)
    kc = first_future_step(sc)
    poses, present = token_step_frames(mt, sample_vocab, kc)
    assert poses.shape == (sc.num_tracks, 5 * (mt.num_steps - kc), 3)
    r = int(np.flatnonzero(mt.valid[:, kc]).min())
    np.testing.assert_allclose(poses[r, 4, :2], mt.reached[r, kc + 1, :2], atol=1e-4)  # a token's last frame is where it ends
    assert present[r, :5].all()


def test_a_run_writes_its_log_and_checkpoints_and_resumes(sample_scenes, tiny_prior, tmp_path, one_torch_thread):
    from smart_marl.embedded import SAMPLES_DIR
    from smart_marl.model.checkpoint import load_checkpoint

    cfg = PriorRLConfig(scenes=str(SAMPLES_DIR), out_dir=str(tmp_path / "run"), init=str(tiny_prior), iterations=2,
                        scenes_per_iteration=2, rollouts=2, save_every=1, top_k=3)
    train_prior_rl(cfg)
    rows = [json.loads(x) for x in (tmp_path / "run" / "train.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2]
    assert all(np.isfinite(r["loss"]) and 0 <= r["at_fault"] <= r["penalised"] <= 1 for r in rows)
    assert load_checkpoint(tmp_path / "run" / "last").step == 2
    before = load_checkpoint(tiny_prior).model.state_dict()
    after = load_checkpoint(tmp_path / "run" / "iter0002").model.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before)
    train_prior_rl(PriorRLConfig(**{**cfg.__dict__, "iterations": 3}))  # resumes at iteration 3
    rows = [json.loads(x) for x in (tmp_path / "run" / "train.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3]


def test_the_command_line_runs_and_resumes(tiny_prior, tmp_path, one_torch_thread):
    from smart_marl.embedded import SAMPLES_DIR
    from smart_marl.model.checkpoint import load_checkpoint
    from smart_marl.prior_rl import main

    args = ["--scenes", str(SAMPLES_DIR), "--out-dir", str(tmp_path / "cli"), "--init", str(tiny_prior), "--iterations", "1",
            "--scenes-per-iteration", "1", "--rollouts", "2", "--top-k", "3", "--offroad", "false", "--progress", "0.5",
            "--lr", "1e-3"]
    main(args)
    main(args[:7] + ["2"] + args[8:])  # one more iteration, from the saved one
    rows = [json.loads(x) for x in (tmp_path / "cli" / "train.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2] and rows[0]["offroad"] == 0.0
    cfg = load_checkpoint(tmp_path / "cli" / "last").meta["data"]["prior_rl"]
    assert cfg["offroad"] is False and cfg["progress"] == 0.5 and cfg["iterations"] == 2


def test_a_vehicle_pushed_off_the_road_is_off_road_from_that_frame(sample_scenes):
    from smart_marl.catk import _agent_shapes
    from smart_marl.geometry_torch import scene_road_edges
    from smart_marl.prior_rl import _vehicles_on_road, first_offroad

    sc = sample_scenes[2]
    edges = scene_road_edges(sc.road_map)
    size = _agent_shapes(sc, np.arange(sc.num_tracks))
    rows = _vehicles_on_road(sc, size, np.ones(sc.num_tracks, bool), edges)
    assert len(rows) >= 3
    tr, cf = sc.tracks, sc.current_frame
    now = np.concatenate([tr.position[:, cf, :2], tr.heading[:, cf, None]], -1).astype(np.float64)
    poses = np.repeat(now[:, None], 6, axis=1)
    side = np.stack([-np.sin(now[:, 2]), np.cos(now[:, 2])], -1)
    poses[:, 3:, :2] += 60.0 * side[:, None]  # from frame 3 on, 60 m to the left of where it stands
    present = np.ones(poses.shape[:2], bool)
    z = tr.position[:, cf, 2]
    got = first_offroad(poses, present, size, z, edges, rows)
    assert (got[np.setdiff1d(np.arange(sc.num_tracks), rows)] == -1).all()  # only the watched vehicles
    assert ((got[rows] == -1) | (got[rows] >= 3)).all() and (got[rows] == 3).mean() > 0.5
    assert (first_offroad(np.repeat(now[:, None], 6, axis=1), present, size, z, edges, rows) == -1).all()


def test_progress_error_is_small_on_the_log_and_one_for_a_car_that_stands(sample_scenes, sample_vocab):
    import dataclasses

    from smart_marl.prior_rl import progress_error

    sc = sample_scenes[2]
    mt = tokenize_motion(sc, sample_vocab)
    kc = first_future_step(sc)
    err = progress_error(sc, mt, kc)
    moving = err > 0
    assert np.median(err[moving]) < 0.05 and err.max() < 0.2  # the log's own tokens (32 a type) drive about its distance
    standing = mt.reached.copy()
    standing[:, kc:] = standing[:, kc : kc + 1]
    err = progress_error(sc, dataclasses.replace(mt, reached=standing), kc)
    logged = np.linalg.norm(np.diff(sc.tracks.position[:, mt.boundaries[kc:], :2], axis=1), axis=-1)
    moved = ((logged * mt.valid[:, kc:]).sum(1) >= 5.0)
    assert moved.sum() >= 5 and moving.sum() <= moved.sum()
    np.testing.assert_allclose(err[moved], 1.0)  # it drove nothing of its logged distance
    assert (err[~moved] == 0).all()  # too short a log to judge


def test_returns_blame_the_steps_before_a_penalty_by_the_discount_and_the_baseline_is_the_groups_mean():
    from smart_marl.prior_rl import group_advantages, token_returns

    penalty = np.array([[3, -1], [-1, -1]])  # rollout 0: agent 0 penalised at step 3; nobody else
    final = np.array([[0.0, -0.2], [-0.1, -0.4]], np.float32)  # the progress term
    ret = token_returns(penalty, final, 6, 0.5)
    np.testing.assert_allclose(ret[0, 0], [-0.125, -0.25, -0.5, -1, -1, -1])  # the penalty replaces progress
    np.testing.assert_allclose(ret[1, 0], [-0.1] * 6)
    np.testing.assert_allclose(ret[:, 1], [[-0.2] * 6, [-0.4] * 6])
    np.testing.assert_allclose(token_returns(penalty, final, 6, 1.0)[0, 0], [-1] * 6)  # undiscounted: the whole drive
    adv = group_advantages(ret, np.array([True, False]))
    np.testing.assert_allclose(adv[:, 0, 2], [-0.2, 0.2])  # -0.5 and -0.1 around their mean -0.3
    np.testing.assert_allclose(adv.sum(0), 0, atol=1e-7)
    assert (adv[:, 1] == 0).all()  # not simulated: no advantage


def test_the_update_in_parts_sums_to_the_gradient_of_the_whole_batch(sample_scenes, sample_vocab, tiny_smart, road_vocab,
                                                                      one_torch_thread):
    from smart_marl.prior_rl import update_in_parts

    model, ref = tiny_smart(sample_vocab).eval(), tiny_smart(sample_vocab).eval()
    parts: list[list] = [[] for _ in range(6)]
    for sc in (sample_scenes[2], sample_scenes[3]):  # two scenes x two rollouts
        road = scene_road(sc, road_vocab)
        mt = sampled_tokens(model, [sc, sc], [road, road], sample_vocab, 3, torch.Generator().manual_seed(0))
        adv = np.random.default_rng(0).normal(size=(2, sc.num_tracks, mt[0].num_steps)).astype(np.float32)
        last = np.full((2, sc.num_tracks), mt[0].num_steps, np.int64)
        for p, g in zip(parts, ([sc, sc], mt, [road, road], list(adv), list(last), [np.zeros(sc.num_tracks, bool)] * 2)):
            p.extend(g)
    cfg = PriorRLConfig(rollouts=2, beta=0.1)
    model.zero_grad()
    got = update_in_parts(model, ref, parts, sample_vocab, cfg)
    in_parts = [p.grad.clone() for p in model.parameters() if p.grad is not None]
    model.zero_grad()
    batch, weight = scene_batch(parts[0], parts[1], parts[2], sample_vocab, parts[3], parts[4], parts[5], first_future_step(parts[0][0]))
    whole = rl_loss(model, ref, batch, weight, 0.1)
    whole["loss"].backward()
    assert got["tokens"] == int(whole["tokens"]) > 0
    assert got["loss"] == pytest.approx(float(whole["loss"].detach()), rel=1e-4, abs=1e-6)
    for a, b in zip(in_parts, [p.grad for p in model.parameters() if p.grad is not None]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_the_rule_recorded_beside_a_plain_draw_takes_out_the_tokens_into_a_braking_leader(sample_scenes, sample_vocab, tiny_smart,
                                                                                          road_vocab, one_torch_thread):
    """``sampled_tokens(excluded=...)`` records, at every drawn step, the tokens the simulator's collision rule
    would not have let each track draw; the draw itself stays the plain one."""
    from smart_marl.braking import brake_along_log, leader_follower_pairs

    sc0 = sample_scenes[2]
    leader, follower, _ = leader_follower_pairs(sc0)[0]
    sc = brake_along_log(sc0, leader, sc0.current_frame + 1, 8.0)
    model, road = tiny_smart(sample_vocab), scene_road(sc, road_vocab)
    scripted = np.zeros(sc.num_tracks, bool)
    scripted[leader] = True
    rule: dict = {}
    got = sampled_tokens(model, [sc, sc], [road, road], sample_vocab, 6, torch.Generator().manual_seed(3), [scripted] * 2,
                         excluded=rule)
    plain = sampled_tokens(model, [sc, sc], [road, road], sample_vocab, 6, torch.Generator().manual_seed(3), [scripted] * 2)
    kc = first_future_step(sc)
    vmax = max(v.size for v in sample_vocab.types.values())
    assert sorted(rule) == [0, 1]
    hits = 0
    for c in (0, 1):
        np.testing.assert_array_equal(got[c].ids, plain[c].ids)  # recording changes no draw
        ex = rule[c]
        assert ex.shape == (sc.num_tracks, got[c].num_steps, vmax)
        assert not ex[:, :kc].any() and not ex[leader].any()  # the history and the scripted leader: nothing
        assert not ex[~got[c].valid.any(1)].any()
        # where the plain draw runs the follower into its stopped leader (their centres within 1.5 m): the rule had
        # taken out the token it drew the step before, and left it others
        gap = np.linalg.norm(got[c].start_pose[follower, kc:, :2] - got[c].start_pose[leader, kc:, :2], axis=-1)
        if gap.min() >= 1.5:
            continue
        hit = kc + int(np.argmax(gap < 1.5))
        assert hit > kc
        drawn = got[c].ids[follower, hit - 1]
        assert ex[follower, hit - 1, drawn] and not ex[follower, hit - 1].all()
        hits += 1
    assert hits >= 1  # (seed 3: the first rollout)


def test_the_rule_loss_is_minus_the_log_of_the_allowed_mass_and_a_step_lowers_the_excluded_mass(sample_scenes, sample_vocab,
                                                                                                tiny_smart, road_vocab,
                                                                                                one_torch_thread):
    from smart_marl.prior_rl import rule_loss

    model, ref, sc, road, mt, kc = _one_rollout(sample_scenes, sample_vocab, tiny_smart, road_vocab)
    vmax = max(v.size for v in sample_vocab.types.values())
    keep = np.flatnonzero(mt.valid.any(1))
    ex = np.zeros((sc.num_tracks, mt.num_steps, vmax), bool)
    ex[keep[0], kc + 1, :10] = True  # a row with tokens taken out (row kc of the batch: token kc + 1)
    ex[keep[1], kc + 2] = True  # everything taken out: the row is left out
    last = np.full(sc.num_tracks, mt.num_steps, np.int64)
    batch, excluded = scene_batch([sc], [mt], [road], sample_vocab, [ex], [last], [np.zeros(sc.num_tracks, bool)], kc)
    assert excluded.dtype == torch.bool and excluded[0, 0, kc, :10].all() and excluded.sum() == 10 + vmax
    res = rule_loss(model, ref, batch, excluded)
    with torch.no_grad():
        feats, _ = model(batch)
    t = int(batch.agent_type[0, 0])
    p = torch.softmax(model.motion_heads[t](feats[0, 0, kc]).detach().float(), -1)
    mass = float(p[:10].sum())
    m = int(batch.target_valid.sum())
    # the same weights: KL(q || p) of the one row is -log(1 - excluded mass), every other row's is 0
    assert float(res["kl"]) == pytest.approx(-np.log(1 - mass) / m, rel=1e-3)
    assert float(res["excluded_mass"]) == pytest.approx(mass, rel=1e-4) and float(res["ruled"]) == 1
    opt = torch.optim.SGD(model.parameters(), lr=20.0)
    opt.zero_grad()
    res["loss"].backward()
    opt.step()
    with torch.no_grad():
        after = rule_loss(model, ref, batch, excluded)
        assert float(after["excluded_mass"]) < mass
        # the rows where nothing is excluded have moved off the reference too; ``anchor`` weighs them
        assert float(after["loss"]) == pytest.approx(float(after["kl"]))
        ruled_only = rule_loss(model, ref, batch, excluded, anchor=0.0)
        half = rule_loss(model, ref, batch, excluded, anchor=0.5)
    assert 0 < float(ruled_only["loss"]) < float(half["loss"]) < float(after["loss"])
    assert float(half["loss"]) == pytest.approx((float(ruled_only["loss"]) + float(after["loss"])) / 2, rel=1e-4)


def test_the_rule_with_offroad_also_takes_out_the_tokens_that_end_a_vehicle_off_the_road(sample_scenes, sample_vocab, tiny_smart,
                                                                                         road_vocab, one_torch_thread):
    from smart_marl.catk import _agent_shapes
    from smart_marl.geometry import box_distance_to_road_edge
    from smart_marl.geometry_torch import scene_road_edges
    from smart_marl.scenario import AgentType

    sc = sample_scenes[2]
    model, road = tiny_smart(sample_vocab), scene_road(sc, road_vocab)
    runs = []
    for offroad in (False, True):
        rule: dict = {}
        mt = sampled_tokens(model, [sc], [road], sample_vocab, 6, torch.Generator().manual_seed(5), excluded=rule, offroad=offroad)[0]
        runs.append((mt, rule[0]))
    (mt, plain), (mt2, both) = runs
    np.testing.assert_array_equal(mt.ids, mt2.ids)  # the draw is plain either way
    edges, size = scene_road_edges(sc.road_map), _agent_shapes(sc, np.arange(sc.num_tracks))
    vv = sample_vocab.types[AgentType.VEHICLE]
    cf = sc.current_frame
    off = []
    for row, k in zip(*np.nonzero((both & ~plain).any(-1))):
        assert sc.tracks.types[row] == int(AgentType.VEHICLE)
        if both[row, k, : vv.size].all():
            continue  # an agent with no free token keeps them all
        x0, y0, h0 = mt.start_pose[row, k]
        for tok in np.flatnonzero(both[row, k, : vv.size] & ~plain[row, k, : vv.size]):
            dx, dy, dh = vv.poses[tok, -1]  # the token's end in its start frame
            x, y = x0 + dx * np.cos(h0) - dy * np.sin(h0), y0 + dx * np.sin(h0) + dy * np.cos(h0)
            d = box_distance_to_road_edge(np.array([x]), np.array([y]), np.array([sc.tracks.position[row, cf, 2]]),
                                          size[row, 0], size[row, 1], size[row, 2], np.array([h0 + dh]), edges)
            off.append(d[0])
    # off the road (within the few cm of the two searches' float32 corners), but for a few that collide: where
    # tokens fail the road test the search goes further down the list and meets collisions the first did not reach
    assert len(off) >= 50 and np.mean(np.array(off) > -0.05) > 0.95
