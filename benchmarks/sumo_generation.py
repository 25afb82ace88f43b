"""Speed of SUMO scene generation (smart_marl.sources.sumo) into a scene cache.

Prints one JSON line per worker count: scenes per second (wall clock) and agent-seconds per
CPU-second (valid agent frames x 0.1 s of the written scenes, over the CPU time of this process
and its children: the worker processes, netgenerate), the median over ``--repeats`` runs with the
seeds 0, 1, 2... (each run simulates different random networks; 1 and 2 workers see the same ones).
Usage: python benchmarks/sumo_generation.py [--scenes 16] [--repeats 3] [--workers 1 2] [--legacy]
(``--legacy``: the first generator's traffic, SumoConfig.legacy(), for a before/after comparison).
Needs the sumo extra: pip install "smart-marl[sumo]".
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import tempfile
import time

from smart_marl.sources.sumo import SumoConfig, generate_to_dir


def _cpu_s() -> float:
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--scenes-per-sim", type=int, default=8)
    parser.add_argument("--legacy", action="store_true", help="the first generator's traffic (SumoConfig.legacy())")
    args = parser.parse_args()
    config = (SumoConfig.legacy if args.legacy else SumoConfig)(scenes_per_sim=args.scenes_per_sim)
    for workers in args.workers:
        rates, agent_rates, agents = [], [], []
        for repeat in range(args.repeats):
            with tempfile.TemporaryDirectory() as out:
                wall0, cpu0 = time.perf_counter(), _cpu_s()
                report = generate_to_dir(out, args.scenes, seed=repeat, config=config, workers=workers, progress=False)
                wall, cpu = time.perf_counter() - wall0, _cpu_s() - cpu0
            rates.append(report.scenes / wall)
            agent_rates.append(report.agent_seconds / cpu)
            agents.append(report.agent_seconds / max(report.scenes, 1) / 9.1)
        print(json.dumps({
            "benchmark": "sumo_generation", "traffic": "legacy" if args.legacy else "tuned", "workers": workers, "scenes": args.scenes, "repeats": args.repeats,
            "scenes_per_s": round(statistics.median(rates), 3),
            "agent_seconds_per_cpu_s": round(statistics.median(agent_rates), 1),
            "mean_valid_agents_per_frame": round(statistics.mean(agents), 1), "cpu_count": os.cpu_count(),
        }), flush=True)


if __name__ == "__main__":
    main()
