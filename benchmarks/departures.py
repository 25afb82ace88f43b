"""Benchmark of the rollout stage's reactivity: does the prior start a standing vehicle whose log drives off?

The vehicles that stand at the current frame (under 0.5 m/s over its last 0.5 s) and whose log drives off (mean
speed at 7-8 s above 3 m/s): a queue moving at a green light, a car leaving a stop sign. Per scene set, one JSON
line: how many, their logged and rollout mean speed at 7-8 s and the ratio (rollout / log), the share of their
rollouts in which they are moving at 7-8 s (above 1 m/s; every log is), and the median time at which the log and
the rollouts first pass 1 m/s (rollouts that never do count as 8 s). Its counterpart, vehicles that keep standing,
is on the same line (their rollout mean speed at 7-8 s).

    .venv/bin/python benchmarks/departures.py [--prior PATH] [--set NAME=PATH] [--rollouts 8] [--seed 0]
        [--sampling default|plain] [--top-k 6] [--lights current|log] [--stop-lines] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import prior_speed_drift as drift  # noqa: E402  (benchmarks/ is not a package)

from smart_marl.scenario import AgentType  # noqa: E402

FRAMES, LATE = drift.NUM_FRAMES, 10  # 8 s at 10 Hz; the last second
STANDING_MPS, DRIVES_OFF_MPS, MOVING_MPS = 0.5, 3.0, 1.0


def standing_vehicles(scene, simulated: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(track indices, logged mean speed at 7-8 s) of the simulated vehicles standing at the current frame whose log
    covers the last second, and whose speeds the caller splits at :data:`DRIVES_OFF_MPS`."""
    tr, cf = scene.tracks, scene.current_frame
    frames = np.arange(cf + 1, cf + 1 + FRAMES)
    out, late_speed = [], []
    for i in np.flatnonzero(simulated & (tr.types[: len(simulated)] == int(AgentType.VEHICLE))):
        if not (tr.valid[i, cf] and tr.valid[i, cf - 5]):
            continue
        if np.linalg.norm(tr.position[i, cf, :2] - tr.position[i, cf - 5, :2]) / 0.5 >= STANDING_MPS:
            continue
        ok = tr.valid[i, frames] & tr.valid[i, frames - 1]
        if not ok[-LATE:].all():
            continue
        out.append(i)
        late_speed.append(drift._speeds_from_positions(tr.position[i, frames, :2], tr.position[i, cf, :2])[-LATE:].mean())
    return np.array(out, np.int64), np.array(late_speed)


def first_moving_s(speed: np.ndarray) -> np.ndarray:
    """[...] the time (s) each speed series [..., T] first passes :data:`MOVING_MPS`, ``T / 10`` where it never does."""
    moving = speed > MOVING_MPS
    return np.where(moving.any(-1), moving.argmax(-1) + 1, speed.shape[-1]) / 10.0


def scene_records(res, scene) -> list[dict]:
    """One record per standing vehicle of a scene and its rollouts ``res`` (a one-scene RolloutResult of 8 s)."""
    tr, cf = scene.tracks, scene.current_frame
    frames = np.arange(cf + 1, cf + 1 + FRAMES)
    tracks, log_late = standing_vehicles(scene, res.simulated[0])
    out = []
    for i, lg in zip(tracks, log_late):
        log_speed = drift._speeds_from_positions(tr.position[i, frames, :2], tr.position[i, cf, :2])
        sim = drift._speeds_from_positions(drift.rollout_xy(res, scene, [i])[:, 0],
                                           np.broadcast_to(tr.position[i, cf, :2], (res.trajectory.shape[0], 2)))  # [R, T]
        out.append({"drives_off": bool(lg > DRIVES_OFF_MPS), "log": float(lg), "rollout": float(sim[:, -LATE:].mean()),
                    "moving": float((sim[:, -LATE:].mean(-1) > MOVING_MPS).mean()), "log_start_s": float(first_moving_s(log_speed)),
                    "rollout_start_s": float(np.median(first_moving_s(sim)))})
    return out


def summarise(records: list[dict], common: dict) -> dict:
    """The JSON line of a scene set's records."""
    off = [r for r in records if r["drives_off"]]
    stay = [r for r in records if not r["drives_off"]]
    row = {"kind": "departures", "standing": len(records), "drive_off_in_log": len(off), **common}
    if off:
        log, sim = np.mean([r["log"] for r in off]), np.mean([r["rollout"] for r in off])
        row.update(log_mps=round(float(log), 2), rollout_mps=round(float(sim), 2), ratio=round(float(sim / max(log, 1e-9)), 3),
                   rollouts_moving=round(float(np.mean([r["moving"] for r in off])), 3),
                   log_start_s=round(float(np.median([r["log_start_s"] for r in off])), 1),
                   rollout_start_s=round(float(np.median([r["rollout_start_s"] for r in off])), 1))
    if stay:
        row.update(keep_standing_log_mps=round(float(np.mean([r["log"] for r in stay])), 2),
                   keep_standing_rollout_mps=round(float(np.mean([r["rollout"] for r in stay])), 2))
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    drift.vehicle_rollout_arguments(ap, rollouts=8)
    args = ap.parse_args(argv)
    model, sets, rollout_kwargs, fields = drift.vehicle_rollout_sets(args)
    for name, scenes in sets.items():
        records = []
        for scene in scenes:
            records += scene_records(drift.rollout_from_log(model, scene, **rollout_kwargs), scene)
        print(json.dumps(summarise(records, {"benchmark": "departures", "set": name, "scenes": len(scenes), **fields})), flush=True)


if __name__ == "__main__":
    main()
