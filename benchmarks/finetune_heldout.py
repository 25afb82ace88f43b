"""Benchmark: one fine-tuned policy against every baseline in its own environment, on held-out scenes (issue 58's
protocol: 200 generated scenes x 8 seeds, the 11 real scenes x 48 seeds).

What comes in: a policy checkpoint (``--policy``, anything ``agents.finetune.load_policy`` reads, e.g.
``runs/ft/checkpoints/policy_best``), held-out sets (``--set NAME=PATH[,PATH...]:SCENES:SEEDS``, SCENES ``all`` for
every scene with a controllable agent) and a folder for the rows (``--run-dir``). What goes out: one JSON line per
(set, row) with the row's metrics (``agents.evaluate.evaluate_policies``: collision, offroad, goal, front collisions,
progress, KL, realism), every row in the policy's environment (its shield, reward and background): the shielded prior at
the policy's top-k and at top-3 first, the fine-tuned policy, the log-following expert restricted to the same action
space (``expert within prior top-K``: of the shielded top K, the token closest to the log; issue 58's goal target is
against it), the log-following expert unrestricted (``expert (log)``: the log's token whatever the mask says), then
the rows named by ``--rows`` (the prior's full softmax, the priors with the
shield off: another environment). ``--table`` prints the Markdown table of the rows found, each against the shielded
prior at the policy's top-k (the policy card's table).

``--shield collision+offroad+gap`` evaluates every row with other shield checks than the policy's (the same for every
row: one environment).

Resumable: each (set, row) is written to ``RUN_DIR/eval_SET_ROW.json`` as it finishes and read back when found (kill
it and start it again with the same arguments); ``--only-set`` runs one set and ``--only-row`` one row, so processes can share the work.

    .venv/bin/python benchmarks/finetune_heldout.py --policy runs/ft58/checkpoints/policy_best --run-dir runs/ft58_eval \\
        --set generated=data/rl_heldout:200:8 \\
        --set real=../shared/data/womd_tfrecord,../shared/data/nocturne_json,../shared/data/scenarionet/waymo,../shared/data/smart_pkl:all:48
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from finetune_generalisation import cached, emit  # noqa: E402

FIRST_ROWS = ("fine-tuned", "expert within", "expert (log)")
"""After the shielded priors, the rows whose names start so, in this order."""


def parse_set(text: str) -> tuple[str, list[str], int | None, int]:
    """``NAME=PATH[,PATH...]:SCENES:SEEDS`` -> (name, paths, scene count or None for all, seeds)."""
    try:
        name, rest = text.split("=", 1)
        paths, scenes, seeds = rest.rsplit(":", 2)
        return name, paths.split(","), None if scenes == "all" else int(scenes), int(seeds)
    except ValueError:
        raise SystemExit(f"--set {text!r}: expected NAME=PATH[,PATH...]:SCENES:SEEDS (SCENES a number or 'all')") from None


def slug(name: str) -> str:
    return name.replace(" ", "_").replace("(", "").replace(")", "").replace(",", "")


def table(run_dir: Path, sets: list[str], reference: str) -> str:
    """The Markdown table of the rows under ``run_dir``: one line per (set, row), against ``reference``."""
    from agents.evaluate import shield_label

    bad = lambda r: r["collision_rate"] + r["offroad_rate"]  # noqa: E731
    out = ["| held-out set | policy | shield | collision | front | offroad | coll. + off. vs ref. | goal | goal vs ref. | "
           "realism (meta) | vs ref. |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in sets:
        rows = {}
        for path in sorted(run_dir.glob(f"eval_{name}_*.json")):
            result = json.loads(path.read_text())
            rows[result["row"]] = result
        if reference not in rows:
            out.append(f"| {name} | (no {reference} row yet) |||||||||")
            continue
        base = rows[reference]["metrics"]
        for row_name, result in sorted(rows.items(), key=lambda kv: result_order(kv[0], reference)):
            r = result["metrics"]
            where = f"{name}, {len(result['scenes'])} x {len(result['seeds'])} seeds"
            out.append(f"| {where} | {row_name} | {shield_label(r.get('shield') or ())} | {r['collision_rate']:.4f} | "
                       f"{r['front_collision_rate']:.4f} | {r['offroad_rate']:.4f} | {bad(r) / max(bad(base), 1e-9):.2f}x | "
                       f"{r['goal_rate']:.3f} | {r['goal_rate'] / max(base['goal_rate'], 1e-9):.2f}x | {r['meta_metric']:.4f} | "
                       f"{r['meta_metric'] - base['meta_metric']:+.4f} |")
    return "\n".join(out)


def result_order(name: str, reference: str) -> tuple:
    """Table order: the reference, the other shielded priors, the policy, the expert, the rest, shield-off rows last."""
    off = "shield off" in name
    first = next((i for i, start in enumerate(FIRST_ROWS) if name.startswith(start)), len(FIRST_ROWS))
    return (off, name != reference, not name.startswith("prior top-"), first, name)


def main(argv: list[str] | None = None) -> int:
    from envs._arguments import shield_option

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", required=True, help="the fine-tuned policy checkpoint (load_policy)")
    p.add_argument("--set", action="append", required=True, dest="sets", metavar="NAME=PATH[,PATH...]:SCENES:SEEDS")
    p.add_argument("--run-dir", required=True, help="where each (set, row) is kept as it finishes")
    p.add_argument("--rows", default="", help="more rows besides the lead ones, comma-separated names (e.g. 'prior full softmax')")
    p.add_argument("--only-set", default=None, help="evaluate this set only")
    p.add_argument("--only-row", default=None, help="evaluate this row only (of those asked for; e.g. 'fine-tuned')")
    p.add_argument("--lead-only", action="store_true",
                   help="the shielded priors at the policy's top-k and at top-3 and the policy only (no expert, no --rows)")
    p.add_argument("--num-envs", type=int, default=32, help="episodes stepped together")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--table", action="store_true", help="print the Markdown table of the rows found and exit")
    p.add_argument("--shield", type=shield_option, default=None, help="the shield's checks for every row, joined with '+' (e.g. "
                   "'collision+offroad+gap'; default: the policy's own)")
    args = p.parse_args(argv)

    import torch

    from agents import finetune as ft
    from agents.evaluate import LEAD_TOP_K, evaluate_policies
    from agents.policy import ExpertWithinTopK
    from smart_marl.scenario import AgentType

    torch.set_num_threads(args.threads)
    sets = [parse_set(s) for s in args.sets]
    run_dir = Path(args.run_dir)
    cfg, net, meta = ft.load_policy(args.policy)
    if args.shield is not None:
        cfg = dataclasses.replace(cfg, shield=args.shield)
    reference = f"prior top-{cfg.reference_top_k}" if cfg.reference_top_k else "prior full softmax"
    if args.table:
        print(table(run_dir, [s[0] for s in sets], reference))
        return 0
    run_dir.mkdir(parents=True, exist_ok=True)
    model, vocab = ft.load_prior(cfg.prior, cfg.device)
    training = set(meta.get("trained_on") or [])
    policies = ft.evaluation_policies(cfg, net)
    restricted = ExpertWithinTopK(cfg.reference_top_k) if cfg.reference_top_k else None
    if restricted is not None:
        policies[restricted.name] = restricted
    lead = [f"prior top-{k}" for k in dict.fromkeys((cfg.reference_top_k, LEAD_TOP_K)) if k]
    experts = ([restricted.name] if restricted is not None else []) + ["expert (log)"]
    shielded_priors = [k for k in policies if k.startswith("prior top-") and "shield off" not in k]
    wanted = lead + ["fine-tuned"] if args.lead_only else shielded_priors + ["fine-tuned"] + experts
    wanted += [] if args.lead_only else [k.strip() for k in args.rows.split(",") if k.strip() and k.strip() not in wanted]
    unknown = [k for k in wanted if k not in policies]
    if unknown:
        raise SystemExit(f"--rows: unknown row(s) {unknown}; known: {list(policies)}")
    if args.only_row is not None:
        if args.only_row not in wanted:
            raise SystemExit(f"--only-row: {args.only_row!r} is not one of the rows asked for: {wanted}")
        wanted = [args.only_row]
    for name, paths, count, num_seeds in sets:
        if args.only_set is not None and name != args.only_set:
            continue
        pool = ft._pool(paths, f"--set {name}")
        scenes = ft.core_scenes(cfg, pool, vocab, len(pool) if count is None else count, exclude=training)
        seeds = list(range(cfg.eval_seed, cfg.eval_seed + num_seeds))
        core = ft.evaluation_core(cfg, model, vocab, len(scenes))
        for row in wanted:
            def run(row=row):
                out = evaluate_policies(core, scenes, {row: policies[row]}, seeds, num_envs=args.num_envs,
                                        vocab_size=vocab[AgentType.VEHICLE].size, num_agents=cfg.max_agents, rules=cfg.eval_rules,
                                        temperature=cfg.temperature, reference_top_k=cfg.reference_top_k)
                return {"row": row, "policy": str(args.policy), "scenes": out["scenes"], "seeds": out["seeds"],
                        "rules": out["rules"], "metrics": out["rows"][row]}
            result = cached(run_dir / f"eval_{name}_{slug(row)}.json", run)
            emit({"benchmark": "finetune_heldout", "set": name, "row": row, "policy": result["policy"],
                  "scenes": len(result["scenes"]), "seeds": len(result["seeds"]), **result["metrics"]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
