"""Parity of smart_marl.metrics with the official WOSAC package: golden numbers from real runs of
waymo-open-dataset 1.6.4 (2024 rules) and 1.6.7 (2025 rules), see tests/golden/README.md."""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import pytest

from smart_marl.metrics import aggregate, logged_scene, score_rollouts
from smart_marl.metrics.baselines import constant_speed_along_heading, constant_velocity, noisy_log_replay
from smart_marl.metrics.submission import rollouts_from_submission
from smart_marl.readers import read_scenarios

GOLDEN = json.loads((Path(__file__).parent / "golden" / "wosac_official.json").read_text())
TOLERANCE = 1e-5


@lru_cache(maxsize=None)
def _scenario(path: str):
    return next(iter(read_scenarios(path)))


@lru_cache(maxsize=None)
def _scene(path: str):
    return logged_scene(_scenario(path))


def _case_id(case):
    return f"{case['rules']}-{case['scene'].split('.')[0]}-{case['rollouts']['kind']}"


@pytest.mark.parametrize("case", GOLDEN["cases"], ids=_case_id)
def test_realism_metrics_match_official_package_within_1e_5(case, shared_data):
    womd = shared_data / "womd_tfrecord"
    path = str(womd / case["scene"])
    scenario, scene = _scenario(path), _scene(path)
    ro = case["rollouts"]
    if ro["kind"] == "submission":
        rollouts = rollouts_from_submission(womd / ro["file"])[scenario.scenario_id].to_rollouts(scenario.frame)
    elif ro["kind"] == "constant_velocity":
        rollouts = constant_velocity(scenario, ro["num_rollouts"], ro["seed"])
    elif ro["kind"] == "constant_speed_along_heading":
        rollouts = constant_speed_along_heading(scenario, ro["num_rollouts"], min_speed_mps=ro["min_speed_mps"])
    else:
        rollouts = noisy_log_replay(scenario, ro["num_rollouts"], ro["seed"])
    ours = aggregate([score_rollouts(scene, rollouts, case["rules"])], case["rules"])
    diffs = {f"likelihoods.{k}": abs(ours["likelihoods"][k] - v) for k, v in case["likelihoods"].items()}
    diffs.update({k: abs(ours[k] - case[k]) for k in ("meta_metric", "kinematic", "interactive", "map_based", "min_ade")})
    assert set(ours["likelihoods"]) == set(case["likelihoods"])
    bad = {k: d for k, d in diffs.items() if not d <= TOLERANCE}
    assert not bad, f"differs from the official package by more than {TOLERANCE}: {bad}"
