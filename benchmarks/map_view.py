"""Benchmark: how much of the road a prior's moving vehicles see.

MotionNet's map-to-agent attention takes each agent's ``map_neighbours`` nearest road pieces within
``map_radius_m`` (:class:`smart_marl.model.SmartConfig`; smart-1m: 32 within 30 m). Where the road is dense the
count binds before the radius: this prints, per scene set, for the vehicles moving faster than 5 m/s at the current
frame, how many road pieces lie within the radius, the distance of the farthest piece the model takes (the radius
it really sees), and how far ahead along the vehicle's heading the farthest piece it takes lies (the road it can
see coming). One JSON line per set::

    {"set": "real", "vehicles": 150, "map_neighbours": 32, "map_radius_m": 30.0, "pieces_within_radius_median": 238,
     "share_count_binds": 1.0, "seen_radius_m_median": 9.4, "seen_ahead_m_median": 8.5, "seen_ahead_m_p10": 6.2}

    .venv/bin/python benchmarks/map_view.py [--prior PATH] [--set NAME=PATH ...] [--max-scenes 80] [--neighbours K]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import prior_speed_drift as drift  # noqa: E402  (benchmarks/ is not a package)

from smart_marl.model.batch import scene_road  # noqa: E402
from smart_marl.model.checkpoint import load_checkpoint  # noqa: E402
from smart_marl.model.layers import knn_within  # noqa: E402
from smart_marl.scenario import AgentType  # noqa: E402

def vehicle_views(scene, road_pose: np.ndarray, neighbours: int, radius_m: float) -> np.ndarray:
    """[M, 3] for each vehicle of ``scene`` moving at the current frame (``prior_speed_drift.MOVING_MPS``): the road
    pieces (poses ``road_pose`` [R, 3]) within ``radius_m``, the distance of the farthest piece the model's own
    neighbour search takes (:func:`~smart_marl.model.layers.knn_within`, the ``neighbours`` nearest within the radius),
    and how far ahead along the vehicle's heading the farthest of those lies (0 where it takes none)."""
    tr, cf = scene.tracks, scene.current_frame
    v = np.linalg.norm(tr.position[:, cf, :2] - tr.position[:, cf - 1, :2], axis=-1) / 0.1
    moving = np.flatnonzero((tr.types == int(AgentType.VEHICLE)) & tr.valid[:, cf] & tr.valid[:, cf - 1]
                            & (v > drift.MOVING_MPS[AgentType.VEHICLE]))
    if not len(moving) or not len(road_pose):
        return np.zeros((len(moving), 3))
    xy = tr.position[moving, cf, :2]
    rel = road_pose[None, :, :2] - xy[:, None]  # [M, R, 2]
    d = np.linalg.norm(rel, axis=-1)
    index, mask = knn_within(torch.from_numpy(xy)[None].float(), torch.from_numpy(road_pose[:, :2])[None].float(), radius_m,
                             neighbours, torch.ones(1, len(moving), dtype=torch.bool), torch.ones(1, len(road_pose), dtype=torch.bool))
    index, mask = index[0].numpy(), mask[0].numpy()  # [M, K]
    heading = tr.heading[moving, cf]
    ahead = np.einsum("mrk,mk->mr", rel, np.stack([np.cos(heading), np.sin(heading)], -1))  # [M, R]
    rows = np.arange(len(moving))[:, None]
    seen = np.where(mask, d[rows, index], 0.0).max(1)
    seen_ahead = np.where(mask, ahead[rows, index], 0.0).max(1).clip(min=0.0)
    return np.stack([(d < radius_m).sum(1), seen, seen_ahead], 1).astype(float)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--prior", default="embedded")
    ap.add_argument("--set", dest="sets", action="append", metavar="NAME=PATH[,PATH...]",
                    help="a named set of scenes; repeatable (default: the shared real 91-frame scenes)")
    ap.add_argument("--max-scenes", type=int, default=0, help="the first N scenes of each set (0: all)")
    ap.add_argument("--neighbours", type=int, default=None, help="map neighbours to measure (default: the prior's)")
    args = ap.parse_args(argv)
    ck = load_checkpoint(args.prior)
    cfg = ck.model.config
    k = args.neighbours or cfg.map_neighbours
    sets = drift.scene_sets(args.sets or [f"real={','.join(str(drift.SHARED / p) for p in drift.REAL_91_FRAMES)}"])
    for name, scenes in sets.items():
        scenes = scenes[: args.max_scenes] if args.max_scenes else scenes
        views = np.concatenate([vehicle_views(sc, scene_road(sc, ck.road_vocab, cfg.road_settings).pose, k, cfg.map_radius_m)
                                for sc in scenes])
        if not len(views):
            continue
        print(json.dumps({"set": name, "scenes": len(scenes), "vehicles": len(views), "prior": args.prior, "map_neighbours": k,
                          "map_radius_m": cfg.map_radius_m, "pieces_within_radius_median": float(np.median(views[:, 0])),
                          "share_count_binds": round(float((views[:, 0] > k).mean()), 3),
                          "seen_radius_m_median": round(float(np.median(views[:, 1])), 1),
                          "seen_ahead_m_median": round(float(np.median(views[:, 2])), 1),
                          "seen_ahead_m_p10": round(float(np.percentile(views[:, 2], 10)), 1)}), flush=True)


if __name__ == "__main__":
    main()
