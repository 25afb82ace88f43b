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
* who hit whom (:func:`first_collision_kinds`): ``collision_rate`` split by where the agent a
  controlled agent first overlapped was a frame before, ``rear_ended_rate`` (behind it: the other ran
  into it), ``front_collision_rate`` (ahead: it ran into the other) and ``side_collision_rate``;
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

from smart_marl.geometry import boxes_overlap
from smart_marl.metrics import Rollouts, SceneNotScorableError, aggregate, logged_scene, score_rollouts
from smart_marl.metrics.config import NUM_SIMULATION_STEPS
from smart_marl.metrics.inputs import simulated_agent_indices
from smart_marl.tokens import FRAMES_PER_TOKEN

from .prior_policy import SampledPolicy, run_episode

RATES = ("goal_rate", "collision_rate", "offroad_rate")
COLLISION_KINDS = ("rear_ended", "front", "side")
"""Where the other agent was, one frame before a controlled agent's first collision, seen from that
agent: behind it (more than 135 degrees off its heading), ahead (within 45 degrees) or to a side."""
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


def first_collision_kinds(poses: np.ndarray, present: np.ndarray, box_size: np.ndarray, ctrl: Sequence[int]) -> list:
    """Per controlled track ``ctrl[i]``: None (no collision) or the :data:`COLLISION_KINDS` entry of its
    first collision: the first frame its rounded box overlaps another present track's (the env's
    collision test, :func:`smart_marl.geometry.boxes_overlap`), the other taken at the frame before,
    in the controlled agent's frame then. poses [N, F, 3] x, y, heading, present [N, F] bool,
    box_size [N, 2+] length, width (``env.trajectories()`` and ``env.static.box_size``)."""
    n, f = present.shape
    length, width = box_size[:, 0, None], box_size[:, 1, None]
    kinds = []
    for c in ctrl:
        c = int(c)
        a = [np.broadcast_to(v, (n, f)) for v in (poses[c, :, 0], poses[c, :, 1], box_size[c, 0], box_size[c, 1], poses[c, :, 2])]
        b = [np.broadcast_to(v, (n, f)) for v in (poses[:, :, 0], poses[:, :, 1], length, width, poses[:, :, 2])]
        hit = boxes_overlap(*a, *b) & present & present[c]
        hit[c] = False
        frames = np.flatnonzero(hit.any(0))
        if not len(frames):
            kinds.append(None)
            continue
        first = int(frames[0])
        other, before = int(np.argmax(hit[:, first])), max(first - 1, 0)
        dx, dy = poses[other, before, :2] - poses[c, before, :2]
        h = poses[c, before, 2]
        angle = abs(math.degrees(math.atan2(-dx * math.sin(h) + dy * math.cos(h), dx * math.cos(h) + dy * math.sin(h))))
        kinds.append("front" if angle < 45.0 else "rear_ended" if angle > 135.0 else "side")
    return kinds


def evaluate_policies(env, policies: Mapping[str, SampledPolicy], scene_indices: Sequence[int], seeds: Sequence[int],
                      rules: str = "2024") -> dict:
    """Every policy on every (scene, seed) of ``env`` (see the module docstring). Returns
    ``{"scenes": [ids], "seeds": [...], "reference": env.reference, "rules": rules,
    "realism_scenes": [ids scored], "rows": {name: metrics}}``."""
    seeds = [int(s) for s in seeds]
    acc = {name: {k: 0.0 for k in ("goal", "collision", "offroad", "progress_m", "return", "kl_to_reference",
                                    "kl_to_full_prior", "steps", "n", *COLLISION_KINDS)} for name in policies}
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
                poses, present = env.trajectories()
                for kind in first_collision_kinds(poses, present, env.static.box_size, env.ctrl_tracks):
                    if kind is not None:
                        a[kind] += 1
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
               "kl_to_full_prior": a["kl_to_full_prior"] / steps, "agent_episodes": int(a["n"]), "steps": int(a["steps"]),
               "rear_ended_rate": a["rear_ended"] / n, "front_collision_rate": a["front"] / n,
               "side_collision_rate": a["side"] / n}
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
             f"{'policy':<20} {'collision':>9} {'rear-ended':>10} {'offroad':>8} {'goal':>6} {'progress':>9} {'KL/step':>8} {'KL full':>8} "
             f"{'realism':>8} {'kinem.':>7} {'interact':>8} {'map':>6} {'minADE':>7}"]
    for name, m in rows.items():
        lines.append(f"{name:<20} {m['collision_rate']:>9.3f} {m['rear_ended_rate']:>10.3f} {m['offroad_rate']:>8.3f} {m['goal_rate']:>6.3f} "
                     f"{m['progress_m']:>8.1f}m {m['kl_to_reference']:>8.3f} {m['kl_to_full_prior']:>8.3f} "
                     f"{m['meta_metric']:>8.4f} {m['kinematic']:>7.4f} {m['interactive']:>8.4f} {m['map_based']:>6.4f} "
                     f"{m['min_ade']:>7.2f}")
    return "\n".join(lines)


__all__ = ["COLLISION_KINDS", "RATES", "REALISM", "evaluate_policies", "first_collision_kinds", "format_table", "scene_logged"]
