"""Policies and fine-tuning on top of envs (the last stage before metrics): the SMART prior as a
policy (:class:`PriorPolicy`), and KL-regularised multi-agent PPO with TorchRL
(:mod:`agents.finetune`, :mod:`agents.kl_ppo`, :mod:`agents.evaluate`).

Imports go smart_marl <- envs <- agents. TorchRL is imported only by the fine-tuning modules
(the ``rl`` extra), so ``PriorPolicy`` works with the env alone."""

from .prior_policy import PriorPolicy, run_episode

__all__ = ["PriorPolicy", "run_episode"]
