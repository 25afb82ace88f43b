"""PettingZoo environments built on smart_marl (parallel_env(), env()). Nothing here yet."""
