"""Benchmark of the rollout stage: per-token-step latency of closed-loop generation, KV-cached
(``mode="cached"``, the model's own step, :meth:`smart_marl.model.SMART.step`) against a full re-computation of
MotionNet over the whole history every step (``mode="full"``), and the wall time of 32 rollouts x
8 s of real scenes.

Latency lines (one per model, agents, mode and token step)::

    {"model": "smart-7m", "agents": 128, "mode": "cached", "step": 16, "ms_per_step": ..., "device": "cpu", ...}

``step`` k (1..16) is the k-th generated token: its time covers the model on the newest step
(cached: that step only against the cache; full: all 2 + k - 1 steps so far), the top-k sampler
and placing the tokens. ``ms_per_step`` is the median over ``--repeats`` fresh rollouts. Agents
are vehicles of a synthetic scene (``smart_marl.synthetic``, every vehicle valid at the current
frame, so ``agents`` is exactly the number simulated), one rollout. Weights are random (a trained
model costs the same), with each config's full vocabulary sizes (vocabularies from the shared WOMD
scenes' snippets on a uniform grid). Road encodings are computed once per scene in both modes.
After the table: a ``speedup`` line per model and agent count (full / cached at the last step).

Rollout lines: 32 rollouts x 16 tokens (8 s) of each real WOMD scene (83 and 257 tracks) in one
batch, wall time including tokenizing the history and encoding the road.

    .venv/bin/python benchmarks/rollout_latency.py [--threads 1] [--repeats 3] [--device cpu]

``--avoidance`` measures only what collision-aware sampling (:mod:`smart_marl.rollout.avoidance`, the
default) costs: the embedded prior's 32 rollouts of each real scene with and without it, alternating.

Measured (2026-11-22, ``--threads 1``, a 2-core CPU shared with other jobs at load 4-9, so absolute
times are noisy; no GPU was lent): ms per step at step 16, cached / full (ratio)

    agents        16                 64                  128                 256
    smart-1m   15.5 / 194 (12x)   43 / 1016 (24x)    60 / 2274 (38x)     217 / 4289 (20x)
    smart-7m   34 / 516 (15x)     148 / 3125 (21x)   216 / 6722 (31x)    512 / 13560 (26x)

Cached latency is flat over the 16 steps (O(1) in the history length); full grows linearly.
32 rollouts x 8 s in one batch: smart-1m 17.9 s (WOMD 637f20cafde22ff8, 83 tracks, 50 simulated),
38.2 s (ee519cf571686d19, 257 tracks, 84 simulated); smart-7m 66 s and 169 s. Most of a cached
step is the model's RPE Fourier MLPs over every (query, neighbour) pair.

On one H100 (2026-11-24, ``--device cuda --repeats 7 --skip-rollouts``; torch 2.11, float32), ms per
step at step 16, cached / full: smart-1m 11.0 / 12.4 (16 agents), 11.7 / 12.9 (128), 12.0 / 14.5 (256);
smart-7m 21.4 / 23.0, 24.5 / 29.2, 31.8 / 28.9. Flat in the agent count: the GPU step is bound by
kernel launches and Python, so the cache saves little there and the paper's 5 ms is not reached.
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
DATA = ROOT.parent / "shared" / "data" / "womd_tfrecord"
SCENE_FILES = ("motion_data_one_scenario.tfrecord", "womd_scenario_input.tfrecord")


def build_model(name: str, snippets, device: str):
    from smart_marl.model.smart import SMART, get_config
    from smart_marl.tokens import uniform_grid_vocabulary

    cfg = get_config(name)
    vocab = uniform_grid_vocabulary(snippets, {t: v for t, v in zip(sorted(snippets), cfg.motion_vocab_sizes)})
    torch.manual_seed(0)
    model = SMART(cfg, [torch.from_numpy(vocab[t].contour) for t in range(3)]).to(device).eval()
    return model, vocab


def synthetic_agents(agents: int):
    """A synthetic scene with exactly ``agents`` vehicles valid at the current frame."""
    from smart_marl.synthetic import synthetic_scenario

    for nv in range(agents, agents + 16):
        sc = synthetic_scenario(0, num_vehicles=nv, num_pedestrians=0, lane_count=max(3, agents // 24))
        if int(sc.tracks.valid[:, sc.current_frame].sum()) == agents:
            return sc
    raise RuntimeError(f"no synthetic scene with {agents} agents at the current frame")


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def step_times(model, vocab, scene, mode: str, steps: int, device: str, avoid_collisions: bool = True) -> list[float]:
    from smart_marl.rollout import RolloutState

    state = RolloutState.start(model, [scene], num_rollouts=1, seed=0, device=device, mode=mode, motion_vocab=vocab,
                               avoid_collisions=avoid_collisions)
    out = []
    for _ in range(steps):
        sync(device)
        t0 = time.perf_counter()
        state.step()
        sync(device)
        out.append(1e3 * (time.perf_counter() - t0))
    return out


def avoidance_cost(args) -> None:
    """One line per real scene: median wall time of ``--rollouts`` x 8 s by the embedded prior with
    collision-aware sampling (the default) and without, runs alternating, and their ratio."""
    from smart_marl.model.checkpoint import EMBEDDED, load_prior
    from smart_marl.readers import read_scenarios
    from smart_marl.rollout import rollout

    prior = load_prior(EMBEDDED, args.device)
    for f in SCENE_FILES:
        sc = next(iter(read_scenarios(DATA / f)))
        walls = {True: [], False: []}
        for _ in range(args.repeats):
            for avoid in (False, True):
                sync(args.device)
                t0 = time.perf_counter()
                rollout(prior, [sc], num_rollouts=args.rollouts, num_steps=16, seed=0, device=args.device,
                        avoid_collisions=avoid)
                sync(args.device)
                walls[avoid].append(time.perf_counter() - t0)
        plain, avoiding = statistics.median(walls[False]), statistics.median(walls[True])
        print(json.dumps({"kind": "avoidance", "prior": "embedded", "scenario_id": sc.scenario_id, "tracks": sc.num_tracks,
                          "rollouts": args.rollouts, "repeats": args.repeats, "plain_wall_s": round(plain, 3),
                          "avoiding_wall_s": round(avoiding, 3), "ratio": round(avoiding / plain, 3),
                          "device": args.device, "threads": torch.get_num_threads()}), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", nargs="+", default=["smart-1m", "smart-7m"])
    ap.add_argument("--agents", nargs="+", type=int, default=[16, 64, 128, 256])
    ap.add_argument("--steps", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rollouts", type=int, default=32)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--skip-rollouts", action="store_true")
    ap.add_argument("--avoidance", action="store_true",
                    help="only the cost of collision-aware sampling: the embedded prior's rollouts of the real scenes with "
                         "and without it, alternating, --repeats each")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.avoidance:
        return avoidance_cost(args)

    from smart_marl.readers import read_scenarios
    from smart_marl.tokens import collect_snippets

    dev = args.device
    gpu = torch.cuda.get_device_name(0) if dev.startswith("cuda") else None
    print(json.dumps({"device": dev, "gpu": gpu or "none (no GPU was lent to this session)", "threads": torch.get_num_threads(),
                      "cpu": platform.processor() or platform.machine(), "torch": torch.__version__}), flush=True)
    real = [next(iter(read_scenarios(DATA / f))) for f in SCENE_FILES]
    snippets, _ = collect_snippets(real)
    speedups = []
    for name in args.models:
        model, vocab = build_model(name, snippets, dev)
        for agents in args.agents:
            scene = synthetic_agents(agents)
            table = {}
            for mode in ("cached", "full"):
                runs = [step_times(model, vocab, scene, mode, args.steps, dev) for _ in range(args.repeats)]
                for k in range(args.steps):
                    ms = statistics.median(r[k] for r in runs)
                    table[mode, k + 1] = ms
                    print(json.dumps({"model": name, "agents": agents, "mode": mode, "step": k + 1, "ms_per_step": round(ms, 3),
                                      "device": dev, "threads": torch.get_num_threads()}), flush=True)
            last = args.steps
            speedups.append({"model": name, "agents": agents, "step": last, "cached_ms": round(table["cached", last], 3),
                             "full_ms": round(table["full", last], 3),
                             "speedup_full_over_cached": round(table["full", last] / table["cached", last], 2), "device": dev})
    for s in speedups:
        print(json.dumps({"speedup": s}), flush=True)
    if args.skip_rollouts:
        return
    from smart_marl.rollout import rollout

    for name in args.models:
        model, vocab = build_model(name, snippets, dev)
        for sc in real:
            sync(dev)
            t0 = time.perf_counter()
            res = rollout(model, [sc], num_rollouts=args.rollouts, num_steps=16, seed=0, device=dev, motion_vocab=vocab)
            sync(dev)
            wall = time.perf_counter() - t0
            print(json.dumps({"rollouts": args.rollouts, "seconds": 8.0, "model": name, "scenario_id": sc.scenario_id,
                              "tracks": sc.num_tracks, "simulated_agents": int(res.simulated[0].sum()),
                              "agents_with_trajectory": int(res.has_trajectory[0].sum()), "wall_s": round(wall, 3),
                              "device": dev, "threads": torch.get_num_threads()}), flush=True)


if __name__ == "__main__":
    main()
