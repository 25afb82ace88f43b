"""Benchmark: does KL-regularised fine-tuning carry over to scenes it never saw, and how does that
depend on the number of training scenes? (The generalisation curve of the fine-tuning docs.)

For each training-set size N (``--sizes``, default 10,100,1000 generated scenes, plus the real
training scenes ``--real-train`` in every run), one fine-tuning run (:func:`agents.finetune.finetune`,
the ``scale`` config, the same number of iterations for every N) on the batched environment; then
every policy (the expert, the prior at the reference's top-k, its full softmax, each fine-tuned
policy) on two held-out sets it never saw: ``--eval-scenes`` generated scenes of another seed
(``--eval-seeds`` seeds each) and the real held-out scenes (``--real-heldout``, ``--real-seeds``
seeds each), same scenes and seeds for every policy. Prints one JSON line per result
({"kind": "run" | "eval", ...}) and draws the curve (held-out collision + offroad and goal rate
relative to the prior top-k, and realism, against N) to ``--png``.

Resumable: every run and every evaluation is written under ``--run-dir`` as it finishes and skipped
when found (kill it and start it again with the same arguments). ``--only`` splits the work into
pieces that can run side by side (``train`` with one size each, ``eval-generated``, ``eval-real``),
then a last call with everything done draws the picture.

    .venv/bin/python benchmarks/finetune_generalisation.py --train data/rl_train --heldout data/rl_heldout \\
        --real-train ../shared/data/gpudrive_json --real-heldout ../shared/data/womd_tfrecord ../shared/data/nocturne_json \\
        ../shared/data/scenarionet/waymo ../shared/data/smart_pkl --run-dir runs/generalisation --png docs/images/finetune_generalisation.png
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def emit(row: dict) -> None:
    print(json.dumps(row, default=float), flush=True)


def held_out(finetune_mod, cfg, vocab, spec, count):
    pool = finetune_mod._pool(spec, "eval_scenes")
    return finetune_mod.core_scenes(cfg, pool, vocab, count)


def evaluate(finetune_mod, cfg, scenes, policies, seeds, model, vocab):
    from agents.evaluate import evaluate_policies
    from smart_marl.scenario import AgentType

    core = finetune_mod.evaluation_core(cfg, model, vocab, len(scenes))
    return evaluate_policies(core, scenes, policies, seeds, num_envs=cfg.num_envs, vocab_size=vocab[AgentType.VEHICLE].size,
                             num_agents=cfg.max_agents, rules=cfg.eval_rules, temperature=cfg.temperature,
                             reference_top_k=cfg.reference_top_k)


def cached(path: Path, make):
    if path.is_file():
        return json.loads(path.read_text())
    out = make()
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1, default=float))
    tmp.replace(path)
    return out


def plot(results: dict, sizes: list[int], reference: str, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for name, style in (("generated", "o-"), ("real", "s--")):
        base = results[name]["baselines"]["rows"][reference]
        tuned = [results[name]["finetuned"][str(n)]["rows"]["fine-tuned"] for n in sizes]
        bad = lambda r: r["collision_rate"] + r["offroad_rate"]  # noqa: E731
        axes[0].plot(sizes, [bad(t) / max(bad(base), 1e-9) for t in tuned], style, label=f"{name} held-out")
        axes[1].plot(sizes, [t["goal_rate"] / max(base["goal_rate"], 1e-9) for t in tuned], style, label=f"{name} held-out")
        axes[2].plot(sizes, [t["meta_metric"] - base["meta_metric"] for t in tuned], style, label=f"{name} held-out")
    for ax, title, targets in ((axes[0], "collision + offroad / prior's", (0.6, 0.85)), (axes[1], "goal rate / prior's", (2.0, 1.3)),
                               (axes[2], "realism - prior's (meta-metric)", (-0.03,))):
        ax.set_xscale("log")
        ax.set_xlabel("training scenes (generated, + the real training scenes)")
        ax.set_title(title)
        for t in targets:
            ax.axhline(t, color="grey", lw=0.8, ls=":")
        ax.axhline(1.0 if "/" in title else 0.0, color="black", lw=0.8)
        ax.legend(fontsize=8)
    fig.suptitle(f"fine-tuned policy on held-out scenes, relative to the {reference}")
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)


def markdown(run_dir: Path, name: str, reference: str) -> str:
    """The held-out rows of one set found under ``run_dir`` as a Markdown table, each against the reference."""
    rows = {}
    for path in sorted(run_dir.glob(f"eval_{name}_*.json")):
        result = json.loads(path.read_text())
        rows.update(result["rows"])
        scenes, seeds = len(result["scenes"]), len(result["seeds"])
    if reference not in rows:
        return f"(no {reference} row under {run_dir})"
    base = rows[reference]
    bad = lambda r: r["collision_rate"] + r["offroad_rate"]  # noqa: E731
    out = [f"{name} held-out: {scenes} scenes x {seeds} seed(s), {base['agent_episodes']} agent-episodes per policy",
           "", "| policy | collision | offroad | coll. + off. vs ref. | goal | goal vs ref. | progress (m) | KL/step to ref. | "
           "realism (meta) | vs ref. |", "|---|---|---|---|---|---|---|---|---|---|"]
    for k, r in sorted(rows.items(), key=lambda kv: (not kv[0].startswith("prior"), kv[0])):
        out.append(f"| {k} | {r['collision_rate']:.3f} | {r['offroad_rate']:.3f} | {bad(r) / max(bad(base), 1e-9):.2f}x | "
                   f"{r['goal_rate']:.3f} | {r['goal_rate'] / max(base['goal_rate'], 1e-9):.2f}x | {r['progress_m']:.1f} | "
                   f"{r['kl_to_reference']:.3f} | {r['meta_metric']:.4f} | {r['meta_metric'] - base['meta_metric']:+.4f} |")
    return "\n".join(out)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train", required=True, help="the generated training pool (a scene cache)")
    p.add_argument("--real-train", nargs="*", default=[], help="real training scenes, in every run")
    p.add_argument("--heldout", required=True, help="generated held-out scenes (another seed)")
    p.add_argument("--real-heldout", nargs="*", default=[], help="real held-out scenes")
    p.add_argument("--sizes", default="10,100,1000")
    p.add_argument("--config", default="scale")
    p.add_argument("--iterations", type=int, default=None)
    p.add_argument("--eval-scenes", type=int, default=200)
    p.add_argument("--eval-seeds", type=int, default=8)
    p.add_argument("--real-seeds", type=int, default=48)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--run-dir", default="runs/generalisation")
    p.add_argument("--png", default="docs/images/finetune_generalisation.png")
    p.add_argument("--rows", default="expert (log),prior full softmax",
                   help="baseline rows besides the reference (prior top-k), comma-separated")
    p.add_argument("--skip-reference", action="store_true",
                   help="leave out the reference's row (the prior at the reference's top-k; one measured elsewhere)")
    p.add_argument("--only", choices=("train", "eval-generated", "eval-real", "table"), default=None,
                   help="do one piece of the work (the runs it needs must exist for eval-*)")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides for every run")
    args = p.parse_args()

    import torch

    from agents import finetune as ft

    torch.set_num_threads(args.threads)
    run_dir = Path(args.run_dir)
    if args.only == "table":  # the Markdown tables of what is done, for the docs
        base = ft.load_finetune_config(args.config, list(args.overrides))
        reference = f"prior top-{base.reference_top_k}" if base.reference_top_k else "prior full softmax"
        print(markdown(run_dir, "generated", reference) + "\n\n" + markdown(run_dir, "real", reference))
        return 0
    run_dir.mkdir(parents=True, exist_ok=True)
    sizes = [int(x) for x in args.sizes.split(",")]
    base = ft.load_finetune_config(args.config, list(args.overrides))
    n_real = sum(len(ft._pool(src, "real-train")) for src in args.real_train)
    model, vocab = ft.load_prior(base.prior)

    runs = {}
    for n in sizes:  # 1. one fine-tuning run per training-set size
        out = run_dir / f"train_{n}"
        over = {"scenes": list(args.real_train) + [args.train], "num_scenes": n_real + n, "out_dir": str(out), "eval_episodes": 0}
        if args.iterations:
            over["iterations"] = args.iterations
        cfg = ft.load_finetune_config(base.to_dict(), over)
        ckpt = out / "checkpoints" / "policy_last.json"
        if not ckpt.is_file() and args.only in (None, "train"):
            t0 = time.perf_counter()
            result = ft.finetune(cfg, on_iteration=lambda row, n=n: emit({"kind": "iteration", "generated_scenes": n, **row}))
            (out / "run.json").write_text(json.dumps({"seconds": time.perf_counter() - t0, "last": result.history[-1]}, default=float))
        if not (out / "run.json").is_file():
            continue  # another process trains it
        info = json.loads((out / "run.json").read_text())
        runs[n] = ckpt
        emit({"kind": "run", "generated_scenes": n, "real_scenes": n_real, "iterations": cfg.iterations, **info})

    if args.only == "train":
        return 0
    results = {}
    eval_sets = [("generated", args.heldout, args.eval_scenes, args.eval_seeds)]
    eval_sets += [("real", args.real_heldout, 10**6, args.real_seeds)] if args.real_heldout else []
    for name, spec, count, num_seeds in eval_sets:  # 2. every policy on the held-out sets, one cached row at a time
        if args.only is not None and args.only != f"eval-{name}":
            continue
        scenes = held_out(ft, base, vocab, spec, count)
        seeds = list(range(base.eval_seed, base.eval_seed + num_seeds))
        baselines = ft.evaluation_policies(base, None)
        reference = next(iter(k for k in baselines if k.startswith("prior top-")), "prior full softmax")
        # the fine-tuned policies and the reference first (what the targets compare), the other rows after
        todo = []
        for n in sorted(runs, reverse=True):
            cfg_n, net, _ = ft.load_policy(runs[n])
            todo.append((f"fine-tuned {n}", ft.evaluation_policies(cfg_n, net)["fine-tuned"], "fine-tuned"))
        if not args.skip_reference:
            todo.append((reference, baselines[reference], "baselines"))
        todo += [(k, p, "baselines") for k, p in baselines.items() if k != reference and k in args.rows.split(",")]
        rows = {}
        for row_name, policy, kind in todo:
            slug = row_name.replace(" ", "_").replace("(", "").replace(")", "")
            rows[row_name] = cached(run_dir / f"eval_{name}_{slug}.json",
                                    lambda: evaluate(ft, base, scenes, {row_name: policy}, seeds, model, vocab))["rows"][row_name]
            emit({"kind": "eval", "set": name, "policy": row_name, "scenes": len(scenes), "seeds": num_seeds, "row": rows[row_name]})
        results[name] = {"baselines": {"rows": {k: v for k, v in rows.items() if not k.startswith("fine-tuned ")}},
                         "finetuned": {str(n): {"rows": {"fine-tuned": rows[f"fine-tuned {n}"]}} for n in runs}}
    if args.only is not None or any(n not in runs for n in sizes):
        return 0
    reference = f"prior top-{base.reference_top_k}" if base.reference_top_k else "prior full softmax"
    plot(results, sizes, reference, Path(args.png))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
