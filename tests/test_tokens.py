"""Motion tokens: k-disks vocabularies, rolling matching, noise, detokenization, vocabulary files.

The mechanics use a 256-token vocabulary built from the package's four sample scenes (SUMO) and
tokenize those scenes or hand-made tracks. What the vocabulary is worth on real driving (reconstruction
without drift, k-disks against a uniform grid, reversing) uses vocabularies built from real scenes
other than the ones the tests evaluate on (build: ScenarioNet WOMD + GPUDrive scenes; evaluate: the
WOMD TFRecord and SMART pickle scenes; ../shared/data)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from smart_marl import read_scenarios
from smart_marl.scenario import AgentType, Tracks, wrap_angle
from smart_marl.synthetic import synthetic_scenario
from smart_marl.tokens import (
    BOX_SIZE_M, MOTION_TYPES, VocabularyFileError, box_contour, build_motion_vocabulary, collect_snippets, compose_poses,
    detokenize, kdisks, load_motion_vocabulary, load_reference_motion_vocabulary, mean_point_distance, reconstruct,
    relative_poses, save_motion_vocabulary, token_boundaries, tokenize_motion, tokenize_tracks, uniform_grid_vocabulary,
)
from smart_marl.tokens.kdisks import kdisks_pass

BUILD_FOLDERS = ("scenarionet/waymo", "gpudrive_json")
EVAL_FOLDERS = ("womd_tfrecord", "smart_pkl")


def _scenes(root: Path, folders) -> list:
    out = []
    for folder in folders:
        out.extend(read_scenarios(root / folder))
    return out


@pytest.fixture(scope="module")
def build_scenes(shared_data):
    return _scenes(shared_data, BUILD_FOLDERS)


@pytest.fixture(scope="module")
def eval_scenes(shared_data):
    return _scenes(shared_data, EVAL_FOLDERS)


@pytest.fixture(scope="module")
def real_snippets(build_scenes):
    return collect_snippets(build_scenes)


@pytest.fixture(scope="module")
def real_vocab(real_snippets):
    snip, prov = real_snippets
    return build_motion_vocabulary(snip, 256, seed=0, provenance=prov, progress=False)


@pytest.fixture(scope="module")
def snippets(sample_scenes):
    return collect_snippets(sample_scenes)


@pytest.fixture(scope="module")
def vocab(snippets):
    snip, prov = snippets
    return build_motion_vocabulary(snip, 256, seed=0, provenance=prov, progress=False)


def _errors(scenes, vocab, **kw):
    pos, final = [], []
    for sc in scenes:
        tok = tokenize_motion(sc, vocab, **kw)
        poses, pv = reconstruct(tok, vocab, sc.num_frames)
        cover = pv & sc.tracks.valid & np.isin(sc.tracks.types, [AgentType.VEHICLE])[:, None]
        for k in range(tok.num_steps):  # anchors are exact by construction: leave them out
            first = tok.valid[:, k] & ~(tok.valid[:, k - 1] if k else False)
            cover[first, tok.boundaries[k]] = False
        err = np.linalg.norm(poses[..., :2] - sc.tracks.position[..., :2], axis=-1)
        pos.append(err[cover])
        has = cover.any(1)
        last = sc.num_frames - 1 - np.argmax(cover[:, ::-1], axis=1)
        final.append(err[np.flatnonzero(has), last[has]])
    return np.concatenate(pos), np.concatenate(final)


# ------------------------------------------------------------------------------------ k-disks
def test_kdisks_pass_equals_the_plain_definition():
    rng = np.random.default_rng(3)
    x = (rng.normal(size=(1500, 24, 2)) * 0.3 + rng.normal(size=(1500, 1, 2)) * 3).astype(np.float32)
    order = np.random.default_rng(7).permutation(len(x))
    for tol in (0.3, 0.6):
        centres, left = kdisks_pass(x, tol, 10**6, seed=7)
        alive, expect = np.ones(len(x), bool), []
        for i in order:  # the definition, one sample at a time
            if alive[i]:
                expect.append(i)
                alive &= mean_point_distance(x, x[i]) > tol
        assert centres.tolist() == expect and left == 0


def test_kdisks_hits_the_requested_size_with_disjoint_centres():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(4000, 11, 2)).astype(np.float32)
    res = kdisks(x, 100, seed=1, progress=False)
    assert len(res.centre_indices) == 100 and res.tolerance_m > 0
    c = x[res.centre_indices]
    d = mean_point_distance(c[:, None], c[None])
    assert (d[~np.eye(100, dtype=bool)] > res.tolerance_m).all()  # no centre inside another's disk
    uncovered = (mean_point_distance(x[:, None], c[None]).min(1) > res.tolerance_m).sum()
    assert uncovered == res.num_uncovered


def test_kdisks_with_fewer_distinct_samples_than_size_returns_all_of_them():
    x = np.repeat(np.arange(5, dtype=np.float32)[:, None, None] * np.ones((1, 3, 2), np.float32), 4, axis=0)
    res = kdisks(x, 64, progress=False)
    assert sorted(x[res.centre_indices][:, 0, 0].tolist()) == [0, 1, 2, 3, 4] and res.tolerance_m == 0.0


# --------------------------------------------------------------------------------- vocabularies
def test_three_type_vocabularies_have_the_requested_size_and_their_type_boxes(vocab, snippets):
    snip, _ = snippets
    for t in MOTION_TYPES:
        v = vocab[t]
        assert v.size == 256 and v.poses.shape == (256, 6, 3) and v.contour.shape == (256, 6, 4, 2)
        assert np.allclose(v.poses[:, 0], 0.0)  # every token starts at its own frame's origin
        np.testing.assert_allclose(v.contour, box_contour(v.poses, *BOX_SIZE_M[t]), atol=1e-5)
        assert (v.length_m, v.width_m) == BOX_SIZE_M[t] and v.tolerance_m > 0
        assert v.num_real_samples == len(snip[t])
    # vehicles: data only (plenty); cyclists are few in these scenes, so augmented up to 4x size
    assert vocab[AgentType.VEHICLE].num_samples == len(snip[AgentType.VEHICLE])
    assert vocab[AgentType.CYCLIST].num_samples == max(4 * 256, len(snip[AgentType.CYCLIST]))
    # vehicle tokens reach faster than pedestrian ones
    assert vocab[AgentType.VEHICLE].poses[:, -1, 0].max() > 3 * vocab[AgentType.PEDESTRIAN].poses[:, -1, 0].max()


def test_vocabulary_build_is_deterministic_given_the_seed(snippets, vocab):
    snip, prov = snippets
    again = build_motion_vocabulary(snip, 256, seed=0, provenance=prov, progress=False)
    other = build_motion_vocabulary(snip, 256, seed=1, provenance=prov, progress=False)
    assert again.content_hash() == vocab.content_hash()
    assert other.content_hash() != vocab.content_hash()


# ---------------------------------------------------------------------------- rolling matching
def test_rolling_matching_reconstructs_real_vehicles_without_drift(real_vocab, eval_scenes):
    pos, final = _errors(eval_scenes, real_vocab)
    assert len(pos) > 5000
    assert pos.mean() < 0.25  # 256 tokens built from other scenes
    assert final.mean() < 3.0 * pos.mean()  # no drift: the final frame is about as good as the mean


def test_kdisks_beats_a_uniform_grid_of_the_same_size(real_vocab, real_snippets, eval_scenes):
    grid = uniform_grid_vocabulary(real_snippets[0], 256)
    scenes = [sc for sc in eval_scenes if sc.num_tracks < 200]
    assert _errors(scenes, grid)[0].mean() > 1.5 * _errors(scenes, real_vocab)[0].mean()


def _check_topk_noise(sc, vocab, max_noisy_m: float) -> None:
    tok = tokenize_motion(sc, vocab, noise_topk=5, rng=0)
    v = tok.valid & (tok.types == AgentType.VEHICLE)[:, None]
    rate = (tok.ids != tok.nearest_ids)[v].mean()
    assert 0.7 < rate < 0.85  # uniform among 5: 4/5 differ from the nearest
    half = tokenize_motion(sc, vocab, noise_topk=5, noise_prob=0.5, rng=0)
    assert 0.3 < (half.ids != half.nearest_ids)[v].mean() < 0.5
    again = tokenize_motion(sc, vocab, noise_topk=5, rng=0)
    assert np.array_equal(again.ids, tok.ids)  # seeded
    clean_pos, _ = _errors([sc], vocab)
    noisy_pos, noisy_final = _errors([sc], vocab, noise_topk=5, rng=0)
    # noised tokens are among the 5 nearest, so they stay close; rolling re-centres on the noised
    # pose, so the noise does not accumulate (final error ~ mean error)
    assert clean_pos.mean() < noisy_pos.mean() < max_noisy_m
    assert noisy_final.mean() < 2.0 * noisy_pos.mean()


def test_topk_noise_changes_tokens_at_the_expected_rate_and_stays_close(real_vocab, eval_scenes):
    _check_topk_noise(eval_scenes[0], real_vocab, 0.6)


def test_topk_noise_on_a_sample_scene_changes_tokens_at_the_expected_rate_and_stays_close(vocab, sample_scenes):
    # sumo-7-000000-01 (21 vehicles) with the sample scenes' own 256 tokens, measured: clean 0.10 m, noisy
    # 0.69 m mean and 1.15 m at the last frame. SUMO's few distinct motions give a sparser vocabulary than
    # the real scenes' (their bound: 0.6 m); on sumo-7-000000-02 the last frame reaches 2.0x the mean.
    _check_topk_noise(sample_scenes[1], vocab, 0.8)


def test_detokenize_chains_tokens_like_the_rolling_matcher_and_batches(vocab, sample_scenes):
    sc = sample_scenes[2]
    tok = tokenize_motion(sc, vocab)
    full = tok.valid.all(1)  # agents valid on every boundary: no re-anchoring
    assert full.sum() > 5
    poses = detokenize(tok.ids[full], tok.reached[full, 0], tok.types[full], vocab)
    assert poses.shape == (full.sum(), 5 * tok.num_steps + 1, 3)
    np.testing.assert_allclose(poses[:, ::5], tok.reached[full], atol=1e-3)
    rec, _ = reconstruct(tok, vocab, sc.num_frames)
    b0 = tok.boundaries[0]
    np.testing.assert_allclose(poses[..., :2], rec[full, b0 : b0 + poses.shape[1], :2], atol=1e-3)
    # batch dims: [2 scenes-or-rollouts, agents, S]
    stacked = detokenize(np.stack([tok.ids[full]] * 2), np.stack([tok.reached[full, 0]] * 2), np.stack([tok.types[full]] * 2), vocab)
    np.testing.assert_array_equal(stacked[1], poses)


def test_token_grid_puts_the_current_frame_on_a_boundary():
    assert token_boundaries(10, 91).tolist() == list(range(0, 91, 5))
    assert token_boundaries(49, 110)[0] == 4 and 49 in token_boundaries(49, 110)


def _one_vehicle(poses: np.ndarray, valid: np.ndarray) -> Tracks:
    t = len(poses)
    return Tracks(ids=[1], types=[AgentType.VEHICLE], position=np.concatenate([poses[None, :, :2], np.zeros((1, t, 1))], -1),
                  heading=poses[None, :, 2], velocity=np.zeros((1, t, 2)), size=np.full((1, t, 3), 2.0), valid=valid[None])


def _tokenize_one(tracks: Tracks, vocab, current_frame=10):
    return tokenize_tracks(tracks.position, tracks.heading, tracks.valid, tracks.types, vocab,
                           token_boundaries(current_frame, tracks.num_frames))


def test_agent_appearing_late_starts_at_its_first_valid_boundary(vocab):
    sc = synthetic_scenario(0)
    late = int(np.flatnonzero(~sc.tracks.valid[:, 0])[0])
    first = int(np.argmax(sc.tracks.valid[late]))  # 15 in the synthetic scene
    tok = tokenize_motion(sc, vocab)
    k0 = int(np.argmax(tok.valid[late]))
    assert tok.boundaries[k0] == -(-first // 5) * 5 and not tok.valid[late, :k0].any()
    np.testing.assert_allclose(tok.reached[late, k0, :2], sc.tracks.position[late, tok.boundaries[k0], :2], atol=1e-5)


def test_gap_reanchors_to_the_ground_truth(vocab):
    t = np.arange(91) * 0.1
    poses = np.stack([8.0 * t, 0.5 * np.sin(t), np.zeros(91)], -1)
    poses[:, 2] = np.arctan2(np.gradient(poses[:, 1]), np.gradient(poses[:, 0]))
    valid = np.ones(91, bool)
    valid[42:53] = False  # a gap over boundaries 45 and 50
    tok = _tokenize_one(_one_vehicle(poses, valid), vocab)
    assert tok.valid[0].tolist() == [k not in (8, 9, 10) for k in range(18)]  # tokens 40-45, 45-50, 50-55
    np.testing.assert_allclose(tok.start_pose[0, 11, :2], poses[55, :2], atol=1e-5)  # re-anchored exactly
    assert tok.reached_valid[0].tolist() == [k not in (9, 10) for k in range(19)]
    rec, rv = reconstruct(tok, vocab, 91)
    assert not rv[0, 41:55].any() and rv[0, 55:].all()
    assert np.linalg.norm(rec[0, 55:, :2] - poses[55:, :2], axis=-1).mean() < 0.3


def test_parked_car_takes_a_zero_motion_token(vocab):
    poses = np.tile([[3.0, -7.0, 1.2]], (91, 1))
    tok = _tokenize_one(_one_vehicle(poses, np.ones(91, bool)), vocab)
    end = vocab[AgentType.VEHICLE].poses[tok.ids[0], -1]
    assert np.abs(end[:, :2]).max() < 0.05 and np.abs(end[:, 2]).max() < 0.02
    rec, _ = reconstruct(tok, vocab, 91)
    assert np.linalg.norm(rec[0, :, :2] - poses[:, :2], axis=-1).max() < 0.1


def test_reversing_vehicle_takes_backward_tokens(real_snippets, real_vocab):
    snip, _ = real_snippets
    vocab = real_vocab  # SUMO's vehicles never reverse
    assert (snip[AgentType.VEHICLE][:, -1, 0] < -0.3).sum() >= 5  # the real scenes hold a few reversing snippets
    assert (vocab[AgentType.VEHICLE].poses[:, -1, 0] < -0.3).sum() >= 3  # and k-disks keeps some (rare, but far from the rest)
    t = np.arange(91) * 0.1
    poses = np.stack([10.0 - 1.0 * t, np.zeros(91), np.zeros(91)], -1)  # heading +x, moving -x at 1 m/s
    tok = _tokenize_one(_one_vehicle(poses, np.ones(91, bool)), vocab)
    end = vocab[AgentType.VEHICLE].poses[tok.ids[0], -1]
    assert (end[:, 0] < 0).mean() > 0.8  # backwards in the agent's own frame
    rec, _ = reconstruct(tok, vocab, 91)
    err = np.linalg.norm(rec[0, :, :2] - poses[:, :2], axis=-1)
    # few reversing snippets in the data, so few backward tokens: coarser than forward driving
    assert err.mean() < 1.0 and np.abs(wrap_angle(rec[0, :, 2] - poses[:, 2].astype(np.float32))).mean() < 0.1


def test_pose_composition_round_trips():
    rng = np.random.default_rng(0)
    origin, local = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    np.testing.assert_allclose(relative_poses(compose_poses(origin, local), origin), local, atol=1e-9)


# ------------------------------------------------------------------------------ vocabulary files
def test_vocabulary_file_round_trip_and_versioned_json(vocab, tmp_path):
    npz, js = save_motion_vocabulary(vocab, tmp_path / "motion_256")
    meta = json.loads(js.read_text())
    assert meta["format"] == "smart-marl-vocabulary" and meta["version"] == 1 and meta["kind"] == "motion"
    assert meta["content_hash"] == vocab.content_hash()
    assert meta["types"]["vehicle"]["box_length_m"] == 4.8 and meta["types"]["cyclist"]["size"] == 256
    assert meta["types"]["pedestrian"]["tolerance_m"] == vocab[AgentType.PEDESTRIAN].tolerance_m
    assert {s["source"] for s in meta["provenance"]["scenes"]} == {"sumo"}
    back = load_motion_vocabulary(npz, expected_hash=vocab.content_hash())
    for t in MOTION_TYPES:
        np.testing.assert_array_equal(back[t].poses, vocab[t].poses)
    with pytest.raises(VocabularyFileError, match="expected"):
        load_motion_vocabulary(npz, expected_hash="0" * 64)
    meta["version"] = 99
    js.write_text(json.dumps(meta))
    with pytest.raises(VocabularyFileError, match="version 99"):
        load_motion_vocabulary(npz)
    meta["version"] = 1
    js.write_text(json.dumps(meta))
    arrays = dict(np.load(npz))
    arrays["veh.poses"] = arrays["veh.poses"] + np.float32(0.0)
    arrays["veh.poses"][3, 5, 0] += 1.0
    arrays["veh.contour"] = box_contour(arrays["veh.poses"], 4.8, 2.0).astype(np.float32)
    np.savez(npz, **arrays)
    with pytest.raises(VocabularyFileError, match="content hash"):
        load_motion_vocabulary(npz)


def test_reference_vocabulary_loads_as_a_yardstick(shared_data):
    ref = load_reference_motion_vocabulary(shared_data / "smart_tokens" / "cluster_frame_5_2048.pkl")
    assert ref.method == "reference" and ref.sizes() == {"vehicle": 2048, "pedestrian": 2048, "cyclist": 2048}
    assert ref[AgentType.VEHICLE].poses[:, -1, 0].max() > 15.0  # 0.5 s at highway speed


def test_cli_vocab_build_writes_loadable_files(shared_data, tmp_path):
    from smart_marl.cli import main
    from smart_marl.tokens import load_road_vocabulary

    src = shared_data / "womd_tfrecord" / "womd_scenario_input.tfrecord"
    assert main(["vocab", "build", str(src), "--sizes", "32,64", "--road-size", "64", "--out", str(tmp_path), "--no-progress"]) == 0
    v64 = load_motion_vocabulary(tmp_path / "motion_64.npz")
    assert v64.sizes()["vehicle"] == 64 and v64.provenance["files"] == [str(src)]
    assert load_motion_vocabulary(tmp_path / "motion_32").sizes() == {"vehicle": 32, "pedestrian": 32}  # no cyclist there
    assert load_road_vocabulary(tmp_path / "road_64").size == 64


def test_cli_vocab_build_on_a_sample_scene_writes_loadable_files(sample_scene_file, tmp_path):
    """The same command on the first sample scene (16 vehicles, 3 pedestrians, 3 cyclists)."""
    from smart_marl.cli import main
    from smart_marl.tokens import load_road_vocabulary

    src = sample_scene_file
    assert main(["vocab", "build", str(src), "--sizes", "16,32", "--road-size", "32", "--out", str(tmp_path), "--no-progress"]) == 0
    v32 = load_motion_vocabulary(tmp_path / "motion_32.npz")
    assert v32.sizes() == {"vehicle": 32, "pedestrian": 32, "cyclist": 32} and v32.provenance["files"] == [str(src)]
    assert load_motion_vocabulary(tmp_path / "motion_16").sizes() == {"vehicle": 16, "pedestrian": 16, "cyclist": 16}
    assert load_road_vocabulary(tmp_path / "road_32").size == 32


def _pair_search_by_brute_force(poses, cur, targets, heading_weight, allowed=None):
    """match_token_path's look-ahead by its definition: every one of the V x V token pairs scored
    (with ``allowed`` [M, V]: every pair whose first token the row allows)."""
    import torch

    from smart_marl.tokens.motion import compose_poses

    p = torch.as_tensor(poses, dtype=torch.float64)[:, 1:]  # (V, 5, 3)
    v = p.shape[0]
    first = p[:, None].expand(v, v, 5, 3)
    second = torch.as_tensor(compose_poses(np.repeat(p[:, -1].numpy()[:, None, None], 5, 2), p.numpy()[None]))
    pair = torch.cat([first, second], 2)  # (V, V, 10, 3): token b placed at the end of token a
    out = []
    for i, (c, t) in enumerate(zip(cur, targets)):
        world = torch.as_tensor(compose_poses(np.repeat(c[None, None, None], 10, 2), pair.numpy()))
        err = (world[..., :2] - t[:, :2]).norm(dim=-1).mean(-1) + heading_weight * torch.as_tensor(
            wrap_angle((world[..., 2] - t[:, 2]).numpy())).abs().mean(-1)
        best = err.amin(1)
        if allowed is not None:
            best = best.masked_fill(~torch.as_tensor(allowed[i]), float("inf"))
        out.append(int(best.argmin()))
    return out


def test_path_matching_look_ahead_equals_scoring_every_token_pair():
    """match_token_path prunes the V x V pairs by a bound (half the first token's error): the same
    choice as scoring every pair, on noisy paths built from token pairs and on random ones."""
    import torch

    from smart_marl.model.checkpoint import load_embedded
    from smart_marl.tokens.motion import compose_poses, match_token_path

    poses = load_embedded().motion_vocab[AgentType.VEHICLE].poses[:160].astype(np.float64)
    rng = np.random.default_rng(0)
    a, b = rng.integers(0, 160, 6), rng.integers(0, 160, 6)
    cur = np.concatenate([rng.normal(0, 5, (6, 2)), rng.uniform(-np.pi, np.pi, (6, 1))], 1)
    local = np.concatenate([poses[a, 1:], compose_poses(poses[a, -1][:, None], poses[b, 1:])], 1)
    local = local + rng.normal(0, 0.2, local.shape)
    local[-2:] = rng.normal(0, 3, (2, 10, 3))  # two paths no pair follows
    targets = compose_poses(cur[:, None], local)
    got = match_token_path(torch.from_numpy(poses), 160, torch.from_numpy(cur), torch.from_numpy(targets), 2.0)
    assert got.tolist() == _pair_search_by_brute_force(poses, cur, targets, 2.0)
    # restricted to a few first tokens per row (a policy's top k), the pair's second token still any:
    # the best allowed pair, which is not the unrestricted choice where that one is not allowed
    allowed = rng.random((6, 160)) < 0.05
    allowed[np.arange(3), got[:3].numpy()] = True  # rows 0-2 keep their unrestricted choice
    allowed[np.arange(3, 6), got[3:].numpy()] = False
    limited = match_token_path(torch.from_numpy(poses), 160, torch.from_numpy(cur), torch.from_numpy(targets), 2.0,
                               allowed=torch.from_numpy(allowed))
    assert limited.tolist() == _pair_search_by_brute_force(poses, cur, targets, 2.0, allowed)
    assert limited[:3].tolist() == got[:3].tolist() and (limited[3:] != got[3:]).all()
    assert allowed[np.arange(6), limited.numpy()].all()
