"""Policies stage: the SMART prior as a policy (the default policy of every controlled agent), the
one KL to the prior, and one episode of any policy on the env.

What comes in: a step of the PettingZoo env ``envs.smart_traffic_v0`` (its observations and
``infos``); what goes out: ``{agent name: token id}``, the actions of the live agents. The prior's
logits are read from ``infos[agent]["prior_logits"]`` or, with ``observation="dict"``, from
``observations[agent]["prior_logits"]``; the env computed them already, so acting costs no model
call.

Every policy here is a :class:`SampledPolicy`: ``log_probs(agents, observations, infos)`` is its
action distribution [A, V] and it acts by :func:`smart_marl.rollout.sample_tokens` on it with its
``top_k`` from a generator seeded by :meth:`SampledPolicy.reset`, so two policies with equal
distributions take equal actions on equal seeds. :class:`PriorPolicy` with ``top_k=5`` is the
prior as it drives (the env's background agents sample so); ``top_k=None`` is its full softmax.

The reference a fine-tuned policy is pulled toward is one of these: the prior's
``softmax(logits / T)`` restricted to its top ``k`` tokens and renormalised
(:func:`smart_marl.rollout.reference_log_probs`; ``k`` None: the full softmax).
:func:`kl_to_prior` is the one KL to it in the project.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import torch

from envs.errors import NoPriorLogitsError
from smart_marl.rollout import reference_log_probs, reference_name, sample_tokens


def kl_to_prior(policy_log_probs: torch.Tensor, prior_logits: torch.Tensor, temperature: float = 1.0,
                top_k: int | None = None) -> torch.Tensor:
    """The exact categorical ``KL(pi || ref) = sum_v pi(v) (log pi(v) - log ref(v))`` per row, ref =
    ``softmax(prior_logits / temperature)`` restricted to its ``top_k`` tokens and renormalised
    (``top_k`` None: the full softmax): policy_log_probs [..., V] (``log pi``, ``-inf`` where pi is
    0), prior_logits [..., V] -> [...]. Tokens pi never takes add 0; mass on a token outside the
    reference's support makes it ``inf``. The one KL of the project (evaluation, batch statistics
    and the PPO loss term, :class:`agents.kl_ppo.PriorKLPPOLoss`); gradients stay finite."""
    ref = reference_log_probs(prior_logits, top_k, temperature)
    taken = policy_log_probs > float("-inf")
    diff = torch.where(taken, policy_log_probs - ref, torch.zeros_like(policy_log_probs))
    return (policy_log_probs.exp() * diff).sum(-1)


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


class SampledPolicy:
    """A policy that acts by sampling its distribution ``log_probs(agents, observations, infos)``
    [A, V] with :func:`smart_marl.rollout.sample_tokens` (``top_k``, temperature 1: the
    distribution is already final) from a generator seeded by :meth:`reset`."""

    name = "policy"
    top_k: int | None = None

    def __init__(self, seed: int = 0) -> None:
        self.generator = torch.Generator().manual_seed(int(seed))

    def reset(self, seed: int) -> None:
        self.generator = torch.Generator().manual_seed(int(seed))

    def log_probs(self, agents: list[str], observations: Mapping, infos: Mapping) -> torch.Tensor:
        raise NotImplementedError

    def sample(self, log_probs: torch.Tensor) -> torch.Tensor:
        """Token ids [A] drawn from ``log_probs`` [A, V]."""
        tokens, _ = sample_tokens(log_probs, self.generator, top_k=self.top_k)
        return tokens

    def __call__(self, observations: Mapping, infos: Mapping, agents: list[str] | None = None) -> dict[str, int]:
        agents = list(observations) if agents is None else list(agents)
        if not agents:
            return {}
        tokens = self.sample(self.log_probs(agents, observations, infos))
        return {a: int(t) for a, t in zip(agents, tokens.tolist())}


class PriorPolicy(SampledPolicy):
    """Acts by sampling the SMART prior's next-token distribution of each live agent.

    ``policy.reset(seed)`` at the start of an episode, then ``actions = policy(observations,
    infos)`` after each env reset/step. ``top_k``: None (the full softmax) or k (top-k
    renormalised, like the env's background agents); ``temperature`` divides the logits.
    """

    def __init__(self, top_k: int | None = None, temperature: float = 1.0, seed: int = 0) -> None:
        super().__init__(seed)
        self.top_k = top_k
        self.temperature = float(temperature)
        self.name = reference_name(top_k, temperature)

    def logits(self, agents: list[str], observations: Mapping, infos: Mapping) -> torch.Tensor:
        """[A, V] the prior's logits (before temperature)."""
        return torch.from_numpy(np.stack([prior_logits_of(a, observations, infos) for a in agents]))

    def log_probs(self, agents: list[str], observations: Mapping, infos: Mapping) -> torch.Tensor:
        return reference_log_probs(self.logits(agents, observations, infos), self.top_k, self.temperature)


def run_episode(env, policy: SampledPolicy, seed: int, scene_index: int | None = None) -> dict:
    """One episode of ``policy`` on the PettingZoo env from ``env.reset(seed=seed)`` (the policy is
    reset with the same seed). Returns per-agent totals over the episode: ``return``, ``goal``,
    ``collision``, ``offroad`` (1.0: the event happened at some step), ``progress_m`` (metres
    gained along the logged route), ``steps``, ``kl_to_reference`` (sum over the agent's steps of
    :func:`kl_to_prior` to the env's reference, ``env.reference_top_k`` and ``env.temperature``)
    and ``kl_to_full_prior`` (the same to the prior's full softmax); per-step mean = sum / steps.
    ``env.trajectories()`` holds the episode's poses until the next reset."""
    options = {"scene_index": scene_index} if scene_index is not None else None
    obs, infos = env.reset(seed=seed, options=options)
    policy.reset(seed)
    names = list(env.possible_agents)
    keys = ("return", "goal", "collision", "offroad", "progress_m", "steps", "kl_to_reference", "kl_to_full_prior")
    out = {k: {a: 0.0 for a in names} for k in keys}
    start_m = {a: float(infos[a]["route_progress_m"]) for a in names}
    ref_k, temp = getattr(env, "reference_top_k", None), env.temperature
    while env.agents:
        live = list(env.agents)
        logp = policy.log_probs(live, obs, infos)
        prior = torch.from_numpy(np.stack([prior_logits_of(a, obs, infos) for a in live]))
        kl_ref = kl_to_prior(logp, prior, temp, ref_k).clamp_min(0.0)
        kl_full = kl_to_prior(logp, prior, temp, None).clamp_min(0.0)
        tokens = policy.sample(logp)
        actions = {a: int(x) for a, x in zip(live, tokens.tolist())}
        obs, rewards, terms, truncs, infos = env.step(actions)
        for i, a in enumerate(live):
            out["return"][a] += rewards[a]
            out["steps"][a] += 1
            out["kl_to_reference"][a] += float(kl_ref[i])
            out["kl_to_full_prior"][a] += float(kl_full[i])
            out["progress_m"][a] = float(infos[a]["route_progress_m"]) - start_m[a]
            for key, ev in (("goal", "goal_reached"), ("collision", "collision"), ("offroad", "offroad")):
                out[key][a] = max(out[key][a], float(infos[a][ev]))
    return out
