"""Scoring windows (issue 59 part 2): ``eval`` scores any scene with 1.1 s of history and 8 s of future at
10 Hz through a 91-frame window (``--window current|all|FRAME``), resampling other rates to 10 Hz.

Pinned here: a WOMD scene scored through its own window gives exactly its plain score; the cut, the list
of windows and the resampling are right on synthetic scenes; the shared Argoverse 2 and nuScenes scenes
are scored; a scene with neither a self-driving car nor tracks to predict is scored around an anchor (the
agent that moves farthest, ties by id) and its nearest neighbours, up to 9 (the shared Nocturne and
GPUDrive scenes), while a scene with a self-driving car keeps it as the anchor; ``--window all`` at scale
merges to the single-process numbers; bad values exit 2."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from smart_marl.metrics import aggregate, logged_scene, score_rollouts
from smart_marl.metrics.baselines import policy_rollouts
from smart_marl.metrics import SceneNotScorableError
from smart_marl.metrics.windows import (EVALUATED_BY, EVALUATED_MAX_TRACKS, ResampleError, WindowError, anchor_track,
                                        cut_window, evaluated_by, evaluated_tracks, frame_step_s, rule_tracks,
                                        scene_windows, to_10hz, window_frames)
from smart_marl.readers import read_scenarios
from smart_marl.readers.scene_cache import write_shard
from smart_marl.scenario import AgentType, Scenario, Tracks
from smart_marl.synthetic import synthetic_scenario

from helpers import run_eval

FAST = ["--policy", "constant_velocity", "--rollouts", "2", "--json"]


def _ok(argv: list[str]) -> dict:
    code, out, err = run_eval(argv)
    assert code == 0, err
    return json.loads(out)


# ------------------------------------------------------------------------ WOMD: the same numbers
def test_a_womd_scene_scored_through_its_own_window_equals_its_plain_score(shared_data):
    path = shared_data / "womd_tfrecord" / "motion_data_one_scenario.tfrecord"
    [scenario] = read_scenarios(path)
    rollouts = policy_rollouts("constant_velocity", scenario, 2, 0)
    for rules in ("2024", "2025"):
        plain = score_rollouts(logged_scene(scenario), rollouts, rules)
        [window] = scene_windows(scenario, "current")
        assert window.scenario.scenario_id == scenario.scenario_id and window.frame == 10 and window.shifted is None
        windowed = score_rollouts(window.logged(), policy_rollouts("constant_velocity", window.scenario, 2, 0), rules)
        assert dataclasses.asdict(windowed) == dataclasses.asdict(plain)  # meta-metric, every likelihood, minADE: bit for bit
    # the command: the default, `--window 10` and `--window all` (one window, 637f20cafde22ff8@10) print the plain numbers
    want = aggregate([plain], "2025")
    for extra in ([], ["--window", "10"], ["--window", "all"]):
        got = _ok(["--scenes", str(path), *FAST, *extra])
        assert got["skipped"] == [] and got["num_scenarios"] == 1
        keys = ("meta_metric", "likelihoods", "min_ade")
        assert {k: got[k] for k in keys} == {k: want[k] for k in keys}


# ------------------------------------------------------------------------------- the window cut
def test_the_window_cut_of_a_synthetic_scene():
    scene = synthetic_scenario(seed=3, num_frames=130)
    window = cut_window(scene, 40, "s@40")
    assert window.num_frames == 91 and window.current_frame == 10 and window.scenario_id == "s@40"
    tr, wt = scene.tracks, window.tracks
    for name in ("position", "heading", "velocity", "size", "valid"):
        np.testing.assert_array_equal(getattr(wt, name), getattr(tr, name)[:, 30:121])
    np.testing.assert_array_equal(window.timestamps_s, scene.timestamps_s[30:121])
    np.testing.assert_array_equal(window.traffic_lights.states, scene.traffic_lights.states[30:121])
    np.testing.assert_array_equal(window.traffic_lights.present, scene.traffic_lights.present[30:121])
    assert window.road_map is scene.road_map and window.frame == scene.frame and window.sdc_index == scene.sdc_index
    np.testing.assert_array_equal(window.predict_indices, scene.predict_indices)
    np.testing.assert_array_equal(wt.ids, tr.ids)
    for frame in (9, 50, 200):  # too little history, too little future, beyond the scene
        with pytest.raises(WindowError, match="need 91 frames"):
            cut_window(scene, frame)


def test_window_lists_all_current_and_frame():
    assert window_frames(synthetic_scenario(num_frames=91)) == [10]
    assert window_frames(synthetic_scenario(num_frames=90)) == []
    scene = synthetic_scenario(num_frames=95)
    assert window_frames(scene) == [10, 11, 12, 13, 14]
    every = scene_windows(scene, "all")
    assert [w.frame for w in every] == [10, 11, 12, 13, 14]
    assert [w.scenario.scenario_id for w in every] == [f"{scene.scenario_id}@{f}" for f in range(10, 15)]
    np.testing.assert_array_equal(every[2].scenario.tracks.position, scene.tracks.position[:, 2:93])
    [own] = scene_windows(scene, "current")
    assert own.frame == 10 and own.scenario.scenario_id == scene.scenario_id and own.shifted is None
    [at] = scene_windows(scene, 12)
    assert at.frame == 12 and at.scenario.scenario_id == f"{scene.scenario_id}@12"
    with pytest.raises(WindowError, match="window at current frame 15 does not fit"):
        scene_windows(scene, 15)
    late = dataclasses.replace(scene, current_frame=60)  # AV2-like: the own current frame lacks future
    [near] = scene_windows(late, "current")
    assert near.frame == 14 and near.scenario.scenario_id == f"{scene.scenario_id}@14" and "60" in near.shifted
    with pytest.raises(WindowError, match="no window fits"):
        scene_windows(synthetic_scenario(num_frames=60), "all")
    valid = scene.tracks.valid.copy()  # no one to evaluate at frame 11: `all` leaves that window out
    valid[[scene.sdc_index, *scene.predict_indices], 11] = False
    gap = dataclasses.replace(scene, tracks=dataclasses.replace(scene.tracks, valid=valid))
    assert [w.frame for w in scene_windows(gap, "all")] == [10, 12, 13, 14]
    nobody = dataclasses.replace(scene, sdc_index=-1, predict_indices=np.zeros(0, np.int64), predict_difficulty=None)
    anchored = scene_windows(nobody, "all")  # no SDC, no tracks to predict: the rule around the farthest mover
    assert [w.frame for w in anchored] == [10, 11, 12, 13, 14]
    assert {evaluated_by(w) for w in anchored} == {EVALUATED_BY[2]}
    frozen = _frozen(nobody)  # ... and when no agent moves 2 m, no one to evaluate anywhere
    with pytest.raises(WindowError, match="no agent to evaluate in any of its 5 windows .* nor an agent for the rule to anchor on"):
        scene_windows(frozen, "all")


def test_evaluated_agents_are_wosacs_where_the_scene_has_tracks_to_predict_else_the_rule():
    scene = synthetic_scenario(seed=1, num_frames=100)
    assert len(scene.predict_indices) and scene.sdc_index >= 0
    assert evaluated_tracks(cut_window(scene, 10), own=True) is None  # logged_scene's own choice: SDC + tracks to predict
    no_ttp = dataclasses.replace(scene, predict_indices=np.zeros(0, np.int64), predict_difficulty=None)
    window = cut_window(no_ttp, 10)
    chosen = evaluated_tracks(window, own=True)
    tr = window.tracks
    others = [int(i) for i in chosen if i != window.sdc_index]
    assert window.sdc_index in chosen and 0 < len(others) <= EVALUATED_MAX_TRACKS
    for i in others:  # valid now and on half the future, moving
        assert tr.valid[i, 10] and tr.valid[i, 11:].sum() >= 40
        assert np.linalg.norm(tr.position[i, tr.valid[i], :2] - tr.position[i, 10, :2], axis=-1).max() >= 2.0
    assert sorted(logged_scene(window, chosen).evaluated_ids) == sorted(tr.ids[chosen].tolist())


# ------------------------------------------------------------------ the rule's anchor without an SDC
def _frozen(scene: Scenario) -> Scenario:
    """``scene`` with every track standing at its current-frame position all along (no one moves)."""
    tr = scene.tracks
    position = np.repeat(tr.position[:, scene.current_frame:scene.current_frame + 1], scene.num_frames, axis=1)
    return dataclasses.replace(scene, tracks=dataclasses.replace(tr, position=position))


def _straight_scene(at, steps, types=None, ids=None, sdc=-1, future_frames=None) -> Scenario:
    """A 91-frame scene (current frame 10), no tracks to predict: track k at ``at[k]`` (x, y) at the current frame,
    moving ``steps[k]`` m a frame along +x (multiples of 1/8 m: every distance exact in float32), valid on every
    frame, or up to frame ``10 + future_frames[k]``; vehicles unless ``types``; ids 1.. unless ``ids``."""
    base = synthetic_scenario(seed=11)
    n, t = len(at), 91
    at, steps = np.asarray(at, np.float64), np.asarray(steps, np.float64)
    position = np.zeros((n, t, 3), np.float32)
    position[:, :, 0] = at[:, :1] + steps[:, None] * (np.arange(t) - 10)
    position[:, :, 1] = at[:, 1:2]
    valid = np.ones((n, t), bool)
    for k, count in enumerate(future_frames or [80] * n):
        valid[k, 11 + count:] = False
    tracks = Tracks(ids=np.asarray(ids if ids is not None else np.arange(1, n + 1), np.int64),
                    types=np.asarray(types if types is not None else [AgentType.VEHICLE] * n, np.int8),
                    position=position, heading=np.zeros((n, t), np.float32), velocity=np.zeros((n, t, 2), np.float32),
                    size=np.tile(np.array([4.5, 2.0, 1.5], np.float32), (n, t, 1)), valid=valid)
    return dataclasses.replace(base, scenario_id="straight", tracks=tracks, sdc_index=sdc,
                               predict_indices=np.zeros(0, np.int64), predict_difficulty=None)


def _ids(scene: Scenario, chosen) -> list[int]:
    return sorted(int(i) for i in scene.tracks.ids[np.asarray(chosen, np.int64)])


def test_without_sdc_or_tracks_to_predict_the_anchor_is_the_eligible_agent_that_moves_farthest_ties_by_id():
    # ids 1..6: an OTHER and a vehicle logged on 39 future frames move farthest but may not anchor; 3 and 5 tie
    at = [(0, 0), (10, 0), (20, 0), (30, 0), (40, 0), (50, 0)]
    steps = [1.0, 1.0, 0.375, 0.25, 0.375, 0.125]  # 80 m, 80 m, 30 m, 20 m, 30 m, 10 m over the 80 future frames
    types = [AgentType.OTHER, *[AgentType.VEHICLE] * 5]
    scene = _straight_scene(at, steps, types=types, future_frames=[80, 39, 80, 80, 80, 80])
    assert anchor_track(scene) == 2  # id 3: travels 30 m like id 5, the lower id
    assert _ids(scene, evaluated_tracks(scene, own=True)) == [3, 4, 5, 6]  # ids 1 and 2 are not eligible at all
    [window] = scene_windows(scene)
    assert evaluated_by(window) == EVALUATED_BY[2] and window.logged().evaluated_ids.tolist() == [3, 4, 5, 6]
    farther = _straight_scene(at, [*steps[:4], 0.5, steps[5]], types=types, future_frames=[80, 39, 80, 80, 80, 80])
    assert anchor_track(farther) == 4  # id 5 now travels 40 m
    on_40 = _straight_scene(at, steps, types=types, future_frames=[80, 40, 80, 80, 80, 80])
    assert anchor_track(on_40) == 1  # logged on 40 of the 80 future frames (11-50): eligible, and its 40 m the farthest


def test_the_anchors_neighbours_are_the_nearest_eligible_agents_at_most_9_in_all():
    # the anchor (id 1, 40 m) at x = 0; twelve eligible agents at |x| = 5, 10, ... 60 in turn left and right; beside
    # the anchor a car creeping 1.875 m, a pedestrian logged on 39 future frames, and an OTHER
    offsets = [5.0 * k * (-1) ** k for k in range(1, 13)]
    at = [(0, 0), *[(x, 3.5) for x in offsets], (1, 1), (2, 1), (3, 1)]
    steps = [0.5, *[0.125] * 12, 0.0234375, 0.25, 0.25]
    types = [*[AgentType.VEHICLE] * 14, AgentType.PEDESTRIAN, AgentType.OTHER]
    future = [80] * 14 + [39, 80]
    scene = _straight_scene(at, steps, types=types, future_frames=future)
    assert anchor_track(scene) == 0
    nearest = rule_tracks(scene, 0)
    assert len(nearest) == EVALUATED_MAX_TRACKS == 8
    assert [int(scene.tracks.ids[i]) for i in nearest] == list(range(2, 10))  # 5 m, 10 m, ... 40 m from the anchor, in order
    chosen = evaluated_tracks(scene, own=True)
    assert _ids(scene, chosen) == list(range(1, 10)) and len(chosen) == EVALUATED_MAX_TRACKS + 1
    # ties in distance go by id: the same two neighbours, ids swapped in order
    twin = _straight_scene([(0, 0), (5, 0), (-5, 0)], [0.5, 0.125, 0.125], ids=[1, 9, 4])
    assert [int(twin.tracks.ids[i]) for i in rule_tracks(twin, 0)] == [4, 9]
    # no one eligible: no agent to evaluate, named with its three reasons
    [window] = scene_windows(_frozen(scene))
    assert window.evaluated is None and evaluated_by(window) is None
    with pytest.raises(SceneNotScorableError, match="straight: no agent to evaluate: no self-driving car, no track to "
                                                    "predict, and no agent for the rule to anchor on .none of its "
                                                    "vehicles, pedestrians or cyclists valid at the current frame and "
                                                    "on at least 40 of the 80 future frames and moving at least 2 m"):
        window.logged()


def test_a_scene_with_a_self_driving_car_keeps_it_as_the_anchor():
    # the SDC (id 1) moves 10 m; id 2 moves 80 m and would anchor a scene without one; the rule goes around the SDC
    at = [(0, 0), (100, 0), *[(5.0 * k, 3.5) for k in range(1, 11)]]
    steps = [0.125, 1.0, *[0.125] * 10]
    scene = _straight_scene(at, steps, sdc=0)
    nearest = [int(scene.tracks.ids[i]) for i in rule_tracks(scene)]
    assert nearest == list(range(3, 11))  # the 8 nearest the SDC, not id 2 far away
    chosen = evaluated_tracks(scene, own=True)
    assert _ids(scene, chosen) == [1, *range(3, 11)]
    [window] = scene_windows(scene)
    assert evaluated_by(window) == EVALUATED_BY[1] and window.logged().evaluated_ids.tolist() == [1, *range(3, 11)]
    assert anchor_track(scene) == 1  # what the anchor would be without the SDC
    valid = scene.tracks.valid.copy()
    valid[0, 10] = False  # an SDC not valid at the current frame cannot anchor: the farthest mover does
    lost = dataclasses.replace(scene, tracks=dataclasses.replace(scene.tracks, valid=valid))
    assert _ids(lost, evaluated_tracks(lost, own=True)) == [2, *range(5, 13)]
    with pytest.raises(SceneNotScorableError, match="its self-driving car .object 1. is not valid at the current frame"):
        scene_windows(_frozen(lost))[0].logged()
    # a scene with tracks to predict never anchors: its own window is WOSAC's, SDC and tracks to predict
    ttp = dataclasses.replace(scene, predict_indices=np.array([5], np.int64), predict_difficulty=None)
    assert evaluated_tracks(ttp, own=True) is None
    [window] = scene_windows(ttp)
    assert evaluated_by(window) == EVALUATED_BY[0] and window.logged().evaluated_ids.tolist() == [1, 6]


def test_the_shared_nocturne_and_gpudrive_scenes_are_scored_around_their_anchor(shared_data):
    for folder, count in (("nocturne_json", 3), ("gpudrive_json", 11)):
        if not (shared_data / folder).is_dir():
            pytest.skip(f"../shared/data/{folder} is absent")
    scenes = read_scenarios(shared_data / "nocturne_json" / "example_scenario.json")
    for scene in scenes:  # the rule, checked against its words on a real scene
        assert scene.sdc_index < 0 and not len(scene.predict_indices)
        [window] = scene_windows(scene)
        tr, chosen = window.scenario.tracks, window.evaluated
        now = tr.position[:, 10, :2].astype(np.float64)
        travel = np.where(tr.valid, np.linalg.norm(tr.position[..., :2] - now[:, None], axis=-1), 0).max(axis=1)
        eligible = (np.isin(tr.types, [0, 1, 2]) & tr.valid[:, 10] & (tr.valid[:, 11:].sum(axis=1) >= 40)
                    & (travel >= 2.0))
        anchor = anchor_track(window.scenario)
        assert eligible[anchor] and travel[anchor] == travel[eligible].max() and anchor in chosen
        assert eligible[chosen].all() and len(chosen) == min(9, int(eligible.sum()))
        distance = np.linalg.norm(now - now[anchor], axis=-1)
        left_out = np.setdiff1d(np.flatnonzero(eligible), chosen)
        assert distance[chosen].max() <= distance[left_out].min(initial=np.inf)
        assert evaluated_by(window) == EVALUATED_BY[2]
    for folder, count in (("nocturne_json", 3), ("gpudrive_json", 11)):  # every scene scored, none skipped
        result = _ok(["--scenes", str(shared_data / folder), *FAST])
        assert result["skipped"] == [] and result["num_scenarios"] == count
        assert 0.0 < result["meta_metric"] < 1.0


# --------------------------------------------------------------------------------- resampling
def _at_rate(scene: Scenario, step_s: float, current: int) -> Scenario:
    """``scene`` relabelled as recorded every ``step_s`` seconds (its frames unchanged)."""
    return dataclasses.replace(scene, timestamps_s=np.arange(scene.num_frames) * step_s, current_frame=current)


def test_resampling_2hz_reproduces_a_straight_constant_speed_path_and_turns_through_the_wrap():
    base = synthetic_scenario(seed=2, num_frames=41)  # 41 frames at 2 Hz: 20 s
    n, t = base.tracks.num_tracks, 41
    times = np.arange(t) * 0.5
    position = np.zeros((n, t, 3), np.float32)
    position[0, :, 0] = 12.5 + 8.0 * times  # 8 m/s along +x, then along a diagonal for the others
    position[1:, :, 0] = -30.0 + 3.0 * times
    position[1:, :, 1] = 5.0 - 4.0 * times
    heading = np.zeros((n, t), np.float32)
    heading[2] = (3.0 + 0.2 * np.arange(t) + np.pi) % (2 * np.pi) - np.pi  # a constant yaw rate across +-pi
    valid = np.ones((n, t), bool)
    valid[3, 7] = False
    tracks = Tracks(ids=base.tracks.ids, types=base.tracks.types, position=position, heading=heading,
                    velocity=np.zeros((n, t, 2), np.float32), size=base.tracks.size, valid=valid)
    scene = dataclasses.replace(base, tracks=tracks, timestamps_s=times, current_frame=2)
    up = to_10hz(scene)
    assert up.num_frames == 201 and up.current_frame == 10 and frame_step_s(up) == pytest.approx(0.1)
    t10 = np.arange(201) * 0.1
    np.testing.assert_allclose(up.timestamps_s, t10, atol=1e-12)
    np.testing.assert_allclose(up.tracks.position[0, :, 0], 12.5 + 8.0 * t10, rtol=0, atol=1e-5)
    np.testing.assert_allclose(up.tracks.position[1, :, 1], 5.0 - 4.0 * t10, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(up.tracks.position[:, ::5], scene.tracks.position)  # source frames bit for bit
    want = (3.0 + 0.04 * np.arange(201) + np.pi) % (2 * np.pi) - np.pi  # 0.2 rad per 0.5 s, through the wrap
    np.testing.assert_allclose(np.angle(np.exp(1j * (up.tracks.heading[2] - want))), 0.0, atol=1e-5)
    assert np.all(np.abs(np.diff(np.unwrap(up.tracks.heading[2].astype(np.float64))) - 0.04) < 1e-5)  # never the long way
    assert not up.tracks.valid[3, 31:40].any() and up.tracks.valid[3, 30] and up.tracks.valid[3, 40]  # a gap stays a gap
    np.testing.assert_array_equal(up.traffic_lights.states[::5], scene.traffic_lights.states)
    np.testing.assert_array_equal(up.traffic_lights.states[1:5], np.repeat(scene.traffic_lights.states[:1], 4, axis=0))
    assert [w.frame for w in scene_windows(scene, "all")] == list(range(10, 121))


def test_resampling_20hz_keeps_every_other_frame_and_refuses_what_it_cannot_do():
    scene = _at_rate(synthetic_scenario(seed=4, num_frames=200), 0.05, current=21)
    down = to_10hz(scene)
    assert down.current_frame == 10 and down.num_frames == 100
    np.testing.assert_array_equal(down.tracks.position, scene.tracks.position[:, 1::2])
    base = synthetic_scenario(seed=4, num_frames=30)
    assert to_10hz(base) is base
    for step, says in ((2.0, "a gap larger than 1 s"), (1 / 3, "neither a whole multiple nor a whole fraction")):
        with pytest.raises(ResampleError, match=says):
            to_10hz(_at_rate(base, step, 0))
    gap = dataclasses.replace(base, timestamps_s=np.r_[np.arange(15) * 0.1, 3.0 + np.arange(15) * 0.1])
    with pytest.raises(ResampleError, match="irregular frame times .a gap of 1.6 s between frames 14 and 15"):
        to_10hz(gap)


def test_eval_scores_a_2hz_scene_and_skips_one_it_cannot_resample(tmp_path):
    folder = tmp_path / "scenes"
    folder.mkdir()
    odd = dataclasses.replace(synthetic_scenario(seed=6, num_frames=41), scenario_id="odd")
    write_shard(folder / "a.smsc", [_at_rate(synthetic_scenario(seed=5, num_frames=41), 0.5, 2), _at_rate(odd, 0.25, 2)])
    result = _ok(["--scenes", str(folder), *FAST])
    assert result["num_scenarios"] == 1
    [skip] = result["skipped"]
    assert skip["scenario_id"] == "odd" and "cannot be resampled to 10 Hz" in skip["reason"]


# --------------------------------------------------------------------------- the shared datasets
@pytest.mark.parametrize("folder, count", [("av2", 1), ("scenarionet/nuscenes", 3)])
def test_the_shared_av2_and_nuscenes_scenes_are_scored(shared_data, folder, count):
    if not (shared_data / folder).is_dir():
        pytest.skip(f"../shared/data/{folder} is absent")
    try:
        import pyarrow  # noqa: F401  (the AV2 reader's)
    except ImportError:
        if folder == "av2":
            pytest.skip("pyarrow (the av2 extra) is not installed")
    result = _ok(["--scenes", str(shared_data / folder), *FAST])
    assert result["skipped"] == [] and result["num_scenarios"] == count
    assert 0.0 < result["meta_metric"] < 1.0


# ------------------------------------------------------------------------------- at scale, arguments
def test_window_all_at_scale_merges_to_the_single_process_numbers(tmp_path):
    folder = tmp_path / "scenes"
    folder.mkdir()
    write_shard(folder / "a.smsc", [synthetic_scenario(seed=7, num_frames=94), synthetic_scenario(seed=8, num_frames=50),
                                    dataclasses.replace(synthetic_scenario(seed=9, num_frames=92), scenario_id="b")])
    argv = ["--scenes", str(folder), "--policy", "random", "--rollouts", "2", "--json", "--window", "all"]
    plain = _ok(argv)
    assert plain["num_scenarios"] == 6 and len(plain["skipped"]) == 1 and "no window fits" in plain["skipped"][0]["reason"]
    for count in (1, 2):
        run = tmp_path / f"run{count}"
        for i in range(count):
            code, _, err = run_eval([*argv, "--out", str(run), "--shard", f"{i}/{count}", "--chunk-size", "2"])
            assert code == 0, err
        assert _ok(["--merge", str(run), "--json"]) == plain
        assert json.loads((run / "run.json").read_text())["config"]["window"] == "all"
    default = tmp_path / "default"  # the default keeps a run's identity: no "window" in its config
    code, _, err = run_eval(["--scenes", str(folder), "--policy", "random", "--rollouts", "2", "--json", "--window", "current",
                             "--out", str(default)])
    assert code == 0, err
    assert "window" not in json.loads((default / "run.json").read_text())["config"]


@pytest.mark.parametrize("value", ["9", "-1", "abc", "1.5", "", "10000000"])
def test_bad_window_values_exit_2_with_one_line(value, tmp_path):
    code, _, err = run_eval(["--scenes", str(tmp_path), "--policy", "constant_velocity", "--window", value])
    errors = [line for line in err.splitlines() if "error:" in line]
    assert code == 2 and len(errors) == 1 and "--window" in errors[0], err


def test_merge_takes_the_window_from_the_run(tmp_path):
    code, _, err = run_eval(["--merge", str(tmp_path), "--window", "all"])
    errors = [line for line in err.splitlines() if "error:" in line]
    assert code == 2 and len(errors) == 1 and "leave out --window" in errors[0], err
