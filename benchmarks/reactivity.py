"""Benchmark of a prior's reactivity in closed loop (issue 33): does the background it drives stop
where traffic stops, stop at red lights, answer a braking leader and a cut-in, and keep out of the
agents a policy drives?

Per set of scenes (``--set NAME=PATH``; by default the 21 shared real scenes of 91 frames), per
sampling (``--sampling default`` collision-aware, ``plain``; both by default) and per seed
(``--seeds 0,1``), one JSON object per line on stdout:

(a) ``slowing``: the prior's rollouts of every scene (``--rollouts``), the vehicles moving faster than
    5 m/s at the current frame: rollout / logged mean speed at 0.5-8 s (``kind: "horizon"``) and, in
    the last second (7-8 s), split by what their log does against their speed now
    (``kind: "late_by_log_trend"``: ``speeds_up`` / ``keeps`` / ``slows`` by more than 20%), and each of
    those groups at 0.5-8 s (``kind: "trend_by_horizon"``: how it gets there); :mod:`benchmarks.prior_speed_drift`'s
    measures on the same rollouts.
(b) ``red_light``: the share of the simulated vehicles that cross a stop line on red, in the rollouts
    (per vehicle-rollout) and in the log (per vehicle): the 2025 sim-agents rules' traffic-light
    violation (:func:`smart_marl.metrics.features.traffic_light_violation`): at a frame t the
    vehicle's nearest surface-street lane has a STOP or ARROW_STOP signal, and the vehicle went
    from behind that lane's stop point (t-1) to beyond it (t) along the lane's segment nearest the
    stop point; frames from the current one (a crossing in the first 0.1 s counts) to 8 s, the
    logged light states of those frames.
(c) ``braking``: on every scene, each vehicle leader (moving faster than 3 m/s) with a follower
    within 30 m behind it in its lane (:func:`leader_follower_pairs`, at most ``--max-pairs`` per
    scene, nearest first) brakes at 4, 6 and 8 m/s2 from 0.5 s on, scripted as the what-if tool
    does (:class:`agents.whatif.Brake`); the follower is the prior's: its rear-end rate (its box
    overlaps the leader's, the metrics' rounded boxes), the minimum gap (box distance) and its
    largest deceleration over a token (0.5 s) after the onset (:func:`follower_response`).
    ``kind: "braking_pin"``: the case of ``tests/test_whatif.py`` (WOMD scene 637f20cafde22ff8,
    1609 at 8 m/s2 from 1 s, 8 rollouts, seed 0, 12 steps): the rate at which 1609 is hit.
(d) ``cut_in``: for each vehicle moving faster than 5 m/s with no vehicle within 30 m ahead in its
    lane (at most ``--max-pairs`` per scene), a scripted vehicle (:func:`cut_in_trajectory`) drives
    in the next lane at 0.8x its speed and moves into its lane over 2 s so that it arrives 10 m
    (centre to centre) ahead of where the follower would be at constant speed; the follower's
    collision rate with it, minimum gap and largest deceleration.
(e) ``controlled``: the PettingZoo env (``envs.smart_traffic_v0.parallel_env``) with the moving
    vehicles (logged route > 10 m, at most 4, nearest the self-driving car) driven by the expert
    (``agents.scripted.LogFollowingPolicy``) and the rest by the prior; per agent-episode the first
    collision split by where the other agent was the frame before
    (:func:`agents.evaluate.first_collision_kinds`): ``rear_ended`` (behind: the background ran
    into the controlled car; the background at fault), ``front`` (ahead: the controlled car ran
    into it), ``side``.

    .venv/bin/python benchmarks/reactivity.py [--prior PATH] [--set NAME=PATH ...] [--parts a,b,c,d,e]
        [--sampling default,plain] [--seeds 0,1] [--rollouts 8] [--max-scenes N] [--threads 2] [--lights current|log]

The measured figures are in docs/experiments/2026-11-26-reactivity.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import prior_speed_drift as drift  # noqa: E402  (benchmarks/ is not a package)

from smart_marl.braking import LANE_HALF_M, leader_follower_pairs, poses_relative_to, speeds_now  # noqa: E402
from smart_marl.geometry import rounded_box_signed_distance  # noqa: E402
from smart_marl.metrics.features import traffic_light_violation  # noqa: E402
from smart_marl.metrics.inputs import SceneNotScorableError, Signals, logged_scene, simulated_agent_indices  # noqa: E402
from smart_marl.model.checkpoint import load_prior  # noqa: E402
from smart_marl.rollout import DEFAULT_TOP_K, rollout  # noqa: E402
from smart_marl.scenario import DT_S, AgentType  # noqa: E402

PARTS = ("a", "b", "c", "d", "e")
SAMPLINGS = {"default": True, "plain": False}
DECELS_MPS2 = (4.0, 6.0, 8.0)
BRAKE_ONSET_S = 0.5
BRAKE_STEPS = 10  # 5 s of rollout: the onset plus a 4 m/s2 stop from 15 m/s
CUT_IN_GAP_M = 10.0
CUT_IN_LATERAL_M = 3.5
CUT_IN_DURATION_S = 2.0
CUT_IN_SPEED_RATIO = 0.8
CUT_IN_MIN_MPS = 5.0
CUT_IN_ID = 990_001


# ------------------------------------------------------------------------------- helpers
def free_road_followers(scene, ahead_m: float = 30.0, max_pairs: int | None = None) -> list[int]:
    """Vehicles valid at the current frame moving faster than :data:`CUT_IN_MIN_MPS` with no other agent within
    ``ahead_m`` ahead in their lane (nor the next lane's first :data:`CUT_IN_GAP_M` + 10 m on either side:
    where the cut-in comes from); fastest first."""
    tr, cf = scene.tracks, scene.current_frame
    v = speeds_now(scene)
    on = tr.valid[:, cf]
    out = []
    for i in np.flatnonzero(on & (tr.types == int(AgentType.VEHICLE)) & (v > CUT_IN_MIN_MPS)):
        rel = poses_relative_to(scene, int(i))
        near = on & (rel[:, 0] > -5.0) & (rel[:, 0] < ahead_m) & (np.abs(rel[:, 1]) < CUT_IN_LATERAL_M + LANE_HALF_M)
        near[i] = False
        if not near.any():
            out.append(int(i))
    out.sort(key=lambda i: -v[i])
    return out[:max_pairs] if max_pairs else out


def cut_in_trajectory(speed_mps: float, num_frames: int, gap_m: float = CUT_IN_GAP_M, side: float = 1.0,
                      lateral_m: float = CUT_IN_LATERAL_M, duration_s: float = CUT_IN_DURATION_S,
                      speed_ratio: float = CUT_IN_SPEED_RATIO) -> np.ndarray:
    """[num_frames + 1, 3] the cutting-in vehicle's poses (frames current .. current + num_frames) in the follower's
    frame at the current frame (x forward, y left): ``side`` * ``lateral_m`` to the side, at ``speed_ratio`` x the
    follower's ``speed_mps``, moving into the follower's lane over ``duration_s`` (a cosine profile) so that it is
    ``gap_m`` ahead (centre to centre) of where the follower would be at constant speed when it arrives."""
    vc = speed_ratio * speed_mps
    x0 = gap_m + duration_s * (speed_mps - vc)
    t = DT_S * np.arange(num_frames + 1)
    u = np.clip(t / duration_s, 0.0, 1.0)
    y = side * lateral_m * 0.5 * (1.0 + np.cos(np.pi * u))
    dy = np.where(t < duration_s, -side * lateral_m * 0.5 * np.pi / duration_s * np.sin(np.pi * u), 0.0)
    return np.stack([x0 + vc * t, y, np.arctan2(dy, max(vc, 0.5))], -1)


def follower_response(follower: np.ndarray, leader: np.ndarray, f_size: np.ndarray, l_size: np.ndarray,
                      start: np.ndarray, onset_frame: int) -> dict:
    """The follower's answer, over R rollouts: ``follower`` / ``leader`` [R, T, 3] poses (frames 1..T after the
    current one, NaN where absent), sizes [2] length and width, ``start`` [3] the follower's pose at the current
    frame, ``onset_frame`` the first frame of the manoeuvre (0-based in T). Returns ``hit`` [R] (boxes overlap on
    some frame from the onset on, the metrics' rounded boxes), ``min_gap_m`` [R] (their least box distance from
    the onset on; negative: overlap) and ``max_decel_mps2`` [R] (the largest drop of the follower's speed over a
    token, 5 frames, from the onset on, per second)."""
    r, t, _ = follower.shape
    gap = rounded_box_signed_distance(follower[..., 0], follower[..., 1], f_size[0], f_size[1], follower[..., 2],
                                      leader[..., 0], leader[..., 1], l_size[0], l_size[1], leader[..., 2])
    gap = np.where(np.isfinite(gap), gap, np.inf)[:, onset_frame:]
    p = np.concatenate([np.broadcast_to(start[None, None, :2], (r, 1, 2)), follower[..., :2]], 1)
    speed = np.linalg.norm(np.diff(p, axis=1), axis=-1) / DT_S  # [R, T]
    lo = max(onset_frame - 1, 0)
    drop = (speed[:, lo:-5] - speed[:, lo + 5:]) / 0.5 if t - lo > 5 else np.zeros((r, 1))
    return {"hit": gap.min(1) < 0, "min_gap_m": gap.min(1), "max_decel_mps2": np.nan_to_num(drop, nan=0.0).max(1)}


def red_light_shares(scene, traj_source: np.ndarray | None) -> tuple[int, int] | None:
    """(vehicles crossing on red, vehicles) over the simulated vehicles of a 91-frame scene: in the log
    (``traj_source`` None) or in rollouts (``traj_source`` [R, A, 80, >=2] x, y in the scene's source frame,
    ``A`` the scene's tracks; counted per vehicle-rollout). None when the scene has no signals or lanes, or does
    not fit the metrics' shape. The violation is the 2025 rules' (module docstring (b))."""
    try:
        ls = logged_scene(scene)
    except SceneNotScorableError:
        return None
    if ls.signals is None or ls.lanes is None:
        return None
    sim = simulated_agent_indices(scene)
    veh = np.flatnonzero(scene.tracks.types[sim] == int(AgentType.VEHICLE))
    if not len(veh):
        return None
    cur = 10  # the metrics' current step
    if traj_source is None:
        xy = ls.position[None, :, cur:, :2]
        valid = ls.valid[None, :, cur:]
    else:
        rr = traj_source.shape[0]
        fut = traj_source[:, sim, :, :2].astype(np.float64)
        xy = np.concatenate([np.broadcast_to(ls.position[None, :, cur:cur + 1, :2], (rr, len(sim), 1, 2)), fut], 2)
        valid = np.ones(xy.shape[:3], bool)
    sig = Signals(ls.signals.lane_ids, ls.signals.states[cur:], ls.signals.stop_points)
    tlv = traffic_light_violation(xy, valid, veh, ls.lanes, sig)  # [B, E, T]
    return int(tlv.any(-1).sum()), int(tlv.shape[0] * tlv.shape[1])


# ------------------------------------------------------------------------------- the parts
def part_slowing_and_lights(model, scenes, rollouts: int, top_k: int, seed: int, avoid: bool, common: dict, parts,
                            lights: str = "current") -> list[dict]:
    rows = []
    roll = drift.SpeedSums.zeros()
    red = {"rollout": [0, 0], "log": [0, 0], "scenes": 0}
    for scene in scenes:
        res = rollout(model, [scene], num_rollouts=rollouts, num_steps=drift.NUM_FRAMES // 5, top_k=top_k, seed=seed,
                      avoid_collisions=avoid, lights=lights)
        if "a" in parts:
            sums = drift.speed_sums(res, scene).get(AgentType.VEHICLE)
            if sums is not None:
                roll = roll.plus(sums)
        if "b" in parts:
            log = red_light_shares(scene, None)
            if log is not None:
                sim = red_light_shares(scene, res.trajectory)
                red["log"] = [a + b for a, b in zip(red["log"], log)]
                red["rollout"] = [a + b for a, b in zip(red["rollout"], sim)]
                red["scenes"] += 1
    if "a" in parts:
        r, lg, n, m, by_trend = roll.sim, roll.log, roll.count, roll.agents, roll.by_trend
        for h in drift.HORIZONS_S:
            k = int(round(h * 10)) - 1
            if n[k]:
                rows.append({"part": "a", "kind": "horizon", "t_s": h, "rollout_mps": round(r[k] / n[k], 3),
                             "log_mps": round(lg[k] / n[k], 3), "ratio": round(r[k] / max(lg[k], 1e-9), 3), "agents": int(m), **common})
        for name, (now, log_late, sim_late, count) in zip(drift.TRENDS, by_trend):
            if count:
                rows.append({"part": "a", "kind": "late_by_log_trend", "log_trend": name, "agents": int(count),
                             "now_mps": round(now / count, 3), "log_mps": round(log_late / count, 3),
                             "rollout_mps": round(sim_late / count, 3), "ratio": round(sim_late / max(log_late, 1e-9), 3), **common})
        rows += [{"part": "a", **row, **common} for row in drift.trend_horizon_rows(roll)]
    if "b" in parts:
        (rc, rn), (lc, ln) = red["rollout"], red["log"]
        rows.append({"part": "b", "kind": "red_light", "scenes_with_signals": red["scenes"], "rollout_crossings": rc,
                     "vehicle_rollouts": rn, "rollout_share": round(rc / max(rn, 1), 4), "log_crossings": lc,
                     "log_vehicles": ln, "log_share": round(lc / max(ln, 1), 4), **common})
    return rows


def _summary(values: list[np.ndarray], key: str) -> dict:
    x = np.concatenate(values) if values else np.zeros(0)
    if key == "hit":
        return {"rate": round(float(x.mean()), 4) if len(x) else None, "n": int(len(x))}
    x = x[np.isfinite(x)]
    return {"median": round(float(np.median(x)), 3) if len(x) else None, "p10": round(float(np.percentile(x, 10)), 3) if len(x) else None}


def part_braking(model, vocab, scenes, rollouts: int, top_k: int, seed: int, avoid: bool, max_pairs: int, common: dict) -> list[dict]:
    from agents.whatif import Brake, WhatIf, prepare, simulate

    acc = {d: {"hit": [], "min_gap_m": [], "max_decel_mps2": []} for d in DECELS_MPS2}
    pairs_n = 0
    for scene in scenes:
        pairs = leader_follower_pairs(scene, max_pairs=max_pairs)
        pairs_n += len(pairs)
        size = scene.tracks.box_size()[:, :2].astype(np.float64)
        cf = scene.current_frame
        for lead, fol, _ in pairs:
            for d in DECELS_MPS2:
                prep = prepare(scene, WhatIf([Brake(agent=int(scene.tracks.ids[lead]), at_s=BRAKE_ONSET_S, decel_mps2=d)]), vocab)
                sim = simulate(model, vocab, prep, rollouts, seed, BRAKE_STEPS, top_k, avoid_collisions=avoid)
                start = np.array([*scene.tracks.position[fol, cf, :2], scene.tracks.heading[fol, cf]], np.float64)
                resp = follower_response(sim.poses[:, fol], sim.poses[:, lead], size[fol], size[lead], start,
                                         int(round(BRAKE_ONSET_S / DT_S)))
                for k, v in resp.items():
                    acc[d][k].append(v)
    rows = []
    for d in DECELS_MPS2:
        hit = _summary(acc[d]["hit"], "hit")
        rows.append({"part": "c", "kind": "braking", "decel_mps2": d, "pairs": pairs_n, "rollouts": hit["n"],
                     "rear_end_rate": hit["rate"], "min_gap_m": _summary(acc[d]["min_gap_m"], "x"),
                     "follower_max_decel_mps2": _summary(acc[d]["max_decel_mps2"], "x"), **common})
    return rows


def braking_pin(model, avoid: bool, common: dict) -> dict | None:
    """The case pinned in tests/test_whatif.py: the rate at which 1609 is hit when it brakes at 8 m/s2."""
    from agents.whatif import Brake, WhatIf, run_whatif
    from smart_marl.readers import read_scenarios

    path = drift.SHARED / "womd_tfrecord" / "motion_data_one_scenario.tfrecord"
    if not path.exists():
        return None
    scene = next(iter(read_scenarios([str(path)])))
    res = run_whatif(model, scene, WhatIf([Brake(agent=1609, at_s=1.0, decel_mps2=8.0)]), num_rollouts=8, seed=0, num_steps=12,
                     realism=False, avoid_collisions=avoid)
    rows = {(r["quantity"], r["agent"]): r for r in res.table}
    row = rows[("collided_rate", "1609 (brake)")]
    return {"part": "c", "kind": "braking_pin", "scene": scene.scenario_id, "hit_rate": row["whatif"],
            "hit_rollouts_of_8": int(round(row["whatif"] * 8)), "baseline_rate": row["baseline"], **{**common, "seed": 0}}


def part_cut_in(model, vocab, scenes, rollouts: int, top_k: int, seed: int, avoid: bool, max_pairs: int, common: dict) -> list[dict]:
    from agents.whatif import Insert, WhatIf, prepare, simulate

    acc = {"hit": [], "min_gap_m": [], "max_decel_mps2": []}
    n_cases = 0
    for scene in scenes:
        size = scene.tracks.box_size()[:, :2].astype(np.float64)
        cf = scene.current_frame
        v = speeds_now(scene)
        for fol in free_road_followers(scene, max_pairs=max_pairs):
            traj = cut_in_trajectory(float(v[fol]), 5 * BRAKE_STEPS)
            edit = Insert(type="vehicle", relative_to=int(scene.tracks.ids[fol]), trajectory=traj.tolist(), id=CUT_IN_ID,
                          size_m=[4.6, 1.9, 1.6], then="hold")
            prep = prepare(scene, WhatIf([edit]), vocab)
            k = int(np.flatnonzero(prep.scene.tracks.ids == CUT_IN_ID)[0])
            sim = simulate(model, vocab, prep, rollouts, seed, BRAKE_STEPS, top_k, avoid_collisions=avoid)
            start = np.array([*scene.tracks.position[fol, cf, :2], scene.tracks.heading[fol, cf]], np.float64)
            resp = follower_response(sim.poses[:, fol], sim.poses[:, k], size[fol], np.array([4.6, 1.9]), start, 0)
            for key, val in resp.items():
                acc[key].append(val)
            n_cases += 1
    hit = _summary(acc["hit"], "hit")
    return [{"part": "d", "kind": "cut_in", "cases": n_cases, "rollouts": hit["n"], "collision_rate": hit["rate"],
             "min_gap_m": _summary(acc["min_gap_m"], "x"), "follower_max_decel_mps2": _summary(acc["max_decel_mps2"], "x"), **common}]


def moving_route_vehicles(scene, min_route_m: float = 10.0) -> np.ndarray:
    """[N] bool, part (e)'s controlled agents: vehicles valid at the current frame whose logged position at their
    last valid frame is more than ``min_route_m`` from where they are now (the fine-tuning runs' "moving_vehicles";
    written out here so that the benchmark does not import the RL stack)."""
    tr, cf = scene.tracks, scene.current_frame
    last = tr.valid.shape[1] - 1 - np.argmax(tr.valid[:, ::-1], axis=1)
    route_m = np.linalg.norm(tr.position[np.arange(tr.num_tracks), last, :2] - tr.position[:, cf, :2], axis=1)
    return tr.valid[:, cf] & (tr.types == int(AgentType.VEHICLE)) & (route_m > min_route_m)


def part_controlled(model, vocab, scenes, seed: int, avoid: bool, top_k: int, common: dict, max_agents: int = 4) -> list[dict]:
    from agents.evaluate import COLLISION_KINDS, first_collision_kinds
    from agents.prior_policy import run_episode
    from agents.scripted import LogFollowingPolicy
    from envs import smart_traffic_v0

    env = smart_traffic_v0.parallel_env(scenarios=list(scenes), prior=model, motion_vocab=vocab, controlled=moving_route_vehicles,
                                        max_agents=max_agents, background="prior", horizon_steps=16, observation="dict",
                                        terminate_on=(), top_k=top_k, avoid_collisions=avoid)
    policy = LogFollowingPolicy(env, seed=seed)
    counts = {k: 0 for k in COLLISION_KINDS}
    by_background = {k: 0 for k in COLLISION_KINDS}
    n = 0
    for i in range(len(scenes)):
        try:
            ep = run_episode(env, policy, seed=seed, scene_index=i)
        except Exception as e:  # a scene with no controllable agent
            if "controll" in str(e):
                continue
            raise
        n += len(ep["return"])
        poses, present = env.trajectories()
        for kind in first_collision_kinds(poses, present, env.static.box_size, env.ctrl_tracks):
            if kind is not None:
                counts[kind] += 1
        for kind in background_collision_kinds(poses, present, env.static.box_size, env.ctrl_tracks):
            if kind is not None:
                by_background[kind] += 1
    env.close()
    rate = lambda c: round(c / max(n, 1), 4)  # noqa: E731
    return [{"part": "e", "kind": "controlled", "agent_episodes": n, "rear_ended_rate": rate(counts["rear_ended"]),
             "front_rate": rate(counts["front"]), "side_rate": rate(counts["side"]),
             "rear_ended_by_background_rate": rate(by_background["rear_ended"]),
             "front_into_background_rate": rate(by_background["front"]), "side_with_background_rate": rate(by_background["side"]),
             "at_fault": {"background (rear-ended)": by_background["rear_ended"], "controlled (front)": by_background["front"],
                          "unclear (side)": by_background["side"],
                          "between controlled agents": sum(counts.values()) - sum(by_background.values())}, **common}]


def background_collision_kinds(poses: np.ndarray, present: np.ndarray, box_size: np.ndarray, ctrl) -> list:
    """:func:`agents.evaluate.first_collision_kinds` counting only collisions with the background: per controlled
    track, its first collision with an agent that is not controlled (the other controlled agents are left out;
    two log-following cars meet where one's log ends, since it then stands at its last logged pose)."""
    from agents.evaluate import first_collision_kinds

    ctrl = [int(c) for c in ctrl]
    out = []
    for c in ctrl:
        keep = present.copy()
        keep[[o for o in ctrl if o != c]] = False
        out += first_collision_kinds(poses, keep, box_size, [c])
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--prior", default="embedded", help="checkpoint path, or 'embedded'")
    ap.add_argument("--set", dest="sets", action="append", metavar="NAME=PATH[,PATH...]",
                    help="a named set of scenes (files, folders, globs); repeatable (default: the shared real 91-frame scenes)")
    ap.add_argument("--parts", default="a,b,c,d,e")
    ap.add_argument("--sampling", default="default,plain", help="comma-separated: default (collision-aware), plain")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--rollouts", type=int, default=8, help="rollouts per scene for (a) and (b)")
    ap.add_argument("--case-rollouts", type=int, default=4, help="rollouts per braking / cut-in case")
    ap.add_argument("--max-pairs", type=int, default=3, help="braking and cut-in cases per scene")
    ap.add_argument("--max-scenes", type=int, default=0)
    ap.add_argument("--top-k", type=int, default=DEFAULT_TOP_K)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--lights", default="current", choices=("current", "log"),
                    help="(a), (b): the light states the prior sees: the current frame's, held, or the log's at every step")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    parts = [p for p in args.parts.split(",") if p]
    bad = sorted(set(parts) - set(PARTS))
    if bad:
        ap.error(f"unknown part(s) {bad}; known: {PARTS}")
    model, vocab = load_prior(args.prior)
    sets = drift.scene_sets(args.sets or [f"real={','.join(str(drift.SHARED / p) for p in drift.REAL_91_FRAMES)}"])
    for sampling in [s for s in args.sampling.split(",") if s]:
        avoid = SAMPLINGS[sampling]
        if "c" in parts:
            pin = braking_pin(model, avoid, {"prior": args.prior, "sampling": sampling})
            if pin:
                print(json.dumps(pin), flush=True)
        for set_name, scenes in sets.items():
            if args.max_scenes:
                scenes = scenes[: args.max_scenes]
            for seed in [int(s) for s in args.seeds.split(",") if s]:
                common = {"set": set_name, "scenes": len(scenes), "sampling": sampling, "seed": seed, "prior": args.prior}
                t0 = time.perf_counter()
                rows = []
                if "a" in parts or "b" in parts:
                    rows += part_slowing_and_lights(model, scenes, args.rollouts, args.top_k, seed, avoid,
                                                    {**common, "rollouts": args.rollouts, "lights": args.lights}, parts, args.lights)
                if "c" in parts:
                    rows += part_braking(model, vocab, scenes, args.case_rollouts, args.top_k, seed, avoid, args.max_pairs, common)
                if "d" in parts:
                    rows += part_cut_in(model, vocab, scenes, args.case_rollouts, args.top_k, seed, avoid, args.max_pairs, common)
                if "e" in parts:
                    rows += part_controlled(model, vocab, scenes, seed, avoid, args.top_k, common)
                for row in rows:
                    print(json.dumps({**row, "wall_s": round(time.perf_counter() - t0, 1)}), flush=True)


if __name__ == "__main__":
    main()
