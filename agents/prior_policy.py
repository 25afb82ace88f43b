"""Policies stage: the SMART prior as a policy (the default policy of every controlled agent).

What comes in: a step of the PettingZoo env ``envs.smart_traffic_v0`` (its observations and
``infos``); what goes out: ``{agent name: token id}``, the actions of the live agents. The prior's
logits are read from ``infos[agent]["prior_logits"]`` or, with ``observation="dict"``, from
``observations[agent]["prior_logits"]``; the env computed them already, so acting costs no model
call.

Sampling uses :func:`smart_marl.rollout.sample_tokens` (the engine's sampler): ``top_k=None``
samples the full ``softmax(logits / temperature)``, the reference distribution that
``KL(pi || prior)`` is measured against (the KL of this policy to the prior is exactly 0);
``top_k=5`` is how the env's own background agents drive. Every policy in agents/ that samples
(this one and :class:`agents.finetune.FinetunedPolicy`) draws through the same function from a
generator seeded by :meth:`reset`, so two policies with equal distributions take equal actions on
equal seeds.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import torch

from envs.errors import NoPriorLogitsError
from smart_marl.rollout import sample_tokens


def kl_to_prior(policy_log_probs: torch.Tensor, prior_logits: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """The exact categorical ``KL(pi || prior) = sum_v pi(v) (log pi(v) - log prior(v))`` per row,
    prior = ``softmax(prior_logits / temperature)``: policy_log_probs [..., V] (``log pi``),
    prior_logits [..., V] -> [...]. The one KL of the project (evaluation, batch statistics and the
    PPO loss term, :class:`agents.kl_ppo.PriorKLPPOLoss`)."""
    prior_log_probs = torch.log_softmax(prior_logits / temperature, -1)
    return (policy_log_probs.exp() * (policy_log_probs - prior_log_probs)).sum(-1)


def prior_logits_of(agent: str, observations: Mapping, infos: Mapping) -> np.ndarray:
    """The prior's logits [V] of one agent's next token, from its info or its dict observation."""
    info = infos.get(agent, {}) if infos else {}
    if "prior_logits" in info:
        return np.asarray(info["prior_logits"], np.float32)
    obs = observations.get(agent) if observations else None
    if isinstance(obs, Mapping) and "prior_logits" in obs:
        return np.asarray(obs["prior_logits"], np.float32)
    raise NoPriorLogitsError(f"no prior logits for {agent}: the env needs a prior (prior=PATH or a model); "
                   f"they are in infos[agent]['prior_logits'] and in the 'dict' observation")


class PriorPolicy:
    """Acts by sampling the SMART prior's next-token distribution of each live agent.

    ``policy.reset(seed)`` at the start of an episode, then ``actions = policy(observations,
    infos)`` after each env reset/step. ``top_k``: None (full distribution, KL 0 to the prior) or
    k (top-k renormalised, like the env's background agents); ``temperature`` divides the logits.
    """

    name = "prior"

    def __init__(self, top_k: int | None = None, temperature: float = 1.0, seed: int = 0) -> None:
        self.top_k = top_k
        self.temperature = float(temperature)
        self.generator = torch.Generator().manual_seed(int(seed))

    def reset(self, seed: int) -> None:
        self.generator = torch.Generator().manual_seed(int(seed))

    def logits(self, agents: list[str], observations: Mapping, infos: Mapping) -> torch.Tensor:
        """[A, V] logits this policy samples from (before temperature)."""
        return torch.from_numpy(np.stack([prior_logits_of(a, observations, infos) for a in agents]))

    def __call__(self, observations: Mapping, infos: Mapping, agents: list[str] | None = None) -> dict[str, int]:
        agents = list(observations) if agents is None else list(agents)
        if not agents:
            return {}
        logits = self.logits(agents, observations, infos)
        tokens, _ = sample_tokens(logits, self.generator, top_k=self.top_k, temperature=self.temperature)
        return {a: int(t) for a, t in zip(agents, tokens.tolist())}


def run_episode(env, policy, seed: int, scene_index: int | None = None) -> dict:
    """One episode of ``policy`` on the PettingZoo env from ``env.reset(seed=seed)`` (the policy is
    reset with the same seed). Returns per-agent totals over the episode: ``return``, ``goal``,
    ``collision``, ``offroad`` (bool: the event happened at some step), ``steps`` and
    ``kl_to_prior`` (sum over the agent's steps of KL(policy || prior) when the policy exposes
    ``logits``; per-step mean = kl_to_prior / steps)."""
    options = {"scene_index": scene_index} if scene_index is not None else None
    obs, infos = env.reset(seed=seed, options=options)
    policy.reset(seed)
    names = list(env.possible_agents)
    out = {k: {a: 0.0 for a in names} for k in ("return", "goal", "collision", "offroad", "steps", "kl_to_prior")}
    while env.agents:
        live = list(env.agents)
        logits = policy.logits(live, obs, infos)
        prior = torch.from_numpy(np.stack([prior_logits_of(a, obs, infos) for a in live]))
        t = getattr(policy, "temperature", 1.0)
        kl = kl_to_prior(torch.log_softmax(logits / t, -1), prior, env.temperature).clamp_min(0.0)
        tokens, _ = sample_tokens(logits, policy.generator, top_k=policy.top_k, temperature=t)
        actions = {a: int(x) for a, x in zip(live, tokens.tolist())}
        obs, rewards, terms, truncs, infos = env.step(actions)
        for i, a in enumerate(live):
            out["return"][a] += rewards[a]
            out["steps"][a] += 1
            out["kl_to_prior"][a] += float(kl[i])
            for key, ev in (("goal", "goal_reached"), ("collision", "collision"), ("offroad", "offroad")):
                out[key][a] = max(out[key][a], float(infos[a][ev]))
    return out


def evaluate_policy(env, policy, scene_indices: Sequence[int], seeds: Sequence[int]) -> dict[str, float]:
    """:func:`run_episode` aggregated over every (scene, seed): ``goal_rate``, ``collision_rate``,
    ``offroad_rate`` (fractions of agent-episodes), ``return`` (mean per agent-episode),
    ``kl_to_prior`` (mean per agent-step), ``agent_episodes`` and ``steps``."""
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
