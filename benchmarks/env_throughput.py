"""Benchmark of the environment stage: how fast ``envs.smart_traffic_v0`` steps on a real scene.

Prints one JSON line per (background, prior, controlled agents, raw or TorchRL-wrapped) with
``env_steps_per_s`` (token steps of 0.5 s), ``agent_steps_per_s`` (every agent present in the
scene advanced by one token: the scene's simulated agents, not only the controlled ones) and
``controlled_agent_steps_per_s``. Resets are timed apart (``raw_reset_ms``, the resets after the
first: the env keeps each scene's freshly started prior state). Actions are uniform random tokens; ``terminate_on=()`` so that every episode runs its
full horizon. The TorchRL rate wraps the same env in ``PettingZooWrapper(use_mask=True,
done_on_any=False)`` and steps it with random actions from its spec.

The default scene is WOMD 637f20cafde22ff8 (``motion_data_one_scenario.tfrecord``, 83 tracks, 50
of them valid at the current frame). The prior is ``--checkpoint`` when given, else a randomly
initialised ``--model`` (default smart-1m) whose vocabularies (``--vocab`` tokens per type) are
built from the shared WOMD scenes: a trained prior costs the same per step.

    .venv/bin/python benchmarks/env_throughput.py [--steps 48] [--threads 1]

Measured on the project's 2-core CPU machine (shared with other jobs, so +-40 %), one torch
thread, WOMD 637f20cafde22ff8, horizon 16, raw env (TorchRL-wrapped in brackets), agent-steps/s:
log background without a prior 14,000-23,000 (8,000-15,000) with 1 controlled agent and
5,800-8,700 (4,000-5,900) with 8; constant velocity without a prior 17,000 (10,700) and 7,400-8,200
(5,000-5,700); any background with a random smart-1m prior 1,400-2,000 (1,100-1,750), i.e. 30-40
env steps/s: the prior's incremental forward dominates. Reset with the prior: ~30 ms.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "womd_tfrecord"


def build_prior(args, scenes):
    from smart_marl.model.smart import SMART, get_config
    from smart_marl.tokens import build_motion_vocabulary, collect_snippets

    if args.checkpoint:
        from smart_marl.model.checkpoint import load_checkpoint

        ck = load_checkpoint(args.checkpoint)
        return ck.model.eval(), ck.motion_vocab, Path(args.checkpoint).name
    snippets, _ = collect_snippets(scenes, stride=1)
    vocab = build_motion_vocabulary(snippets, args.vocab, seed=0, progress=False)
    cfg = get_config(args.model, motion_vocab_sizes=(args.vocab,) * 3, dropout=0.0)
    torch.manual_seed(0)
    model = SMART(cfg, motion_contours=[vocab[t].contour for t in range(3)]).eval()
    return model, vocab, f"{args.model} (random init, vocab {args.vocab})"


def time_raw(env, steps: int, seed: int) -> tuple[float, int, int, int]:
    """(seconds stepping, env steps, agent steps, controlled agent steps) over ``steps`` env steps;
    ``env.reset_times_s`` gets the resets after the first (which starts the scene's prior)."""
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    env.reset_times_s = []
    elapsed, done_steps, agent_steps, ctrl_steps = 0.0, 0, 0, 0
    while done_steps < steps:
        if not env.agents:
            t0 = time.perf_counter()
            env.reset()
            env.reset_times_s.append(time.perf_counter() - t0)
        actions = {a: int(rng.integers(env.action_space(a).n)) for a in env.agents}
        moving = int(env.present.sum())
        t0 = time.perf_counter()
        env.step(actions)
        elapsed += time.perf_counter() - t0
        done_steps += 1
        agent_steps += moving
        ctrl_steps += len(actions)
    return elapsed, done_steps, agent_steps, ctrl_steps


def time_torchrl(env, steps: int, seed: int) -> tuple[float, int, int, int]:
    from torchrl.envs import PettingZooWrapper
    from torchrl.envs.utils import step_mdp

    wrapped = PettingZooWrapper(env, use_mask=True, done_on_any=False, categorical_actions=True)
    wrapped.set_seed(seed)
    td = wrapped.reset()
    elapsed, done_steps, agent_steps, ctrl_steps = 0.0, 0, 0, 0
    while done_steps < steps:
        td = wrapped.full_action_spec.rand().update(td)
        moving = int(env.present.sum())
        live = len(env.agents)
        t0 = time.perf_counter()
        td = wrapped.step(td)
        elapsed += time.perf_counter() - t0
        done_steps += 1
        agent_steps += moving
        ctrl_steps += live
        td = step_mdp(td)
        if bool(td["done"].all()) or not env.agents:
            td = wrapped.reset()
    return elapsed, done_steps, agent_steps, ctrl_steps


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default=str(DATA / "motion_data_one_scenario.tfrecord"))
    p.add_argument("--checkpoint", default=None, help="a SMART checkpoint as the prior (default: a random --model)")
    p.add_argument("--model", default="smart-1m")
    p.add_argument("--vocab", type=int, default=512, help="tokens per type of the built vocabulary (random prior)")
    p.add_argument("--steps", type=int, default=48, help="env steps timed per configuration")
    p.add_argument("--horizon", type=int, default=16)
    p.add_argument("--threads", type=int, default=1, help="torch threads (the prior's forward)")
    p.add_argument("--no-torchrl", action="store_true")
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    from envs import smart_traffic_v0
    from smart_marl.readers import read_scenarios

    scene = next(iter(read_scenarios(args.scene)))
    vocab_scenes = [s for f in sorted(DATA.glob("*.tfrecord")) for s in read_scenarios(f)]
    model, vocab, prior_name = build_prior(args, vocab_scenes)
    common = dict(scene=scene.scenario_id, tracks=scene.num_tracks,
                  agents_at_current_frame=int(scene.tracks.valid[:, scene.current_frame].sum()), horizon_steps=args.horizon,
                  torch_threads=args.threads, cpu=platform.processor() or platform.machine())
    for background in ("prior", "log", "constant_velocity"):
        for use_prior in ((True,) if background == "prior" else (False, True)):
            for n_ctrl in (1, 8):
                kw = dict(scenarios=[scene], prior=model if use_prior else None, motion_vocab=vocab, background=background,
                          horizon_steps=args.horizon, terminate_on=(), controlled="sdc" if n_ctrl == 1 else "vehicles",
                          max_agents=n_ctrl)
                rates = {}
                for kind in ("raw", "torchrl"):
                    if kind == "torchrl" and args.no_torchrl:
                        continue
                    env = smart_traffic_v0.parallel_env(**kw)
                    timer = time_raw if kind == "raw" else time_torchrl
                    secs, steps, agent_steps, ctrl_steps = timer(env, args.steps, seed=0)
                    rates[kind] = dict(env_steps_per_s=round(steps / secs, 2), agent_steps_per_s=round(agent_steps / secs, 1),
                                       controlled_agent_steps_per_s=round(ctrl_steps / secs, 1))
                    if kind == "raw" and env.reset_times_s:
                        rates[kind]["reset_ms"] = round(1000 * float(np.mean(env.reset_times_s)), 1)
                    env.close()
                line = dict(benchmark="env_throughput", background=background, prior=prior_name if use_prior else None,
                            controlled_agents=n_ctrl, **{f"{k}_{m}": v for k, r in rates.items() for m, v in r.items()}, **common)
                print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
