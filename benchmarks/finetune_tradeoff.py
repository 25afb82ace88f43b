"""Benchmark: the realism / safety / goal trade-off of KL-regularised fine-tuning, one point per beta.

For each KL coefficient beta (0 included) a policy is fine-tuned (agents.finetune, the top-k
reference by default) on the training scenes, then every policy drives the same held-out scenes
(none used for fine-tuning) with the same seeds for the full 8 s horizon, nobody removed on an
event (agents.evaluate.evaluate_policies): the expert (log-following), the prior top-k (as it
drives; also at other k), the prior's full softmax, and each fine-tuned policy. One more run adds
the reward's prior log-likelihood term (SPACeR's idea: ``reward.prior_log_likelihood = W``).

Output: one JSON object per line on stdout ({"kind": "setup" | "baseline" | "finetuned" | "summary"}),
and a picture (PNG): realism of the controlled agents (sim-agents meta-metric, the controlled
agents as the evaluated ones, one rollout per seed) against collision + offroad rate, and against
goal rate, one point per beta, the prior and the expert marked.

Rerun on another prior with one command (about an hour of CPU at the defaults, see docs/finetuning.md;
``--reuse EARLIER.jsonl`` keeps an earlier run's rows and makes only the runs it lacks):

    .venv/bin/python benchmarks/finetune_tradeoff.py --prior PATH/TO/CHECKPOINT.json \\
        --out docs/images/finetune_tradeoff.png > runs/finetune_tradeoff.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from smart_marl.config_files import split_override  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
TRAIN_SCENES = [str(SHARED / "gpudrive_json")]  # WOMD training-split scenes
HELD_OUT_SCENES = [str(SHARED / "nocturne_json"), str(SHARED / "scenarionet" / "waymo" / "sd_training.*.pkl"),
                   str(SHARED / "smart_pkl"), str(SHARED / "womd_tfrecord" / "motion_data_one_scenario.tfrecord")]


def emit(obj) -> None:
    print(json.dumps(obj, default=float), flush=True)


def bad_rate(row: dict) -> float:
    """Collision + offroad rate of a row (the two fractions of agent-episodes, added)."""
    return row["collision_rate"] + row["offroad_rate"]


def draw(path: Path, baselines: dict, tuned: dict, reference: str, title: str) -> None:
    """Realism against collision + offroad rate and against goal rate, one point per policy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), sharey=True)
    marks = {"expert (log)": ("D", "black"), reference: ("*", "tab:green"), "prior full softmax": ("X", "tab:red")}
    for ax, (xkey, xlabel) in zip(axes, ((bad_rate, "collision + offroad rate (agent-episodes)"),
                                         (lambda r: r["goal_rate"], "goal rate (agent-episodes)"))):
        for name, row in baselines.items():
            m, c = marks.get(name, ("o", "tab:gray"))
            ax.scatter(xkey(row), row["meta_metric"], marker=m, s=140 if m == "*" else 70, color=c, zorder=3, label=name)
        betas = [(n, r) for n, r in tuned.items() if "log-lik" not in n]
        if betas:
            ax.plot([xkey(r) for _, r in betas], [r["meta_metric"] for _, r in betas], "-o", color="tab:blue", zorder=2,
                    label="fine-tuned (one point per beta)")
            for n, r in betas:
                ax.annotate(n.replace("fine-tuned ", ""), (xkey(r), r["meta_metric"]), textcoords="offset points",
                            xytext=(5, 4), fontsize=8, color="tab:blue")
        for n, r in tuned.items():
            if "log-lik" in n:
                ax.scatter(xkey(r), r["meta_metric"], marker="s", s=60, color="tab:purple", zorder=3, label=n)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("realism of the controlled agents (meta-metric)")
    axes[1].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _arguments() -> argparse.ArgumentParser:
    """The command line: the prior, the fine-tuning and held-out scenes, the betas and reward terms of the runs, the output."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--prior", default="embedded", help="SMART checkpoint (NAME.json) or 'embedded'")
    ap.add_argument("--scenes", nargs="*", default=TRAIN_SCENES, help="fine-tuning scene paths / globs")
    ap.add_argument("--num-scenes", type=int, default=6)
    ap.add_argument("--eval-scenes", nargs="*", default=HELD_OUT_SCENES, help="held-out scene paths / globs")
    ap.add_argument("--eval-num-scenes", type=int, default=4)
    ap.add_argument("--rollouts", type=int, default=16, help="seeds (rollouts) per held-out scene, every policy")
    ap.add_argument("--eval-seed", type=int, default=None,
                    help="the first evaluation seed (default: the fine-tuning config's, 1000); another block of seeds")
    ap.add_argument("--max-agents", type=int, default=4)
    ap.add_argument("--betas", type=float, nargs="*", default=[0.0, 0.03, 0.1, 0.3, 1.0])
    ap.add_argument("--loglik-weight", type=float, default=0.05, help="reward.prior_log_likelihood of the extra run (0: none)")
    ap.add_argument("--loglik-beta", type=float, default=0.1)
    ap.add_argument("--reference-top-k", type=int, default=None,
                    help="the reference's k (0: the full softmax; default: the fine-tuning config's, 3)")
    ap.add_argument("--background-top-k", type=int, default=None,
                    help="the background prior's top-k (default: the fine-tuning config's, DEFAULT_TOP_K)")
    ap.add_argument("--compare-k", type=int, nargs="*", default=[5, 10], help="extra prior top-k rows (0: none)")
    ap.add_argument("--reward", nargs="*", default=[], metavar="TERM=W",
                    help="reward weights of every fine-tuning run (envs RewardConfig terms, e.g. collision=-3); "
                         "the runs' names say them")
    ap.add_argument("--actor-head", default=None,
                    help="the fine-tuned actor's residual head, per_token or motion (default: the config's)")
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--frames-per-batch", type=int, default=240)
    ap.add_argument("--lr", type=float, default=0.003)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="docs/images/finetune_tradeoff.png", help="the picture (PNG)")
    ap.add_argument("--run-dir", default=None, help="fine-tuning runs' folder (default: a temporary one)")
    ap.add_argument("--reuse", default=None, metavar="JSONL", help="the output of an earlier run with the same prior, "
                    "held-out scenes, seeds and reference: its baseline and fine-tuned rows are kept (marked reused), "
                    "only the runs it lacks are made")
    return ap


def _base_config(args: argparse.Namespace) -> dict:
    """The fine-tuning config every run starts from (the tiny named config, overridden by the command line)."""
    base = {"scenes": list(args.scenes), "prior": args.prior, "num_scenes": args.num_scenes, "max_agents": args.max_agents,
            "background": "prior", "iterations": args.iterations, "frames_per_batch": args.frames_per_batch, "lr": args.lr,
            "eval_episodes": 0, "eval_scenes": list(args.eval_scenes), "eval_num_scenes": args.eval_num_scenes,
            "seed": args.seed, "torch_threads": args.threads, "tensorboard": False, "checkpoint_every": args.iterations}
    if args.reference_top_k is not None:
        base["reference_top_k"] = args.reference_top_k or None
    if args.background_top_k is not None:
        base["top_k"] = args.background_top_k
    if args.eval_seed is not None:
        base["eval_seed"] = args.eval_seed
    if args.actor_head is not None:
        base["actor_head"] = args.actor_head
    return base


def _reused_rows(args: argparse.Namespace, held_ids: list, seeds: list, reference: str, cfg):
    """(baseline rows, fine-tuned rows) of ``--reuse``'s earlier output (fine-tuned ones only from a run with this config);
    None when it was made with another prior, held-out scenes, seeds or reference."""
    reused_base, reused_tuned = {}, {}
    if args.reuse:
        same_training = False  # fine-tuned rows are reused only from a run with this fine-tuning config
        for line in Path(args.reuse).read_text().splitlines():
            d = json.loads(line)
            if d["kind"] == "setup":
                if (d["prior"], d["held_out_scenes"], d["seeds"], d["reference"]) != (args.prior, held_ids, seeds, reference):
                    print(f"--reuse {args.reuse}: another prior, held-out scenes, seeds or reference", file=sys.stderr)
                    return None
                same_training = d["config"] == json.loads(json.dumps(cfg.to_dict(), default=float))
            if d["kind"] == "baseline" or (d["kind"] == "finetuned" and same_training):
                row = {k: v for k, v in d.items() if k not in ("kind", "policy", "reused")}
                (reused_base if d["kind"] == "baseline" else reused_tuned)[d["policy"]] = row
    return reused_base, reused_tuned


def _summary(baselines: dict, tuned: dict, reference: str, t0: float) -> dict:
    """The summary row: the best fine-tuned run (fewest bad outcomes net of goals) against the reference prior."""
    ref = baselines[reference]
    best = None
    for name, row in tuned.items():
        if "log-lik" in name:
            continue
        if best is None or bad_rate(row) - row["goal_rate"] < bad_rate(tuned[best]) - tuned[best]["goal_rate"]:
            best = name
    summary = {"kind": "summary", "seconds": time.perf_counter() - t0, "reference": reference, "best": best}
    if best is not None:
        b = tuned[best]
        summary["must_show"] = {
            "bad_rate_ratio_to_prior_top_k": bad_rate(b) / bad_rate(ref) if bad_rate(ref) > 0 else math.nan,
            "bad_rate_at_most_0.7x": bad_rate(b) <= 0.7 * bad_rate(ref),
            "goal_rate_above_prior_top_k": b["goal_rate"] > ref["goal_rate"],
            "realism_minus_prior_top_k": b["meta_metric"] - ref["meta_metric"],
            "realism_within_0.03": abs(b["meta_metric"] - ref["meta_metric"]) <= 0.03,
        }
        zero = next((r for n, r in tuned.items() if n == "fine-tuned beta=0"), None)
        if zero is not None:
            summary["must_show"]["realism_falls_at_beta_0"] = zero["meta_metric"] < ref["meta_metric"]
    return summary


def main() -> int:
    ap = _arguments()
    args = ap.parse_args()
    try:
        reward = {k: float(v) for k, v in (split_override(item, ValueError) for item in args.reward)}
    except (TypeError, ValueError):
        ap.error(f"--reward: expected TERM=WEIGHT items, got {args.reward}")

    from agents.evaluate import evaluate_policies
    from agents.finetune import (FinetuneConfigError, evaluation_core, evaluation_policies, finetune, held_out_scenes, load_finetune_config,
                                 load_policy, load_prior, training_pool)
    from agents.policy import FinetunedTensorPolicy, PriorTensorPolicy
    from smart_marl.rollout import reference_name
    from smart_marl.scenario import AgentType

    torch.set_num_threads(args.threads)
    run_dir = Path(args.run_dir or tempfile.mkdtemp(prefix="finetune_tradeoff_"))
    base = _base_config(args)
    try:
        cfg = load_finetune_config("tiny", base)
    except FinetuneConfigError as exc:
        ap.error(str(exc))
    t0 = time.perf_counter()
    model, vocab = load_prior(cfg.prior)
    training = training_pool(cfg).scenario_ids()
    scenes = held_out_scenes(cfg, vocab, training)
    core = evaluation_core(cfg, model, vocab, len(scenes))
    reference = reference_name(cfg.reference_top_k, cfg.temperature)
    seeds = list(range(cfg.eval_seed, cfg.eval_seed + args.rollouts))
    held_ids = [s.static.scenario.scenario_id for s in scenes]

    def evaluate(policies):
        return evaluate_policies(core, scenes, policies, seeds, num_envs=cfg.num_envs, vocab_size=vocab[AgentType.VEHICLE].size,
                                 num_agents=cfg.max_agents, rules=cfg.eval_rules, temperature=cfg.temperature,
                                 reference_top_k=cfg.reference_top_k)["rows"]

    emit({"kind": "setup", "prior": args.prior, "training_scenes": training, "held_out_scenes": held_ids, "seeds": seeds,
          "reference": reference, "config": cfg.to_dict(), "torch": torch.__version__})

    reused = _reused_rows(args, held_ids, seeds, reference, cfg)
    if reused is None:
        return 2
    reused_base, reused_tuned = reused

    # the baselines: independent of beta, run once on the same scenes and seeds
    if reused_base:
        baselines = reused_base
    else:
        policies = evaluation_policies(cfg, None)
        for k in args.compare_k:
            if k and k != cfg.reference_top_k:
                p = PriorTensorPolicy(top_k=k, temperature=cfg.temperature)
                policies[p.name] = p
        t = time.perf_counter()
        baselines = evaluate(policies)
        emit({"kind": "timing", "what": "baselines", "seconds": time.perf_counter() - t})
    for name, row in baselines.items():
        emit({"kind": "baseline", "policy": name, **row, **({"reused": True} if reused_base else {})})

    tag = "".join(f", {k} {v:g}" for k, v in reward.items())
    runs = [(f"fine-tuned beta={b:g}{tag}", b, reward) for b in args.betas]
    if args.loglik_weight:
        runs.append((f"fine-tuned beta={args.loglik_beta:g}{tag} + prior log-lik {args.loglik_weight:g}", args.loglik_beta,
                     {**reward, "prior_log_likelihood": args.loglik_weight}))
    tuned = {}
    for name, beta, reward in runs:
        if name in reused_tuned:
            tuned[name] = reused_tuned[name]
            emit({"kind": "finetuned", "policy": name, **reused_tuned[name], "reused": True})
            continue
        t = time.perf_counter()
        run_cfg = load_finetune_config(cfg.to_dict(), {"beta": beta, "reward": reward,
                                                       "out_dir": str(run_dir / name.replace(" ", "_").replace("=", ""))})
        res = finetune(run_cfg)
        train_s = time.perf_counter() - t
        _, net, _ = load_policy(res.checkpoint)
        row = evaluate({name: FinetunedTensorPolicy(net)})[name]
        tuned[name] = row
        last = res.history[-1]
        emit({"kind": "finetuned", "policy": name, "beta": beta, "reward": reward, "train_seconds": train_s,
              "eval_seconds": time.perf_counter() - t - train_s, "train_last": {k: last[k] for k in
              ("goal_rate", "collision_rate", "offroad_rate", "kl_to_prior", "return_per_agent_episode")}, **row})

    summary = _summary(baselines, tuned, reference, t0)
    emit(summary)
    title = (f"prior {args.prior}; {len(training)} fine-tuning scenes, {len(scenes)} held-out scenes x {len(seeds)} seeds "
             f"x {cfg.max_agents} controlled vehicles; {cfg.iterations} iterations x {cfg.frames_per_batch} env steps; "
             f"reference {reference}")
    draw(Path(args.out), {k: v for k, v in baselines.items() if k in ("expert (log)", reference, "prior full softmax")},
         tuned, reference, title)
    return 0


if __name__ == "__main__":
    sys.exit(main())
