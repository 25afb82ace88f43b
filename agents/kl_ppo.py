"""Fine-tuning stage, the objective: TorchRL's clipped PPO loss plus ``beta * KL(pi || reference)``.

What comes in: a batch of multi-agent transitions (TensorDict keyed by group, e.g.
``("agents", "action")``) holding the prior's logits of every agent at every step (the env
provides them: ``("agents", "observation", "prior_logits")``) and the mask of the agents that
acted (``("agents", "mask")``). What goes out: TorchRL's loss TensorDict (``loss_objective``,
``loss_critic``, ``loss_entropy``) with ``loss_prior_kl`` added, and ``kl_to_prior`` for logging.

PPO itself is not rewritten: :class:`PriorKLPPOLoss` subclasses
:class:`torchrl.objectives.ClipPPOLoss`, keeps the distribution of the current policy that the
parent builds for its importance weights, and adds the exact (analytic, categorical) KL

    KL(pi || ref) = sum_v pi(v) (log pi(v) - log ref(v)),  ref = softmax(prior_logits / T) on its top k tokens

(renormalised there, ``reference_top_k=None``: the full softmax; :func:`agents.prior_policy.kl_to_prior`) averaged over the agents that acted (masked rows, and rows
whose prior logits are all zero: agents the prior no longer simulates, are left out). The parent's
own reductions use the same mask (``loss_mask_key``), so done agents contribute to no term.
"""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.objectives import ClipPPOLoss

from smart_marl.rollout import reference_name

from .prior_policy import kl_to_prior


class PriorKLPPOLoss(ClipPPOLoss):
    """``ClipPPOLoss`` + ``beta * KL(pi || reference)``.

    Extra keyword arguments: ``beta`` (the KL coefficient), ``prior_logits_key`` (where the prior's
    logits are), ``agent_mask_key`` (bool, True for agents that acted; also the mask of the parent's
    losses), ``prior_temperature`` (the prior's sampling temperature T), ``reference_top_k`` (the
    reference's k; None: the full softmax), ``imitation`` (with > 0, ``imitation`` times the
    cross-entropy of the expert's tokens at ``expert_action_key`` is added as ``loss_imitation``).
    ``loss.reference`` names the reference. Everything else goes to :class:`~torchrl.objectives.ClipPPOLoss`.
    """

    def __init__(self, actor_network, critic_network, *, beta: float = 0.1,
                 prior_logits_key: NestedKey = ("agents", "observation", "prior_logits"),
                 agent_mask_key: NestedKey | None = ("agents", "mask"), prior_temperature: float = 1.0,
                 reference_top_k: int | None = None, imitation: float = 0.0,
                 expert_action_key: NestedKey = ("agents", "expert_action"), **kwargs) -> None:
        super().__init__(actor_network, critic_network, **kwargs)
        self.register_buffer("beta", torch.tensor(float(beta)))
        self.imitation, self.expert_action_key = float(imitation), expert_action_key
        self.prior_logits_key = prior_logits_key
        self.agent_mask_key = agent_mask_key
        self.prior_temperature = float(prior_temperature)
        self.reference_top_k = None if reference_top_k is None else int(reference_top_k)
        self.reference = reference_name(self.reference_top_k, self.prior_temperature)
        if agent_mask_key is not None:
            self.loss_mask_key = agent_mask_key
        self._current_dist = None

    def _log_weight(self, tensordict, adv_shape):
        out = super()._log_weight(tensordict, adv_shape)
        self._current_dist = out[1]  # the current policy's distribution, reused for the KL term
        return out

    def prior_kl(self, policy_log_probs: torch.Tensor, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """(KL(pi || prior) per row [...], bool mask of the rows that count [...]) from the policy's
        log-probabilities [..., V] and the batch's prior logits."""
        prior_logits = tensordict.get(self.prior_logits_key)
        kl = kl_to_prior(policy_log_probs, prior_logits, self.prior_temperature, self.reference_top_k)
        valid = prior_logits.ne(0).any(-1)
        if self.agent_mask_key is not None:
            valid = valid & tensordict.get(self.agent_mask_key).reshape(valid.shape)
        return kl, valid

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        td_out = super().forward(tensordict)
        dist, self._current_dist = self._current_dist, None
        logp = torch.log_softmax(dist.logits, -1)
        kl, valid = self.prior_kl(logp, tensordict)
        count = valid.sum().clamp_min(1)
        kl_mean = torch.where(valid, kl, torch.zeros_like(kl)).sum() / count
        td_out.set("loss_prior_kl", self.beta * kl_mean)
        td_out.set("kl_to_prior", kl_mean.detach())
        if self.imitation > 0:
            td_out.set("loss_imitation", self.imitation * self.imitation_loss(logp, tensordict, valid))
        return td_out

    def imitation_loss(self, policy_log_probs: torch.Tensor, tensordict: TensorDictBase, valid: torch.Tensor) -> torch.Tensor:
        """The mean cross-entropy of the expert's tokens (``expert_action_key`` [...]) under the policy,
        over the ``valid`` rows whose expert token the policy can take."""
        expert = tensordict.get(self.expert_action_key, None)
        if expert is None:
            raise KeyError(f"imitation: the batch has no expert tokens at {self.expert_action_key!r} (an env that labels them: "
                           "agents.finetune.ExpertLabelledEnv)")
        expert = expert.reshape(valid.shape)
        nll = -policy_log_probs.gather(-1, expert[..., None].long()).squeeze(-1)
        ok = valid & torch.isfinite(nll)
        return torch.where(ok, nll, torch.zeros_like(nll)).sum() / ok.sum().clamp_min(1)
