"""Fine-tuning stage, evaluation as the literature does it (HR-PPO, SPACeR): every policy drives the
controlled agents of the same held-out scenes with the same seeds for the full horizon, nobody
removed on an event, and is scored on what happened and on how human-like it drove.

What comes in: a PettingZoo env ``envs.smart_traffic_v0`` (built with ``terminate_on=()``, the
background and reference of the run), named policies (:class:`agents.prior_policy.SampledPolicy`:
the expert :class:`agents.scripted.LogFollowingPolicy`, :class:`~agents.prior_policy.PriorPolicy`
top-k and full softmax, a fine-tuned policy), scene indices and seeds. What goes out: one row per
policy (:func:`evaluate_policies`):

* ``goal_rate``, ``collision_rate``, ``offroad_rate``: fractions of agent-episodes in which the
  event happened at some step; ``progress_m``: metres gained along the logged route per
  agent-episode; ``return`` per agent-episode;
* ``kl_to_reference`` / ``kl_to_full_prior``: mean per agent-step of the exact KL(policy || the
  env's reference) and KL(policy || the prior's full softmax) (:func:`agents.prior_policy.kl_to_prior`;
  ``inf`` when the policy puts mass where the reference has none);
* realism of the controlled agents: the project's sim-agents metrics
  (:mod:`smart_marl.metrics`) with the controlled agents as the evaluated ones and every seed as
  one rollout of the scene (``meta_metric``, ``kinematic``, ``interactive``, ``map_based``,
  ``min_ade``), averaged over the scenes that fit the metrics (91 frames, 16 steps of horizon).

Fairness: scene ``i`` with seed ``s`` seeds the env (the background prior's sampler) and the
policy's sampler (:func:`agents.prior_policy.run_episode`), for every policy, scene and seed.
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np

from smart_marl.metrics import Rollouts, SceneNotScorableError, aggregate, logged_scene, score_rollouts
from smart_marl.metrics.config import NUM_SIMULATION_STEPS
from smart_marl.metrics.inputs import simulated_agent_indices
from smart_marl.tokens import FRAMES_PER_TOKEN

from .prior_policy import SampledPolicy, run_episode

RATES = ("goal_rate", "collision_rate", "offroad_rate")
REALISM = ("meta_metric", "kinematic", "interactive", "map_based", "min_ade")


def scene_logged(env, scene_index: int):
    """The metrics' logged scene of ``scene_index`` with the env's controlled agents as the
    evaluated ones, or None when the scene or the episodes do not fit the metrics (they need 91
    frames, the full 8 s horizon and nobody removed: ``terminate_on=()``)."""
    if env.horizon_steps * FRAMES_PER_TOKEN != NUM_SIMULATION_STEPS or env.terminate_on:
        return None
    env.reset(seed=0, options={"scene_index": int(scene_index)})
    try:
        return logged_scene(env.static.scenario, evaluated_tracks=env.ctrl_tracks)
    except SceneNotScorableError:
        return None


def episode_rollout(env, sim_tracks: np.ndarray) -> np.ndarray:
    """[A, 80, 4] x, y, z, heading of the simulated tracks in the episode just run (z held at the
    logged z of the current frame)."""
    poses, _ = env.trajectories()  # [N, 80, 3]
    p = poses[sim_tracks]
    z = np.broadcast_to(env.static.z[sim_tracks][:, None, None], (*p.shape[:2], 1))
    return np.concatenate([p[..., :2], z, p[..., 2:]], -1)


def evaluate_policies(env, policies: Mapping[str, SampledPolicy], scene_indices: Sequence[int], seeds: Sequence[int],
                      rules: str = "2024") -> dict:
    """Every policy on every (scene, seed) of ``env`` (see the module docstring). Returns
    ``{"scenes": [ids], "seeds": [...], "reference": env.reference, "rules": rules,
    "realism_scenes": [ids scored], "rows": {name: metrics}}``."""
    seeds = [int(s) for s in seeds]
    acc = {name: {k: 0.0 for k in ("goal", "collision", "offroad", "progress_m", "return", "kl_to_reference",
                                    "kl_to_full_prior", "steps", "n")} for name in policies}
    scored = {name: [] for name in policies}
    scene_ids, realism_ids = [], []
    for i in scene_indices:
        logged = scene_logged(env, int(i))
        sc = env.scenes[int(i)]
        scene_ids.append(sc.scenario_id)
        sim = simulated_agent_indices(sc)
        if logged is not None:
            realism_ids.append(sc.scenario_id)
        for name, policy in policies.items():
            a = acc[name]
            rollouts = []
            for s in seeds:
                ep = run_episode(env, policy, seed=s, scene_index=int(i))
                for agent in ep["return"]:
                    for key in ("goal", "collision", "offroad", "progress_m", "return", "kl_to_reference", "kl_to_full_prior",
                                "steps"):
                        a[key] += ep[key][agent]
                    a["n"] += 1
                if logged is not None:
                    rollouts.append(episode_rollout(env, sim))
            if logged is not None:
                traj = np.stack(rollouts)  # [R, A, 80, 4]
                scored[name].append(score_rollouts(logged, Rollouts.from_array(sc.tracks.ids[sim], traj), rules))
    rows = {}
    for name, a in acc.items():
        n, steps = max(a["n"], 1), max(a["steps"], 1)
        row = {"goal_rate": a["goal"] / n, "collision_rate": a["collision"] / n, "offroad_rate": a["offroad"] / n,
               "progress_m": a["progress_m"] / n, "return": a["return"] / n, "kl_to_reference": a["kl_to_reference"] / steps,
               "kl_to_full_prior": a["kl_to_full_prior"] / steps, "agent_episodes": int(a["n"]), "steps": int(a["steps"])}
        if scored[name]:
            agg = aggregate(scored[name], rules)
            row.update({k: agg[k] for k in REALISM})
        else:
            row.update({k: math.nan for k in REALISM})
        rows[name] = row
    return {"scenes": scene_ids, "seeds": seeds, "reference": env.reference, "rules": rules, "realism_scenes": realism_ids,
            "rows": rows}


def format_table(result: dict) -> str:
    """The evaluation as a fixed-width table."""
    rows = result["rows"]
    first = next(iter(rows.values()))
    lines = [f"{len(result['scenes'])} held-out scene(s) x {len(result['seeds'])} seed(s) = {first['agent_episodes']} "
             f"agent-episodes per policy (same scenes, same seeds); KL reference: {result['reference']}; realism "
             f"({result['rules']} rules, controlled agents) on {len(result['realism_scenes'])} scene(s)",
             f"{'policy':<20} {'collision':>9} {'offroad':>8} {'goal':>6} {'progress':>9} {'KL/step':>8} {'KL full':>8} "
             f"{'realism':>8} {'kinem.':>7} {'interact':>8} {'map':>6} {'minADE':>7}"]
    for name, m in rows.items():
        lines.append(f"{name:<20} {m['collision_rate']:>9.3f} {m['offroad_rate']:>8.3f} {m['goal_rate']:>6.3f} "
                     f"{m['progress_m']:>8.1f}m {m['kl_to_reference']:>8.3f} {m['kl_to_full_prior']:>8.3f} "
                     f"{m['meta_metric']:>8.4f} {m['kinematic']:>7.4f} {m['interactive']:>8.4f} {m['map_based']:>6.4f} "
                     f"{m['min_ade']:>7.2f}")
    return "\n".join(lines)


__all__ = ["RATES", "REALISM", "evaluate_policies", "format_table", "scene_logged"]
