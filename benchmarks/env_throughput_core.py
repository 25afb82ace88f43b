"""Benchmark of the environment's batched core on its own (``envs._core.TrafficCore``, the engine under
both faces of the environment), for machines that have torch but not TorchRL or PettingZoo (a lent
GPU machine): how many agent-steps per second one process gets at a given number of scenes.

Prints one JSON line per number of scenes: ``num_scenes``, ``device`` (and ``gpu``), ``agent_steps_per_s``
(every agent present in a scene advanced by one 0.5 s token), ``controlled_agent_steps_per_s``,
``outside_forward_share`` (the share of the step outside the prior's forward: sampling with collision-aware
token exclusion, dynamics, events, rewards, observations), ``refill_ms_per_scene``, peak memory. The step
is the core's, with observations and the controlled agents' prior logits read every step, as the TorchRL
face reads them; TorchRL's own bookkeeping is not included (``env_throughput.py`` measures the TorchRL face).
Actions: each controlled agent's prior most likely token (with ``--shield [CHECKS]``, of the tokens the shield leaves).
Finished scenes are refilled from the pool in order (their starts are kept after the first pass, which is not
timed). Medians of ``--repeats``.

    python benchmarks/env_throughput_core.py --device cuda --num-scenes 32,128,512,1024 --scenes DIR_OR_SHARDS...
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_core(core, pool, args, types, steps: int) -> dict:
    from envs._pool import next_scenes

    dev = core.device
    step_s = refill_s = forward_s = 0.0
    agents = ctrl = refilled = 0
    for _ in range(steps):
        done = ~core.live.any(1)
        if bool(done.any()):
            rows = done.nonzero().squeeze(1).tolist()
            sync(dev)
            t0 = time.perf_counter()
            _, scenes = next_scenes(pool, len(rows), args.controlled, args.max_agents, types)
            core.refill(rows, scenes)
            core.observations(), core.prior_logits()
            sync(dev)
            refill_s += time.perf_counter() - t0
            refilled += len(rows)
        present, live = int(core.present.sum()), int(core.live.sum())
        f0 = core.timing["forward_s"]
        sync(dev)
        t0 = time.perf_counter()
        actions = core.prior_logits().argmax(-1)
        core.step(actions)
        core.observations()
        core.prior_logits()  # the next step's logits: the forward of the step the TorchRL face returns
        sync(dev)
        step_s += time.perf_counter() - t0
        forward_s += core.timing["forward_s"] - f0
        agents += present
        ctrl += live
    return dict(step_s=step_s, refill_s=refill_s, forward_s=forward_s, agents=agents, ctrl=ctrl, refilled=refilled, steps=steps)


def main() -> int:
    from envs._arguments import shield_option
    from envs._shield import DEFAULT_SHIELD_CHECKS

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="*", default=["embedded"], help="scene sources (default: the package's sample scenes)")
    p.add_argument("--prior", default="embedded")
    p.add_argument("--num-scenes", default="8,32,128")
    p.add_argument("--steps", type=int, default=32)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--horizon", type=int, default=16)
    p.add_argument("--controlled", default="moving_vehicles")
    p.add_argument("--max-agents", type=int, default=4)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--no-collision-avoidance", action="store_true")
    p.add_argument("--shield", nargs="?", type=shield_option, const=DEFAULT_SHIELD_CHECKS, default=(),
                   help="the controlled agents' shield (envs._shield), checked to the top 3: its checks joined with '+' "
                   "(alone: collision+offroad, shield=True)")
    p.add_argument("--tf32", action="store_true", help="CUDA: TensorFloat-32 matrix products (torch.backends.cuda.matmul.allow_tf32)")
    p.add_argument("--profile", action="store_true", help="also print torch.profiler's table of the timed steps' heaviest operations")
    args = p.parse_args()
    checks = args.shield
    torch.set_num_threads(args.threads)
    if args.tf32:
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True

    from envs._core import TrafficCore
    from envs._pool import ScenePool, next_scenes
    from smart_marl.model.checkpoint import load_prior
    from smart_marl.tokens import MOTION_TYPES

    device = torch.device(args.device)
    model, vocab = load_prior(args.prior, device)
    size = vocab[MOTION_TYPES[0]].size
    types = [int(t) for t in MOTION_TYPES if vocab[t].size == size]
    common = dict(benchmark="env_throughput_core", background="prior", prior=args.prior, controlled=args.controlled,
                  max_agents=args.max_agents, horizon_steps=args.horizon, device=str(device), torch=torch.__version__,
                  torch_threads=args.threads, cpu=platform.processor() or platform.machine(), cpus=os.cpu_count(),
                  avoid_collisions=not args.no_collision_avoidance, shield="+".join(checks) or False, tf32=args.tf32)
    if device.type == "cuda":
        common["gpu"] = torch.cuda.get_device_name(device)
    for b in [int(x) for x in args.num_scenes.split(",")]:
        pool = ScenePool(args.scenes, "sequential", max_loaded=4096)
        common["pool_scenes"] = len(pool)
        core = TrafficCore(model, vocab, "prior", args.horizon, terminate_on=(), device=device, prior_cache_size=4096,
                           avoid_collisions=not args.no_collision_avoidance,
                           **(dict(shield=checks, shield_top_k=3) if checks else {}))
        t0 = time.perf_counter()
        _, scenes = next_scenes(pool, b, args.controlled, args.max_agents, types)
        core.reset(scenes, seed=0, num_agents=args.max_agents)
        core.observations(), core.prior_logits()
        sync(device)
        first_reset_s = time.perf_counter() - t0
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        time_core(core, pool, args, types, max(args.horizon, len(pool) * args.horizon // b + 1))  # warm-up: every scene started
        runs = [time_core(core, pool, args, types, args.steps) for _ in range(args.repeats)]
        if args.profile:
            from torch.profiler import ProfilerActivity, profile

            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
            with profile(activities=acts) as prof:
                time_core(core, pool, args, types, 4)
            key = "cuda_time_total" if device.type == "cuda" else "cpu_time_total"
            print(prof.key_averages().table(sort_by=key, row_limit=25), file=sys.stderr, flush=True)
        rate = [r["agents"] / r["step_s"] for r in runs]
        line = dict(num_scenes=b, agent_steps_per_s=round(statistics.median(rate), 1),
                    controlled_agent_steps_per_s=round(statistics.median(r["ctrl"] / r["step_s"] for r in runs), 1),
                    scene_steps_per_s=round(statistics.median(b * r["steps"] / r["step_s"] for r in runs), 1),
                    outside_forward_share=round(1 - statistics.median(r["forward_s"] for r in runs)
                                                / statistics.median(r["step_s"] for r in runs), 3),
                    refill_ms_per_scene=round(1000 * statistics.median(r["refill_s"] / max(r["refilled"], 1) for r in runs), 2),
                    agents_per_scene=round(statistics.median(r["agents"] / (b * r["steps"]) for r in runs), 1),
                    first_reset_s=round(first_reset_s, 2), agent_steps_per_s_runs=[round(x, 1) for x in rate], **common)
        if device.type == "cuda":
            line["cuda_peak_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20)
        print(json.dumps(line), flush=True)
        del core
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
