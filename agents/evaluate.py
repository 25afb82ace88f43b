"""Fine-tuning stage, evaluation as the literature does it (HR-PPO, SPACeR): every policy drives the
controlled agents of the same held-out scenes with the same seeds for the full horizon, nobody
removed on an event, and is scored on what happened and on how human-like it drove.

What comes in: the batched environment's core (:class:`envs._core.TrafficCore`, built with
``terminate_on=()``, ``record=True``, the background of the run), the held-out scenes with their
controlled agents, named policies that act on every scene at once (:class:`agents.policy.TensorPolicy`:
the expert :class:`~agents.policy.ExpertTensorPolicy`, the prior at the reference's top-k and its
full softmax :class:`~agents.policy.PriorTensorPolicy`, a fine-tuned actor), seeds, and how many
episodes run side by side. What goes out: one row per policy (:func:`evaluate_policies`):

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

Fairness: every policy runs the same episodes (scene, seed) in the same waves of ``num_envs``
scenes, each wave's background sampler and policy sampler seeded alike, so the policies differ only
by what they do.

One environment (issue 58): rows compare only under the same environment options. With the core's
shield on (:mod:`envs._shield`), :func:`same_environment_policies` puts first the strongest baselines
in that environment, the shielded prior at the policy's own top-k and the shielded prior top-3, and
keeps those two with the shield off (:class:`ShieldOff`, named ``"..., shield off"``) as extra rows of
another environment, last. Every row says which environment it ran in (``"shield"``: the checks that
were on, ``[]`` for none) and :func:`format_table` prints it ("on" / "off") and compares the
fine-tuned row with the first prior row of its own environment only. The log-following expert reads no
logits, so the shield never takes its tokens out: its row is the same with the shield on or off.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from typing import Mapping, Sequence

import numpy as np
import torch

from envs._core import CoreScene, TrafficCore
from envs._shield import DEFAULT_SHIELD_CHECKS
from smart_marl.geometry import bearing_deg, first_overlaps
from smart_marl.metrics import Rollouts, SceneNotScorableError, aggregate, logged_scene, score_rollouts
from smart_marl.metrics.config import NUM_SIMULATION_STEPS
from smart_marl.metrics.inputs import simulated_agent_indices
from smart_marl.rollout import reference_name
from smart_marl.tokens import FRAMES_PER_TOKEN

from .policy import FinetunedTensorPolicy, PriorTensorPolicy, TensorPolicy
from .prior_policy import kl_to_prior

RATES = ("goal_rate", "collision_rate", "offroad_rate")
COLLISION_KINDS = ("rear_ended", "front", "side")
"""Where the other agent was, one frame before a controlled agent's first collision, seen from that
agent: behind it (more than 135 degrees off its heading), ahead (within 45 degrees) or to a side."""
REALISM = ("meta_metric", "kinematic", "interactive", "map_based", "min_ade")
LEAD_TOP_K = 3
"""The second baseline a shielded table leads with, after the prior at the policy's own top-k: the prior top-3 (the
project's default reference and the scale issue's), with the same shield."""
SHIELD_OFF = "shield off"
"""What the name of a row run with the shield off ends with (``"prior top-3, shield off"``)."""


class ShieldOff(TensorPolicy):
    """``policy`` run with the environment's shield off: a row of another environment, kept beside a shielded
    table for reference (its prior logits are the unshielded ones; everything else is ``policy``'s)."""

    def __init__(self, policy: TensorPolicy) -> None:
        self.policy, self.top_k, self.name = policy, policy.top_k, f"{policy.name}, {SHIELD_OFF}"

    def reset(self, seed: int) -> None:
        self.policy.reset(seed)

    def log_probs(self, core, observation, prior_logits):
        return self.policy.log_probs(core, observation, prior_logits)

    def act(self, log_probs):
        return self.policy.act(log_probs)


def same_environment_policies(policies: Mapping[str, TensorPolicy], shield: Sequence[str], top_k: int | None,
                              temperature: float = 1.0) -> dict[str, TensorPolicy]:
    """The rows of an evaluation in one environment (module docstring), in table order. Without a shield:
    ``policies`` as they are. With one (``shield``: the core's checks): the prior at the policy's top-k
    (``top_k``, the fine-tuned policy's reference k) and at :data:`LEAD_TOP_K`, both shielded, first (taken
    from ``policies`` where they are there already), then the rest of ``policies``, then those two priors
    with the shield off (:class:`ShieldOff`), last."""
    if not shield:
        return dict(policies)
    lead: dict[str, TensorPolicy] = {}
    for k in dict.fromkeys((top_k, LEAD_TOP_K)):
        name = PriorTensorPolicy(top_k=k, temperature=temperature).name
        lead[name] = policies.get(name) or PriorTensorPolicy(top_k=k, temperature=temperature)
    rows = {**lead, **{name: p for name, p in policies.items() if name not in lead}}
    for p in lead.values():
        off = ShieldOff(p)
        rows[off.name] = off
    return rows


def shield_label(checks: Sequence[str]) -> str:
    """"on" (the checks of ``shield=True``, :data:`envs._shield.DEFAULT_SHIELD_CHECKS`), "off" (none) or the checks
    joined with "+"."""
    checks = tuple(checks)
    return "off" if not checks else "on" if set(checks) == set(DEFAULT_SHIELD_CHECKS) else "+".join(checks)


@contextmanager
def _shield_as(core: TrafficCore, checks: Sequence[str]):
    """``core`` with its shield's checks set to ``checks`` for the block (a :class:`ShieldOff` row's), then as it was."""
    before = core.shield
    core.shield = tuple(checks)
    try:
        yield
    finally:
        core.shield = before


def first_collision_kinds(poses: np.ndarray, present: np.ndarray, box_size: np.ndarray, ctrl: Sequence[int]) -> list:
    """Per controlled track ``ctrl[i]``: None (no collision) or the :data:`COLLISION_KINDS` entry of its
    first collision: the first frame its rounded box overlaps another present track's (the env's
    collision test, :func:`smart_marl.geometry.first_overlaps`), the lowest-indexed other taken at the frame before,
    in the controlled agent's frame then. poses [N, F, 3] x, y, heading, present [N, F] bool,
    box_size [N, 2+] length, width (``env.trajectories()`` and ``env.static.box_size``)."""
    first, partners = first_overlaps(poses, present, box_size[:, 0], box_size[:, 1], np.asarray(ctrl, np.int64))
    kinds = []
    for c, frame, others in zip(ctrl, first, partners):
        if frame < 0:
            kinds.append(None)
            continue
        c, before = int(c), max(int(frame) - 1, 0)
        dx, dy = poses[int(others[0]), before, :2] - poses[c, before, :2]
        angle = bearing_deg(float(dx), float(dy), float(poses[c, before, 2]))
        kinds.append("front" if angle < 45.0 else "rear_ended" if angle > 135.0 else "side")
    return kinds


def scene_logged(core: TrafficCore, scene: CoreScene):
    """The metrics' logged scene with the scene's controlled agents as the evaluated ones, or None
    when the scene or the episodes do not fit the metrics (they need 91 frames, the full 8 s horizon
    and nobody removed: ``terminate_on=()``)."""
    if core.horizon_steps * FRAMES_PER_TOKEN != NUM_SIMULATION_STEPS or core.terminate_on:
        return None
    try:
        return logged_scene(scene.static.scenario, evaluated_tracks=scene.controlled)
    except SceneNotScorableError:
        return None


def episode_rollout(core: TrafficCore, row: int, sim_tracks: np.ndarray) -> np.ndarray:
    """[A, 80, 4] x, y, z, heading of the simulated tracks in row ``row``'s episode (z held at the
    logged z of the current frame)."""
    poses, _ = core.trajectories(row)  # [N, 80, 3]
    p = poses[sim_tracks]
    z = np.broadcast_to(core.scenes.statics[row].z[sim_tracks][:, None, None], (*p.shape[:2], 1))
    return np.concatenate([p[..., :2], z, p[..., 2:]], -1)


_SUMS = ("goal", "collision", "offroad", "progress_m", "return", "kl_to_reference", "kl_to_full_prior", "steps", "n", *COLLISION_KINDS)


def _run_wave(core: TrafficCore, scenes: Sequence[CoreScene], policy: TensorPolicy, seed: int, vocab_size: int, num_agents: int,
              temperature: float, reference_top_k: int | None, acc: dict) -> None:
    """One wave of episodes (one per row, the full horizon) of ``policy``; per agent-episode sums into ``acc``."""
    core.reset(list(scenes), seed, num_agents=num_agents)
    policy.reset(seed)
    b, c = core.ctrl_track.shape
    start = core.progress_m.clone()
    acted = torch.zeros(b, c, dtype=torch.bool, device=core.device)
    sums = {k: torch.zeros(b, c, dtype=torch.float64, device=core.device) for k in ("return", "kl_to_reference", "kl_to_full_prior",
                                                                                   "steps", "goal", "collision", "offroad")}
    while bool(core.live.any()):
        live = core.live
        obs, prior = core.observations(), core.prior_logits()[..., :vocab_size].float()
        logp = policy.log_probs(core, obs, prior)
        for key, k in (("kl_to_reference", reference_top_k), ("kl_to_full_prior", None)):
            sums[key] += torch.where(live, kl_to_prior(logp, prior, temperature, k).clamp_min(0.0).double(), 0.0)
        r = core.step(policy.act(logp))
        acted |= live
        sums["return"] += torch.where(live, r.reward, 0.0)
        sums["steps"] += live
        for key, event in (("goal", r.goal_reached), ("collision", r.collision), ("offroad", r.offroad)):
            sums[key] = torch.maximum(sums[key], event.double())
    sums["progress_m"] = (core.progress_m - start).double()
    for key, value in sums.items():
        acc[key] += float(torch.where(acted, value, 0.0).sum())
    acc["n"] += int(acted.sum())
    for row, scene in enumerate(scenes):
        poses, present = core.trajectories(row)
        for kind in first_collision_kinds(poses, present, scene.static.box_size, scene.controlled):
            if kind is not None:
                acc[kind] += 1


def evaluate_policies(core: TrafficCore, scenes: Sequence[CoreScene], policies: Mapping[str, TensorPolicy], seeds: Sequence[int],
                      num_envs: int, vocab_size: int, num_agents: int, rules: str = "2024", temperature: float = 1.0,
                      reference_top_k: int | None = None) -> dict:
    """Every policy on every (scene, seed) (see the module docstring), ``num_envs`` episodes at a time
    on ``core`` (built with ``record=True`` and ``terminate_on=()``; its prior also drives the
    background), ``num_agents`` controlled slots per scene (the policies' group size), tokens of the
    group's ``vocab_size``. The episodes are cut into waves in the same order for every policy, and wave ``w``
    seeds the background's sampler and the policy's with ``seeds[0] + w``. Returns ``{"scenes": [ids],
    "seeds": [...], "reference": ..., "rules": rules, "realism_scenes": [ids scored], "shield": [the core's checks],
    "rows": {name: metrics}}``; each row's ``"shield"`` holds the checks it ran with (none for a :class:`ShieldOff`
    policy, the core's for every other; :func:`same_environment_policies` orders the rows of a shielded core)."""
    seeds = [int(s) for s in seeds]
    episodes = [(i, s) for i in range(len(scenes)) for s in seeds]
    waves = [episodes[lo:lo + num_envs] for lo in range(0, len(episodes), num_envs)]
    logged = [scene_logged(core, sc) for sc in scenes]
    sim = [simulated_agent_indices(sc.static.scenario) for sc in scenes]
    rows = {}
    for name, policy in policies.items():
        acc = {k: 0.0 for k in _SUMS}
        rollouts: dict[int, list] = {i: [] for i in range(len(scenes))}
        checks = () if isinstance(policy, ShieldOff) else tuple(core.shield)
        with _shield_as(core, checks):
            for w, wave in enumerate(waves):
                wave_scenes = [scenes[i] for i, _ in wave]
                _run_wave(core, wave_scenes, policy, seeds[0] + w, vocab_size, num_agents, temperature, reference_top_k, acc)
                for row, (i, _) in enumerate(wave):
                    if logged[i] is not None:
                        rollouts[i].append(episode_rollout(core, row, sim[i]))
        scored = [score_rollouts(logged[i], Rollouts.from_array(scenes[i].static.scenario.tracks.ids[sim[i]], np.stack(r)), rules)
                  for i, r in rollouts.items() if r]
        n, steps = max(acc["n"], 1), max(acc["steps"], 1)
        row = {"goal_rate": acc["goal"] / n, "collision_rate": acc["collision"] / n, "offroad_rate": acc["offroad"] / n,
               "progress_m": acc["progress_m"] / n, "return": acc["return"] / n, "kl_to_reference": acc["kl_to_reference"] / steps,
               "kl_to_full_prior": acc["kl_to_full_prior"] / steps, "agent_episodes": int(acc["n"]), "steps": int(acc["steps"]),
               "rear_ended_rate": acc["rear_ended"] / n, "front_collision_rate": acc["front"] / n, "side_collision_rate": acc["side"] / n}
        agg = aggregate(scored, rules) if scored else {}
        row.update({k: agg.get(k, math.nan) for k in REALISM})
        row["shield"] = list(checks)
        rows[name] = row
    return {"scenes": [sc.static.scenario.scenario_id for sc in scenes], "seeds": seeds,
            "reference": reference_name(reference_top_k, temperature), "rules": rules,
            "realism_scenes": [sc.static.scenario.scenario_id for sc, lg in zip(scenes, logged) if lg is not None],
            "shield": list(core.shield), "rows": rows}


def _times(a: float, b: float) -> str:
    """``a / b`` as ``"1.35x"`` (``"inf"`` when only ``b`` is 0, ``"n/a"`` when both are or either is NaN)."""
    if math.isnan(a) or math.isnan(b) or (a == 0 and b == 0):
        return "n/a"
    return f"{a / b:.2f}x" if b else "inf"


def lead_row(result: dict, name: str = FinetunedTensorPolicy.name) -> str | None:
    """The row ``name`` is compared with: the first prior row (in table order) of the same environment (the same
    shield); None when there is none or no row ``name``."""
    rows = result["rows"]
    if name not in rows:
        return None
    env = rows[name].get("shield", result.get("shield", []))
    return next((k for k, m in rows.items() if k != name and k.startswith("prior") and m.get("shield", result.get("shield", [])) == env),
                None)


def format_table(result: dict) -> str:
    """The evaluation as a fixed-width table: a row per policy in the result's order, its environment in the
    ``shield`` column ("on" / "off"), and a last line comparing the fine-tuned row with :func:`lead_row` (the first
    prior row of its own environment)."""
    rows = result["rows"]
    first = next(iter(rows.values()))
    env = result.get("shield", [])
    shields = {name: m.get("shield", env) for name, m in rows.items()}
    width = max(20, *(len(name) for name in rows))
    lines = [f"{len(result['scenes'])} held-out scene(s) x {len(result['seeds'])} seed(s) = {first['agent_episodes']} "
             f"agent-episodes per policy (same scenes, same seeds); KL reference: {result['reference']}; realism "
             f"({result['rules']} rules, controlled agents) on {len(result['realism_scenes'])} scene(s); "
             f"environment: shield {shield_label(env)}"]
    if any(checks != env for checks in shields.values()):
        lines.append(f"rows with shield {', '.join(sorted({shield_label(c) for c in shields.values() if c != env}))} ran in another "
                     f"environment: compare them only with each other")
    lines.append(f"{'policy':<{width}} {'shield':>6} {'collision':>9} {'rear-ended':>10} {'offroad':>8} {'goal':>6} {'progress':>9} "
                 f"{'KL/step':>8} {'KL full':>8} {'realism':>8} {'kinem.':>7} {'interact':>8} {'map':>6} {'minADE':>7}")
    for name, m in rows.items():
        lines.append(f"{name:<{width}} {shield_label(shields[name]):>6} {m['collision_rate']:>9.3f} {m['rear_ended_rate']:>10.3f} "
                     f"{m['offroad_rate']:>8.3f} {m['goal_rate']:>6.3f} {m['progress_m']:>8.1f}m {m['kl_to_reference']:>8.3f} "
                     f"{m['kl_to_full_prior']:>8.3f} {m['meta_metric']:>8.4f} {m['kinematic']:>7.4f} {m['interactive']:>8.4f} "
                     f"{m['map_based']:>6.4f} {m['min_ade']:>7.2f}")
    tuned, lead = FinetunedTensorPolicy.name, lead_row(result)
    if lead is not None:
        t, b = rows[tuned], rows[lead]
        bad = lambda m: m["collision_rate"] + m["offroad_rate"]  # noqa: E731
        lines.append(f"{tuned} against {lead} in the same environment (shield {shield_label(shields[tuned])}): goal "
                     f"{_times(t['goal_rate'], b['goal_rate'])}, collision + offroad {_times(bad(t), bad(b))}, "
                     f"realism {t['meta_metric'] - b['meta_metric']:+.4f}")
    return "\n".join(lines)


__all__ = ["COLLISION_KINDS", "LEAD_TOP_K", "RATES", "REALISM", "SHIELD_OFF", "ShieldOff", "episode_rollout", "evaluate_policies",
           "first_collision_kinds", "format_table", "lead_row", "same_environment_policies", "scene_logged", "shield_label"]
