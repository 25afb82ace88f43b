"""Environment stage: PettingZoo environments built on smart_marl.

``envs.smart_traffic_v0``: ``parallel_env()``, ``env()`` (AEC) and ``raw_env()``; the motion-token
driving environment with the SMART prior as background and as the logits a policy is regularised
towards. pettingzoo and gymnasium are core dependencies of the package (``pip install smart-marl``
brings them). ``import envs; envs.smart_traffic_v0.parallel_env()`` and ``from envs import smart_traffic_v0``
both work.

``envs.errors``: the environment's errors, each a ``SmartMarlError`` with the builtin base a caller
catches (``ValueError``, ``KeyError``, ``TypeError``, ``RuntimeError``).
"""

from . import errors, smart_traffic_v0

__all__ = ["smart_traffic_v0", "errors"]
