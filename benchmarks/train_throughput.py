"""Training throughput of the SMART sizes: one JSON line per measurement.

Measures full training steps (forward, backward, AdamW step; bf16 autocast on CUDA) on one batch of
real scenes (``--scenes``: a file, folder or glob; default the two WOMD records in ../shared/data),
tokenized once beforehand (in training, tokenization runs in DataLoader workers; its own rate is
reported as ``data_scenes_per_s``, single process). Vocabularies of each config's sizes are the
tokenizer's uniform-grid motion vocabulary and a random sample of the scenes' road pieces as road
tokens: the step's cost depends on vocabulary sizes, not on which tokens they hold. The process
memory settings are those of ``smart-marl train`` (:func:`smart_marl.cpu_memory.keep_freed_memory`
on the CPU, where the measured tree has it).

Fields: ``tokens_per_s`` (valid next-motion-token targets per second, from the median step),
``seconds_per_step`` (median of ``--steps`` timed steps after one warm-up step), ``scenes_per_s``,
``peak_memory_mb`` (CUDA: max allocated; CPU: peak resident set of the process), ``device``,
``parameters``, ``batch_scenes``, ``target_tokens_per_batch``, ``tree`` (which source tree ran).

Before/after, side by side: ``--compare-rev REV`` exports that git revision of this repository to
a temporary folder and measures it and the working tree alternately, each in a fresh process,
``--repeats`` times per size, then prints one ``"kind": "comparison"`` line per size with the
median tokens/s of each and their ratio (medians of alternating runs: the machine is shared).

Usage: python benchmarks/train_throughput.py [--sizes smart-1m smart-7m] [--steps 3] [--batch-scenes 2]
       [--device cpu] [--compare-rev 591cde0 --repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SCENES = str(ROOT.parent / "shared" / "data" / "womd_tfrecord" / "*.tfrecord")
SIZES = ("smart-1m", "smart-7m", "smart-26m", "smart-101m")


def device_name(device) -> str:
    import torch

    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return f"CPU {line.split(':', 1)[1].strip()} ({torch.get_num_threads()} threads)"
    except OSError:
        pass
    return f"CPU {platform.processor()} ({torch.get_num_threads()} threads)"


def measure(sizes: list[str], scenes_glob: str, batch_scenes: int, steps: int, device_arg: str, tree: str) -> None:
    """Time training steps of each size on one batch; print one JSON line per size (the child's job)."""
    import numpy as np
    import torch

    from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors
    from smart_marl.model.losses import NextTokenLoss
    from smart_marl.model.smart import SMART, get_config
    from smart_marl.readers import read_scenarios
    from smart_marl.scenario import AgentType
    from smart_marl.tokens import collect_snippets, uniform_grid_vocabulary
    from smart_marl.tokens.road import RoadVocabulary, road_pieces
    from smart_marl.train import DistInfo, load_train_config, make_optimizer, make_scheduler, train_step

    device = torch.device(device_arg)
    if device.type == "cpu":
        try:  # what `smart-marl train` does on the CPU (absent from older trees)
            from smart_marl.cpu_memory import keep_freed_memory

            keep_freed_memory()
        except ImportError:
            pass
    scenes = list(read_scenarios(scenes_glob))
    while len(scenes) < batch_scenes:
        scenes = scenes + scenes
    scenes = scenes[:batch_scenes]
    snippets, _ = collect_snippets(scenes)
    snippets = {k: (v if len(v) else snippets[AgentType.VEHICLE]) for k, v in snippets.items()}  # a type absent from these scenes
    pieces = np.concatenate([road_pieces(s.road_map).local for s in scenes])
    for name in sizes:
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
        times = []
        for _ in range(steps):
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            t0 = time.perf_counter()
            train_step(module, opt, sched, batch, 1.0, DistInfo(), device, amp=True)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            times.append(time.perf_counter() - t0)
        dt = statistics.median(times)
        peak = (torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda"
                else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
        tokens = int(batch.target_valid.sum())
        print(json.dumps({
            "kind": "measurement", "tree": tree, "model": name, "parameters": sum(p.numel() for p in model.parameters()),
            "device": device_name(device), "batch_scenes": batch.num_scenes, "target_tokens_per_batch": tokens,
            "seconds_per_step": round(dt, 4), "step_seconds": [round(t, 3) for t in times],
            "tokens_per_s": round(tokens / dt, 1), "scenes_per_s": round(batch.num_scenes / dt, 3),
            "peak_memory_mb": round(peak, 1), "data_scenes_per_s": round(data_rate, 2),
        }), flush=True)
        del model, module, opt
        if device.type == "cuda":
            torch.cuda.empty_cache()


def export_revision(rev: str, dest: Path) -> None:
    """The files of git revision ``rev`` of this repository in ``dest`` (git archive | tar)."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", rev], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)


def run_child(tree_dir: Path, tree: str, size: str, args) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree_dir))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", tree, "--sizes", size, "--steps", str(args.steps),
           "--batch-scenes", str(args.batch_scenes), "--scenes", args.scenes, "--device", args.device]
    out = subprocess.run(cmd, env=env, cwd=tree_dir, check=True, capture_output=True, text=True).stdout
    line = json.loads([ln for ln in out.splitlines() if ln.startswith("{")][-1])
    print(json.dumps(line), flush=True)
    return line


def compare(args) -> None:
    with tempfile.TemporaryDirectory(prefix="train_throughput_") as tmp:
        base_dir = Path(tmp)
        export_revision(args.compare_rev, base_dir)
        trees = {f"rev {args.compare_rev}": base_dir, "working tree": ROOT}
        for size in args.sizes:
            rates: dict[str, list[float]] = {t: [] for t in trees}
            peaks: dict[str, list[float]] = {t: [] for t in trees}
            for _ in range(args.repeats):
                for tree, path in trees.items():  # alternate: both see the same machine load
                    line = run_child(path, tree, size, args)
                    rates[tree].append(line["tokens_per_s"])
                    peaks[tree].append(line["peak_memory_mb"])
            (b_name, b), (c_name, c) = rates.items()
            print(json.dumps({
                "kind": "comparison", "model": size, "baseline": b_name, "baseline_tokens_per_s": statistics.median(b),
                "tokens_per_s": statistics.median(c), "speedup": round(statistics.median(c) / statistics.median(b), 2),
                "baseline_peak_memory_mb": statistics.median(peaks[b_name]), "peak_memory_mb": statistics.median(peaks[c_name]),
                "repeats": args.repeats, "baseline_runs": b, "runs": c,
            }), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=SIZES)
    parser.add_argument("--scenes", default=DEFAULT_SCENES)
    parser.add_argument("--batch-scenes", type=int, default=2)
    parser.add_argument("--steps", type=int, default=3, help="timed steps per measurement (after one warm-up step)")
    parser.add_argument("--device", default=None, help="default: cuda when available, else cpu")
    parser.add_argument("--compare-rev", metavar="REV", help="measure this git revision and the working tree alternately")
    parser.add_argument("--repeats", type=int, default=3, help="with --compare-rev: fresh-process runs per tree and size")
    parser.add_argument("--child", metavar="TREE", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.device is None:
        import torch

        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.compare_rev and not args.child:
        compare(args)
    else:
        measure(args.sizes, args.scenes, args.batch_scenes, args.steps, args.device, args.child or "working tree")


if __name__ == "__main__":
    sys.exit(main())
