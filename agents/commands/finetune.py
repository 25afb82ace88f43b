"""``smart-marl finetune --config FILE|NAME [key=value ...]``: KL-regularised PPO of controlled
agents against the SMART prior (TorchRL); ``--evaluate CHECKPOINT`` runs the expert, the prior
(top-k and full softmax) and a fine-tuned policy on held-out scenes with the same seeds and prints
a table (rates, progress, KL, realism of the controlled agents).

Stage: fine-tuning; the pipeline is :mod:`agents.finetune` and :mod:`agents.evaluate`. Registered
through the ``smart_marl.commands`` entry point (see :mod:`agents.commands`). The command needs the
``env`` and ``rl`` extras (pettingzoo, torchrl): they are optional, so the pipeline is imported
inside :func:`run`, which says what to install when they are missing, and ``--help`` works
without them.
"""

from __future__ import annotations

import json
import sys

from smart_marl.commands.arguments import device, output_dir, rollouts, seed
from smart_marl.config_files import apply_command_flags, strict_json


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "finetune", help="fine-tune controlled agents with PPO + KL to the SMART prior (TorchRL); --evaluate compares with the prior",
        description="Fine-tune the agents a policy controls in the smart_traffic_v0 env with multi-agent PPO (MAPPO or IPPO, "
                    "TorchRL) plus beta * KL(policy || SMART prior). The config is a JSON/TOML file of FinetuneConfig fields or a "
                    "named config (agents/configs/finetune/: tiny, default, scale, shield); key=value overrides follow, e.g. scenes=DIR prior=CKPT "
                    "beta=0.1 iterations=50 out_dir=runs/ft. Writes finetune.csv, TensorBoard logs, policy checkpoints and, "
                    "with eval_episodes > 0, evaluation.json (held-out scenes). With --evaluate CHECKPOINT, runs the expert "
                    "(log-following), the prior top-k, the prior's full softmax and that policy on held-out scenes (eval_scenes; "
                    "default: the scenes after the fine-tuning ones) with the same seeds, full horizon, no termination, and "
                    "prints collision / offroad / goal rates, progress, KL and the controlled agents' realism (overrides apply "
                    "to the checkpoint's config).")
    p.add_argument("--config", default=None, help="fine-tuning config file (.json/.toml) or a named config (tiny, default, scale, shield)")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides, values parsed as JSON when they parse")
    p.add_argument("--out", default=None, type=output_dir, metavar="DIR", help="the run's folder (default: the config's out_dir)")
    p.add_argument("--device", default=None, type=device, help="torch device for the policy and its updates (default: the config's, cpu)")
    p.add_argument("--seed", type=seed, default=None, help="random seed (default: the config's); with --evaluate, the first evaluation seed")
    p.add_argument("--evaluate", default=None, metavar="CHECKPOINT", help="evaluate this policy checkpoint next to the expert and the prior on held-out scenes and exit")
    p.add_argument("--episodes", type=rollouts, default=None, help="with --evaluate: rollouts (seeds) per held-out scene (default: the config's eval_episodes)")
    p.add_argument("--select", default=None, metavar="RUN", help="score every policy checkpoint of the run folder RUN alone on "
                   "--val-scenes (goal rate - collision rate - offroad rate), write RUN/checkpoints/selection.json and "
                   "policy_best (a copy of the best) and print the scores (agents.select_policy)")
    p.add_argument("--val-scenes", default=None, metavar="PATH", help="with --select: validation scenes, neither the run's "
                   "training nor its test (eval_scenes) scenes")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.add_argument("--print-config", action="store_true", help="print the resolved config and exit")
    p.set_defaults(func=run)


def run(args) -> int:
    try:  # the optional env and rl extras
        from ..evaluate import format_table
        from ..finetune import evaluate_checkpoint, finetune, load_finetune_config
        from ..select_policy import select_policy
    except ImportError as exc:
        print(f"smart-marl finetune: error: needs the env and rl extras (pip install 'smart-marl[env,rl]'): {exc}", file=sys.stderr)
        return 2
    if args.select or args.val_scenes:
        return _select(args, select_policy)
    if args.evaluate:
        if args.out:
            print("smart-marl finetune: error: --out does not apply to --evaluate (it prints its table)", file=sys.stderr)
            return 2
        overrides = list(args.overrides)
        if args.device:
            overrides.append(f"device={args.device}")
        result = evaluate_checkpoint(args.evaluate, overrides, episodes=args.episodes, seed=args.seed)
        print(strict_json(result) if args.json else format_table(result))
        return 0
    if not args.config:
        print("smart-marl finetune: error: --config FILE|NAME is required (or --evaluate CHECKPOINT)", file=sys.stderr)
        return 2
    cfg = load_finetune_config(args.config, args.overrides)
    apply_command_flags(cfg, args)
    if args.print_config:
        print(json.dumps(cfg.to_dict(), indent=1))
        return 0

    def show(row: dict) -> None:
        print(f"iter {row['iteration']:>4}  frames {row['frames']:>7}  return {row['return_per_agent_episode']:+.3f}  "
              f"goal {row['goal_rate']:.3f}  collision {row['collision_rate']:.3f}  offroad {row['offroad_rate']:.3f}  "
              f"KL {row['kl_to_prior']:.4f}", file=sys.stderr, flush=True)

    result = finetune(cfg, on_iteration=show)
    summary = {"out_dir": str(result.out_dir), "checkpoint": str(result.checkpoint), "scenes": result.scene_ids,
               "last": result.history[-1]}
    if result.evaluation is not None:
        if args.json:
            summary["evaluation"] = result.evaluation
        else:
            print(format_table(result.evaluation))
    print(strict_json(summary))
    return 0


def _select(args, select_policy) -> int:
    """``--select RUN --val-scenes PATH``: ``select_policy`` (:func:`agents.select_policy.select_policy`), printed."""
    if not (args.select and args.val_scenes):
        print("smart-marl finetune: error: --select RUN and --val-scenes PATH go together", file=sys.stderr)
        return 2
    if args.config or args.evaluate or args.overrides or args.out or args.print_config:
        print("smart-marl finetune: error: --select takes only --val-scenes, --episodes, --seed and --json", file=sys.stderr)
        return 2
    selection = select_policy(args.select, args.val_scenes, episodes=args.episodes, seed=args.seed)
    if args.json:
        print(strict_json(selection))
        return 0
    for r in selection["checkpoints"]:
        row = r["row"]
        print(f"{r['checkpoint']:<14} iteration {r['iteration']!s:>5}  score {r['score']:+.3f}  goal {row['goal_rate']:.3f}  "
              f"collision {row['collision_rate']:.3f}  offroad {row['offroad_rate']:.3f}")
    print(f"best: {selection['best']} -> {args.select}/checkpoints/policy_best")
    return 0
