"""Benchmark of the arithmetic precision (:mod:`smart_marl.model.precision`): float32 against bfloat16, side by
side in one run (the two alternate within every repeat, so a load that comes and goes weighs on both), on the
same scenes and seeds. One JSON line per measurement, then one ``"kind": "ratio"`` line per row (bf16 / fp32).

Rows:

* ``cached_step``: the median ms of a KV-cached rollout step (the model on the newest step, the sampler, placing
  the tokens) of smart-1m and smart-7m with random weights at 128 agents of a synthetic scene
  (``benchmarks/rollout_latency.py``'s setup), steps 3..16 of ``--repeats`` fresh rollouts, with collision-aware
  sampling (``sampling: "default"``) and drawn plainly (``"plain"``: the model's part of the step, without the
  float32 box geometry that random weights make the sampler search through token after token);
* ``batched_env``: agent-steps/s of the batched env (embedded prior, traffic control on, the default) at 32 and 128
  scenes over the shared real scenes (``benchmarks/env_throughput.py``'s setup and timing);
* ``eval``: seconds per scene of ``smart-marl eval``'s rollouts (the embedded prior, 32 rollouts x 8 s) of the two
  shared WOMD tfrecord scenes;
* ``train``: smart-1m and smart-7m (``--train-models``) trained ``--train-steps`` steps from one initialisation on
  the shared real scenes (two a batch), tokens/s, and the validation loss after those steps on scenes it never
  trained on, computed in float32 for both runs. The process keeps freed memory as ``smart-marl train`` does
  (:func:`smart_marl.cpu_memory.keep_freed_memory`); bfloat16 on the CPU trains a bfloat16 working copy of the
  float32 weights (:func:`smart_marl.model.precision.training_copy`), as ``smart-marl train`` does.

    .venv/bin/python benchmarks/precision.py [--repeats 3] [--threads 2] [--device cpu] [--skip train,eval]

On a GPU (``--device cuda``) the same rows.
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
sys.path.insert(0, str(ROOT / "benchmarks"))

from smart_marl.model.precision import PRECISIONS  # noqa: E402  (after the path set-up)


def emit(**row) -> None:
    print(json.dumps(row), flush=True)


def cached_step(args, common) -> list[dict]:
    import rollout_latency as rl

    from smart_marl.model.precision import inference_model
    from smart_marl.readers import read_scenarios
    from smart_marl.tokens import collect_snippets

    real = [next(iter(read_scenarios(rl.DATA / f))) for f in rl.SCENE_FILES]
    snippets, _ = collect_snippets(real)
    scene = rl.synthetic_agents(args.agents)
    rows = []
    for name in ("smart-1m", "smart-7m"):
        model, vocab = rl.build_model(name, snippets, args.device)
        models = {p: inference_model(model, p) for p in PRECISIONS}
        for sampling in ("default", "plain"):
            times = {p: [] for p in PRECISIONS}
            for _ in range(args.repeats):
                for p in PRECISIONS:
                    times[p] += rl.step_times(models[p], vocab, scene, "cached", 16, args.device, sampling == "default")[2:]
            for p in PRECISIONS:
                rows.append(dict(row="cached_step", model=name, agents=args.agents, sampling=sampling, precision=p,
                                 ms_per_step=round(statistics.median(times[p]), 2), steps_timed=len(times[p]), **common))
                emit(**rows[-1])
    return rows


def batched_env(args, common) -> list[dict]:
    import env_throughput as et

    from envs.smart_traffic_batched_v0 import SmartTrafficBatchedEnv
    from smart_marl.model.checkpoint import load_prior

    scenes = et.real_scenes()
    model, vocab = load_prior("embedded", args.device)
    envs = {}
    for b in (32, 128):
        for p in PRECISIONS:
            env = SmartTrafficBatchedEnv(scenarios=scenes, prior=model, motion_vocab=vocab, num_scenes=b, max_agents=4,
                                         scene_order="sequential", terminate_on=(), device=args.device, precision=p)
            et.time_batched(env, 16)  # warm-up: the scenes' priors started
            envs[b, p] = env
    runs = {key: [] for key in envs}
    for _ in range(args.repeats):
        for (b, p), env in envs.items():
            runs[b, p].append(et.time_batched(env, 16))
    rows = []
    for (b, p), r in runs.items():
        s = et.summarise(r)
        rows.append(dict(row="batched_env", num_scenes=b, precision=p, agent_steps_per_s=s["agent_steps_per_s"],
                         forward_us_per_agent_step=s["forward_us_per_agent_step"], outside_forward_share=s["outside_forward_share"],
                         runs=s["agent_steps_per_s_runs"], scenes=len(scenes), **common))
        emit(**rows[-1])
    return rows


def eval_rollouts(args, common) -> list[dict]:
    import rollout_latency as rl

    from smart_marl.commands.eval import prior_rollouts
    from smart_marl.model.checkpoint import load_prior
    from smart_marl.readers import read_scenarios

    scenes = [next(iter(read_scenarios(rl.DATA / f))) for f in rl.SCENE_FILES]
    prior = load_prior("embedded", args.device)
    walls = {p: [] for p in PRECISIONS}
    for _ in range(args.repeats):
        for p in PRECISIONS:
            t0 = time.perf_counter()
            for sc in scenes:
                prior_rollouts(prior, sc, 32, 0, args.device, precision=p)
            walls[p].append((time.perf_counter() - t0) / len(scenes))
    rows = []
    for p in PRECISIONS:
        rows.append(dict(row="eval", precision=p, seconds_per_scene=round(statistics.median(walls[p]), 3),
                         runs=[round(w, 3) for w in walls[p]], rollouts=32, scenes=len(scenes), **common))
        emit(**rows[-1])
    return rows


def train(args, common) -> list[dict]:
    rows = []
    for name in args.train_models.split(","):
        rows += train_model(args, common, name)
    return rows


def train_model(args, common, name: str) -> list[dict]:
    import numpy as np

    import env_throughput as et

    from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors
    from smart_marl.model.losses import NextTokenLoss
    from smart_marl.model.smart import SMART, get_config
    from smart_marl.scenario import AgentType
    from smart_marl.tokens import collect_snippets, uniform_grid_vocabulary
    from smart_marl.tokens.road import RoadVocabulary, road_pieces
    from smart_marl.train import DistInfo, evaluate_sums, finish_metrics, load_train_config, make_optimizer, make_scheduler, train_step

    from smart_marl.cpu_memory import keep_freed_memory

    keep_freed_memory()  # as `smart-marl train` does
    device = torch.device(args.device)
    scenes = et.real_scenes()
    n_val = max(2, len(scenes) // 4)
    train_scenes, val_scenes = scenes[:-n_val], scenes[-n_val:]
    cfg = get_config(name, dropout=0.0)
    snippets, _ = collect_snippets(train_scenes)
    snippets = {k: (v if len(v) else snippets[AgentType.VEHICLE]) for k, v in snippets.items()}
    mv = uniform_grid_vocabulary({AgentType(k): v for k, v in snippets.items()}, {AgentType(t): cfg.motion_vocab_sizes[t] for t in range(3)})
    pieces = np.concatenate([road_pieces(s.road_map).local for s in train_scenes])
    rng = np.random.default_rng(0)
    rv = RoadVocabulary(points=pieces[rng.choice(len(pieces), cfg.road_vocab_size, replace=len(pieces) < cfg.road_vocab_size)],
                        tolerance_m=0.0, requested_size=cfg.road_vocab_size)
    keep = cfg.map_radius_m + cfg.num_road_layers * cfg.road_radius_m
    arrays = [scene_tensors(s, mv, scene_road(s, rv), noise_topk=5, rng=i, road_keep_radius_m=keep) for i, s in enumerate(train_scenes)]
    batches = [collate_scenes(arrays[i:i + 2]) for i in range(0, len(arrays) - 1, 2)]
    val = [collate_scenes([scene_tensors(s, mv, scene_road(s, rv), road_keep_radius_m=keep)]) for s in val_scenes]
    tcfg = load_train_config(name, {"max_steps": args.train_steps})
    state = {}
    for p in PRECISIONS:
        torch.manual_seed(0)
        model = SMART(cfg, [torch.from_numpy(mv[t].contour) for t in range(3)]).to(device)
        module = NextTokenLoss(model, 0.1)
        opt, sched = make_optimizer(model, tcfg), None
        sched = make_scheduler(opt, tcfg)
        state[p] = dict(model=model, module=module, opt=opt, sched=sched, seconds=0.0, tokens=0)
    for step in range(args.train_steps):  # the two runs alternate step by step
        batch = batches[step % len(batches)]
        for p in PRECISIONS:
            s = state[p]
            torch.manual_seed(step)  # the same dropout and noise draws in both
            t0 = time.perf_counter()
            train_step(s["module"], s["opt"], s["sched"], batch, 1.0, DistInfo(), device, amp=False, precision=p)
            if step >= 1:  # the first step (lazy kernels, allocator) untimed
                s["seconds"] += time.perf_counter() - t0
                s["tokens"] += int(batch.target_valid.sum())
    rows = []
    for p in PRECISIONS:
        s = state[p]
        s["model"].eval()
        with torch.no_grad():
            metrics = finish_metrics(evaluate_sums(s["model"], val, device, 0.0, amp=False, precision="float32"))
        rows.append(dict(row="train", model=name, precision=p, steps=args.train_steps, tokens_per_s=round(s["tokens"] / s["seconds"], 1),
                         val_motion_loss=round(float(metrics["motion_loss"]), 5), val_scenes=len(val), train_scenes=len(train_scenes),
                         **common))
        emit(**rows[-1])
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument("--agents", type=int, default=128)
    p.add_argument("--train-steps", type=int, default=40)
    p.add_argument("--train-models", default="smart-1m,smart-7m", help="comma-separated model sizes of the train row")
    p.add_argument("--skip", default="", help="comma-separated rows to leave out: cached_step,batched_env,eval,train")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    common = dict(benchmark="precision", device=args.device, threads=torch.get_num_threads(), repeats=args.repeats,
                  cpu=platform.processor() or platform.machine(), torch=torch.__version__)
    if args.device.startswith("cuda"):
        common["gpu"] = torch.cuda.get_device_name(args.device)
    skip = set(filter(None, args.skip.split(",")))
    rows = []
    for name, fn in (("cached_step", cached_step), ("batched_env", batched_env), ("eval", eval_rollouts), ("train", train)):
        if name not in skip:
            rows += fn(args, common)
    # bf16 against fp32, row by row
    value = {"cached_step": "ms_per_step", "batched_env": "agent_steps_per_s", "eval": "seconds_per_scene", "train": "tokens_per_s"}
    faster_when_lower = {"cached_step", "eval"}
    keyed = {}
    for r in rows:
        key = (r["row"], r.get("model"), r.get("num_scenes"), r.get("sampling"))
        keyed.setdefault(key, {})[r["precision"]] = r
    for (row, model, scenes, sampling), pair in keyed.items():
        if set(pair) != set(PRECISIONS):
            continue
        a, b = pair["float32"][value[row]], pair["bfloat16"][value[row]]
        speedup = a / b if row in faster_when_lower else b / a
        extra = {} if sampling is None else {"sampling": sampling}
        if row == "train":
            fa, fb = pair["float32"]["val_motion_loss"], pair["bfloat16"]["val_motion_loss"]
            extra = dict(val_loss_float32=fa, val_loss_bfloat16=fb, val_loss_relative_difference=round((fb - fa) / fa, 4))
        emit(kind="ratio", row=row, model=model, num_scenes=scenes, bf16_speedup=round(speedup, 3), **extra, **common)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
