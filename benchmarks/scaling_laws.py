"""Scaling runs, one command: the held-out next-token loss of SMART against model size N and data size D, and the
closed-loop realism of every run against its loss (issue 59; the paper's Figure 4).

A grid of runs, each with the project's own trainer (``smart_marl.train.train``: under ``torchrun`` and on a GPU it
runs unchanged), every run the same number of steps at the same batch size, the same seed, the vocabularies fixed
(the embedded prior's, so that every loss counts over the same tokens), teacher forcing without token noise (each
scene tokenized once and kept: what makes the grid affordable on a CPU):

* sizes: the ``smart-1m`` layout at hidden widths ``--widths`` (heads fixed at 8), trained on every training scene;
* data: the ``--data-width`` model on the first D shards of the training token cache, D in ``--data-shards``.

The training data is a token cache (``smart-marl pretokenize``: every scene tokenized once with the embedded prior's
vocabularies, shared by every run; tokenizing a scene costs more than a training step of these models); a data
size is a whole number of its shards (a folder of links to them and a manifest listing them, ``OUT/data_K``).

Every run's held-out loss (motion next-token cross-entropy, no label smoothing, teacher-forced, no token noise) on
one fixed validation set of generated scenes (``--val``) and, separately, on the shared real scenes with 91 frames;
with ``--realism DIR``, the sim-agents meta-metric of its last checkpoint on DIR's scenes (2024 rules, ``--rollouts``
rollouts). One JSON line per run (stdout and ``OUT/runs.jsonl``); a run already in ``OUT/runs.jsonl`` with the same
settings is not run again, and a run cut short resumes from its last checkpoint (the trainer's own resume). Then
one ``"kind": "fit"`` line per (axis, validation set): ``L = E + A x^-alpha`` and ``L = A x^-alpha``
(:mod:`smart_marl.scaling`) with standard errors, the paper's exponent beside them, and ``OUT/scaling.png``.

    .venv/bin/smart-marl generate-sumo --scenes 320 --out data/scaling_train --seed 7301
    .venv/bin/smart-marl generate-sumo --scenes 48 --out data/scaling_val --seed 7302
    .venv/bin/smart-marl pretokenize data/scaling_train/*.smsc --out data/scaling_tokens --workers 2
    .venv/bin/python benchmarks/scaling_laws.py --tokens data/scaling_tokens --val data/scaling_val --out runs/scaling \
        --realism data/real7 > runs/scaling/lines.jsonl

On a GPU: the same command with ``--device cuda`` and wider ``--widths`` / more ``--steps``.
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


def scene_batches(scenes, mv, rv, cfg) -> list:
    """One noise-free batch per scene (the validation the trainer does, scene by scene)."""
    from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors

    keep = cfg.map_radius_m + cfg.num_road_layers * cfg.road_radius_m
    return [collate_scenes([scene_tensors(s, mv, scene_road(s, rv, cfg.road_settings), road_mask_prob=0.0, road_keep_radius_m=keep)])
            for s in scenes]


def held_out_loss(model, batches, device) -> float:
    from smart_marl.train import evaluate_sums, finish_metrics

    with torch.no_grad():
        return float(finish_metrics(evaluate_sums(model, batches, device, 0.0, amp=False))["motion_loss"])


def realism(checkpoint, scenes, rollouts: int, seed: int, device) -> float:
    from smart_marl.commands.eval import prior_rollouts
    from smart_marl.metrics import aggregate, logged_scene, score_rollouts

    results = []
    for sc in scenes:
        ro = prior_rollouts(checkpoint, sc, rollouts, seed, str(device))
        results.append(score_rollouts(logged_scene(sc), ro, rules="2024"))
    return float(aggregate(results, "2024")["meta_metric"])


def scenes_of(path: str) -> list:
    """The scenes of ``path`` (anything ``read_scenarios`` reads), or the package's sample scenes for ``"embedded"``."""
    from smart_marl.embedded import sample_scenarios
    from smart_marl.readers import read_scenarios

    return list(sample_scenarios()) if path == "embedded" else list(read_scenarios(path))


def token_subset(tokens: Path, shards: int, out: Path) -> Path:
    """A token cache of the first ``shards`` shards of ``tokens``: a folder of links to them and a manifest that
    lists them alone (made once; ``shards`` 0: ``tokens`` itself)."""
    from smart_marl.token_cache import MANIFEST

    manifest = json.loads((tokens / MANIFEST).read_text())
    if shards <= 0 or shards >= len(manifest["shards"]):
        return tokens
    folder = out / f"data_{shards}"
    if not (folder / MANIFEST).is_file():
        folder.mkdir(parents=True, exist_ok=True)
        kept = manifest["shards"][:shards]
        for shard in kept:
            link = folder / shard["file"]
            if not link.exists():
                link.symlink_to((tokens / shard["file"]).resolve())
        subset = {**manifest, "shards": kept, "num_scenes": sum(len(sh["scenario_ids"]) for sh in kept)}
        (folder / MANIFEST).write_text(json.dumps(subset, indent=1))
    return folder


def target_tokens(data: Path) -> tuple[int, int]:
    """(scenes, next-motion-token targets) of a token cache."""
    from smart_marl.model.batch import collate_scenes
    from smart_marl.token_cache import TokenCache

    cache = TokenCache(data)
    return len(cache), int(sum(int(collate_scenes([cache[i]]).target_valid.sum()) for i in range(len(cache))))


def run_one(name: str, width: int, data: Path, args, vocab_paths, road_settings: dict, val, device) -> dict:
    from smart_marl.model.checkpoint import load_checkpoint
    from smart_marl.train import load_train_config, train

    out_dir = Path(args.out) / name
    cfg = load_train_config("smart-1m", {
        "model_overrides": {"hidden_dim": width, "head_dim": width // 8, **road_settings}, "data": str(data),
        "motion_vocab": vocab_paths[0], "road_vocab": vocab_paths[1], "max_steps": args.steps, "batch_size": args.batch_size,
        "val_every": args.steps, "val_scenes": 1, "ckpt_every": max(args.steps // 4, 1), "log_every": max(args.steps // 10, 1),
        "out_dir": str(out_dir), "seed": args.seed, "num_workers": 0, "tensorboard": False, "progress": False,
        "device": args.device, "precision": args.precision, "token_noise_topk": 0})  # a token cache: no token noise
    t0 = time.perf_counter()
    train(cfg)
    seconds = time.perf_counter() - t0
    ck = load_checkpoint(out_dir / "checkpoints" / "last", map_location=device)
    model = ck.model.eval()
    scenes, tokens = target_tokens(data)
    row = {"run": name, "width": width, "parameters": int(sum(p.numel() for p in model.parameters())), "train_scenes": scenes,
           "train_target_tokens": tokens, "steps": args.steps, "batch_size": args.batch_size, "seed": args.seed,
           "precision": args.precision, "device": str(device), "train_seconds_this_process": round(seconds, 1)}
    for key, batches in val.items():
        row[f"val_loss_{key}"] = round(held_out_loss(model, batches(ck), device), 5)
    if args.realism:
        row["realism_meta"] = round(realism(ck, scenes_of(args.realism), args.rollouts, args.seed, device), 5)
        row["realism_rollouts"] = args.rollouts
    return row


def plot(rows: list[dict], fits: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from smart_marl.scaling import PowerLawFit

    panels = [("size", "parameters", "model size N (parameters)"), ("data", "train_target_tokens", "data size D (training target tokens)")]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for ax, (axis, key, label) in zip(axes, panels):
        for val, color in (("generated", "tab:blue"), ("real", "tab:orange")):
            pts = sorted((r[key], r[f"val_loss_{val}"]) for r in rows if r["axis"] == axis)
            if not pts:
                continue
            x, y = np.array(pts, float).T
            ax.scatter(x, y, color=color, label=f"held-out {val}")
            fit = next((f for f in fits if f["axis"] == axis and f["val"] == val and f["form"] == "E + A x^-alpha"), None)
            if fit and np.isfinite(fit["exponent"]):
                grid = np.geomspace(x.min(), x.max(), 50)
                model = PowerLawFit(**{k: fit[k] for k in PowerLawFit.__dataclass_fields__})
                ax.plot(grid, model.predict(grid), color=color,
                        label=f"E + A x^{fit['exponent']:.3f} (+-{fit['exponent_se']:.3f})")
        ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("next-token loss")
        ax.set_title(f"loss vs {axis} (paper: N^-0.157)" if axis == "size" else f"loss vs {axis}")
        ax.legend(fontsize=7)
    ax = axes[2]
    pts = [(r["val_loss_real"], r["realism_meta"]) for r in rows if "realism_meta" in r]
    if pts:
        x, y = np.array(pts).T
        ax.scatter(x, y)
        for r in rows:
            if "realism_meta" in r:
                ax.annotate(r["run"], (r["val_loss_real"], r["realism_meta"]), fontsize=6)
        ax.set_xlabel("held-out loss, real scenes")
        ax.set_ylabel("realism meta-metric (2024)")
        ax.set_title("does realism follow the loss?")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    from smart_marl.model.checkpoint import checkpoint_paths, embedded_checkpoint_path
    from smart_marl.model.precision import PRECISIONS
    from smart_marl.scaling import PAPER_EXPONENT, fit_power_law, fit_pure_power_law

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tokens", required=True, help="the training scenes as a token cache (smart-marl pretokenize, the embedded "
                                                   "prior's vocabularies)")
    p.add_argument("--val", required=True, help="held-out generated scenes")
    p.add_argument("--real-val", default=None, help="held-out real scenes (default: the shared real scenes with 91 frames)")
    p.add_argument("--out", default="runs/scaling")
    p.add_argument("--widths", default="16,32,64,128")
    p.add_argument("--data-shards", default="3,6,15,0", help="data sizes in token-cache shards (0: all)")
    p.add_argument("--data-width", type=int, default=32)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--realism", default=None, help="scenes to score each run's realism on (e.g. data/real7)")
    p.add_argument("--rollouts", type=int, default=8)
    p.add_argument("--device", default="cpu")
    p.add_argument("--precision", default="float32", choices=PRECISIONS)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    emb = checkpoint_paths(embedded_checkpoint_path())
    vocab_paths = (str(emb["motion_vocab"]), str(emb["road_vocab"]))
    val_generated = scenes_of(args.val)
    tokens = Path(args.tokens)
    meta = json.loads(embedded_checkpoint_path().read_text())["model_config"]
    road_settings = {k: meta[k] for k in ("road_types", "stop_signs") if k in meta}  # the token cache's (and the prior's)
    if args.real_val:
        val_real = scenes_of(args.real_val)
    else:
        import env_throughput

        val_real = env_throughput.real_scenes()
    made: dict = {}  # every run has the same vocabularies, road settings and radii: the batches are made once

    def batches_of(scenes, name):
        return lambda ck: made.setdefault(name, scene_batches(scenes, ck.motion_vocab, ck.road_vocab, ck.model.config))

    val = {"generated": batches_of(val_generated, "generated"), "real": batches_of(val_real, "real")}
    every = len(json.loads((tokens / "token_cache.json").read_text())["shards"])
    grid = [("size", f"w{w}_s{every}", w, 0) for w in map(int, args.widths.split(","))]
    grid += [("data", f"w{args.data_width}_s{k or every}", args.data_width, k) for k in map(int, args.data_shards.split(","))]
    done_path = out / "runs.jsonl"
    done = {}
    if done_path.is_file():
        for line in done_path.read_text().splitlines():
            r = json.loads(line)
            done[r["run"], r["steps"], r["batch_size"], r["seed"], r["precision"]] = r
    rows = []
    for axis, name, width, shards in grid:
        key = (name, args.steps, args.batch_size, args.seed, args.precision)
        row = done.get(key)
        if row is None:
            row = run_one(name, width, token_subset(tokens, shards, out), args, vocab_paths, road_settings, val, device)
            with open(done_path, "a") as f:
                f.write(json.dumps(row) + "\n")
            done[key] = row
        row = {**row, "axis": axis}
        rows.append(row)
        print(json.dumps({"kind": "run", **row}), flush=True)
    fits = []
    for axis, key in (("size", "parameters"), ("data", "train_target_tokens")):
        for valset in ("generated", "real"):
            pts = [(r[key], r[f"val_loss_{valset}"]) for r in rows if r["axis"] == axis]
            if len({x for x, _ in pts}) < 2:
                continue
            x, y = map(np.array, zip(*pts))
            for fit in (fit_power_law(x, y) if len(pts) >= 3 else None, fit_pure_power_law(x, y)):
                if fit is None:
                    continue
                line = {"kind": "fit", "axis": axis, "x": key, "val": valset, **fit.to_dict(), "paper_exponent": PAPER_EXPONENT,
                        "steps": args.steps, "batch_size": args.batch_size}
                fits.append(line)
                print(json.dumps(line), flush=True)
    (out / "fit.json").write_text(json.dumps(fits, indent=1))
    plot(rows, fits, out / "scaling.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
