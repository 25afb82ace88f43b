"""Sim-agents realism metrics (Waymo Open Sim Agents Challenge, 2024 and 2025 rules), without TensorFlow.

Stage: metrics, the last stage of the data flow. Pure functions of arrays:

* :func:`~.inputs.logged_scene` (Scenario -> :class:`~.inputs.LoggedScene`) and
  :class:`~.inputs.Rollouts` ([R, A, 80] x, y, z, heading);
* :func:`score_rollouts` -> :class:`~.likelihood.ScenarioMetrics` (every likelihood, the
  meta-metric, minADE) and :func:`~.likelihood.aggregate` over scenarios (+ category scores);
* :mod:`.submission`: rollouts <-> ``SimAgentsChallengeSubmission`` files;
* :mod:`.baselines`: constant-velocity, log-replay and random rollouts.

The numbers match the official ``waymo-open-dataset`` package (1.6.4 for 2024, 1.6.7 for 2025)
to 1e-5 on the pinned test scenes (tests/golden).
"""

from __future__ import annotations

from .config import FEATURES, RULES, get_rules
from .features import Features, compute_features
from .inputs import (LoggedScene, RolloutError, Rollouts, SceneNotScorableError, align_rollouts, is_vehicle, logged_scene,
                     metric_frame_rollouts)
from .likelihood import ScenarioMetrics, aggregate, score_features

__all__ = [
    "FEATURES", "RULES", "get_rules", "Features", "compute_features", "LoggedScene", "RolloutError", "Rollouts", "SceneNotScorableError",
    "align_rollouts", "logged_scene", "metric_frame_rollouts", "ScenarioMetrics", "aggregate", "score_features", "score_rollouts",
    "score_scenario",
]


def score_rollouts(scene: LoggedScene, rollouts: Rollouts, rules: str = "2025", where: str = "") -> ScenarioMetrics:
    """Realism metrics of one scene's rollouts (any agent order; checked against the scene)."""
    r = get_rules(rules)
    rollouts = metric_frame_rollouts(scene, align_rollouts(scene, rollouts, where))
    log = compute_features(scene, None, traffic_lights=r.traffic_lights)
    sim = compute_features(scene, rollouts, traffic_lights=r.traffic_lights)
    return score_features(log, sim, r, scene.scenario_id, is_vehicle(scene)[scene.evaluated])


def score_scenario(scenario, rollouts: Rollouts, rules: str = "2025") -> ScenarioMetrics:
    """:func:`score_rollouts` for a :class:`~smart_marl.scenario.Scenario` (local-frame rollouts)."""
    return score_rollouts(logged_scene(scenario), rollouts, rules)
