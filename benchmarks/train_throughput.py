"""Training throughput of the SMART sizes: one JSON line per model size.

Measures full training steps (forward, backward, AdamW step; bf16 autocast on CUDA) on batches of
real scenes (``--scenes``: a file, folder or glob; default the WOMD test scenes in ../shared/data),
tokenized once beforehand (in training, tokenization runs in DataLoader workers; its own rate is
reported as ``data_scenes_per_s``, single process). Vocabularies of each config's sizes are the
tokenizer's uniform-grid motion vocabulary and a random sample of the scenes' road pieces as road
tokens: the step's cost depends on vocabulary sizes, not on which tokens they hold.

Fields: ``tokens_per_s`` (valid next-motion-token targets per second), ``scenes_per_s``,
``seconds_per_step``, ``peak_memory_mb`` (CUDA: max allocated; CPU: peak resident set of the
process so far), ``device``, ``parameters``, ``batch_scenes``, ``target_tokens_per_batch``.

Usage: python benchmarks/train_throughput.py [--sizes smart-1m smart-7m] [--steps 3] [--batch-scenes 2] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors
from smart_marl.model.losses import NextTokenLoss
from smart_marl.model.smart import NAMED_CONFIGS, SMART, get_config
from smart_marl.readers import read_scenarios
from smart_marl.scenario import AgentType
from smart_marl.tokens import collect_snippets, uniform_grid_vocabulary
from smart_marl.tokens.road import RoadVocabulary, road_pieces
from smart_marl.train import DistInfo, load_train_config, make_optimizer, make_scheduler, train_step

ROOT = Path(__file__).resolve().parents[1]


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return f"CPU {line.split(':', 1)[1].strip()} ({torch.get_num_threads()} threads)"
    except OSError:
        pass
    return f"CPU {platform.processor()} ({torch.get_num_threads()} threads)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", nargs="+", default=list(NAMED_CONFIGS))
    parser.add_argument("--scenes", default=str(ROOT.parent / "shared" / "data" / "womd_tfrecord" / "*.tfrecord"))
    parser.add_argument("--batch-scenes", type=int, default=2)
    parser.add_argument("--steps", type=int, default=3, help="timed steps (after one warm-up step)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    device = torch.device(args.device)
    scenes = list(read_scenarios(args.scenes))
    while len(scenes) < args.batch_scenes:
        scenes = scenes + scenes
    scenes = scenes[: args.batch_scenes]
    snippets, _ = collect_snippets(scenes)
    snippets = {k: (v if len(v) else snippets[AgentType.VEHICLE]) for k, v in snippets.items()}  # a type absent from these scenes
    pieces = np.concatenate([road_pieces(s.road_map).local for s in scenes])
    for name in args.sizes:
        cfg = get_config(name, dropout=0.1)
        mv = uniform_grid_vocabulary({AgentType(k): v for k, v in snippets.items()},
                                     {AgentType(t): cfg.motion_vocab_sizes[t] for t in range(3)})
        rng = np.random.default_rng(0)
        rv = RoadVocabulary(points=pieces[rng.choice(len(pieces), cfg.road_vocab_size, replace=len(pieces) < cfg.road_vocab_size)],
                            tolerance_m=0.0, requested_size=cfg.road_vocab_size)
        keep = cfg.map_radius_m + cfg.num_road_layers * cfg.road_radius_m
        scene_tensors(scenes[0], mv, scene_road(scenes[0], rv), noise_topk=5, rng=0)  # warm-up (first-call costs)
        t0 = time.perf_counter()
        arrays = [scene_tensors(s, mv, scene_road(s, rv), noise_topk=5, rng=i, road_keep_radius_m=keep) for i, s in enumerate(scenes)]
        batch = collate_scenes(arrays)
        data_rate = len(scenes) / (time.perf_counter() - t0)
        torch.manual_seed(0)
        model = SMART(cfg, [torch.from_numpy(mv[t].contour) for t in range(3)]).to(device)
        module = NextTokenLoss(model, 0.1)
        tcfg = load_train_config(name, {"max_steps": 1000})
        opt = make_optimizer(model, tcfg)
        sched = make_scheduler(opt, tcfg)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        train_step(module, opt, sched, batch, 1.0, DistInfo(), device, amp=True)  # warm-up
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        for _ in range(args.steps):
            train_step(module, opt, sched, batch, 1.0, DistInfo(), device, amp=True)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        dt = (time.perf_counter() - t0) / args.steps
        peak = (torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda"
                else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
        tokens = int(batch.target_valid.sum())
        print(json.dumps({
            "model": name, "parameters": sum(p.numel() for p in model.parameters()), "device": device_name(device),
            "batch_scenes": batch.num_scenes, "target_tokens_per_batch": tokens, "seconds_per_step": round(dt, 4),
            "tokens_per_s": round(tokens / dt, 1), "scenes_per_s": round(batch.num_scenes / dt, 3),
            "peak_memory_mb": round(peak, 1), "data_scenes_per_s": round(data_rate, 2),
        }), flush=True)
        del model, module, opt
        if device.type == "cuda":
            torch.cuda.empty_cache()


if __name__ == "__main__":
    sys.exit(main())
