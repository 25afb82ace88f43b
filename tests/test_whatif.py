"""What-if scenarios (agents.whatif): each kind's effect and the ``smart-marl whatif`` command on the
package's sample scene sumo-7-000000-02; the YAML scripts the package ships (agents/whatif/examples,
written for the embedded sample scene sumo-7-000000-03) on that scene.

The mechanics use a small randomly initialised SMART model whose motion vocabulary is built from
the sample scenes (a trained prior is not needed for them); the behavioural claim (vehicles behind a
braking car slow down) uses the embedded trained prior, on the real scene and on the sample scene.

Sample-scene facts used below (current frame 10): vehicle 67 leads its lane at 11.4 m/s with 6
(11.9 m/s) 24 m behind it; 26 drives at 6.8 m/s elsewhere; lane 8 has no traffic light.
Real-scene facts: a lane of vehicles driving towards -x at y = -20 m, 1670, 1645, 1630, 1609 from
the back (1609 at 12 m/s)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from agents import scripted
from agents.whatif import (
    EXAMPLES_DIR, Brake, CutIn, Follow, Insert, Jaywalker, Prepared, Remove, StalledVehicle, Stop, TrafficLightOverride, WhatIf,
    WhatIfError, load_script, override_road_lights, prepare, run_whatif, simulate,
)
from smart_marl.rollout import RolloutState
from smart_marl.scenario import SignalState
from smart_marl.tokens import road_pieces

VOCAB = 32  # tokens per type of conftest's sample_vocab
EXAMPLES = EXAMPLES_DIR
EXAMPLE_SCENE = "sumo-7-000000-03"  # the embedded sample scene the shipped examples are written for
LEAD, FOLLOWER, OTHER = 67, 6, 26  # sample scene sumo-7-000000-02 (module docstring)


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture(scope="module")
def scene(sample_scenes):
    return sample_scenes[2]


@pytest.fixture(scope="module")
def vocab(sample_vocab):
    return sample_vocab


@pytest.fixture(scope="module")
def model(sample_model):
    return sample_model


@pytest.fixture(scope="module")
def womd_scene(womd_scenes):
    return womd_scenes[0]


def run(model, vocab, scene, *edits, rollouts=2, steps=16, seed=0):
    prepared = prepare(scene, WhatIf(list(edits)), vocab)
    return prepared, simulate(model, vocab, prepared, rollouts, seed, steps)


def column(sim, track_id):
    return int(np.flatnonzero(sim.scene.tracks.ids == track_id)[0])


# ----------------------------------------------------------------------------- each kind
def test_removed_agents_are_gone_from_every_later_frame_and_the_past_is_unchanged(model, vocab, scene):
    prepared, sim = run(model, vocab, scene, Remove(agents=[LEAD]), Remove(agents=[FOLLOWER], at_s=2.0))
    assert LEAD not in sim.scene.tracks.ids  # removed before the rollout: not even in the history
    k = column(sim, FOLLOWER)
    assert sim.present[:, k, :20].all() and not sim.present[:, k, 20:].any()  # gone from frame 2.0 s on
    # the same seed without the late removal: identical up to the removal, different after
    base = simulate(model, vocab, Prepared(prepared.scene, [], [], [], {}, {}, {}), 2, 0, 16, scripted_on=False)
    np.testing.assert_array_equal(sim.poses[:, :, :20], base.poses[:, :, :20])
    others = np.arange(sim.scene.num_tracks) != k
    assert not np.allclose(np.nan_to_num(sim.poses[:, others, 20:]), np.nan_to_num(base.poses[:, others, 20:]))


@pytest.mark.parametrize("kind,decel", [(Brake, 8.0), (Stop, 3.0)])
def test_braking_car_speed_reaches_zero_within_the_stated_time(model, vocab, scene, kind, decel):
    _, sim = run(model, vocab, scene, kind(agent=LEAD, at_s=1.0, decel_mps2=decel), rollouts=3)
    k = column(sim, LEAD)
    speed = sim.speed_mps()[:, k]  # (R, T), frame j ends at (j + 1) * 0.1 s
    onset = 10  # frames: brake from 1.0 s
    v0 = speed[:, onset - 1]
    assert (v0 > 2.0).all()  # it was moving when the brake started (the random test model: 2.4, 9.3, 9.3 m/s)
    xy = sim.poses[:, k, :, :2]
    token_speed = np.linalg.norm(xy[:, 9::5][:, 1:] - xy[:, 9::5][:, :-1], axis=-1) / 0.5  # (R, 15) per token after 1.0 s
    for r in range(3):
        # stopped (under 0.3 m/s over every later token) one token after v0 / decel at the latest
        stop_token = int(np.ceil(scripted.stop_time_s(v0[r], decel) / 0.5)) + 1
        assert token_speed[r, stop_token:].max() < 0.3, (r, token_speed[r].round(2))
        assert speed[r, -10:].max() < 0.05  # and standing still at the end
        # where the braking distance v0^2 / 2a says
        travelled = np.linalg.norm(xy[r, -1] - xy[r, onset - 1])
        assert abs(travelled - v0[r] ** 2 / (2 * decel)) < 1.5, (travelled, v0[r] ** 2 / (2 * decel))
        assert sim.scripted[r, k, onset:].all() and not sim.scripted[r, k, :onset].any()


def test_inserted_pedestrian_follows_the_given_path(model, vocab, scene):
    # crosses the road 25 m ahead of vehicle 6, from its right to its left, at 1 m/s after 0.5 s
    edit = Jaywalker(relative_to=FOLLOWER, start=(25, -8), end=(25, 8), speed_mps=1.0, wait_s=0.5)
    prepared, sim = run(model, vocab, scene, edit)
    tid = next(t for t, what in prepared.affected.items() if what == "jaywalker")
    k = column(sim, tid)
    logged = prepared.scene.tracks.position[k, 11:91, :2].astype(np.float64)  # the script, frames 0.1 .. 8 s
    err = np.linalg.norm(sim.poses[:, k, :, :2] - logged[None], axis=-1)
    assert err.max() < 0.6, err.max()
    # it really walks: at 8 s it has walked 7.5 m across
    walked = np.linalg.norm(sim.poses[:, k, -1, :2] - logged[0], axis=-1)
    assert np.all(np.abs(walked - 7.5) < 0.6), walked


def test_inserted_agent_with_tokens_moves_by_exactly_those_tokens(model, vocab, scene):
    tokens = [int(t) for t in np.random.default_rng(0).integers(0, VOCAB, 6)]
    edit = Insert(type="vehicle", relative_to=FOLLOWER, pose=(12, 0, 0), tokens=tokens, speed_mps=5.0, id=99999)
    prepared, sim = run(model, vocab, scene, edit, steps=6)
    k = column(sim, 99999)
    start = prepared.scene.tracks.position[k, 10, :2].astype(np.float64)
    pose = np.array([*start, prepared.scene.tracks.heading[k, 10]], np.float64)
    from smart_marl.tokens import compose_poses

    out = []
    for tok in tokens:
        placed = compose_poses(pose, vocab[0].poses[tok, 1:].astype(np.float64))
        out.append(placed)
        pose = placed[-1]
    expected = np.concatenate(out)[4::5]  # each token's end (the frames in between are the rollout's Hermite curve)
    ends = sim.poses[:, k, 4::5]
    np.testing.assert_allclose(ends, np.broadcast_to(expected, ends.shape), atol=2e-3)


def test_follow_tokens_forces_exactly_those_tokens_from_the_onset(model, vocab, scene):
    tokens = [3, 7, 7, 1]
    _, sim = run(model, vocab, scene, Follow(agent=OTHER, at_s=1.0, tokens=tokens), steps=8)
    k = column(sim, OTHER)
    from smart_marl.tokens import compose_poses

    pose = sim.poses[:, k, 9]  # where the agent is at 1.0 s, per rollout
    for j, tok in enumerate(tokens):  # each token's end is where that token takes it
        placed = compose_poses(pose, np.broadcast_to(vocab[0].poses[tok, 1:].astype(np.float64), (len(pose), 5, 3)).transpose(1, 0, 2))
        np.testing.assert_allclose(sim.poses[:, k, 14 + 5 * j], placed[-1], atol=2e-3)
        pose = placed[-1]
    assert sim.scripted[:, k, 10:30].all() and not sim.scripted[:, k, 30:].any()  # released after the last token


def test_inserted_vehicle_on_a_path_follows_it_then_the_prior_takes_over(model, vocab, scene):
    edit = Insert(type="vehicle", relative_to=FOLLOWER, path=[[12, 0], [40, 0]], speed_mps=8.0, id=99998)
    prepared, sim = run(model, vocab, scene, edit)
    k = column(sim, 99998)
    logged = prepared.scene.tracks.position[k, 11:91, :2].astype(np.float64)
    reach = int(np.ceil(28 / 8.0 / 0.1))  # frames until the path's end
    err = np.linalg.norm(sim.poses[:, k, :reach, :2] - logged[None, :reach], axis=-1)
    # the 32 test tokens of the sample scenes include one at 7.9 m/s: the car stays near the path (measured
    # 0.46 m at most, 0.22 m on average; with the real WOMD scenes' tokens, ~4.5, 6.6, 8, 9.5, 11 m/s, it
    # alternated around 8 m/s: 1.59 m and 0.54 m)
    assert err.max() < 1.0 and err.mean() < 0.4, err
    assert sim.scripted[:, k, :reach].all() and not sim.scripted[:, k, reach + 5:].any()


def test_stalled_vehicle_stays_where_it_is(model, vocab, scene):
    _, sim = run(model, vocab, scene, StalledVehicle(agent=FOLLOWER))
    k = column(sim, FOLLOWER)
    start = scene.tracks.position[np.flatnonzero(scene.tracks.ids == FOLLOWER)[0], 10, :2]
    assert np.linalg.norm(sim.poses[:, k, :, :2] - start, axis=-1).max() < 0.05


def test_new_stalled_vehicle_stands_at_its_pose_and_has_a_standing_history(model, vocab, scene):
    prepared, sim = run(model, vocab, scene, StalledVehicle(relative_to=FOLLOWER, pose=(50, 0, 0)))
    tid = next(iter(prepared.affected))
    k = column(sim, tid)
    tr = prepared.scene.tracks
    assert np.ptp(tr.position[k, :11, :2], axis=0).max() == 0.0  # history: standing still
    assert np.linalg.norm(sim.poses[:, k, :, :2] - tr.position[k, 10, :2], axis=-1).max() < 0.05
    assert prepared.followers[tid] == [LEAD, FOLLOWER]  # the cars in its lane behind it, nearest first


def test_cut_in_shifts_the_agent_by_the_stated_offset(model, vocab, scene):
    prepared, sim = run(model, vocab, scene, CutIn(agent=OTHER, at_s=0.5, lateral_m=-3.7, duration_s=2.0))
    k = column(sim, OTHER)
    onset = sim.poses[:, k, 4]  # pose at 0.5 s
    end = sim.poses[:, k, 24]  # at 2.5 s
    d = end[:, :2] - onset[:, :2]
    lateral = -np.sin(onset[:, 2]) * d[:, 0] + np.cos(onset[:, 2]) * d[:, 1]
    np.testing.assert_allclose(lateral, -3.7, atol=1.0)  # the test vocabulary has 32 vehicle tokens
    assert sim.scripted[:, k, 5:25].all() and not sim.scripted[:, k, 30:].any()  # released after the manoeuvre


def test_traffic_light_override_reaches_the_models_road_encodings(model, vocab, scene):
    tl = scene.traffic_lights
    stop = int(SignalState.STOP)
    # at_s = 0: a scene edit; the road pieces of every signalised lane carry STOP
    prepared = prepare(scene, WhatIf([TrafficLightOverride(lanes="all", state="stop")]), vocab)
    state = RolloutState.start(model, prepared.scene, motion_vocab=vocab)
    pieces = road_pieces(scene.road_map, tl)
    lit = torch.from_numpy(pieces.traffic_light_index >= 0)
    assert lit.any() and (state.road_light[0, : len(lit)][lit] == stop).all()
    # at_s > 0: overriding a running state gives the road encodings and KV-cache road rows of a
    # state started on the overridden scene, and changes the next step's logits
    running = RolloutState.start(model, scene, motion_vocab=vocab)
    before = running.cache.road_rows.clone()
    override_road_lights(running, pieces.traffic_light_index, np.arange(len(tl.lane_ids)), stop)
    torch.testing.assert_close(running.road_x, state.road_x)
    torch.testing.assert_close(running.cache.road_rows, state.cache.road_rows)
    assert not torch.allclose(before, running.cache.road_rows)
    torch.testing.assert_close(running.logits(), state.logits())
    assert len(prepared.approaching[0][1]) >= 3  # vehicles in front of the scene's stop lines, whose speeds the table reports
    # the scene's signal states (what the animation and the realism metric read) change from the onset frame
    later = prepare(scene, WhatIf([TrafficLightOverride(lanes=[int(tl.lane_ids[0])], state="go", at_s=1.0)]), vocab)
    assert later.lights[0][0] == 2 and (later.scene.traffic_lights.states[20:, 0] == int(SignalState.GO)).all()
    np.testing.assert_array_equal(later.scene.traffic_lights.states[:20], tl.states[:20])


@pytest.mark.parametrize("edit", [Remove(agents=[LEAD], at_s=2.0), Brake(agent=LEAD, at_s=30.0)])
def test_an_edit_after_the_rollouts_end_is_refused_before_anything_runs(scene, edit):
    """Issue 34: an onset at or after the last step (at_s 30 with 4 steps = 2 s) never happens; it is refused up
    front, naming the edit and the rollout's end, instead of failing after both simulations."""
    with pytest.raises(WhatIfError, match=r"edit 0: .*at_s .* is at or after the rollout's end \(4 steps = 2 s\)"):
        run_whatif("no-such-checkpoint", scene, WhatIf([edit]), num_rollouts=2, seed=3, num_steps=4, realism=False)


def test_table_reports_the_braking_cars_speed_drop(model, vocab, scene):
    result = run_whatif(model, scene, WhatIf([Brake(agent=LEAD, at_s=1.0)]), num_rollouts=2, seed=0, num_steps=16)
    rows = {(r["quantity"], r["agent"]): r for r in result.table}
    final = rows[("final_speed_mps", f"{LEAD} (brake)")]
    assert final["whatif"] < 0.3 and final["baseline"] > 1.0
    assert ("followers_mean_speed_after_onset_mps", f"1 behind {LEAD}") in rows  # vehicle 6
    realism = rows[("realism_meta_metric", "unedited agents")]
    assert 0.0 < realism["baseline"] < 1.0 and 0.0 < realism["whatif"] < 1.0


# ------------------------------------------------------------------------------- scripts
@pytest.fixture(scope="module")
def example_scene_and_vocab():
    from smart_marl.embedded import sample_scenarios
    from smart_marl.model.checkpoint import load_prior

    return next(s for s in sample_scenarios() if s.scenario_id == EXAMPLE_SCENE), load_prior("embedded")[1]


@pytest.mark.parametrize("name", sorted(p.stem for p in EXAMPLES.glob("*.yaml")))
def test_example_scripts_parse_and_apply_to_the_embedded_scene(example_scene_and_vocab, name):
    scene, vocab = example_scene_and_vocab
    script = load_script(EXAMPLES / f"{name}.yaml")
    prepared = prepare(scene, script, vocab)
    assert script.name and script.description
    assert prepared.affected or prepared.lights or prepared.scene.traffic_lights.states[11:].tolist() != scene.traffic_lights.states[11:].tolist()


def test_every_kind_has_an_example_script():
    from agents.whatif import KINDS

    kinds = set()
    for p in EXAMPLES.glob("*.yaml"):
        kinds |= {e["kind"] for e in __import__("yaml").safe_load(p.read_text())["edits"]}
    assert kinds == set(KINDS)


@pytest.mark.parametrize("text,problem", [
    ("edits: [{kind: teleport, agent: 1}]", "unknown kind 'teleport'"),
    ("edits: [{kind: brake, agent: 67, decel: 3}]", "unknown keys ['decel']"),
    ("edits: [{kind: brake, agent: 424242}]", "agent 424242 is not a track"),
    ("edits: [{kind: brake, agent: 67, at_s: -1}]", "at_s must be >= 0"),
    ("edits: [{kind: traffic_light, lanes: [8], state: stop}]", "lanes [8] have no traffic light"),
    ("edits: [{kind: traffic_light, state: purple}]", "state must be one of"),
    ("name: x", "'edits' list"),
])
def test_bad_scripts_raise_errors_that_name_the_file_and_the_edit(vocab, scene, tmp_path, text, problem):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(WhatIfError) as info:
        prepare(scene, load_script(path), vocab)
    assert str(path) in str(info.value) and problem in str(info.value)


# ------------------------------------------------------------------------------- command
def test_whatif_command_writes_the_table_and_the_animation(model, vocab, sample_scenes, sample_scene_file, tmp_path, capsys):
    pytest.importorskip("imageio", reason="the render extra is not installed")
    from smart_marl.cli import main
    from smart_marl.model.checkpoint import save_checkpoint
    from smart_marl.tokens import build_road_vocabulary

    local = np.concatenate([road_pieces(s.road_map, s.traffic_lights).local for s in sample_scenes])
    ckpt = save_checkpoint(tmp_path / "tiny", model, vocab, build_road_vocabulary(local, 8, seed=0, progress=False))
    script = tmp_path / "brake.yaml"  # on the first sample scene (sumo-7-000000-00): its SDC, 51, at 7.7 m/s
    script.write_text("name: the SDC brakes hard\ndescription: Vehicle 51 brakes at 8 m/s^2 one second in.\n"
                      "edits:\n  - {kind: brake, agent: 51, at_s: 1.0, decel_mps2: 8.0}\n")
    out = tmp_path / "out"
    args = ["whatif", str(sample_scene_file), "--script", str(script), "--out", str(out),
            "--checkpoint", str(ckpt), "--rollouts", "2", "--steps", "4", "--seed", "1", "--no-realism"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "51 (brake)" in printed and "the SDC brakes hard" in printed
    rows = list(csv.DictReader((out / "table.csv").open()))
    assert {"colliding_agents_per_rollout", "final_speed_mps", "min_distance_m"} <= {r["quantity"] for r in rows}
    import imageio.v3 as iio

    frames = iio.imread(out / "whatif.gif")
    assert frames.shape[0] == 20 and frames.shape[2] > frames.shape[1]  # 4 steps x 5 frames, side by side
    bad = tmp_path / "bad.yaml"
    bad.write_text("edits: [{kind: brake, agent: 424242}]")
    assert main(args[:2] + ["--script", str(bad)] + args[4:]) == 1
    assert "bad.yaml" in capsys.readouterr().err


# ------------------------------------------------------------------------ the trained prior
def _hard_brake(scene, lead: int):
    """The embedded prior with and without ``lead`` braking at 8 m/s2 at 1 s (8 rollouts, seed 0)."""
    return run_whatif(None, scene, WhatIf([Brake(agent=lead, at_s=1.0, decel_mps2=8.0)]), num_rollouts=8, seed=0,
                      num_steps=12, realism=False)


@pytest.fixture(scope="module")
def hard_brake(womd_scene):
    # 1609 leads its lane at 12 m/s with 1630 (27 m behind) and 1645 behind it; it brakes hard at 1 s
    return _hard_brake(womd_scene, 1609)


@pytest.fixture(scope="module")
def sample_hard_brake(scene):
    # 67 leads its lane at 11.4 m/s with 6 (11.9 m/s) 24 m behind it; it brakes hard at 1 s
    return _hard_brake(scene, LEAD)


def _check_followers_slow_down(result, lead: int, follower: int) -> None:
    sb, sp = result.baseline.speed_mps(), result.perturbed.speed_mps()
    k = column(result.baseline, lead)
    assert np.nanmean(sb[:, k, :10]) > 5.0  # under the prior it was driving on, so the brake is a real change
    rows = {(r["quantity"], r["agent"]): r for r in result.table}
    follow = [r for (q, _), r in rows.items() if q == "followers_mean_speed_after_onset_mps"]
    assert follow and follow[0]["whatif"] < follow[0]["baseline"] - 0.5
    # the nearest follower is slower over the last 2 s than without the brake
    kb, kp = column(result.baseline, follower), column(result.perturbed, follower)
    assert np.nanmean(sp[:, kp, -20:]) < np.nanmean(sb[:, kb, -20:])


def test_vehicles_behind_a_braking_car_slow_down_under_the_prior(hard_brake):
    """With the embedded prior, 8 rollouts, seed 0, one torch thread. Measured with the prior of
    issue 13 (stage 2): followers' mean speed after the onset 11.06 m/s without the brake -> 9.03
    with it (the previous prior, which slowed everyone down: 6.28 -> 5.33)."""
    _check_followers_slow_down(hard_brake, 1609, 1630)


def test_vehicles_behind_a_braking_car_slow_down_under_the_prior_on_a_sample_scene(sample_hard_brake):
    """The same on the sample scene (SUMO, like the prior's training data): 67 brakes, 6 follows."""
    _check_followers_slow_down(sample_hard_brake, LEAD, FOLLOWER)


def test_the_braking_car_is_never_hit_from_behind_with_collision_aware_sampling(hard_brake):
    """Sampled plainly, the issue-13 priors' followers slow down too little for an 8 m/s2 stop and hit
    the braking car in 5-7 of 8 rollouts (the stage-1 prior: 0 of 8, because it drove everyone at half
    speed). Collision-aware sampling (smart_marl.rollout.avoidance, the default) brings it to 0 of 8
    with the stage-5 prior (issue 33's target, pinned; since issue 33 the rule also sees the braking
    car's forced token where it really goes); see docs/model_card.md, Limits."""
    rows = {(r["quantity"], r["agent"]): r for r in hard_brake.table}
    assert rows[("collided_rate", "1609 (brake)")]["whatif"] == 0.0


@pytest.mark.xfail(strict=True, reason="issue 33's target for the weights alone (at most 1 of 8 sampled plainly) is "
                                       "not met: the stage-5 prior's follower hits the braking car in 5 of 8")
def test_the_braking_car_is_rarely_hit_from_behind_sampled_plainly(womd_scene):
    """The same what-if sampled plainly (no collision-aware rule): the weights' own answer."""
    result = run_whatif(None, womd_scene, WhatIf([Brake(agent=1609, at_s=1.0, decel_mps2=8.0)]), num_rollouts=8, seed=0,
                        num_steps=12, realism=False, avoid_collisions=False)
    rows = {(r["quantity"], r["agent"]): r for r in result.table}
    assert rows[("collided_rate", "1609 (brake)")]["whatif"] <= 1 / 8


def test_the_braking_car_is_rarely_hit_from_behind_on_a_sample_scene(sample_hard_brake):
    rows = {(r["quantity"], r["agent"]): r for r in sample_hard_brake.table}
    assert rows[("collided_rate", f"{LEAD} (brake)")]["whatif"] <= 0.25
