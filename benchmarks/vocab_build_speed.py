"""How long k-disks takes to build a motion vocabulary from many snippets on this machine.

The real scenes in ../shared/data hold only ~80k vehicle snippets, so the 1M snippets are the real
vehicle snippets plus jittered copies of them (``augment_snippets``: speed scaled by up to +-15 %,
heading and lateral increments jittered), said so in the output. Prints one JSON line: snippets,
vocab_size, seconds, tolerance_m, passes, uncovered, torch threads.

    .venv/bin/python benchmarks/vocab_build_speed.py [--snippets 1000000] [--size 2048]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from smart_marl.scenario import AgentType  # noqa: E402
from smart_marl.tokens import BOX_SIZE_M, augment_snippets, box_contour, collect_snippets, kdisks  # noqa: E402
from token_reconstruction import load_real_scenes  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--snippets", type=int, default=1_000_000)
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    snippets, prov = collect_snippets(load_real_scenes(args.data))
    real = snippets[AgentType.VEHICLE]
    rng = np.random.default_rng(args.seed)
    extra = max(args.snippets - len(real), 0)
    samples = np.concatenate([real, augment_snippets(real, extra, rng)])[: args.snippets]
    contour = box_contour(samples, *BOX_SIZE_M[AgentType.VEHICLE]).reshape(len(samples), -1, 2)
    t0 = time.time()
    res = kdisks(contour, args.size, seed=args.seed, progress=True, desc="k-disks veh")
    seconds = time.time() - t0
    print(json.dumps({"agent_type": "vehicle", "snippets": len(samples), "real_snippets": int(min(len(real), len(samples))),
                      "augmented_snippets": int(extra), "vocab_size": len(res.centre_indices), "seconds": round(seconds, 1),
                      "tolerance_m": round(res.tolerance_m, 4), "passes": res.passes, "uncovered": res.num_uncovered,
                      "torch_threads": torch.get_num_threads()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
