"""Speed of the sim-agents realism metrics (smart_marl.metrics) per scenario, against the official package.

Prints one JSON line per (scene, rollouts, rules): ``seconds_per_scenario`` is the median of
``--repeats`` runs of the whole scoring of one scenario with 32 rollouts (logged features,
simulated features, likelihoods; reading the file excluded), on this CPU. ``official_seconds`` is
the official waymo-open-dataset package's time for the same scenario and rollouts, measured once
(tests/golden/wosac_official.json says how and where) and recorded as a constant reference;
``speedup`` = official / ours. Usage: python benchmarks/metrics_speed.py [--repeats 5] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from smart_marl.metrics import logged_scene, score_rollouts
from smart_marl.metrics.baselines import constant_velocity, noisy_log_replay
from smart_marl.metrics.submission import rollouts_from_submission
from smart_marl.readers import read_scenarios

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "golden" / "wosac_official.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    args = parser.parse_args()
    womd = Path(args.data) / "womd_tfrecord"
    golden = json.loads(GOLDEN.read_text())
    official = {(c["scene"], c["rollouts"]["kind"], c["rules"]): c["official_seconds"] for c in golden["cases"]}
    cases = [
        ("motion_data_one_scenario.tfrecord", "submission",
         lambda sc: rollouts_from_submission(womd / "sim_agents_test_submission.binproto")[sc.scenario_id].to_rollouts(sc.frame)),
        ("motion_data_one_scenario.tfrecord", "noisy_log_replay", lambda sc: noisy_log_replay(sc, 32, 20240)),
        ("womd_scenario_input.tfrecord", "constant_velocity", lambda sc: constant_velocity(sc, 32)),
        ("womd_scenario_input.tfrecord", "noisy_log_replay", lambda sc: noisy_log_replay(sc, 32, 20241)),
    ]
    for scene_file, kind, make in cases:
        scenario = next(iter(read_scenarios(str(womd / scene_file))))
        rollouts = make(scenario)
        for rules in ("2024", "2025"):
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                scene = logged_scene(scenario)
                score_rollouts(scene, rollouts, rules)
                times.append(time.perf_counter() - t0)
            ours = statistics.median(times)
            ref = official.get((scene_file, kind, rules))
            print(json.dumps({
                "benchmark": "metrics_speed", "scene": scene_file, "rollouts": kind, "rules": rules,
                "num_rollouts": rollouts.num_rollouts, "simulated_agents": int(rollouts.x.shape[1]),
                "evaluated_agents": int(len(scene.evaluated)), "seconds_per_scenario": round(ours, 4),
                "official_seconds": ref, "speedup": round(ref / ours, 1) if ref else None,
                "official_reference": "waymo-open-dataset-tf-2-12-0 1.6.4/1.6.7, TF 2.12 CPU, 1 intra-op thread, "
                                      "same machine class (2 shared cores); see tests/golden/wosac_official.json" if ref else None,
            }), flush=True)


if __name__ == "__main__":
    main()
