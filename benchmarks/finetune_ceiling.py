"""Benchmark: how good can a policy restricted to the prior's top k tokens be? (The ceiling of the
fine-tuning action space.)

The fine-tuned policies pick among the prior's top 3 tokens (``reference_top_k=3``). This runs a
policy that knows the answer within that space: the log-following expert restricted to the prior's
top k (:class:`agents.policy.ExpertWithinTopK`: of those tokens, the one that, followed by any token,
comes closest to the logged path over the next two token steps), on the held-out
scenes and seeds of ``benchmarks/finetune_generalisation.py`` with its rows' settings. If even this policy
stays near the prior, no reward or amount of data can teach a top-k policy much more. One JSON
line per (set, k), rows cached in ``--run-dir`` like the generalisation benchmark's.

    .venv/bin/python benchmarks/finetune_ceiling.py --heldout data/rl_heldout --ks 3,16 --run-dir runs/generalisation
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from finetune_generalisation import cached, emit, evaluate, held_out  # noqa: E402

from agents.policy import ExpertWithinTopK  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--heldout", required=True, help="generated held-out scenes (a scene cache)")
    p.add_argument("--real-heldout", nargs="*", default=[], help="real held-out scenes")
    p.add_argument("--ks", default="3,16")
    p.add_argument("--eval-scenes", type=int, default=200)
    p.add_argument("--eval-seeds", type=int, default=1)
    p.add_argument("--real-seeds", type=int, default=48)
    p.add_argument("--config", default="scale")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--run-dir", default="runs/generalisation")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE")
    args = p.parse_args()

    from agents import finetune as ft

    torch.set_num_threads(args.threads)
    base = ft.load_finetune_config(args.config, list(args.overrides))
    model, vocab = ft.load_prior(base.prior)
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    sets = [("generated", args.heldout, args.eval_scenes, args.eval_seeds)]
    sets += [("real", args.real_heldout, 10**6, args.real_seeds)] if args.real_heldout else []
    for name, spec, count, num_seeds in sets:
        scenes = held_out(ft, base, vocab, spec, count)
        seeds = list(range(base.eval_seed, base.eval_seed + num_seeds))
        for k in (int(x) for x in args.ks.split(",")):
            policy = ExpertWithinTopK(k)
            path = run_dir / f"eval_{name}_expert_within_top-{k}.json"
            row = cached(path, lambda: evaluate(ft, base, scenes, {policy.name: policy}, seeds, model, vocab))["rows"][policy.name]
            emit({"kind": "eval", "set": name, "policy": policy.name, "k": k, "scenes": len(scenes), "seeds": num_seeds, "row": row})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
