"""The realism-metric configurations of the Waymo Open Sim Agents Challenge (2024 and 2025 rules).

Stage: metrics (the end of the data flow). Plain constants: which features exist, their estimator
(histogram range and bins, or Bernoulli), the additive-smoothing pseudocount, the meta-metric
weight and the category each belongs to. Numbers are those of the official configs
(``challenge_2024_config.textproto`` of waymo-open-dataset 1.6.4 and
``challenge_2025_sim_agents_config.textproto`` of 1.6.5-1.6.7).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scenario import CURRENT_FRAME, DT_S

CURRENT_STEP = CURRENT_FRAME
"""The step the simulation starts from: the scenes' current frame (10)."""
NUM_HISTORY_STEPS = CURRENT_STEP + 1
"""Logged steps before the simulation (indices 0-10; the current step is 10)."""
NUM_SIMULATION_STEPS = 80
NUM_STEPS = NUM_HISTORY_STEPS + NUM_SIMULATION_STEPS
NUM_ROLLOUTS = 32
STEP_S = DT_S  # the metrics' time step is the scenes' frame step

FEATURES = (
    "linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration",
    "distance_to_nearest_object", "collision_indication", "time_to_collision",
    "distance_to_road_edge", "offroad_indication", "traffic_light_violation",
)
CATEGORIES = {
    "kinematic": ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration"),
    "interactive": ("distance_to_nearest_object", "collision_indication", "time_to_collision"),
    "map_based": ("distance_to_road_edge", "offroad_indication", "traffic_light_violation"),
}


@dataclass(frozen=True)
class FeatureConfig:
    """One feature's estimator: a histogram (``bins`` > 0) or a Bernoulli (``bins`` == 0)."""

    name: str
    weight: float
    min_val: float = 0.0
    max_val: float = 0.0
    bins: int = 0
    pseudocount: float = 0.1

    def edges(self) -> np.ndarray:
        """Histogram edges [bins + 1] exactly as the official code makes them (float32
        ``tf.linspace``: ``start + i * step`` in float32, the last edge the maximum)."""
        a, b = np.float32(self.min_val), np.float32(self.max_val)
        step = (b - a) / np.float32(self.bins)
        e = a + np.arange(self.bins + 1, dtype=np.float32) * step
        e[-1] = b
        return e


_BERNOULLI_PSEUDOCOUNT = float(np.float32(0.001))  # the proto default, a float32


def _hist(name, weight, lo, hi, bins):
    return FeatureConfig(name, weight, lo, hi, bins, float(np.float32(0.1)))


def _bern(name, weight):
    return FeatureConfig(name, weight, pseudocount=_BERNOULLI_PSEUDOCOUNT)


@dataclass(frozen=True)
class Rules:
    """A challenge's metric rules: its features and the rule switches that differ by year."""

    name: str
    features: dict
    ttc_vehicles_only: bool
    traffic_lights: bool

    def categories(self) -> dict[str, tuple[str, ...]]:
        return {k: tuple(f for f in v if f in self.features) for k, v in CATEGORIES.items()}


_COMMON = [
    _hist("linear_speed", 0.05, 0.0, 25.0, 10),
    _hist("linear_acceleration", 0.05, -12.0, 12.0, 11),
    _hist("angular_speed", 0.05, -0.628, 0.628, 11),
    _hist("angular_acceleration", 0.05, -3.14, 3.14, 11),
    _hist("distance_to_nearest_object", 0.10, -5.0, 40.0, 10),
    _bern("collision_indication", 0.25),
    _hist("time_to_collision", 0.10, 0.0, 5.0, 10),
    _bern("offroad_indication", 0.25),
]

RULES = {
    "2024": Rules("2024", {f.name: f for f in _COMMON + [_hist("distance_to_road_edge", 0.10, -20.0, 40.0, 10)]},
                  ttc_vehicles_only=False, traffic_lights=False),
    "2025": Rules("2025", {f.name: f for f in _COMMON + [_hist("distance_to_road_edge", 0.05, -20.0, 40.0, 10),
                                                          _bern("traffic_light_violation", 0.05)]},
                  ttc_vehicles_only=True, traffic_lights=True),
}


def get_rules(name: str | int) -> Rules:
    try:
        return RULES[str(name)]
    except KeyError:
        raise ValueError(f"unknown sim-agents rules {name!r}: expected one of {sorted(RULES)}") from None
