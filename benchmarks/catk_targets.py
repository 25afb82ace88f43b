"""Benchmark: what CAT-K trains on, against teacher forcing (why closed-loop fine-tuning drives the prior off
the road; docs/experiments/2026-11-26-keeping-gaps.md).

For the first ``--scenes`` scenes of a scene cache, the vehicles' future tokens (from the current frame on)
are made twice: by rolling matching of the log (teacher forcing, what the prior was trained on) and by CAT-K
under ``--prior`` (``smart_marl.catk``: among the prior's top K, the closest to the log; with ``--avoid``
keeping gaps). Per mode, one JSON line: how far the token sequence has drifted from the log at each step
(metres; of the vehicles whose log moves at least 2 m/s in the step), and what its targets ask for in 0.5 s: sideways offset and turn (|left| m,
|turn| rad, p50 / p90 / p99), the target's end error against the logged pose (m), and the share of targets
outside the prior's own top K (a target the model itself would never draw).

    .venv/bin/python benchmarks/catk_targets.py --cache data/rl_train --scenes 16 --prior embedded --top-k 32
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from smart_marl.cache import SceneCache  # noqa: E402
from smart_marl.catk import catk_tokens, first_future_step  # noqa: E402
from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors  # noqa: E402
from smart_marl.model.checkpoint import load_checkpoint, resolve_checkpoint_path  # noqa: E402
from smart_marl.scenario import AgentType  # noqa: E402
from smart_marl.tokens import compose_poses, tokenize_motion  # noqa: E402


MOVING_M = 1.0
"""A vehicle counts at a token step when its log moves at least this far in it (2 m/s)."""


def _quantiles(x: np.ndarray) -> list[float]:
    return [round(float(v), 3) for v in np.quantile(x, [0.5, 0.9, 0.99])] if len(x) else []


def target_stats(model, scenes, roads, vocab, tokens, top_k: int) -> dict:
    """The module docstring's figures for ``tokens`` (one MotionTokens per scene)."""
    v = vocab[AgentType.VEHICLE]
    drift, left, turn, end_err, outside = [], [], [], [], []
    for sc, road, mt in zip(scenes, roads, tokens):
        kc = first_future_step(sc)
        batch = collate_scenes([scene_tensors(sc, vocab, road, road_mask_prob=0.0, rng=0, motion_tokens=mt)])
        with torch.no_grad():
            feats, _ = model(batch)
        keep = np.flatnonzero(mt.valid.any(1))
        tr = sc.tracks
        for j, row in enumerate(keep):
            if tr.types[row] != int(AgentType.VEHICLE):
                continue
            with torch.no_grad():  # [S, V]: position k predicts token k + 1
                logits = model.motion_heads[0](feats[0, j]).numpy()
            for k in range(kc, mt.num_steps):
                if not (mt.valid[row, k] and mt.reached_valid[row, k]):
                    continue
                b0, b1 = mt.boundaries[k], mt.boundaries[k + 1]
                if np.linalg.norm(tr.position[row, b1, :2] - tr.position[row, b0, :2]) < MOVING_M:
                    continue  # parked and waiting cars: their tokens are exact either way
                drift.append(np.linalg.norm(mt.reached[row, k, :2] - tr.position[row, b0, :2]))
                target = int(mt.nearest_ids[row, k])
                end = v.poses[target, -1]
                left.append(abs(end[1]))
                turn.append(abs(end[2]))
                placed = compose_poses(mt.start_pose[row, k].astype(np.float64), end.astype(np.float64)[None])[0]
                end_err.append(np.linalg.norm(placed[:2] - tr.position[row, b1, :2]))
                if k >= 1:
                    top = np.argpartition(-logits[k - 1], top_k)[:top_k]
                    outside.append(target not in top)
    return {"vehicle_targets": len(left), "drift_m_p50_p90_p99": _quantiles(np.array(drift)),
            "target_abs_left_m_p50_p90_p99": _quantiles(np.array(left)), "target_abs_turn_rad_p50_p90_p99": _quantiles(np.array(turn)),
            "target_end_error_m_p50_p90_p99": _quantiles(np.array(end_err)),
            "targets_outside_prior_top_k": round(float(np.mean(outside)), 4) if outside else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", required=True, help="a scene cache folder")
    ap.add_argument("--scenes", type=int, default=16)
    ap.add_argument("--prior", default="embedded")
    ap.add_argument("--top-k", type=int, default=32)
    ap.add_argument("--avoid", action="store_true", help="CAT-K keeping gaps (catk_avoid)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    ck = load_checkpoint(resolve_checkpoint_path(args.prior))
    model, vocab, road_vocab = ck.model.eval(), ck.motion_vocab, ck.road_vocab
    cache = SceneCache(args.cache)
    scenes = [cache[i] for i in range(min(args.scenes, len(cache)))]
    roads = [scene_road(sc, road_vocab, model.config.road_settings) for sc in scenes]
    modes = {"teacher_forcing": [tokenize_motion(sc, vocab) for sc in scenes],
             "catk": catk_tokens(model, scenes, roads, vocab, args.top_k, avoid=args.avoid)}
    for mode, tokens in modes.items():
        row = {"mode": mode, "prior": args.prior, "scenes": len(scenes), "top_k": args.top_k, "avoid": args.avoid,
               **target_stats(model, scenes, roads, vocab, tokens, args.top_k)}
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
