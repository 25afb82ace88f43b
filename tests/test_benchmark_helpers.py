"""Helpers of the benchmark scripts that decide what a figure measures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from smart_marl.scenario import AgentType

from helpers import load_benchmark

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_drop_parked_leaves_out_exactly_the_vehicles_that_stand_all_log(sample_scenes):
    """prior_speed_drift --drop-parked: the parked vehicles (on every frame, < 0.5 m over the log) go, every
    other track stays as it was, the self-driving car included."""
    drift = load_benchmark("prior_speed_drift")
    scene = sample_scenes[0]  # sumo-7-000000-00: 22 tracks, most of its vehicles stand at lights or parked
    tr = scene.tracks
    out = drift.without_parked(scene)
    moved = np.linalg.norm(tr.position[:, -1, :2] - tr.position[:, 0, :2], axis=-1)
    parked = (tr.types == int(AgentType.VEHICLE)) & tr.valid.all(1) & (moved < 0.5)
    parked[scene.sdc_index] = False
    assert parked.sum() >= 5
    assert out.num_tracks == scene.num_tracks - parked.sum()
    assert set(out.tracks.ids.tolist()) == set(tr.ids[~parked].tolist())
    assert out.tracks.ids[out.sdc_index] == tr.ids[scene.sdc_index]
    kept = np.flatnonzero(~parked)
    np.testing.assert_array_equal(out.tracks.position, tr.position[kept])


def test_speed_groups_by_horizon_match_the_log_when_the_rollouts_are_the_log(sample_scenes):
    """prior_speed_drift's trend_by_horizon rows: rollouts that replay the log at half its pace give ratio 0.5
    for every log trend and horizon, the groups' agents add up to the late_by_log_trend counts, and the slowing
    group's logged speed at 8 s is below its speed at 0.5 s (the rows are the groups' own speeds)."""
    from types import SimpleNamespace

    drift = load_benchmark("prior_speed_drift")
    sums = drift.SpeedSums.zeros()
    for scene in sample_scenes:
        tr, cf, f = scene.tracks, scene.current_frame, drift.NUM_FRAMES
        if scene.num_frames < cf + 1 + f:
            continue
        now = tr.position[:, cf, None, :2].astype(np.float64)
        half = now + 0.5 * (tr.position[:, cf + 1:cf + 1 + f, :2] - now)  # every agent at half its logged speed
        replay = SimpleNamespace(trajectory=half[None],
                                 simulated=tr.valid[None, :, cf].copy(), agent_types=tr.types[None].copy())
        entry = drift.speed_sums(replay, scene).get(AgentType.VEHICLE)
        if entry is not None:
            sums = sums.plus(entry)
    rows = drift.trend_horizon_rows(sums)
    assert {r.get("log_trend") for r in rows} >= {"keeps", "slows"} and {r.get("past_trend") for r in rows} >= {"steady"}
    for r in rows:
        assert r["ratio"] == 0.5
        if r["kind"] == "trend_by_horizon":
            assert r["agents"] == int(sums.by_trend[drift.TRENDS.index(r["log_trend"]), 3])
    assert sum(sums.past_agents) <= sums.agents
    slows = {r["t_s"]: r["log_mps"] for r in rows if r.get("log_trend") == "slows"}
    assert slows[8.0] < slows[0.5]


def test_past_trend_groups_by_the_speed_change_before_the_current_frame():
    """prior_speed_drift's past groups: more than 10% up, within 10%, more than 10% down (PAST_TRENDS order)."""
    drift = load_benchmark("prior_speed_drift")
    earlier = np.array([10.0, 10.0, 10.0, 10.0, 10.0])
    recent = np.array([11.5, 10.9, 10.0, 9.2, 8.5])
    assert [drift.PAST_TRENDS[g] for g in drift.past_trend(recent, earlier)] == [
        "accelerating", "steady", "steady", "steady", "decelerating"]


def test_speed_change_calibration_rows_read_the_slope_and_the_bins():
    """prior_speed_drift's teacher_forced_dv rows: logged changes half the predicted ones give slope 0.5, and each
    quantile bin holds its share of the rows with the means of its own rows."""
    drift = load_benchmark("prior_speed_drift")
    predicted = np.linspace(-2.0, 2.0, 1001)
    rows = drift.dv_calibration_rows(predicted, 0.5 * predicted + 0.1)
    assert rows[0]["bin"] == "slope" and rows[0]["slope"] == 0.5 and rows[0]["rows"] == 1001
    bins = rows[1:]
    assert [b["bin"] for b in bins] == [list(q) for q in zip(drift.DV_QUANTILES[:-1], drift.DV_QUANTILES[1:])]
    assert sum(b["rows"] for b in bins) == 1001 and bins[0]["rows"] == 50
    for b in bins:
        assert abs(b["target_dv_mps"] - (0.5 * b["predicted_dv_mps"] + 0.1)) < 2e-3  # both rounded to 1e-3
    assert drift.dv_calibration_rows(np.zeros(1), np.zeros(1)) == []
    fast = np.arange(1001) >= 900  # saturated rows with a flat logged change are left out, counted
    mixed = drift.dv_calibration_rows(predicted, np.where(fast, 0.0, 0.5 * predicted + 0.1), fast)
    assert mixed[0]["slope"] == 0.5 and mixed[0]["rows"] == 900 and mixed[0]["saturated_rows_left_out"] == 101


def test_scene_pack_round_trips_the_sample_scenes_within_its_grids(tmp_path):
    """benchmarks/scene_pack.py (how scenes travel to a lent GPU): unpacked scenes are the packed ones, in
    order, with every metric array within half a grid step and everything else equal."""
    from envs._pool import ScenePool

    pack = load_benchmark("scene_pack")
    info = pack.pack(["embedded"], str(tmp_path / "s.npz.xz"), count=None)
    assert pack.unpack(str(tmp_path / "s.npz.xz"), str(tmp_path / "cache")) == {"scenes": info["scenes"]}
    before, after = ScenePool("embedded"), ScenePool(str(tmp_path / "cache"))
    assert len(after) == len(before) == info["scenes"] >= 2
    for i in range(len(before)):
        (a, meta_a), (b, meta_b) = before.scenario(i).to_arrays(), after.scenario(i).to_arrays()
        assert meta_a == meta_b and a.keys() == b.keys()
        for name in a:
            if name in pack.GRIDS:
                step = pack.GRIDS[name][0]
                np.testing.assert_allclose(b[name], a[name], rtol=0, atol=step * 0.51 + 1e-4, err_msg=name)
            else:
                np.testing.assert_array_equal(b[name], a[name], err_msg=name)


def test_gpu_scripts_unpack_a_scene_set_once_and_leave_no_marker_on_failure(tmp_path):
    """benchmarks/gpu_common.sh (sourced by the GPU scripts, two of which may share a machine): gpu_unpack
    makes the scene cache and its marker; called again it leaves the folder alone; an unpack that fails
    (a missing pack) leaves no marker, so the next call tries again."""
    import os
    import subprocess
    import sys

    pack = load_benchmark("scene_pack")
    pack.pack(["embedded"], str(tmp_path / "s.npz.xz"), count=2)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}

    def unpack(packed: str, out: Path) -> None:
        script = f'. benchmarks/gpu_common.sh && gpu_unpack "{packed}" "{out}" "{tmp_path / "log"}"'
        subprocess.run(["bash", "-c", script], cwd=BENCHMARKS.parent, env=env, check=False, timeout=120)

    cache = tmp_path / "cache"
    unpack(str(tmp_path / "s.npz.xz"), cache)
    assert (tmp_path / "cache.done").exists() and (cache / "manifest.json").exists()
    (cache / "manifest.json").unlink()  # a second unpack would write it again
    unpack(str(tmp_path / "s.npz.xz"), cache)
    assert not (cache / "manifest.json").exists()
    unpack(str(tmp_path / "missing.npz.xz"), tmp_path / "other")
    assert not (tmp_path / "other.done").exists()


def test_log_steps_replays_the_tokenized_log_before_the_prior_drives(sample_scenes):
    """prior_speed_drift --log-steps: forced for all 16 steps, every rollout is the tokenized log (the same in
    each rollout, and its speeds within tokenization error of the logged ones); forced for 0, the prior's own draws."""
    from smart_marl.model.checkpoint import load_checkpoint

    drift = load_benchmark("prior_speed_drift")
    ck = load_checkpoint("embedded")
    scene = sample_scenes[2]  # 14 moving vehicles
    full = drift.rollout_speeds(ck, scene, 2, 6, 1.0, 0, log_steps=16)[AgentType.VEHICLE]
    free = drift.rollout_speeds(ck, scene, 2, 6, 1.0, 0, log_steps=0)[AgentType.VEHICLE]
    window = lambda x: x.reshape(-1, 5).sum(1)  # noqa: E731  speeds summed over each token's 0.5 s, the first included
    replayed, drawn = (np.abs(window(r.sim) - window(r.log)).sum() for r in (full, free))
    assert replayed < 0.02 * window(full.log).sum()  # the tokenized log: within its tokens' error (0.8% here)
    assert drawn > 10 * replayed  # the prior does not replay the log by itself
    from smart_marl.rollout import RolloutState

    state = RolloutState.start(ck, [scene], num_rollouts=2, seed=0)
    tokens = drift.logged_tokens(state, scene, 4)
    outs = state.run(4, before_step=lambda st, k, last: tokens[k])
    forced = tokens >= 0
    assert forced.any()
    for k, out in enumerate(outs):
        assert torch.equal(out.tokens[forced[k]], tokens[k][forced[k]])  # the slots with a log take its token



def test_log_steps_for_some_tracks_only(sample_scenes):
    """rollout_from_log(tracks=...): the tracks named follow their tokenized log (their tokens those of a rollout in
    which everyone does), the others are drawn; slowing_causes.queue_leaders names simulated leaders only."""
    from smart_marl.model.checkpoint import load_checkpoint

    drift, causes = load_benchmark("prior_speed_drift"), load_benchmark("slowing_causes")
    ck = load_checkpoint("embedded")
    scene = sample_scenes[2]
    cf = scene.current_frame
    logged_throughout = np.flatnonzero(scene.tracks.valid[:, cf:cf + 81].all(1) & causes.simulated_tracks(scene))
    j = int(logged_throughout[0])
    everyone = drift.rollout_from_log(ck, scene, 16, num_rollouts=2, seed=0)
    one = drift.rollout_from_log(ck, scene, 16, tracks=[j], num_rollouts=2, seed=0)
    assert np.array_equal(one.tokens[:, j], everyone.tokens[:, j])
    others = np.setdiff1d(np.flatnonzero(one.simulated[0]), [j])
    assert not np.array_equal(one.tokens[:, others], everyone.tokens[:, others])
    leaders = causes.queue_leaders(scene)
    assert causes.simulated_tracks(scene)[leaders].all()


def test_departures_count_the_standing_vehicles_that_drive_off_and_read_a_replayed_log_as_the_log(sample_scenes):
    """benchmarks/departures.py: rollouts that replay the tokenized log start every standing vehicle that drives off
    in its log (all rollouts moving at 7-8 s, within tokenization error of its speed); a speed series' first moving
    time is the first frame above 1 m/s, or 8 s."""
    from smart_marl.model.checkpoint import load_checkpoint

    drift, dep = load_benchmark("prior_speed_drift"), load_benchmark("departures")
    assert dep.first_moving_s(np.array([[0.0, 0.5, 1.5, 3.0], [0.0, 0.0, 0.2, 0.9]])).tolist() == [0.3, 0.4]
    scene = sample_scenes[1]  # 13 vehicles stand at the current frame, 9 of them drive off in the log
    ck = load_checkpoint("embedded")
    replayed = dep.scene_records(drift.rollout_from_log(ck, scene, 16, num_rollouts=2, seed=0), scene)
    off = [r for r in replayed if r["drives_off"]]
    assert len(replayed) == 13 and len(off) == 9
    assert all(r["moving"] == 1.0 for r in off)
    assert abs(sum(r["rollout"] for r in off) / sum(r["log"] for r in off) - 1) < 0.05
    row = dep.summarise(replayed, {})
    assert row["drive_off_in_log"] == 9 and row["rollouts_moving"] == 1.0

def test_map_view_measures_the_nearest_pieces_the_model_takes(sample_scenes):
    """benchmarks/map_view.py: on a straight road of pieces every 2 m along a moving vehicle's heading, taking its 8
    nearest within 30 m it sees 7 m around it and 7 m ahead; taking 100, the radius binds (29 m, the last piece)."""
    view = load_benchmark("map_view")
    scene = sample_scenes[0]
    tr, cf = scene.tracks, scene.current_frame
    moving = view.vehicle_views(scene, np.zeros((0, 3)), 8, 30.0)
    assert len(moving) >= 1 and (moving == 0).all()  # no road: nothing within, nothing seen
    i = int(np.flatnonzero((tr.types == int(AgentType.VEHICLE)) & tr.valid[:, cf] & tr.valid[:, cf - 1]
                           & (np.linalg.norm(tr.position[:, cf, :2] - tr.position[:, cf - 1, :2], axis=-1) > 0.5))[0])
    h = tr.heading[i, cf]
    along = np.arange(-59, 60, 2.0)  # pieces at +-1, +-3, ... (none on the 30 m boundary)
    road = np.stack([tr.position[i, cf, 0] + along * np.cos(h), tr.position[i, cf, 1] + along * np.sin(h), np.full_like(along, h)], 1)
    row = view.vehicle_views(scene, road, 8, 30.0)[0]  # the first moving vehicle is i
    assert row[0] == 30 and abs(row[1] - 7.0) < 1e-6 and abs(row[2] - 7.0) < 1e-6  # 30 within 30 m; the 8 nearest reach 7 m
    wide = view.vehicle_views(scene, road, 100, 30.0)[0]
    assert abs(wide[1] - 29.0) < 1e-6 and abs(wide[2] - 29.0) < 1e-6  # every piece within 30 m taken


def test_room_ahead_is_the_nearest_agent_ahead_in_the_lane(sample_scenes):
    import dataclasses

    from smart_marl.braking import leader_follower_pairs

    room_ahead = load_benchmark("speed_by_space_ahead").room_ahead
    sc = sample_scenes[2]
    pairs = leader_follower_pairs(sc)
    assert pairs
    tr, cf = sc.tracks, sc.current_frame
    for leader, follower, _ in pairs:
        apart = float(np.linalg.norm(tr.position[leader, cf, :2] - tr.position[follower, cf, :2]))
        assert 0 < room_ahead(sc, follower) <= apart + 1e-6  # the leader is ahead in its lane; something nearer may be too
    leader, follower, _ = pairs[0]
    alone = tr.valid.copy()
    alone[:, cf] = False
    alone[[leader, follower], cf] = True
    only_two = dataclasses.replace(sc, tracks=dataclasses.replace(tr, valid=alone))
    d = tr.position[leader, cf, :2] - tr.position[follower, cf, :2]
    h = tr.heading[follower, cf]
    assert room_ahead(only_two, follower) == pytest.approx(np.cos(h) * d[0] + np.sin(h) * d[1])  # along its heading
    assert room_ahead(only_two, leader) == np.inf  # its follower is behind it, nobody else is there


def test_finetune_heldout_reads_its_sets_and_lays_out_the_card_table_against_the_shielded_prior(tmp_path):
    """finetune_heldout: ``--set`` is parsed (a bad one is refused, naming it); the table puts the reference (the
    shielded prior at the policy's top-k) first, the policy after the shielded priors, then the expert restricted to
    the action space and the unrestricted one, and divides by the reference."""
    heldout = load_benchmark("finetune_heldout")
    assert heldout.parse_set("real=a,b:all:48") == ("real", ["a", "b"], None, 48)
    assert heldout.parse_set("gen=data/x:200:8") == ("gen", ["data/x"], 200, 8)
    with pytest.raises(SystemExit, match="--set 'gen=data/x:8'"):
        heldout.parse_set("gen=data/x:8")
    metrics = lambda coll, goal, meta: {"collision_rate": coll, "offroad_rate": 0.0, "front_collision_rate": coll / 2,  # noqa: E731
                                        "goal_rate": goal, "meta_metric": meta, "shield": ["collision", "offroad"]}
    for row, m in (("expert (log)", metrics(0.2, 0.9, 0.78)), ("fine-tuned", metrics(0.02, 0.6, 0.74)),
                   ("expert within prior top-16", metrics(0.05, 0.95, 0.8)), ("prior top-3", metrics(0.005, 0.35, 0.77)),
                   ("prior top-16", metrics(0.01, 0.3, 0.775))):
        (tmp_path / f"eval_real_{heldout.slug(row)}.json").write_text(
            json.dumps({"row": row, "scenes": ["a"] * 11, "seeds": list(range(48)), "metrics": m}))
    lines = heldout.table(tmp_path, ["real"], "prior top-16").splitlines()[2:]
    assert [line.split(" | ")[1] for line in lines] == ["prior top-16", "prior top-3", "fine-tuned", "expert within prior top-16",
                                                        "expert (log)"]
    assert "| 0.0200 | 0.0100 | 0.0000 | 2.00x | 0.600 | 2.00x | 0.7400 | -0.0350 |" in lines[2]


def test_finetune_heldout_only_row_refuses_a_row_it_was_not_asked_for(tmp_path):
    """``--only-row`` picks one of the rows asked for (so processes can share a set); any other name is refused, naming
    the rows it could have been, before anything is evaluated."""
    heldout = load_benchmark("finetune_heldout")
    with pytest.raises(SystemExit, match=r"--only-row: 'expert \(log\)' is not one of the rows asked for: \['prior top-16', "
                                         r"'prior top-3', 'fine-tuned'\]"):
        heldout.main(["--policy", "embedded", "--lead-only", "--only-row", "expert (log)", "--set", "g=nowhere:1:1",
                      "--run-dir", str(tmp_path / "run")])
    assert not list((tmp_path / "run").glob("eval_*.json"))


def test_finetune_heldout_refuses_an_unknown_shield_check_by_name(tmp_path, capsys):
    """``--shield`` takes the checks joined with '+'; a check the shield does not know is refused, named, before
    anything runs."""
    heldout = load_benchmark("finetune_heldout")
    with pytest.raises(SystemExit):
        heldout.main(["--policy", "embedded", "--lead-only", "--shield", "collision+seatbelt", "--set", "g=nowhere:1:1",
                      "--run-dir", str(tmp_path / "run")])
    assert "argument --shield: unknown check(s) ['seatbelt']" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
