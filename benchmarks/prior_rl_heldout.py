"""The prior-RL objective on held-out scenes: the share of simulated agent-rollouts that run into another
agent (or leave the road) when every leader with a follower brakes hard, for each checkpoint given.

Exactly the rollouts and penalties of :mod:`smart_marl.prior_rl` (:func:`~smart_marl.prior_rl.rollout_group`),
on the first ``--scenes`` scenes of a set the runs did not train on, with fixed seeds, so that checkpoints
are compared on the same scenes, braking edits and draws. One JSON line per checkpoint.

    .venv/bin/python benchmarks/prior_rl_heldout.py --scenes data/rl_heldout embedded runs/prior_rl/iter0020
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from smart_marl.model.batch import scene_road
from smart_marl.model.checkpoint import load_checkpoint, load_embedded
from smart_marl.prior_rl import PriorRLConfig, rollout_group
from smart_marl.train_data import open_scenes


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+", help="checkpoint paths, or 'embedded'")
    p.add_argument("--scenes", default="data/rl_heldout")
    p.add_argument("--num-scenes", type=int, default=32)
    p.add_argument("--rollouts", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    scenes = open_scenes(args.scenes)
    scenes = [scenes[i] for i in range(min(args.num_scenes, len(scenes)))]
    cfg = PriorRLConfig(rollouts=args.rollouts, brake_share=1.0)
    for path in args.checkpoints:
        ck = load_embedded() if path == "embedded" else load_checkpoint(path)
        model, vocab = ck.model.eval(), ck.motion_vocab
        t0 = time.time()
        sums: dict[str, float] = {}
        for i, sc in enumerate(scenes):
            road = scene_road(sc, ck.road_vocab, model.config.road_settings)
            rng = np.random.default_rng([args.seed, i])
            gen = torch.Generator().manual_seed(args.seed * 7919 + i)
            *_, shares = rollout_group(model, sc, road, vocab, cfg, rng, gen)
            for k, v in shares.items():
                sums[k] = sums.get(k, 0.0) + v
        print(json.dumps({"checkpoint": path, "scenes": len(scenes), "rollouts": args.rollouts, "seed": args.seed,
                          **{f"{k}_share": round(v / len(scenes), 4) for k, v in sums.items()},
                          "seconds": round(time.time() - t0, 1)}), flush=True)


if __name__ == "__main__":
    main()
