"""Policies and fine-tuning on top of envs (the last stage before metrics): the SMART prior as a
policy (:class:`PriorPolicy`), scripted manoeuvres (:mod:`agents.scripted`), KL-regularised
multi-agent PPO with TorchRL (:mod:`agents.finetune`, :mod:`agents.kl_ppo`, :mod:`agents.evaluate`),
what-if scenarios (:mod:`agents.whatif`) and their commands (:mod:`agents.commands`).

Imports go smart_marl <- envs <- agents. TorchRL is imported only by the fine-tuning modules
(the ``rl`` extra), so ``PriorPolicy`` works with the env alone."""

from .prior_policy import PriorPolicy, SampledPolicy, kl_to_prior, run_episode

__all__ = ["PriorPolicy", "SampledPolicy", "kl_to_prior", "run_episode"]
