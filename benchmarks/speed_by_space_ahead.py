"""Where a prior slows: the late speed of the moving vehicles of the shared real scenes, grouped by how much room
they have ahead at the current frame, for each prior given (side by side: the same scenes, rollouts and seeds).

A vehicle's room ahead is the distance to the nearest agent ahead of it in its lane (centre within
:data:`LANE_HALF_M` of its heading line) at the current frame; the groups are 0-15 m, 15-30 m, 30-60 m and
60 m or none. For each group and prior: the logged and the rollouts' mean speed over 7-8 s (8 rollouts) and,
from the second prior on, its ratio to the first prior's. Used to ask whether a fine-tuned prior slows only
behind others (what braking training should teach) or everywhere. One JSON line per (prior, group).

    .venv/bin/python benchmarks/speed_by_space_ahead.py embedded runs/prior_rl/iter0020
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from prior_speed_drift import LATE_FRAMES, NUM_FRAMES, _speeds_from_positions, rollout_from_log, rollout_xy, scene_sets  # noqa: E402
from smart_marl.braking import LANE_HALF_M, poses_relative_to, speeds_now  # noqa: E402
from smart_marl.model.checkpoint import load_checkpoint, load_embedded  # noqa: E402
from smart_marl.scenario import AgentType  # noqa: E402

GROUPS_M = (0.0, 15.0, 30.0, 60.0, np.inf)
MOVING_MPS = 3.0


def room_ahead(scene, i: int) -> float:
    """Metres to the nearest agent valid at the current frame ahead of track ``i`` in its lane (inf: none)."""
    rel = poses_relative_to(scene, i)
    ahead = scene.tracks.valid[:, scene.current_frame] & (rel[:, 0] > 0) & (np.abs(rel[:, 1]) < LANE_HALF_M)
    ahead[i] = False
    return float(rel[ahead, 0].min()) if ahead.any() else np.inf


def late_speeds(priors: dict, scenes, rollouts: int, seed: int) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(room ahead [V], logged late speed [V], {prior: rollouts' late speed [V]}) of the moving vehicles."""
    room, logged, sim = [], [], {k: [] for k in priors}
    late = slice(NUM_FRAMES - LATE_FRAMES, NUM_FRAMES)
    for sc in scenes:
        tr, cf = sc.tracks, sc.current_frame
        frames = np.arange(cf + 1, cf + 1 + NUM_FRAMES)
        res = {k: rollout_from_log(m, sc, 0, num_rollouts=rollouts, seed=seed) for k, m in priors.items()}
        first = next(iter(res.values()))
        a = first.agent_types.shape[1]
        v = speeds_now(sc)[:a]
        rows = first.simulated[0] & (tr.types[:a] == int(AgentType.VEHICLE)) & (v > MOVING_MPS) & tr.valid[:a][:, frames].all(1)
        for i in np.flatnonzero(rows):
            room.append(room_ahead(sc, int(i)))
            logged.append(_speeds_from_positions(tr.position[i, frames, :2], tr.position[i, cf, :2])[late].mean())
            for k, r in res.items():
                xy = rollout_xy(r, sc, np.array([i]))[:, 0]
                sim[k].append(_speeds_from_positions(xy, np.broadcast_to(tr.position[i, cf, :2], (len(xy), 2)))[:, late].mean())
    return np.array(room), np.array(logged), {k: np.array(x) for k, x in sim.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("priors", nargs="+", help="checkpoint paths, or 'embedded'; the first is the reference of the ratios")
    p.add_argument("--rollouts", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    priors = {name: load_embedded() if name == "embedded" else load_checkpoint(name) for name in args.priors}
    scenes = scene_sets(None)["real"]
    room, logged, sim = late_speeds(priors, scenes, args.rollouts, args.seed)
    ref = sim[args.priors[0]]
    for lo, hi in zip(GROUPS_M[:-1], GROUPS_M[1:]):
        m = (room >= lo) & ((room < hi) | np.isinf(hi))  # the last group: this far or nothing ahead
        for name, s in sim.items():
            row = {"prior": name, "room_ahead_m": [lo, None if np.isinf(hi) else hi], "vehicles": int(m.sum()),
                   "log_mps": round(float(logged[m].mean()), 3), "rollout_mps": round(float(s[m].mean()), 3),
                   "of_log": round(float(s[m].sum() / logged[m].sum()), 3), "of_first_prior": round(float(s[m].sum() / ref[m].sum()), 3),
                   "scenes": len(scenes), "rollouts": args.rollouts, "seed": args.seed, "late_s": [7.0, 8.0]}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
