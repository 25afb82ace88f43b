"""Benchmark of why the prior keeps going where real traffic slows (issue 33, "find the causes"): the
vehicles whose log slows, split by what their log shows slowing them, with the prior's speed next to the
log's for each group.

The vehicles are those of ``benchmarks/reactivity.py`` part (a) (``late_by_log_trend``, ``slows``): simulated
vehicles moving faster than 5 m/s at the current frame whose logged mean speed in the last second of an 8 s
rollout (7-8 s) is more than 20% below their speed now, logged on at least half of those frames. Each one's
log is read for what it meets ahead (its own frame: x forward, y left, at the frame the other thing is seen),
from the current frame to 8 s:

* ``red_light``: a controlled lane's stop point, its signal STOP, ARROW_STOP or FLASHING_STOP on that frame,
  0-40 m ahead within 3.5 m sideways, its signal red on the current frame already; ``red_light_later``: the
  same where it turned red since (a light that changes while it drives: the prior sees the current frame's
  states);
* ``stop_sign``: a stop sign of the map 0-40 m ahead within 6 m sideways;
* ``queue``: in the last second, a vehicle or cyclist 0-30 m ahead in its lane (within 1.75 m sideways,
  heading within 30 degrees): it slows behind someone;
* ``crossing``: a pedestrian or cyclist 0-20 m ahead within 4 m sideways, not going its way;
* ``turn``: its heading turns by more than 30 degrees;
* ``none``: none of these.

A vehicle counts once, under the first of these that it meets (``cause``), and under every one it meets
(``kind: "meets"``). Per group: how many, their speed now, their logged and rollout mean speed at 7-8 s and
the ratio (rollout / log, the issue's measure). For the queued ones, the leader (nearest in the last
second) too: its logged and rollout speed at 7-8 s where the prior drives it, i.e. whether the prior's leader
slowed in the rollouts, and the follower's mean centre gap to it at 7-8 s, logged and in the rollouts.
``--leaders-from-log``: those leaders follow their tokenized log for all 8 s (and are left out of the records), so
that the rows say whether the prior's followers answer a leader that slows as logged.

    .venv/bin/python benchmarks/slowing_causes.py [--prior PATH] [--set NAME=PATH] [--rollouts 4] [--seed 0]
        [--sampling default|plain] [--lights current|log] [--max-scenes N] [--threads 2] [--log-steps S]
        [--leaders-from-log]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import prior_speed_drift as drift  # noqa: E402  (benchmarks/ is not a package)
from prior_speed_drift import _speeds_from_positions, rollout_xy  # noqa: E402

from smart_marl.braking import LANE_HALF_M, SAME_DIRECTION_RAD  # noqa: E402
from smart_marl.model.losses import TREND_BAND  # noqa: E402
from smart_marl.road_map import MapFeatureType  # noqa: E402
from smart_marl.scenario import AgentType, SignalState, wrap_angle  # noqa: E402
from smart_marl.tokens.motion import MOTION_TYPES  # noqa: E402

CAUSES = ("red_light", "red_light_later", "stop_sign", "queue", "crossing", "turn", "none")
RED = (SignalState.STOP, SignalState.ARROW_STOP, SignalState.FLASHING_STOP)
LIGHT_AHEAD_M, LIGHT_SIDE_M = 40.0, 3.5
SIGN_AHEAD_M, SIGN_SIDE_M = 40.0, 6.0
QUEUE_AHEAD_M = 30.0
CROSSING_AHEAD_M, CROSSING_SIDE_M = 20.0, 4.0
TURN_RAD = math.radians(30.0)
FRAMES = drift.NUM_FRAMES
LATE = drift.LATE_FRAMES


def _ahead(pose: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """[..., 2] points ``xy`` [..., 2] in the frame of ``pose`` [..., 3] (x forward, y left), broadcast."""
    d = xy - pose[..., :2]
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def slowing_vehicles(scene, simulated: np.ndarray) -> list[tuple[int, float, float, np.ndarray]]:
    """(track, speed now, logged mean speed at 7-8 s, the late frames it is logged on [F] bool) of the
    simulated vehicles whose log slows (module docstring)."""
    tr, cf = scene.tracks, scene.current_frame
    frames = np.arange(cf + 1, cf + 1 + FRAMES)
    out = []
    for i in np.flatnonzero(simulated & (tr.types[: len(simulated)] == int(AgentType.VEHICLE))):
        if not (tr.valid[i, cf] and tr.valid[i, cf - 1]):
            continue
        now = float(np.linalg.norm(tr.position[i, cf, :2] - tr.position[i, cf - 1, :2]) / 0.1)
        if now <= drift.MOVING_MPS[AgentType.VEHICLE]:
            continue
        ok = tr.valid[i, frames] & tr.valid[i, frames - 1]
        late = ok & (np.arange(FRAMES) >= FRAMES - LATE)
        if late.sum() * 2 < LATE:
            continue
        speed = _speeds_from_positions(tr.position[i, frames, :2], tr.position[i, cf, :2])
        log_late = float(speed[late].mean())
        if log_late < (1 - TREND_BAND) * now:
            out.append((int(i), now, log_late, late))
    return out


def what_it_meets(scene, i: int) -> tuple[list[str], int | None]:
    """The causes (:data:`CAUSES` order, without ``none``) that track ``i``'s log meets from the current frame
    to 8 s, and its nearest leader in the last second (a track index, or None)."""
    tr, rm, tl, cf = scene.tracks, scene.road_map, scene.traffic_lights, scene.current_frame
    frames = np.arange(cf, cf + 1 + FRAMES)
    frames = frames[tr.valid[i, frames]]
    pose = np.concatenate([tr.position[i, frames, :2], tr.heading[i, frames, None]], -1).astype(np.float64)  # [F, 3]
    found = []
    if len(tl.lane_ids):
        rel = _ahead(pose[:, None], tl.stop_points[None, :, :2].astype(np.float64))  # [F, L, 2]
        red = np.isin(tl.states[frames], RED) & tl.present[frames]
        met = (red & (rel[..., 0] > 0) & (rel[..., 0] <= LIGHT_AHEAD_M) & (np.abs(rel[..., 1]) <= LIGHT_SIDE_M)).any(0)  # [L]
        if met.any():  # red already on the current frame (its first), or turned red since
            found.append("red_light" if (met & red[0]).any() else "red_light_later")
    signs = rm.indices_of(MapFeatureType.STOP_SIGN)
    if len(signs):
        pts = np.stack([rm.feature_points(int(k))[0, :2] for k in signs]).astype(np.float64)
        rel = _ahead(pose[:, None], pts[None])
        if ((rel[..., 0] > 0) & (rel[..., 0] <= SIGN_AHEAD_M) & (np.abs(rel[..., 1]) <= SIGN_SIDE_M)).any():
            found.append("stop_sign")
    others = tr.position[:, frames, :2].astype(np.float64).transpose(1, 0, 2)  # [F, N, 2]
    rel = _ahead(pose[:, None], others)
    dh = np.abs(wrap_angle(tr.heading[:, frames].T.astype(np.float64) - pose[:, None, 2]))
    valid = tr.valid[:, frames].T.copy()
    valid[:, i] = False
    types = tr.types[None, :]
    lane = valid & np.isin(types, (int(AgentType.VEHICLE), int(AgentType.CYCLIST))) & (rel[..., 0] > 0) \
        & (rel[..., 0] <= QUEUE_AHEAD_M) & (np.abs(rel[..., 1]) <= LANE_HALF_M) & (dh < SAME_DIRECTION_RAD)
    late = frames > cf + FRAMES - LATE
    leader = None
    if (lane & late[:, None]).any():
        found.append("queue")
        gap = np.where(lane & late[:, None], rel[..., 0], np.inf)  # [F, N]
        leader = int(np.argmin(gap.min(0)))
    crossing = valid & np.isin(types, (int(AgentType.PEDESTRIAN), int(AgentType.CYCLIST))) & (rel[..., 0] > 0) \
        & (rel[..., 0] <= CROSSING_AHEAD_M) & (np.abs(rel[..., 1]) <= CROSSING_SIDE_M) & (dh >= SAME_DIRECTION_RAD)
    if crossing.any():
        found.append("crossing")
    if abs(float(wrap_angle(pose[-1, 2] - pose[0, 2]))) > TURN_RAD:
        found.append("turn")
    return found, leader


def simulated_tracks(scene) -> np.ndarray:
    """[A] bool: the tracks the rollouts simulate (vehicles, pedestrians and cyclists valid at the current frame)."""
    return scene.tracks.valid[:, scene.current_frame] & np.isin(scene.tracks.types, [int(t) for t in MOTION_TYPES])


def queue_leaders(scene) -> np.ndarray:
    """The track indices of the leaders (:func:`what_it_meets`) of a scene's slowing vehicles, simulated ones only."""
    sim = simulated_tracks(scene)
    found = {what_it_meets(scene, i)[1] for i, *_ in slowing_vehicles(scene, sim)}
    return np.array(sorted(j for j in found if j is not None and j < len(sim) and sim[j]), np.int64)


def scene_records(res, scene, skip=None) -> list[dict]:
    """One record per slowing vehicle of a scene and its rollouts ``res`` (a one-scene
    :class:`~smart_marl.rollout.RolloutResult` of :data:`FRAMES` frames), but those of track indices ``skip``."""
    tr, cf = scene.tracks, scene.current_frame
    simulated = res.simulated[0]
    frames = np.arange(cf + 1, cf + 1 + FRAMES)

    def rollout_late(j: int, on: np.ndarray) -> float:
        sim = _speeds_from_positions(rollout_xy(res, scene, [j])[:, 0], np.broadcast_to(tr.position[j, cf, :2], (res.trajectory.shape[0], 2)))
        return float(sim.mean(0)[on].mean())

    out = []
    for i, now, log_late, late in slowing_vehicles(scene, simulated):
        if skip is not None and i in skip:
            continue
        causes, leader = what_it_meets(scene, i)
        rec = {"now": now, "log": log_late, "rollout": rollout_late(i, late), "causes": causes,
               "cause": causes[0] if causes else "none"}
        if leader is not None and leader < len(simulated) and simulated[leader]:
            both = late & tr.valid[leader, frames] & tr.valid[leader, frames - 1]
            if both.any():
                lead_log = _speeds_from_positions(tr.position[leader, frames, :2], tr.position[leader, cf, :2])
                rec["leader_log"], rec["leader_rollout"] = float(lead_log[both].mean()), rollout_late(leader, both)
                log_gap = np.linalg.norm(tr.position[leader, frames, :2] - tr.position[i, frames, :2], axis=-1)
                sim_gap = np.linalg.norm(res.trajectory[:, leader, :, :2] - res.trajectory[:, i, :, :2], axis=-1).mean(0)
                rec["gap_log"], rec["gap_rollout"] = float(log_gap[both].mean()), float(sim_gap[both].mean())
        out.append(rec)
    return out


def summarise(records: list[dict], common: dict) -> list[dict]:
    """JSON rows: per primary cause, per cause met, and the queued vehicles' leaders."""
    rows = []

    def group(kind: str, name: str, recs: list[dict]) -> None:
        if recs:
            log, sim = np.mean([r["log"] for r in recs]), np.mean([r["rollout"] for r in recs])
            rows.append({"kind": kind, "cause": name, "vehicles": len(recs), "now_mps": round(float(np.mean([r["now"] for r in recs])), 2),
                         "log_mps": round(float(log), 2), "rollout_mps": round(float(sim), 2), "ratio": round(float(sim / max(log, 1e-9)), 3),
                         **common})

    group("all", "all", records)
    for c in CAUSES:
        group("cause", c, [r for r in records if r["cause"] == c])
    for c in CAUSES[:-1]:
        group("meets", c, [r for r in records if c in r["causes"]])
    led = [r for r in records if "leader_log" in r]
    if led:
        rows.append({"kind": "queued_leaders", "vehicles": len(led),
                     "leader_log_mps": round(float(np.mean([r["leader_log"] for r in led])), 2),
                     "leader_rollout_mps": round(float(np.mean([r["leader_rollout"] for r in led])), 2),
                     "follower_log_mps": round(float(np.mean([r["log"] for r in led])), 2),
                     "follower_rollout_mps": round(float(np.mean([r["rollout"] for r in led])), 2),
                     "gap_log_m": round(float(np.mean([r["gap_log"] for r in led])), 2),
                     "gap_rollout_m": round(float(np.mean([r["gap_rollout"] for r in led])), 2), **common})
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    drift.vehicle_rollout_arguments(ap, rollouts=4)
    drift.log_steps_flag(ap)
    ap.add_argument("--leaders-from-log", action="store_true",
                    help="the leaders of the queued slowing vehicles follow their tokenized log for all 8 s (the followers "
                         "and everyone else the prior); the leaders' own records are left out")
    args = ap.parse_args(argv)
    model, sets, rollout_kwargs, fields = drift.vehicle_rollout_sets(args)
    for name, scenes in sets.items():
        records = []
        for scene in scenes:
            leaders = queue_leaders(scene) if args.leaders_from_log else None
            res = drift.rollout_from_log(model, scene, FRAMES // 5 if leaders is not None else args.log_steps, tracks=leaders,
                                         **rollout_kwargs)
            records += scene_records(res, scene, skip=leaders)
        common = {"benchmark": "slowing_causes", "set": name, "scenes": len(scenes), **fields, "log_steps": args.log_steps,
                  "leaders_from_log": args.leaders_from_log}
        for row in summarise(records, common):
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
