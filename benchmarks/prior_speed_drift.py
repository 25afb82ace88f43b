"""Benchmark of a prior's kinematics in closed loop: do the vehicles it drives keep their speed?

For every scene, the vehicles moving faster than ``--moving-mps`` at the current frame (simulated
by the prior), the mean speed in the prior's rollouts against the logged mean speed of the same
vehicles, at several horizons; and the teacher-forced bias of the model's most likely next token
(the training path, logged history as input): mean speed of the argmax token over the mean speed
of the target token, for the same moving vehicles at every step.

Output (stdout, one JSON object per line)::

    {"kind": "horizon", "t_s": 2.0, "rollout_mps": ..., "log_mps": ..., "ratio": ..., "vehicles": ...}
    {"kind": "teacher_forced", "argmax_mps": ..., "target_mps": ..., "ratio": ..., "rows": ...}

A prior with no drift has ratios near 1 at every horizon (the log itself slows down where the
traffic does, which the rollout should follow, not exceed).

    .venv/bin/python benchmarks/prior_speed_drift.py [--prior PATH] [--scenes GLOB ...] [--rollouts 8]

Default: the embedded prior on the two shared WOMD records, 8 rollouts, top-5 sampling, seed 0.
Measured figures (embedded prior at steps 250 and 800) are in the README's model card.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
HORIZONS_S = (0.5, 1.0, 2.0, 4.0, 6.0, 8.0)


def rollout_speeds(checkpoint, scene, num_rollouts: int, top_k: int, seed: int, moving_mps: float):
    """(rollout mean speed [T], logged mean speed [T]) of the moving vehicles, frames cf+1..cf+80."""
    from smart_marl.rollout import rollout
    from smart_marl.scenario import AgentType

    res = rollout(checkpoint, [scene], num_rollouts=num_rollouts, num_steps=16, top_k=top_k, seed=seed)
    tr, cf = scene.tracks, scene.current_frame
    a = res.agent_types.shape[1]
    v_now = np.linalg.norm(tr.velocity[:a, cf], axis=-1)
    moving = res.simulated[0] & (res.agent_types[0] == int(AgentType.VEHICLE)) & (v_now > moving_mps)
    xy = res.trajectory[:, moving, :, :2]  # [R, M, 80, 2]
    start = np.broadcast_to(tr.position[:a][moving, cf, None, :2], (xy.shape[0], int(moving.sum()), 1, 2))
    speed = np.linalg.norm(np.diff(np.concatenate([start, xy], 2), axis=2), axis=-1) / 0.1  # [R, M, 80]
    frames = slice(cf + 1, cf + 1 + xy.shape[2])
    logged = np.where(tr.valid[:a][moving, frames], np.linalg.norm(tr.velocity[:a][moving, frames], axis=-1), np.nan)
    return speed.mean((0, 1)) if moving.any() else np.full(xy.shape[2], np.nan), logged, int(moving.sum())


def teacher_forced_bias(ck, scene, moving_mps: float):
    """(sum of argmax-token speeds, sum of target-token speeds, rows) over the moving vehicles' steps."""
    from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors
    from smart_marl.scenario import AgentType
    from smart_marl.tokens.motion import tokenize_motion

    mv = ck.motion_vocab
    mt = tokenize_motion(scene, mv)
    d = scene_tensors(scene, mv, scene_road(scene, ck.road_vocab), noise_topk=0, road_mask_prob=0.0, rng=0, motion_tokens=mt)
    b = collate_scenes([d])
    with torch.no_grad():
        feats, _ = ck.model(b)
        logits = ck.model.motion_logits(feats, b.agent_type)[int(AgentType.VEHICLE)][0]  # [N, S, V]
    keep = np.flatnonzero(mt.valid.any(1))
    tr = scene.tracks
    moving = (tr.types[keep] == int(AgentType.VEHICLE)) & (np.linalg.norm(tr.velocity[keep, scene.current_frame], axis=-1) > moving_mps)
    rows = torch.from_numpy(moving)[:, None] & b.target_valid[0]
    token_mps = torch.from_numpy(mv[AgentType.VEHICLE].poses[:, -1, :2]).norm(dim=-1) / 0.5
    pred, tgt = logits.argmax(-1)[rows], b.target_tokens[0][rows]
    return float(token_mps[pred].sum()), float(token_mps[tgt].sum()), int(rows.sum())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--prior", default="embedded", help="checkpoint path, or 'embedded'")
    ap.add_argument("--scenes", nargs="*", default=[str(SHARED / "womd_tfrecord" / "*.tfrecord")])
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--top-k", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--moving-mps", type=float, default=5.0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    from smart_marl.model.checkpoint import load_checkpoint
    from smart_marl.readers import read_scenarios

    ck = load_checkpoint(args.prior)  # a path or "embedded"
    ck.model.eval()
    roll_sum, log_sum, log_count, tf = 0.0, 0.0, 0.0, np.zeros(3)
    vehicles = 0
    for pattern in args.scenes:
        for scene in read_scenarios(pattern):
            r, lg, m = rollout_speeds(ck, scene, args.rollouts, args.top_k, args.seed, args.moving_mps)
            if m:
                roll_sum = roll_sum + r * m
                log_sum, log_count = log_sum + np.nansum(lg, 0), log_count + np.isfinite(lg).sum(0)
                vehicles += m
                tf += teacher_forced_bias(ck, scene, args.moving_mps)
            print(json.dumps({"kind": "scene", "scenario_id": scene.scenario_id, "moving_vehicles": m}), flush=True)
    roll_mean = np.asarray(roll_sum) / max(vehicles, 1)
    log_mean = np.asarray(log_sum) / np.maximum(log_count, 1)  # over the vehicles logged at each frame
    for t in HORIZONS_S:
        k = int(round(t * 10)) - 1
        line = {"kind": "horizon", "t_s": t, "rollout_mps": round(float(roll_mean[k]), 3), "log_mps": round(float(log_mean[k]), 3),
                "ratio": round(float(roll_mean[k] / log_mean[k]), 3), "vehicles": vehicles, "rollouts": args.rollouts,
                "top_k": args.top_k, "prior": args.prior}
        print(json.dumps(line), flush=True)
    print(json.dumps({"kind": "teacher_forced", "argmax_mps": round(tf[0] / max(tf[2], 1), 3), "target_mps": round(tf[1] / max(tf[2], 1), 3),
                      "ratio": round(tf[0] / max(tf[1], 1e-9), 3), "rows": int(tf[2]), "prior": args.prior}), flush=True)


if __name__ == "__main__":
    main()
