"""Benchmark of the environment stage's input checks: what checking a step's actions costs the batched
TorchRL env (``envs.smart_traffic_batched_v0.check_actions``: the tensor's dtype and shape, every live
agent's token id in 0..V-1 and finite, one ``.any()`` the only host sync).

``env.step`` on ``--num-scenes`` scenes (default 32; the embedded scenes and prior, 4 controlled moving
vehicles a scene, each taking its prior's most likely token), timed with the check on and with it
bypassed: ``check_actions`` replaced, in this process, by a pass-through (the core then casts the
actions itself, as the env did before the check). The two settings alternate over ``--repeats`` runs
each; every run starts from the same reset (``set_seed(0)``) and times ``--steps`` steps.

Prints one JSON line per run (``check`` "on" or "off", ``repeat``, ``step_ms``: the median of its steps)
and a last line, ``summary``: the medians of the runs side by side, their difference, and the check
alone timed on the same step's tensors (``check_alone_us``, per call).

    .venv/bin/python benchmarks/env_input_checks.py [--num-scenes 32] [--steps 8] [--repeats 5] [--threads 1]
"""

from __future__ import annotations

import argparse
import json
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


def time_steps(env, steps: int) -> list[float]:
    """Seconds of each of ``steps`` steps from a fresh reset (the same scenes and seed every call)."""
    from torchrl.envs.utils import step_mdp

    env.set_seed(0)
    td = env.reset()
    out = []
    for _ in range(steps):
        td["agents", "action"] = td["agents", "observation", "prior_logits"].argmax(-1)
        sync(env.device)
        t0 = time.perf_counter()
        td = env.step(td)
        sync(env.device)
        out.append(time.perf_counter() - t0)
        td = step_mdp(td)
    return out


def time_check_alone(module, env, calls: int = 2000) -> float:
    """Microseconds per call of the check on a step's actions and live mask."""
    env.set_seed(0)
    td = env.reset()
    actions, live = td["agents", "observation", "prior_logits"].argmax(-1), env.core.live
    module.check_actions(actions, live, env.vocab_size)  # warm
    sync(env.device)
    t0 = time.perf_counter()
    for _ in range(calls):
        module.check_actions(actions, live, env.vocab_size)
    sync(env.device)
    return 1e6 * (time.perf_counter() - t0) / calls


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--num-scenes", type=int, default=32)
    p.add_argument("--max-agents", type=int, default=4)
    p.add_argument("--steps", type=int, default=8, help="timed steps per run (at most the horizon, 16)")
    p.add_argument("--repeats", type=int, default=5, help="runs per setting, the settings alternating")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu")
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    from envs import smart_traffic_batched_v0 as module

    env = module.SmartTrafficBatchedEnv(scenarios="embedded", prior="embedded", num_scenes=args.num_scenes,
                                        max_agents=args.max_agents, horizon_steps=16, terminate_on=(), device=args.device)
    common = dict(benchmark="env_input_checks", num_scenes=args.num_scenes, max_agents=args.max_agents, steps=args.steps,
                  torch_threads=args.threads, device=args.device, cpu=platform.processor() or platform.machine())
    checked = module.check_actions
    bypass = lambda actions, live, vocab_size: actions  # noqa: E731  the core casts them, as before the check
    time_steps(env, 2)  # warm-up: every scene's prior started once, kept for the resets after
    runs: dict[str, list[float]] = {"on": [], "off": []}
    try:
        for repeat in range(args.repeats):
            for check in ("on", "off") if repeat % 2 == 0 else ("off", "on"):
                module.check_actions = checked if check == "on" else bypass
                step_ms = 1000 * statistics.median(time_steps(env, args.steps))
                runs[check].append(step_ms)
                print(json.dumps({**common, "check": check, "repeat": repeat, "step_ms": round(step_ms, 2)}), flush=True)
    finally:
        module.check_actions = checked
    on, off = statistics.median(runs["on"]), statistics.median(runs["off"])
    print(json.dumps({**common, "summary": True, "step_ms_check_on": round(on, 2), "step_ms_check_off": round(off, 2),
                      "difference_ms": round(on - off, 3), "difference_share": round((on - off) / off, 4),
                      "check_alone_us": round(time_check_alone(module, env), 1), "runs_per_setting": args.repeats}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
