"""Fine-tuning stage, evaluation: a fine-tuned policy against the SMART prior on the same scenes
and seeds, measured on the PettingZoo env itself (no TorchRL in the loop).

What comes in: a policy checkpoint (:func:`agents.finetune.load_policy`) or the actor network of a
run, and the run's config (scenes, prior, env settings). What goes out: one row per policy with
``goal_rate``, ``collision_rate``, ``offroad_rate`` (fractions of agent-episodes in which the
event happened), ``return`` (mean per agent-episode) and ``kl_to_prior`` (mean per agent-step of
the exact KL(policy || prior)), plus ``agent_episodes`` and ``steps``.

Fairness: every policy runs the same episodes: scene ``i`` with env seed ``s`` (which seeds the
background prior's sampler) and policy seed ``s`` (which seeds the policy's sampler, the same
sampling function for every policy), for every scene and ``s`` in ``eval_seed ..
eval_seed + episodes - 1``. The rows:

* ``prior``: :class:`~agents.prior_policy.PriorPolicy` sampling the full softmax (the reference
  the KL is taken against: its KL is 0);
* ``prior top-k``: the prior with the background's top-k sampling (how SMART is usually driven);
* ``fine-tuned``: the fine-tuned actor, sampled.
"""

from __future__ import annotations

from typing import Sequence

from .prior_policy import PriorPolicy, run_episode

METRICS = ("goal_rate", "collision_rate", "offroad_rate", "return", "kl_to_prior")


def evaluate_policy(env, policy, scene_indices: Sequence[int], seeds: Sequence[int]) -> dict[str, float]:
    """Aggregate :func:`~agents.prior_policy.run_episode` over every (scene, seed)."""
    goal, coll, off, ret, kl, steps, n = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0
    for i in scene_indices:
        for s in seeds:
            ep = run_episode(env, policy, seed=int(s), scene_index=int(i))
            for a in ep["return"]:
                goal += ep["goal"][a]
                coll += ep["collision"][a]
                off += ep["offroad"][a]
                ret += ep["return"][a]
                kl += ep["kl_to_prior"][a]
                steps += ep["steps"][a]
                n += 1
    return {"goal_rate": goal / n, "collision_rate": coll / n, "offroad_rate": off / n, "return": ret / n,
            "kl_to_prior": kl / max(steps, 1), "agent_episodes": n, "steps": int(steps)}


def compare_policies(cfg, net, scenes=None, model=None, vocab=None, episodes: int | None = None,
                     seed: int | None = None) -> dict:
    """Prior, prior top-k and the fine-tuned actor ``net`` on the run's scenes and the same seeds.
    Returns ``{"scenes": [...], "seeds": [...], "rows": {name: metrics}}``."""
    from .finetune import FinetunedPolicy, load_prior, scene_env, select_scenes

    if model is None or vocab is None:
        model, vocab = load_prior(cfg.prior)
    if scenes is None:
        scenes = select_scenes(cfg, model, vocab)
    episodes = cfg.eval_episodes if episodes is None else int(episodes)
    seed0 = cfg.eval_seed if seed is None else int(seed)
    seeds = list(range(seed0, seed0 + max(episodes, 1)))
    env = scene_env(cfg, scenes, model, vocab)
    idx = list(range(len(scenes)))
    rows = {
        "prior": evaluate_policy(env, PriorPolicy(top_k=None, temperature=cfg.temperature), idx, seeds),
        f"prior top-{cfg.top_k}": evaluate_policy(env, PriorPolicy(top_k=cfg.top_k, temperature=cfg.temperature), idx, seeds),
        "fine-tuned": evaluate_policy(env, FinetunedPolicy(net), idx, seeds),
    }
    return {"scenes": [sc.scenario_id for sc in scenes], "seeds": seeds, "rows": rows}


def evaluate_checkpoint(path, overrides: Sequence[str] = (), episodes: int | None = None, seed: int | None = None) -> dict:
    """:func:`compare_policies` for a policy checkpoint, with its run's config (``key=value``
    overrides, e.g. ``scenes=OTHER`` to evaluate on other scenes with the same agent count)."""
    from .finetune import load_finetune_config, load_policy

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
