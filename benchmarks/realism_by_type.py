"""Where a prior loses kinematic realism, per agent type: the WOSAC kinematic likelihoods pooled over
one agent type's scored (agent, step) pairs.

WOSAC scores every evaluated agent against a histogram of its own 32 rollouts and averages over all
agents of a scene; this script runs the same rollouts and the same histograms (``smart_marl.metrics``)
and splits the per-step log-likelihoods by agent type, pooled over all the scenes, so that a type
whose rollouts never visit the bins its log visits shows up (a logged value in an empty bin scores
log(0.1 / 2561) = -10). The figures are not per-scene means, so they do not average to the realism
table's categories. It also prints, per type, the quantiles of |angular speed| of the log and of the
rollouts over the same steps.

Output (stdout, one JSON object per line)::

    {"kind": "likelihood", "type": "pedestrian", "feature": "angular_speed", "likelihood": ..., "steps": ...}
    {"kind": "abs_angular_speed", "type": "pedestrian", "quantiles": [0.25, 0.5, 0.75, 0.9], "log": [...], "rollouts": [...]}

    .venv/bin/python benchmarks/realism_by_type.py --scenes DIR [--prior PATH] [--seed 0] [--top-k 6] [--rollouts 32]

Measured figures are in docs/experiments/2026-11-25-swaying-pedestrians-stage5.md.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from smart_marl.commands.eval import prior_rollouts
from smart_marl.metrics import align_rollouts, compute_features, get_rules, logged_scene, metric_frame_rollouts
from smart_marl.metrics.features import kinematic_validity
from smart_marl.metrics.likelihood import histogram_log_likelihood
from smart_marl.model.checkpoint import EMBEDDED, load_prior
from smart_marl.readers import expand_paths, read_scenarios
from smart_marl.rollout import DEFAULT_TOP_K
from smart_marl.scenario import AgentType

FEATURES = ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration")
QUANTILES = (0.25, 0.5, 0.75, 0.9)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", required=True, help="scene files, folders or globs (e.g. the 7 held-out real scenes)")
    parser.add_argument("--prior", default=None, help="checkpoint (default: the embedded prior)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--top-k", type=int, default=DEFAULT_TOP_K)
    parser.add_argument("--rollouts", type=int, default=32)
    parser.add_argument("--rules", default="2024", choices=("2024", "2025"))
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    rules = get_rules(args.rules)
    prior = load_prior(args.prior or EMBEDDED)
    sums: dict[tuple[int, str], list[float]] = {}
    angular: dict[int, tuple[list, list]] = {}
    for path in expand_paths(args.scenes):
        for scenario in read_scenarios(path):
            scene = logged_scene(scenario)
            rollouts = prior_rollouts(prior, scenario, args.rollouts, args.seed, "cpu", args.top_k)
            rollouts = metric_frame_rollouts(scene, align_rollouts(scene, rollouts, path))
            log = compute_features(scene, None, traffic_lights=rules.traffic_lights)
            sim = compute_features(scene, rollouts, traffic_lights=rules.traffic_lights)
            speed_valid, accel_valid = kinematic_validity(log.valid[0])
            types = scene.object_types[scene.evaluated]
            for name in FEATURES:
                mask = speed_valid if name in ("linear_speed", "angular_speed") else accel_valid
                cfg = rules.features[name]
                ll = histogram_log_likelihood(getattr(log, name)[0], getattr(sim, name), cfg.edges(), cfg.pseudocount)
                for t in np.unique(types):
                    m = mask & (types == t)[:, None]
                    acc = sums.setdefault((int(t), name), [0.0, 0])
                    acc[0] += float(ll[m].sum())
                    acc[1] += int(m.sum())
            for t in np.unique(types):
                m = speed_valid & (types == t)[:, None]
                logged, simulated = angular.setdefault(int(t), ([], []))
                logged.append(np.abs(log.angular_speed[0][m]))
                simulated.append(np.abs(sim.angular_speed[:, m]).ravel())
    for (t, name), (total, steps) in sorted(sums.items()):
        if steps:
            print(json.dumps({"kind": "likelihood", "type": AgentType(t).name.lower(), "feature": name,
                              "likelihood": round(float(np.exp(total / steps)), 4), "steps": steps}))
    for t, (logged, simulated) in sorted(angular.items()):
        logged, simulated = np.concatenate(logged), np.concatenate(simulated)
        if len(logged):
            print(json.dumps({"kind": "abs_angular_speed", "type": AgentType(t).name.lower(), "quantiles": list(QUANTILES),
                              "log": np.round(np.nanquantile(logged, QUANTILES), 3).tolist(),
                              "rollouts": np.round(np.nanquantile(simulated, QUANTILES), 3).tolist()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
