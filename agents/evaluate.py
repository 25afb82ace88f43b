"""Fine-tuning stage, evaluation: a fine-tuned policy checkpoint against the SMART prior on the same
scenes and seeds, measured on the PettingZoo env itself (no TorchRL in the loop); what
``smart-marl finetune --evaluate`` prints.

What comes in: a policy checkpoint (:func:`agents.finetune.load_policy`) and its run's config
(scenes, prior, env settings), with ``key=value`` overrides. What goes out: one row per policy with
``goal_rate``, ``collision_rate``, ``offroad_rate`` (fractions of agent-episodes in which the
event happened), ``return`` (mean per agent-episode) and ``kl_to_prior`` (mean per agent-step of
the exact KL(policy || prior)), plus ``agent_episodes`` and ``steps``: the rows of
:func:`agents.finetune.compare_policies` (which says how every policy runs the same episodes),
each aggregated by :func:`agents.prior_policy.evaluate_policy`.
"""

from __future__ import annotations

from typing import Sequence

from .finetune import compare_policies, load_finetune_config, load_policy
from .prior_policy import evaluate_policy

METRICS = ("goal_rate", "collision_rate", "offroad_rate", "return", "kl_to_prior")


def evaluate_checkpoint(path, overrides: Sequence[str] = (), episodes: int | None = None, seed: int | None = None) -> dict:
    """:func:`compare_policies` for a policy checkpoint, with its run's config (``key=value``
    overrides, e.g. ``scenes=OTHER`` to evaluate on other scenes with the same agent count)."""
    cfg, net, meta = load_policy(path)
    if overrides:
        cfg = load_finetune_config(cfg.to_dict(), overrides)
    result = compare_policies(cfg, net, episodes=episodes, seed=seed)
    result["checkpoint"] = str(path)
    result["iteration"] = meta.get("iteration")
    return result


def format_table(result: dict) -> str:
    """The comparison as a fixed-width table."""
    rows = result["rows"]
    n_sc, n_seed = len(result["scenes"]), len(result["seeds"])
    first = next(iter(rows.values()))
    lines = [f"prior vs fine-tuned: {n_sc} scene(s) x {n_seed} seed(s) = {first['agent_episodes']} agent-episodes per policy "
             f"(same scenes, same seeds)",
             f"{'policy':<14} {'goal rate':>9} {'collision':>9} {'offroad':>9} {'return':>9} {'KL/step':>9}"]
    for name, m in rows.items():
        lines.append(f"{name:<14} {m['goal_rate']:>9.3f} {m['collision_rate']:>9.3f} {m['offroad_rate']:>9.3f} "
                     f"{m['return']:>9.3f} {m['kl_to_prior']:>9.4f}")
    return "\n".join(lines)


__all__ = ["METRICS", "compare_policies", "evaluate_checkpoint", "evaluate_policy", "format_table"]
