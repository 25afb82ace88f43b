"""Environment stage: PettingZoo environments built on smart_marl.

``envs.smart_traffic_v0``: ``parallel_env()``, ``env()`` (AEC) and ``raw_env()``; the motion-token
driving environment with the SMART prior as background and as the logits a policy is regularised
towards. Needs the ``env`` extra (pettingzoo, gymnasium). Import the module you want:
``from envs import smart_traffic_v0``.
"""

__all__ = ["smart_traffic_v0"]
